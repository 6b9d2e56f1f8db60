"""Scores of a session's anatomical frame (atlas.json ``anatomy``) against the phantom's."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cystomap.anatomy import DOME_CAP_DEG, NECK_CAP_DEG, WALL_SECTORS, Anatomy, covered_regions
from cystomap.evaluate.trajectory import Sim3
from cystomap.evaluate.truth import Truth


def score_anatomy(truth: Truth, atlas_meta: dict[str, Any], sim3: Sim3) -> dict[str, Any] | None:
    """Neck direction error, roll error (degrees) and the region of each true lesion.

    The estimated frame is taken into the truth frame by ``sim3`` (model → truth). The roll
    error is the signed angle, about the true dome axis (clockwise seen from the neck), from
    the true anterior to the estimated anterior made orthogonal to the true neck. Lesions
    (lesions.csv with a ``region`` column) are taken into the model frame and located in the
    estimated frame. Region rule (:data:`cystomap.anatomy.STRADDLE_RULE`, :func:`straddle_match`):
    a lesion is named by the region of its centre; one whose disc (``diameter_mm``) crosses a
    region border straddles it, in the true frame or in the estimated one (where changes.csv
    says so in ``straddles``), and is right when the two sides' regions meet.
    ``regions_correct`` counts the lesions named right by that rule, ``regions_centre_correct``
    those whose centre's region is the truth's (the strict count), ``regions_straddling``
    those that straddle a border; per lesion ``border_mm`` is how far (on the wall, about) its
    centre lies from the nearest border in the true frame.
    """
    if "anatomy" not in atlas_meta or "anatomy" not in truth.meta:
        return None
    est = Anatomy.from_json(atlas_meta["anatomy"])
    true = Anatomy.from_json(truth.meta["anatomy"])
    neck = est.neck @ sim3.rotation.T
    ant = est.anterior @ sim3.rotation.T
    neck_err = math.degrees(math.acos(float(np.clip(neck @ true.neck, -1, 1))))
    a = ant - (ant @ true.neck) * true.neck
    roll = math.degrees(math.atan2(float(a @ true.left), float(a @ true.anterior)))
    origin = sim3.apply(est.origin[None])[0]
    out: dict[str, Any] = {"neck_error_deg": neck_err, "roll_error_deg": roll,
                           "roll_abs_error_deg": abs(roll),
                           "origin_error_mm": float(np.linalg.norm(origin - true.origin)),
                           "source": est.source}
    try:
        lesions = truth.lesions
    except Exception:
        return out
    if len(lesions) and "region" in lesions.columns:
        xyz = lesions[["x", "y", "z"]].to_numpy(np.float64).reshape(-1, 3)
        est_regions = est.regions(sim3.inverse().apply(xyz))
        hours, _ = est.clock_polar(sim3.inverse().apply(xyz))
        true_hours, _ = true.clock_polar(xyz)
        diam = (lesions["diameter_mm"].to_numpy(np.float64) if "diameter_mm" in lesions.columns
                else np.zeros(len(lesions)))
        covered = covered_regions(true, xyz, diam)
        named = covered_regions(est, sim3.inverse().apply(xyz), diam / sim3.scale)
        margin = border_distance(true, xyz)
        rows = []
        for i, r in enumerate(lesions.itertuples(index=False)):
            dh = (hours[i] - true_hours[i] + 6) % 12 - 6
            name = str(est_regions[i])
            rows.append({"id": int(r.id), "region_true": str(r.region),
                         "regions_covered": covered[i], "straddles": len(covered[i]) > 1,
                         "region": name, "straddles_named": named[i][1:],
                         "correct": straddle_match(name, named[i], str(r.region), covered[i]),
                         "centre_correct": str(r.region) == name, "clock_error_h": float(dh),
                         "border_mm": float(margin[i]), "diameter_mm": float(diam[i])})
        n_ok = sum(r["correct"] for r in rows)
        out.update(regions_correct=n_ok, regions_n=len(rows), regions_accuracy=n_ok / len(rows),
                   regions_centre_correct=sum(r["centre_correct"] for r in rows),
                   regions_straddling=sum(r["straddles"] for r in rows), lesions=rows)
    return out


def border_distance(anatomy: Anatomy, points: np.ndarray) -> np.ndarray:
    """About how far (model units, on the wall) each point lies from its region's nearest
    border: the angle to the nearest border (polar caps and, between them, the clock
    sectors' meridians) times the point's distance from the origin."""
    hours, polar = anatomy.clock_polar(points)
    r = np.linalg.norm(np.asarray(points, np.float64) - anatomy.origin, axis=1)
    caps = np.minimum(np.abs(polar - NECK_CAP_DEG), np.abs(polar - (180.0 - DOME_CAP_DEG)))
    starts = np.array([s for _, s, _ in WALL_SECTORS])
    dh = np.abs((hours[:, None] - starts[None] + 6.0) % 12.0 - 6.0).min(axis=1)
    wall = (polar >= NECK_CAP_DEG) & (polar <= 180.0 - DOME_CAP_DEG)
    meridian = np.where(wall, np.degrees(np.arcsin(np.clip(
        np.sin(np.radians(dh * 30.0)) * np.sin(np.radians(polar)), -1, 1))), np.inf)
    return np.radians(np.minimum(caps, meridian)) * r


def straddle_match(name: str, named: list[str], true_name: str, covered: list[str]) -> bool:
    """Whether a patch named ``name`` (covering ``named``: its region first, then those it
    straddles, as the pipeline reports them) is the lesion of region ``true_name`` covering
    ``covered`` (in the true frame): the named region is one the lesion covers, or the
    lesion's region is one the pipeline says the patch straddles. A patch inside one region
    on both sides must have the lesion's region."""
    return name in covered or true_name in named
