"""A change's centroid on the wall as session B's 3-D points see it, not as the mesh does.

The mesh is a smooth robust fit to the sparse cloud (:mod:`cystomap.mesh`): it runs under a
raised lesion (a papillary tumour several millimetres high) as under any other bump, so a
region's centroid cast onto the mesh lies at the lesion's base, millimetres below its top.
The SfM points on the lesion do not: they sit on it. For each region, the points seen from the
barycentre within a small cone about the centroid's direction (``core`` times the region's
radius, widened until it holds ``min_points`` points, at most to the whole region) give the
wall's height over the mesh there (their median radial offset into the cavity), and the points
of a ring about the region (1.5 to 2.5 radii) how far the points scatter about the mesh where
nothing is raised. The centroid moves onto the points only where the core's median stands out
of that scatter (``z`` standard errors of a median); elsewhere (a flat lesion, a scar) it stays
on the mesh. Neither the mesh, the atlas nor the region's outline changes: only where its
centre is said to be.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from cystomap.atlas.projection import SurfaceRays

log = logging.getLogger(__name__)

#: 1.4826 MAD = sigma of a normal; 1.2533 sigma / sqrt(n) = standard error of a median
_MAD_SIGMA = 1.4826
_MEDIAN_SE = 1.2533


@dataclass(frozen=True)
class Lift:
    """A region's height over the mesh at its centroid (mm, into the cavity) and its test."""

    height: float  # median offset of the core's points (0 when too few)
    noise: float  # standard error of that median, from the ring's scatter
    n_core: int
    raised: bool  # height - ring's median > z * noise


class PointHeights:
    """Session B's 3-D points as radial offsets from its mesh, seen from the barycentre."""

    def __init__(self, points: np.ndarray, barycentre: np.ndarray, rays: SurfaceRays,
                 threads: int = 1) -> None:
        from scipy.spatial import cKDTree

        self.barycentre = np.asarray(barycentre, dtype=np.float64)
        v = np.asarray(points, dtype=np.float64).reshape(-1, 3) - self.barycentre
        r = np.linalg.norm(v, axis=1)
        ok = r > 1e-9
        u = v[ok] / r[ok, None]
        t, _ = rays.cast(self.barycentre, u)
        hit = np.isfinite(t)
        self.dirs = u[hit]
        self.offset = (t - r[ok])[hit]  # > 0: the point lies inside the mesh (into the cavity)
        self.tree = cKDTree(self.dirs) if len(self.dirs) else None
        self.threads = max(1, threads)

    def _within(self, d: np.ndarray, angle: float) -> np.ndarray:
        if self.tree is None:
            return np.zeros(0, np.int64)
        chord = 2.0 * math.sin(min(angle, math.pi) / 2.0)
        return np.asarray(self.tree.query_ball_point(d, chord, workers=self.threads), np.int64)

    def lift(self, direction: np.ndarray, distance: float, radius_mm: float, core: float,
             min_points: int, z: float) -> Lift:
        """The wall's height over the mesh along unit ``direction`` (the mesh at ``distance``
        from the barycentre), for a region of equivalent radius ``radius_mm``."""
        d = np.asarray(direction, dtype=np.float64)
        ang = radius_mm / max(distance, 1e-9)  # the region's angular radius
        frac = core
        while True:
            idx = self._within(d, frac * ang)
            if len(idx) >= min_points or frac >= 1.0:
                break
            frac = min(1.0, frac * 1.5)
        inner, outer = self._within(d, 1.5 * ang), self._within(d, 2.5 * ang)
        ring = np.setdiff1d(outer, inner, assume_unique=True)
        if len(idx) < min_points or len(ring) < min_points:
            return Lift(0.0, math.inf, len(idx), False)
        height = float(np.median(self.offset[idx]))
        ring_off = self.offset[ring]
        ring_med = float(np.median(ring_off))
        sigma = _MAD_SIGMA * float(np.median(np.abs(ring_off - ring_med)))
        noise = _MEDIAN_SE * sigma / math.sqrt(len(idx))
        return Lift(height, noise, len(idx), height - ring_med > z * noise and height > 0)


def lift_centroid(heights: PointHeights, centroid: np.ndarray, radius_mm: float, core: float,
                  min_points: int, z: float) -> tuple[np.ndarray, Lift]:
    """``centroid`` (on the mesh) moved along its direction from the barycentre onto the
    points where the wall there is raised (:meth:`PointHeights.lift`), else unchanged."""
    v = np.asarray(centroid, dtype=np.float64) - heights.barycentre
    dist = float(np.linalg.norm(v))
    d = v / max(dist, 1e-12)
    res = heights.lift(d, dist, radius_mm, core, min_points, z)
    if not res.raised:
        return np.asarray(centroid, dtype=np.float64), res
    return heights.barycentre + (dist - res.height) * d, res


#: the core cone's radius as a share of the region's (a dome's height at 0.35 of its radius
#: is 0.77 of its top's; the median over the cone about 0.9) and the fewest points a median
#: is taken of
CORE_SHARE = 0.35
MIN_POINTS = 5


def raise_centroids(regions: list[Any], points: np.ndarray, barycentre: np.ndarray,
                    rays: SurfaceRays, cfg: Any) -> list[Any]:
    """``regions`` (:class:`cystomap.compare.changes.Region`, session B's frame) with the
    centroids of raised ones moved onto B's 3-D ``points`` (those the compare stage's track and
    error filters keep; ``relief_mm`` set); ``cfg``: CompareConfig (``relief_z``, ``threads``)."""
    if cfg.relief_z <= 0 or not regions:
        return regions
    heights = PointHeights(points, barycentre, rays, cfg.threads)
    out = []
    for g in regions:
        c = np.array([g.x, g.y, g.z], dtype=np.float64)
        c2, res = lift_centroid(heights, c, g.diameter_mm / 2, CORE_SHARE, MIN_POINTS,
                                cfg.relief_z)
        if res.raised:
            log.info("compare: change at %s (%.1f mm) is raised %.1f mm over the mesh (median "
                     "of %d points, %.0f standard errors): its centroid is put on them",
                     np.round(c, 1).tolist(), g.diameter_mm, res.height, res.n_core,
                     res.height / max(res.noise, 1e-12))
            g = replace(g, x=float(c2[0]), y=float(c2[1]), z=float(c2[2]),
                        relief_mm=res.height)
        out.append(g)
    return out
