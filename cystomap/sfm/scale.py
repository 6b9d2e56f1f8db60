"""Metric scale of a model from the bladder's known size (largest extent or volume).

Both measures are rotation invariant: the extent is the largest distance between two inlier
wall points (found among the vertices of their convex hull), the volume is that of the convex
hull of the inlier points, or of a star-shaped estimate around their centroid. Inliers are
the points that survive a statistical outlier removal, each averaged with its nearest
neighbours (which removes the outward bias that depth noise gives the largest distance).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Scale:
    factor: float  # model units -> mm; 1.0 when unknown
    source: str  # "extent_mm", "volume_ml" or "none"
    metric: bool
    model_extent: float | None  # before scaling, model units
    model_volume: float | None  # before scaling, model units^3
    inlier_points: int
    total_points: int
    cross_check: dict[str, float]  # the other measure's factor, when both are known

    def to_dict(self) -> dict[str, Any]:
        return {
            "factor": self.factor, "source": self.source, "metric": self.metric,
            "units": "mm" if self.metric else "arbitrary",
            "model_extent": self.model_extent, "model_volume": self.model_volume,
            "inlier_points": self.inlier_points, "total_points": self.total_points,
            **({"cross_check": self.cross_check} if self.cross_check else {}),
        }


def inlier_points(xyz: np.ndarray, cfg: SfmConfig) -> np.ndarray:
    """Statistical outlier removal: drop points whose mean distance to their neighbours is
    more than ``outlier_std_ratio`` standard deviations above the mean of all points."""
    from scipy.spatial import cKDTree

    k = min(cfg.outlier_neighbors, len(xyz) - 1)
    if k < 2:
        return xyz
    dist, _ = cKDTree(xyz).query(xyz, k=k + 1)
    mean = dist[:, 1:].mean(axis=1)
    keep = mean <= mean.mean() + cfg.outlier_std_ratio * mean.std()
    return xyz[keep]


def smooth_points(xyz: np.ndarray, k: int) -> np.ndarray:
    """Each point replaced by the mean of its ``k`` nearest points (itself included).

    Depth noise of the points lies mostly along the viewing rays, i.e. across the wall, and
    pushes the largest distance between two points outwards; averaging neighbours along the
    wall removes most of that bias (and shrinks a curved wall only slightly)."""
    from scipy.spatial import cKDTree

    k = min(k, len(xyz))
    if k < 2:
        return xyz
    _, idx = cKDTree(xyz).query(xyz, k=k)
    return xyz[idx].mean(axis=1)


def max_extent(xyz: np.ndarray) -> float:
    """Largest pairwise distance (via the convex hull's vertices)."""
    from scipy.spatial import ConvexHull
    from scipy.spatial.distance import pdist

    if len(xyz) < 2:
        return 0.0
    try:
        pts = xyz[ConvexHull(xyz).vertices]
    except Exception:  # flat or degenerate cloud: fall back to all points
        pts = xyz
    return float(pdist(pts).max())


def hull_volume(xyz: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    try:
        return float(ConvexHull(xyz).volume)
    except Exception:
        return 0.0


def star_volume(xyz: np.ndarray, n_el: int = 12, n_az: int = 24) -> float:
    """Volume of the star-shaped body whose radius per direction bin (about the centroid) is
    the median radius of the points in that bin; empty bins take the overall median."""
    c = xyz.mean(axis=0)
    v = xyz - c
    r = np.linalg.norm(v, axis=1)
    ok = r > 0
    v, r = v[ok], r[ok]
    if not len(r):
        return 0.0
    el = np.arccos(np.clip(v[:, 2] / r, -1, 1))
    az = np.arctan2(v[:, 1], v[:, 0]) + math.pi
    # equal-area bins in cos(elevation)
    ie = np.minimum(((1 - np.cos(el)) / 2 * n_el).astype(int), n_el - 1)
    ia = np.minimum((az / (2 * math.pi) * n_az).astype(int), n_az - 1)
    key = ie * n_az + ia
    fallback = float(np.median(r))
    solid = 4 * math.pi / (n_el * n_az)
    vol = 0.0
    for b in range(n_el * n_az):
        rb = r[key == b]
        rad = float(np.median(rb)) if len(rb) else fallback
        vol += solid * rad**3 / 3
    return vol


def estimate_scale(
    xyz: np.ndarray, cfg: SfmConfig, extent_mm: float | None, volume_ml: float | None
) -> Scale:
    total = len(xyz)
    inl = inlier_points(xyz, cfg) if total >= 4 else xyz
    if cfg.scale_smooth_neighbors > 1:
        inl = smooth_points(inl, cfg.scale_smooth_neighbors)
    extent = max_extent(inl) if len(inl) >= 2 else None
    volume = None
    if len(inl) >= 4:
        volume = star_volume(inl) if cfg.volume_method == "star" else hull_volume(inl)
    f_ext = extent_mm / extent if extent_mm and extent else None
    f_vol = math.cbrt(volume_ml * 1000.0 / volume) if volume_ml and volume else None
    cross: dict[str, float] = {}
    if f_ext is not None:
        factor, source = f_ext, "extent_mm"
        if f_vol is not None:
            cross = {"volume_ml_factor": f_vol, "relative_difference": f_vol / f_ext - 1}
    elif f_vol is not None:
        factor, source = f_vol, "volume_ml"
    else:
        factor, source = 1.0, "none"
        if extent_mm or volume_ml:
            log.warning("scale: the model has too few points to measure; units stay arbitrary")
    if cross and abs(cross["relative_difference"]) > 0.1:
        log.warning("scale: extent and volume disagree by %.0f %%",
                    100 * cross["relative_difference"])
    metric = source != "none"
    log.info("scale: factor %.5g from %s (%d of %d points are inliers)",
             factor, source, len(inl), total)
    return Scale(factor, source, metric, extent, volume, len(inl), total, cross)


def apply_scale(rec: Any, factor: float) -> None:
    import pycolmap

    if factor != 1.0:
        rec.transform(pycolmap.Sim3d(factor, pycolmap.Rotation3d(), np.zeros(3)))
