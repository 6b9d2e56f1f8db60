"""Local relief on top of the mesh stage's smooth radial fit.

The radial fit (:mod:`cystomap.mesh`) keeps the wall smooth at the scale of a spherical-harmonic
degree of about ``smooth_degree`` and gives no weight to points farther from it than
``reject_k`` robust standard deviations. Both are right for noise and wrong for a raised
lesion: a papillary tumour of 20 mm stands up to 6 mm into the cavity, its SfM points all lie
far inside the smooth surface, and the fit drew the wall under it (measured on FROC pair 229:
the mesh 5.4 mm under the dome's top, whose SfM points lay within 0.7 mm of it). The 3-D model
then has no tumour, the atlas paints the dome's texture onto the wall beneath, and a change's
centroid lies as far from the lesion as the dome is tall.

The relief is what the fit rejected but the points agree on. Around each direction of the
icosphere (within two of its vertex spacings) the median of the points' residuals against the
smooth surface (every filtered point, not the voxel means the fit uses: a dome's top holds
few); where it lies beyond the fit's own rejection level (``reject_k`` times the residuals'
robust standard deviation) into the cavity, with at least ``min_points`` points, that
neighbourhood is relief. Over it and one more neighbourhood around it (so the surface returns
to the smooth wall where the residuals do, without a step) the surface moves by the residuals'
median weighted by a Gaussian of half a vertex spacing, in ``passes`` steps (the surface is
interpolated between vertices, so a narrow top needs more than one); directions there with
too few points of their own take their neighbours' mean. Elsewhere the smooth fit is kept.
Isolated outliers, and noise however strong, move no median that far. Outwards it is left
alone: there the coherent residuals are the openings (the neck into the urethra, the
ureteric orifices), which the closed surface is meant to bridge.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from cystomap.geometry.sphere import direction_weights, vertex_adjacency
from cystomap.stats import weighted_median

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Relief:
    offset: np.ndarray  # (V,) radial offset per icosphere vertex (negative: into the cavity)
    sigma: float  # robust standard deviation of the residuals
    level: float  # |median residual| beyond which a neighbourhood is relief
    vertices: int  # icosphere vertices that moved
    max_inward: float  # the largest offset into the cavity (>= 0)
    max_outward: float  # the largest offset outwards (>= 0)

    def info(self) -> dict[str, float | int]:
        return {"vertices": self.vertices, "level": self.level, "residual_sigma": self.sigma,
                "max_inward": self.max_inward, "max_outward": self.max_outward}


def local_relief(points: np.ndarray, centre: np.ndarray, sphere_v: np.ndarray,
                 sphere_f: np.ndarray, radii: np.ndarray, reject_k: float,
                 min_points: int = 5, passes: int = 3) -> Relief:
    """The relief of ``points`` against the smooth surface ``centre + radii * sphere_v``."""
    from scipy.spatial import cKDTree

    rel = points - centre
    r_obs = np.linalg.norm(rel, axis=1)
    ok = r_obs > 0
    dirs, r_obs = rel[ok] / r_obs[ok, None], r_obs[ok]
    interp = direction_weights(dirs, sphere_v, sphere_f)
    res = r_obs - interp @ radii
    sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))
    level = reject_k * sigma
    offset = np.zeros(len(sphere_v))
    if len(res) < min_points or sigma <= 0:
        return Relief(offset, sigma, level, 0, 0.0, 0.0)
    # two vertex spacings of the icosphere, as a chord on the unit sphere
    # (the median over two sides of every triangle: what the FROC figures were measured with)
    e = np.concatenate([sphere_f[:, [0, 1]], sphere_f[:, [1, 2]]])
    spacing = float(np.median(np.linalg.norm(sphere_v[e[:, 0]] - sphere_v[e[:, 1]], axis=1)))
    radius = 2.0 * spacing
    near = cKDTree(dirs).query_ball_point(sphere_v, radius)
    count = np.array([len(n) for n in near])
    has = count >= min_points
    median = np.zeros(len(sphere_v))
    for v in np.flatnonzero(has):
        median[v] = np.median(res[near[v]])
    relief = median < -level  # into the cavity only
    if not relief.any():
        return Relief(offset, sigma, level, 0, 0.0, 0.0)
    # the relief's neighbourhoods and one more around them follow the points
    grown = np.zeros(len(sphere_v), bool)
    for idx in cKDTree(sphere_v).query_ball_point(sphere_v[relief], radius):
        grown[idx] = True
    adj = vertex_adjacency(sphere_f, len(sphere_v))
    deg = np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1)
    for _ in range(passes):
        # the height at each direction: the residuals' median weighted by a Gaussian of half
        # a vertex spacing (the plain median over the neighbourhood averages a dome's top with
        # its flanks); the surface moves by it, and again by what is left (a surface
        # interpolated between vertices reaches a narrow top in a few steps)
        res = r_obs - interp @ (radii + offset)
        step = np.zeros(len(sphere_v))
        for v in np.flatnonzero(grown & has):
            idx = np.asarray(near[v])
            g = np.exp(-0.5 * (np.linalg.norm(dirs[idx] - sphere_v[v], axis=1)
                               / (0.5 * spacing)) ** 2)
            step[v] = weighted_median(res[idx], g)
        # directions of the relief without points of their own take their neighbours' mean
        # (a harmonic fill: no hole where a dome's top has few triangulated points)
        fill = grown & ~has
        for _ in range(100 if fill.any() else 0):
            step[fill] = (adj @ step)[fill] / deg[fill]
        offset = np.minimum(offset + step, 0.0)
    moved = offset != 0
    return Relief(offset, sigma, level, int(moved.sum()),
                  float(max(0.0, -offset.min())), float(max(0.0, offset.max())))


def relief_summary(relief: Relief, mean_radius: float) -> str:
    """One log line."""
    share = relief.vertices / max(len(relief.offset), 1)
    return (f"local relief: {relief.vertices} of {len(relief.offset)} directions "
            f"({100 * share:.1f} %) beyond {relief.level:.3g} (reject_k x sigma "
            f"{relief.sigma:.3g}); up to {relief.max_inward:.3g} into the cavity, "
            f"{relief.max_outward:.3g} outwards (mean radius {mean_radius:.3g})")

