"""Similarity transforms p' = scale · R p + t and their least-squares fit (Umeyama 1991).

The one Sim(3) of the pipeline: compare co-registers two sessions with it (inside MSAC, see
:mod:`cystomap.compare.registration`), the evaluation brings a model into the truth frame.
The fit is numpy's SVD (pycolmap's Sim3d estimator would change the figures bit for bit, and
compare's MSAC needs the plain least-squares fit of 3-point samples anyway).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """p' = scale · R p + t."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    def apply(self, p: np.ndarray) -> np.ndarray:
        return self.scale * (np.asarray(p, float) @ self.rotation.T) + self.translation

    def inverse(self) -> Similarity:
        rt = self.rotation.T
        return Similarity(rt, -(rt @ self.translation) / self.scale, 1.0 / self.scale)

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def to_dict(self) -> dict[str, Any]:
        """Scale, rotation and translation (the evaluation's Sim(3) JSON)."""
        return {"scale": float(self.scale), "rotation": self.rotation.tolist(),
                "translation": self.translation.tolist()}

    def to_json(self) -> dict[str, Any]:
        return {"scale": self.scale, "rotation": self.rotation.tolist(),
                "translation": self.translation.tolist(), "matrix_4x4": self.matrix().tolist(),
                "convention": "p_B = scale * rotation @ p_A + translation"}


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Similarity | None:
    """Least-squares similarity src → dst (Umeyama 1991); None when degenerate."""
    if len(src) < 3:
        return None
    ms, md = src.mean(0), dst.mean(0)
    xs, xd = src - ms, dst - md
    var = float((xs ** 2).sum() / len(src))
    if var <= 1e-12:
        return None
    cov = xd.T @ xs / len(src)
    u, s, vt = np.linalg.svd(cov)
    d = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2, 2] = -1
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(s) @ d) / var) if with_scale else 1.0
    if not (scale > 0 and math.isfinite(scale)):
        return None
    return Similarity(rot, md - scale * rot @ ms, scale)
