"""The neck's cap measured by :func:`cystomap.compare.neck.chroma_band` on a synthetic sphere.

A 40 mm sphere seen from its centre, the neck at its bottom; the colour significance of the
compared wall is noise of the wall's level, far above it over the cap (the opening, whose
texture differs between sessions), a little above it in the band around the cap (the wall
filmed at grazing angles), and far above it over a lesion beside the cap.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from cystomap.atlas.projection import Projection, SurfaceRays
from cystomap.compare import neck
from cystomap.compare.difference import wall_grid

RADIUS = 40.0
CAP_DEG = 12.0


@pytest.fixture(scope="module")
def sphere():
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=60)
    rays = SurfaceRays(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    width = round(2 * math.pi * RADIUS / 0.5)
    return wall_grid(Projection("equirectangular", width, width // 2), rays)


def _significance(grid, lesion_mm: float, lesion_deg: float) -> SimpleNamespace:
    """What chroma_band reads of a Difference: noise (|N(0, 1)|, seeded) times 25 within
    ``CAP_DEG`` of the neck, 1.8 out to 45°, 1 beyond; 60 over a lesion of ``lesion_mm``
    centred ``lesion_deg`` from the neck (0 mm: none)."""
    rng = np.random.default_rng(5)
    pts = np.nan_to_num(grid.points)
    ang = np.degrees(np.arccos(np.clip(-pts[..., 2] / RADIUS, -1, 1)))
    level = np.where(ang < CAP_DEG, 25.0, np.where(ang < 45.0, 1.8, 1.0))
    sig_c = np.abs(rng.normal(size=grid.shape)) * level
    if lesion_mm:
        el = math.radians(lesion_deg - 90.0)
        centre = RADIUS * np.array([math.cos(el), 0.0, math.sin(el)])
        sig_c[np.linalg.norm(pts - centre, axis=-1) < lesion_mm / 2] = 60.0
    bright = np.abs(rng.normal(size=grid.shape))
    return SimpleNamespace(significance=sig_c.astype(np.float32), joint=grid.hit.copy(),
                           significance_colour=sig_c.astype(np.float32),
                           brightness=bright.astype(np.float32))


@pytest.mark.parametrize("lesion_mm", [0.0, 26.0])
def test_the_cap_ends_where_the_wall_is_quiet_whatever_lies_beside_it(sphere, lesion_mm,
                                                                      monkeypatch) -> None:
    """The cap reaches to the first quiet ring beyond the noisy opening (12° here), with or
    without a 26 mm lesion beside it (centred 32° from the neck: 13-51°, most of the rings'
    width in the noisy band). Each ring's level is the median of its sectors' levels: the
    lesion fills a few sectors. Measured: 14.3° both. With one sector (the ring's median
    over all its wall, the previous rule) the lesion's rings look like cap and the cap
    grows over the lesion (43.0°), cutting most of it out."""
    grid = sphere
    opening = np.array([[0.0, 0.0, -1.0]])
    diff = _significance(grid, lesion_mm, 32.0)
    _, cap, _, info = neck.chroma_band(diff, grid, opening, 2.0)
    assert CAP_DEG < cap < CAP_DEG + 2 * info["ring_deg"] + 0.01, info
    if lesion_mm:
        monkeypatch.setattr(neck, "SECTORS", 1)
        _, whole, _, info = neck.chroma_band(diff, grid, opening, 2.0)
        assert whole > 30.0, info
