"""Settings of the scorer (the ``evaluate:`` section of the config)."""

from __future__ import annotations

import re
from dataclasses import dataclass


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
    alignment_trim: float = 0.0
    #: Which of several SfM models the mesh, atlas and changes are in: "first" (the model
    #: directory itself, or its first numbered sub-model, as the mesh stage picks it; or the
    #: first path given) or "largest" (most registered frames).
    reference_model: str = "first"
    #: Fewer matched frames than this and the trajectory (and all that needs it) is left out.
    min_alignment_frames: int = 3
    #: Points sampled on each mesh for accuracy and completeness.
    surface_samples: int = 20000
    #: A point of the seen true wall is "reconstructed" when a reconstructed mesh is this close.
    completeness_threshold_mm: float = 2.0
    #: Seed of the surface sampling (scores are reproducible).
    seed: int = 0
    #: A detection matches a true lesion within max(tolerance_mm, factor × true diameter).
    lesion_tolerance_mm: float = 5.0
    lesion_tolerance_diameter_factor: float = 0.5
    #: True lesion diameters are grouped to this step (mm) for the recall per diameter.
    lesion_diameter_step_mm: float = 0.5
    #: Lower bound on |cos(incidence)| when weighting atlas pixels by wall area.
    atlas_min_cos_incidence: float = 0.1

    def __post_init__(self) -> None:
        try:
            rx = re.compile(self.frame_pattern)
        except re.error as exc:
            msg = f"frame_pattern {self.frame_pattern!r} is not a regex ({exc})"
            raise ValueError(msg) from exc
        if self.reference_model not in ("first", "largest"):
            raise ValueError(f"reference_model: first or largest, not {self.reference_model!r}")
        if rx.groups < 1:
            raise ValueError(f"frame_pattern {self.frame_pattern!r} needs a capture group")
        positive = {
            "surface_samples": self.surface_samples,
            "completeness_threshold_mm": self.completeness_threshold_mm,
            "lesion_diameter_step_mm": self.lesion_diameter_step_mm,
        }
        for name, value in positive.items():
            if value <= 0:
                raise ValueError(f"{name} must be positive, got {value}")
        if self.min_alignment_frames < 3:
            raise ValueError(f"min_alignment_frames must be >= 3, got {self.min_alignment_frames}")
        if self.alignment_trim < 0:
            raise ValueError(f"alignment_trim must be >= 0, got {self.alignment_trim}")
        if self.lesion_tolerance_mm < 0 or self.lesion_tolerance_diameter_factor < 0:
            raise ValueError("lesion tolerances must be >= 0")
        if not 0 < self.atlas_min_cos_incidence <= 1:
            raise ValueError(
                f"atlas_min_cos_incidence must be in (0, 1], got {self.atlas_min_cos_incidence}"
            )
