"""Benchmark: every stage of full-size phantom sessions, timed and scored against truth.

The first seed's session is timed (``repeats`` runs per stage, medians); the other seeds are
run once and scored, so that the scores are not those of one lucky phantom.
"""

from __future__ import annotations

import logging
import shutil
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cystomap.atlas import AtlasConfig, build_atlas
from cystomap.bench.common import Timing, timed
from cystomap.camera import Camera
from cystomap.evaluate import evaluate_session
from cystomap.frames import FramesConfig, extract_frames
from cystomap.mesh import MeshConfig, build_mesh
from cystomap.phantom import PhantomConfig, bladder_extent_mm, default_camera, generate_session
from cystomap.preprocess import PreprocessConfig, preprocess_frames
from cystomap.sfm import SfmConfig, run_sfm

log = logging.getLogger(__name__)

TARGETS_S = {"sfm": None, "mesh": 20, "atlas": 20}
# score key -> (label, target as text)
SCORES = {
    "registration.registered_share": ("registered share", "all usable frames"),
    "reprojection.mean_error_px": ("reprojection px", "<= 0.7"),
    "trajectory.rmse_mm": ("trajectory RMSE mm", "<= 0.1"),
    "trajectory.scale_error": ("scale error", "<= 0.02"),
    "surface.accuracy_mean_mm": ("surface mean mm (wall)", "<= 0.5"),
    "surface.accuracy_mean_mm_with_closure": ("surface mean mm (with aperture closure)", ""),
    "surface.completeness": ("seen wall within 2 mm", ">= 0.95"),
    "atlas.coverage_error_pp": ("coverage error pp", "within ±2"),
    "atlas.ssim": ("atlas SSIM", ">= 0.7"),
    "atlas.ssim_stretched": ("atlas SSIM (contrast-stretched)", ""),
    "atlas.detail_correlation": ("atlas detail correlation", ""),
    "atlas.sharpness_ratio": ("atlas sharpness ratio", ""),
}
STAGES = ("frames", "preprocess", "sfm", "mesh", "atlas")


def run_session(root: Path, cfg: PhantomConfig, session: int, camera: Camera,
                repeats: int = 1) -> tuple[Path, list[Timing]]:
    """Render one phantom session into ``root/truth`` and run every stage into ``root/<stage>``."""
    truth = generate_session(root / "truth", session, cfg, camera)
    steps = {
        "frames": lambda out: extract_frames(truth / "video.mp4", out, FramesConfig(), camera),
        "preprocess": lambda out: preprocess_frames(root / "frames", out, camera, PreprocessConfig()),
        "sfm": lambda out: run_sfm(root / "preprocess", out, SfmConfig(),
                                   extent_mm=bladder_extent_mm(cfg, session)),
        "mesh": lambda out: build_mesh(root / "sfm", out, MeshConfig()),
        "atlas": lambda out: build_atlas(root / "sfm", root / "preprocess", root / "mesh/surface.ply",
                                         out, AtlasConfig()),
    }
    timings = []
    for name in STAGES:
        out, fn = root / name, steps[name]

        def run(i: int, fn=fn, out: Path = out, name: str = name) -> Path:
            shutil.rmtree(out, ignore_errors=True)
            log.info("%s: stage %s (run %d)", root.name, name, i + 1)
            return fn(out)

        timing, _ = timed(name, run, repeats)
        timings.append(timing)
    return truth, timings


def bench_pipeline(work: Path, repeats: int = 1, seeds: Sequence[int] = (7, 8, 9), session: int = 1,
                   width: int = 1280, height: int = 720) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Time each stage on the first seed's session, score every seed; (timing rows, score rows)."""
    camera = default_camera(width, height)
    results = {}
    rows: list[dict[str, Any]] = []
    for k, seed in enumerate(seeds):
        root = work / f"pipeline_seed{seed}_s{session}"
        truth, timings = run_session(root, PhantomConfig(seed=seed), session, camera, repeats if k == 0 else 1)
        if k == 0:
            for t in timings:
                t.extra = {"seed": seed, "target_s": TARGETS_S.get(t.name)}
                rows.append(t.row())
        results[seed] = evaluate_session(truth, root / "sfm", root / "mesh/surface.ply", root / "atlas")
    scores = []
    for key, (label, target) in SCORES.items():
        row: dict[str, Any] = {"metric": label, "target": target}
        values = [_get(results[s], key) for s in seeds]
        row |= {f"seed {s}": v for s, v in zip(seeds, values, strict=True)}
        known = [v for v in values if isinstance(v, int | float)]
        row["median"] = round(statistics.median(known), 4) if known else None
        scores.append(row)
    return rows, scores


def _get(d: dict[str, Any], dotted: str) -> Any:
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return None
        d = d[part]
    return round(d, 4) if isinstance(d, float) else d
