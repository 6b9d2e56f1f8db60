"""Scores of a session's anatomical frame (atlas.json ``anatomy``) against the phantom's."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cystomap.anatomy import Anatomy
from cystomap.evaluate.trajectory import Sim3
from cystomap.evaluate.truth import Truth


def score_anatomy(truth: Truth, atlas_meta: dict[str, Any], sim3: Sim3) -> dict[str, Any] | None:
    """Neck direction error, roll error (degrees) and the region of each true lesion.

    The estimated frame is taken into the truth frame by ``sim3`` (model → truth). The roll
    error is the signed angle, about the true dome axis (clockwise seen from the neck), from
    the true anterior to the estimated anterior made orthogonal to the true neck. Lesions
    (lesions.csv with a ``region`` column) are taken into the model frame and located in the
    estimated frame: ``regions_correct`` counts those whose region matches the truth's.
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
        rows = []
        for i, r in enumerate(lesions.itertuples(index=False)):
            dh = (hours[i] - true_hours[i] + 6) % 12 - 6
            rows.append({"id": int(r.id), "region_true": str(r.region),
                         "region": str(est_regions[i]), "correct": str(r.region) == est_regions[i],
                         "clock_error_h": float(dh)})
        out.update(regions_correct=sum(r["correct"] for r in rows), regions_n=len(rows),
                   regions_accuracy=sum(r["correct"] for r in rows) / len(rows), lesions=rows)
    return out
