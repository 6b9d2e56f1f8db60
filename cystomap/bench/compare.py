"""Benchmark: the compare stage on full-size phantom session pairs, timed and scored.

Pairs (session 1 → session 2 of one phantom bladder, each run through every stage first):
``default`` (six lesions of 5-30 mm appear), ``deformed`` (the same with the bladder filled
7 % differently) and ``no_change`` (no lesions: every detection is a false positive).
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cystomap.bench.common import timed
from cystomap.bench.pipeline import run_session
from cystomap.compare import CompareConfig, compare_sessions
from cystomap.compare.stage import SessionPaths
from cystomap.evaluate import evaluate_changes
from cystomap.phantom import PhantomConfig, default_camera

log = logging.getLogger(__name__)

PAIRS: dict[str, dict[str, Any]] = {
    "default": {},
    "deformed": {"deformation": 0.07},
    "no_change": {"lesion_diameters_mm": ()},
}


def _paths(root: Path) -> SessionPaths:
    return SessionPaths(root / "sfm", root / "preprocess", root / "mesh/surface.ply", root / "atlas")


def bench_compare(work: Path, repeats: int = 1, pairs: Sequence[str] = tuple(PAIRS), seed: int = 7,
                  width: int = 1280, height: int = 720) -> list[dict[str, Any]]:
    """One row per pair: compare time (median of ``repeats``), registration and lesion scores."""
    camera = default_camera(width, height)
    rows = []
    for name in pairs:
        cfg = PhantomConfig(seed=seed, **PAIRS[name])
        roots = [work / f"compare_{name}_seed{seed}_s{s}" for s in (1, 2)]
        truths = [run_session(root, cfg, s, camera)[0] for s, root in zip((1, 2), roots, strict=True)]
        out = work / f"compare_{name}_seed{seed}"

        def run(i: int, out: Path = out, roots: list[Path] = roots) -> Path:
            shutil.rmtree(out, ignore_errors=True)
            log.info("compare %s (run %d)", out.name, i + 1)
            return compare_sessions(_paths(roots[0]), _paths(roots[1]), out, CompareConfig())

        timing, _ = timed("compare", run, repeats)
        reg = json.loads((out / "registration.json").read_text())
        scores = evaluate_changes(truths[1], roots[1] / "sfm", out / "changes.csv").get("lesions", {})
        sizes = {e["diameter_mm"]: e for e in scores.get("lesions", [])}
        row: dict[str, Any] = {
            "pair": name, "seed": seed, "registered": reg.get("registered"),
            "inliers": reg.get("inliers"),
            "true_lesions": scores.get("n_true"), "found": scores.get("n_matched"),
            "false_positives": scores.get("false_positives"),
            "centroid_error_mm_mean": _r(scores.get("localisation_error_mm_mean")),
            "centroid_error_mm_max": _r(scores.get("localisation_error_mm_max")),
            "size_abs_error_pct_mean": _r(scores.get("size_abs_error_percent_mean")),
            "missed_mm": ",".join(f"{d:g}" for d, e in sorted(sizes.items()) if not e["detected"]),
            **{k: v for k, v in timing.row().items() if k != "step"},
        }
        rows.append(row)
        log.info("compare %s: %s", name, row)
    return rows


def _r(v: Any) -> Any:
    return round(v, 2) if isinstance(v, float) else v
