"""Benchmark: every stage of one full-size phantom session, timed and scored against truth."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any

from cystomap.atlas import AtlasConfig, build_atlas
from cystomap.bench.common import timed
from cystomap.evaluate import evaluate_session
from cystomap.frames import FramesConfig, extract_frames
from cystomap.mesh import MeshConfig, build_mesh
from cystomap.phantom import PhantomConfig, bladder_extent_mm, default_camera, generate_session
from cystomap.preprocess import PreprocessConfig, preprocess_frames
from cystomap.sfm import SfmConfig, run_sfm

log = logging.getLogger(__name__)

TARGETS_S = {"sfm": None, "mesh": 20, "atlas": 20}
SCORES = {
    "registration.registered_share": "registered share",
    "reprojection.mean_error_px": "reprojection px",
    "trajectory.rmse_mm": "trajectory RMSE mm",
    "trajectory.scale_error": "scale error",
    "surface.accuracy_mean_mm": "surface mean mm",
    "surface.completeness": "completeness 2 mm",
    "atlas.coverage_error_pp": "coverage error pp",
}


def bench_pipeline(work: Path, repeats: int = 1, seed: int = 7, session: int = 1,
                   width: int = 1280, height: int = 720) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Time each stage on one phantom session; return (timing rows, score rows)."""
    camera = default_camera(width, height)
    cfg = PhantomConfig(seed=seed)
    root = work / f"pipeline_seed{seed}_s{session}"
    truth = generate_session(root / "truth", session, cfg, camera)
    steps = [
        ("frames", lambda out: extract_frames(truth / "video.mp4", out, FramesConfig(), camera)),
        ("preprocess", lambda out: preprocess_frames(root / "frames", out, camera, PreprocessConfig())),
        ("sfm", lambda out: run_sfm(root / "preprocess", out, SfmConfig(), extent_mm=bladder_extent_mm(cfg, session))),
        ("mesh", lambda out: build_mesh(root / "sfm", out, MeshConfig())),
        ("atlas", lambda out: build_atlas(root / "sfm", root / "preprocess", root / "mesh/surface.ply", out,
                                          AtlasConfig())),
    ]
    rows = []
    for name, fn in steps:
        out = root / name

        def run(i: int, fn=fn, out: Path = out, name: str = name) -> Path:
            shutil.rmtree(out, ignore_errors=True)
            log.info("stage %s (run %d)", name, i + 1)
            return fn(out)

        timing, _ = timed(name, run, repeats)
        timing.extra = {"target_s": TARGETS_S.get(name)}
        rows.append(timing.row())
    result = evaluate_session(truth, root / "sfm", root / "mesh/surface.ply", root / "atlas")
    scores = [{"metric": label, "value": _get(result, key)} for key, label in SCORES.items()]
    return rows, scores


def _get(d: dict[str, Any], dotted: str) -> Any:
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return None
        d = d[part]
    return round(d, 4) if isinstance(d, float) else d
