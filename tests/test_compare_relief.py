"""A raised change's centroid on session B's points (cystomap.compare.relief), on a synthetic
sphere: a dome of points stands out of a smooth wall the mesh does not follow."""

from __future__ import annotations

import numpy as np

from cystomap.atlas.projection import SurfaceRays
from cystomap.compare.relief import CORE_SHARE, MIN_POINTS, PointHeights, lift_centroid
from cystomap.mesh import icosphere

RADIUS = 40.0  # mm, the wall's
NOISE = 0.15  # mm, the points' scatter about it
DOME_R, DOME_H = 8.0, 4.0  # mm, a papillary lesion's outline radius and height


def _scene(seed: int) -> tuple[np.ndarray, SurfaceRays, np.ndarray]:
    """Points on a sphere (``NOISE`` mm scatter), raised into the cavity by a dome
    h = DOME_H (1 - s^2)^2 about +z; the mesh: the sphere itself (the smooth fit)."""
    rng = np.random.default_rng(seed)
    v, f = icosphere(5)
    v = v / np.linalg.norm(v, axis=1, keepdims=True) * RADIUS
    u = rng.normal(size=(40000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    s = np.arccos(np.clip(u[:, 2], -1, 1)) * RADIUS / DOME_R
    h = DOME_H * np.clip(1 - s ** 2, 0, None) ** 2
    pts = u * (RADIUS - h + rng.normal(0, NOISE, len(u)))[:, None]
    return pts, SurfaceRays(v, f), np.zeros(3)


def test_a_raised_lesions_centroid_moves_to_its_top() -> None:
    pts, rays, bary = _scene(0)
    heights = PointHeights(pts, bary, rays)
    base = rays.cast(bary, np.array([[0.0, 0.0, 1.0]]))[0][0] * np.array([0.0, 0.0, 1.0])
    top = np.array([0.0, 0.0, RADIUS - DOME_H])
    c, res = lift_centroid(heights, base, DOME_R, CORE_SHARE, MIN_POINTS, 3.0)
    assert res.raised
    # the core's median: 3.42-3.54 mm of the top's 4 (seeds 0-3), the lifted centroid 0.46-0.58 mm
    # from the top
    assert np.linalg.norm(c - top) < 0.8, (c, top, res)
    assert np.linalg.norm(base - top) > 3.5  # the mesh's centroid was the base


def test_flat_wall_and_off_dome_centroids_stay_on_the_mesh() -> None:
    pts, rays, bary = _scene(1)
    heights = PointHeights(pts, bary, rays)
    for d in ([1.0, 0.0, 0.0], [0.0, -0.6, -0.8], [0.0, 0.0, -1.0]):
        d = np.asarray(d) / np.linalg.norm(d)
        on_mesh = rays.cast(bary, d[None])[0][0] * d
        for radius in (2.5, 5.0, 12.0):
            c, res = lift_centroid(heights, on_mesh, radius, CORE_SHARE, MIN_POINTS, 3.0)
            assert not res.raised, (d, radius, res)
            assert np.array_equal(c, on_mesh)


def test_too_few_points_leave_the_centroid_alone() -> None:
    _, rays, bary = _scene(2)
    heights = PointHeights(np.array([[0.0, 0.0, 35.0], [0.0, 0.1, 35.0]]), bary, rays)
    base = np.array([0.0, 0.0, RADIUS])
    c, res = lift_centroid(heights, base, DOME_R, CORE_SHARE, MIN_POINTS, 3.0)
    assert not res.raised and res.n_core < MIN_POINTS
    assert np.array_equal(c, base)
