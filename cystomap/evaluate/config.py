"""Settings of the scorer (the ``evaluate:`` section of the config)."""

from __future__ import annotations

import re
from dataclasses import dataclass

from cystomap.settings import setting, validate


@dataclass(frozen=True)
class EvalConfig:
    """How reconstructions are compared with the phantom's ground truth.

    Distances are in the truth's millimetres. Every score is computed from the documented
    output files only, so any reconstruction written in those formats can be scored.
    """

    #: Regex searched in an image's basename; group 1 is the 0-based video frame index.
    frame_pattern: str = r"(\d+)\.[A-Za-z0-9]+$"
    #: 0 = plain Umeyama Sim(3); > 0 = refit on frames whose error is at most
    #: ``alignment_trim`` × the median error (three rounds), to resist a few wild cameras.
    alignment_trim: float = setting(0.0, ">= 0")
    #: Which of several SfM models the mesh, atlas and changes are in: "first" (the model
    #: directory itself, or its first numbered sub-model, as the mesh stage picks it; or the
    #: first path given) or "largest" (most registered frames).
    reference_model: str = setting("first", choices=("first", "largest"))
    #: Fewer matched frames than this and the trajectory (and all that needs it) is left out.
    min_alignment_frames: int = setting(3, ">= 3")
    #: Points sampled on each mesh for accuracy and completeness.
    surface_samples: int = setting(20000, "> 0")
    #: A point of the seen true wall is "reconstructed" when a reconstructed mesh is this close.
    completeness_threshold_mm: float = setting(2.0, "> 0")
    #: Seed of the surface sampling (scores are reproducible).
    seed: int = setting(0, ">= 0")
    #: A detection matches a true lesion within max(tolerance_mm, factor × true diameter).
    lesion_tolerance_mm: float = setting(5.0, ">= 0")
    lesion_tolerance_diameter_factor: float = setting(0.5, ">= 0")
    #: True lesion diameters are grouped to this step (mm) for the recall per diameter.
    lesion_diameter_step_mm: float = setting(0.5, "> 0")
    #: Lower bound on |cos(incidence)| when weighting atlas pixels by wall area.
    atlas_min_cos_incidence: float = setting(0.1, "(0, 1]")

    def __post_init__(self) -> None:
        try:
            rx = re.compile(self.frame_pattern)
        except re.error as exc:
            msg = f"frame_pattern {self.frame_pattern!r} is not a regex ({exc})"
            raise ValueError(msg) from exc
        if rx.groups < 1:
            raise ValueError(f"frame_pattern {self.frame_pattern!r} needs a capture group")
        validate(self, "evaluate")
