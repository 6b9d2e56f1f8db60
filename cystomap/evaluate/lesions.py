"""Scores of the detected changes (session A → B) against the true lesions of session B."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.anatomy import Anatomy, covered_regions
from cystomap.evaluate.anatomy import straddle_match
from cystomap.evaluate.config import EvalConfig
from cystomap.evaluate.trajectory import Sim3
from cystomap.evaluate.truth import Truth, equirect_directions, read_csv

log = logging.getLogger(__name__)

CHANGE_COLUMNS = ("x", "y", "z", "diameter_mm")
_INFEASIBLE = 1e12


def match_lesions(
    true_xyz: np.ndarray, tolerance: np.ndarray, det_xyz: np.ndarray
) -> list[tuple[int, int, float]]:
    """One-to-one matches (true index, detection index, distance) within each true tolerance.

    Hungarian assignment: the most matches first, then the least total distance.
    """
    from scipy.optimize import linear_sum_assignment

    if len(true_xyz) == 0 or len(det_xyz) == 0:
        return []
    dist = np.linalg.norm(true_xyz[:, None, :] - det_xyz[None, :, :], axis=2)
    feasible = dist <= tolerance[:, None]
    cost = np.where(feasible, dist, _INFEASIBLE)
    rows, cols = linear_sum_assignment(cost)
    return [(int(i), int(j), float(dist[i, j])) for i, j in zip(rows, cols, strict=True)
            if feasible[i, j]]


def score_changes(
    truth_b: Truth, changes_csv: Path, sim3_b: Sim3, cfg: EvalConfig
) -> dict[str, Any]:
    """Recall, false positives, localisation and size errors of ``changes.csv``.

    Detections (centroids and diameters in session B's model frame) are taken into the truth
    frame by ``sim3_b`` (model → truth, so diameters scale by its scale) and matched one-to-one
    to the true lesions within max(lesion_tolerance_mm, factor × true diameter).

    Region rule (:data:`cystomap.anatomy.STRADDLE_RULE`,
    :func:`cystomap.evaluate.anatomy.straddle_match`): a detection's region is right when it
    is one of the regions its lesion covers in the true frame, or the lesion's region is one
    changes.csv says the detection straddles (``region_accuracy``); ``region_centre_accuracy``
    the strict share (the region of the lesion's centre).
    """
    det = read_csv(changes_csv, CHANGE_COLUMNS)
    true = truth_b.lesions
    det_xyz = sim3_b.apply(det[["x", "y", "z"]].to_numpy(np.float64).reshape(-1, 3))
    det_diam = det["diameter_mm"].to_numpy(np.float64) * sim3_b.scale
    true_xyz = true[["x", "y", "z"]].to_numpy(np.float64).reshape(-1, 3)
    true_diam = true["diameter_mm"].to_numpy(np.float64)
    tol = np.maximum(cfg.lesion_tolerance_mm, cfg.lesion_tolerance_diameter_factor * true_diam)
    matches = match_lesions(true_xyz, tol, det_xyz)
    by_true = {i: (j, d) for i, j, d in matches}
    matched_det = {j for _, j, _ in matches}

    covered = _covered(truth_b, true_xyz, true_diam)
    lesions = []
    for i, row in enumerate(true.itertuples(index=False)):
        entry: dict[str, Any] = {"id": _plain(row.id), "diameter_mm": float(true_diam[i]),
                                 "detected": i in by_true}
        if i in by_true:
            j, d = by_true[i]
            if "region" in det.columns and "region" in true.columns:
                name = str(det["region"].iloc[j])
                ok = covered[i] if covered else [str(row.region)]
                other = det["straddles"].iloc[j] if "straddles" in det.columns else ""
                named = [name] + [x.strip() for x in str(other).split(";")
                                  if isinstance(other, str) and x.strip()]
                entry.update(region_true=str(row.region), region=name, regions_covered=ok,
                             region_correct=straddle_match(name, named, str(row.region), ok),
                             region_centre_correct=name == str(row.region))
            entry.update(
                detection_row=j,
                localisation_error_mm=d,
                detected_diameter_mm=float(det_diam[j]),
                size_error_percent=100.0 * (det_diam[j] - true_diam[i]) / true_diam[i],
            )
        lesions.append(entry)

    by_diam: dict[str, dict[str, Any]] = {}
    step = cfg.lesion_diameter_step_mm
    for entry in lesions:
        key = f"{round(entry['diameter_mm'] / step) * step:g}"
        b = by_diam.setdefault(key, {"n": 0, "detected": 0})
        b["n"] += 1
        b["detected"] += int(entry["detected"])
    for b in by_diam.values():
        b["recall"] = b["detected"] / b["n"]

    loc = np.array([e["localisation_error_mm"] for e in lesions if e["detected"]])
    size = np.array([e["size_error_percent"] for e in lesions if e["detected"]])
    fp_rows = [j for j in range(len(det)) if j not in matched_det]
    regions = [e["region_correct"] for e in lesions if "region_correct" in e]
    out: dict[str, Any] = {
        "n_true": len(true),
        "n_detected": len(det),
        "n_matched": len(matches),
        "recall": len(matches) / len(true) if len(true) else None,
        "precision": len(matches) / len(det) if len(det) else None,
        "false_positives": len(fp_rows),
        "localisation_error_mm_mean": float(loc.mean()) if len(loc) else None,
        "localisation_error_mm_median": float(np.median(loc)) if len(loc) else None,
        "localisation_error_mm_max": float(loc.max()) if len(loc) else None,
        "size_error_percent_mean": float(size.mean()) if len(size) else None,
        "size_abs_error_percent_mean": float(np.abs(size).mean()) if len(size) else None,
        "average_precision": _average_precision(det, matched_det, len(true)),
        "region_accuracy": sum(regions) / len(regions) if regions else None,
        "region_centre_accuracy": (sum(e["region_centre_correct"] for e in lesions
                                       if "region_centre_correct" in e) / len(regions)
                                   if regions else None),
        "recall_by_diameter": by_diam,
        "lesions": lesions,
        "false_positive_rows": fp_rows,
    }
    log.info("%s: %d/%d lesions found, %d false positive(s)", changes_csv, len(matches), len(true),
             len(fp_rows))
    return out


def _average_precision(det: Any, matched: set[int], n_true: int) -> float | None:
    """Area under precision–recall when detections are ranked by their ``score`` column."""
    if "score" not in det.columns or n_true == 0 or len(det) == 0:
        return None
    scores = det["score"].to_numpy(np.float64)
    order = np.argsort(-scores, kind="stable")
    tp = np.array([j in matched for j in order], dtype=np.float64)
    cum_tp = np.cumsum(tp)
    precision = cum_tp / np.arange(1, len(tp) + 1)
    return float((precision * tp).sum() / n_true)


def seen_share(truth: Truth, xyz: np.ndarray, diameter_mm: np.ndarray) -> np.ndarray:
    """Share of each lesion's disc (centre ``xyz`` in the truth frame, ``diameter_mm``) that
    the frames of ``truth``'s session saw: its ``seen`` mask over the cone about the
    barycentre that the disc subtends, each pixel weighted by its wall area (cos elevation).

    A lesion of session B scored against session A's truth (the phantom's sessions share the
    world frame) says whether A filmed the site at all: a change on wall A never saw cannot be
    told from the wall A would have shown there. Approximate by the deformation between the
    sessions (a few mm at most) and at the poles of the grid."""
    seen = truth.seen
    h, w = seen.shape
    dirs = equirect_directions(h, w).reshape(-1, 3)
    weight = np.hypot(dirs[:, 0], dirs[:, 1])  # cos elevation: the wall area of each pixel
    flat = seen.reshape(-1)
    out = np.full(len(xyz), np.nan)
    for i, (p, d) in enumerate(zip(np.asarray(xyz, np.float64).reshape(-1, 3),
                                   np.asarray(diameter_mm, np.float64), strict=True)):
        v = p - truth.barycentre
        dist = float(np.linalg.norm(v))
        if dist <= 0 or d <= 0:
            continue
        inside = dirs @ (v / dist) >= np.cos(np.arctan2(d / 2.0, dist))
        total = float(weight[inside].sum())
        if total > 0:
            out[i] = float(weight[inside & flat].sum()) / total
    return out


def _plain(value: Any) -> Any:
    return value.item() if isinstance(value, np.generic) else value


def _covered(truth: Truth, xyz: np.ndarray, diam: np.ndarray) -> list[list[str]] | None:
    """The regions each true lesion covers in the true anatomical frame (None without it)."""
    meta = truth.meta.get("anatomy") if isinstance(truth.meta, dict) else None
    if not meta or not len(xyz):
        return None
    return covered_regions(Anatomy.from_json(meta), xyz, diam)
