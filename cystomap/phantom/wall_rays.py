"""Rays from inside the phantom onto its wall: hit points (world and material), the wall's
distance per direction (:class:`RadiusTable`). Casting is :func:`cystomap.geometry.raycast.cast_rays`."""

from __future__ import annotations

import numpy as np

from cystomap.geometry.raycast import cast_rays as cast
from cystomap.phantom.geometry import Bladder, unit

__all__ = ["RadiusTable", "cast", "interpolate_hit", "surface_points"]


class RadiusTable:
    """Wall distance from the session-1 barycentre per direction (equirectangular, bilinear)."""

    def __init__(self, scene, centre: np.ndarray, res_deg: float = 0.5) -> None:
        self.res = res_deg
        self.w = round(360 / res_deg)
        self.h = round(180 / res_deg)
        az = -180 + (np.arange(self.w) + 0.5) * res_deg
        el = 90 - (np.arange(self.h) + 0.5) * res_deg
        from cystomap.phantom.geometry import direction

        d = direction(az[None, :], el[:, None]).reshape(-1, 3)
        t = cast(scene, np.broadcast_to(centre, d.shape), d)["t_hit"]
        t = np.where(np.isfinite(t), t, np.nan).reshape(self.h, self.w)
        fill = np.nanmedian(t)
        self.table = np.where(np.isfinite(t), t, fill).astype(np.float32)

    def __call__(self, d: np.ndarray) -> np.ndarray:
        d = unit(np.asarray(d, np.float64))
        az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
        el = np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))
        x = (az + 180) / self.res - 0.5
        y = (90 - el) / self.res - 0.5
        x0 = np.floor(x).astype(int)
        y0 = np.clip(np.floor(y).astype(int), 0, self.h - 2)
        fx, fy = x - x0, np.clip(y - y0, 0, 1)
        xa, xb = x0 % self.w, (x0 + 1) % self.w
        tb = self.table
        top = tb[y0, xa] * (1 - fx) + tb[y0, xb] * fx
        bot = tb[y0 + 1, xa] * (1 - fx) + tb[y0 + 1, xb] * fx
        return top * (1 - fy) + bot * fy


def surface_points(scene, bladder: Bladder, origin: np.ndarray, dirs: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hit of rays from ``origin``: (world point, material point, wall?) — misses → NaN."""
    hit = cast(scene, np.broadcast_to(origin, dirs.shape), dirs)
    return interpolate_hit(bladder, hit)


def interpolate_hit(bladder: Bladder, hit: dict[str, np.ndarray], with_normals: bool = False):
    """World point, material point (and vertex normal) at ray hits by barycentric interpolation."""
    t = hit["t_hit"]
    ok = np.isfinite(t)
    pid = np.where(ok, hit["primitive_ids"], 0).astype(np.int64)
    uv = hit["primitive_uvs"].astype(np.float64)
    w = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], -1)
    tri = bladder.triangles[pid]
    world = np.einsum("nk,nkc->nc", w, bladder.vertices[tri])
    material = np.einsum("nk,nkc->nc", w, bladder.material[tri])
    world[~ok] = np.nan
    material[~ok] = np.nan
    wall = ok & (pid < bladder.n_wall_tris)
    if with_normals:
        nrm = unit(np.einsum("nk,nkc->nc", w, bladder.normals[tri]))
        nrm[~ok] = np.nan
        return world, material, wall, nrm
    return world, material, wall
