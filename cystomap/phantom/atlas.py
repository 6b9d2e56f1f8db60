"""Ground-truth atlases: equirectangular albedo and seen mask about the session barycentre.

Grid: ``height`` rows x ``2 * height`` columns; column j → azimuth -180 + (j + 0.5) * 360 / W
(degrees, left to right), row i → elevation 90 - (i + 0.5) * 180 / H (top to bottom); the
direction of (az, el) is (cos el cos az, cos el sin az, sin el) in world axes. Each pixel
shows the first wall point hit by the ray from the barycentre in that direction; directions
through the aperture (into the urethra) are not wall: black in albedo.png, 0 in seen.png.
"""

from __future__ import annotations

import numpy as np

from cystomap.camera import Camera
from cystomap.phantom.cubemap import CubeMap
from cystomap.phantom.geometry import Bladder, az_el, direction
from cystomap.phantom.render import project_points, rotate
from cystomap.phantom.wall_rays import cast, interpolate_hit

BLOCK = 16


class Atlas:
    def __init__(self, bladder: Bladder, scene, height: int) -> None:
        self.h, self.w = height, 2 * height
        az = -180 + (np.arange(self.w) + 0.5) * 360 / self.w
        el = 90 - (np.arange(self.h) + 0.5) * 180 / self.h
        self.el = el
        d = direction(az[None, :], el[:, None]).reshape(-1, 3)
        self.centre = bladder.barycentre
        hit = cast(scene, np.broadcast_to(self.centre, d.shape), d)
        world, material, wall, nrm = interpolate_hit(bladder, hit, with_normals=True)
        self.wall = wall
        self.world = world
        self.material = material
        t = hit["t_hit"]
        cos_inc = np.abs(np.einsum("ij,ij->i", np.nan_to_num(nrm), d))
        self.cos_inc = np.where(wall, np.maximum(cos_inc, 1e-3), 1.0)
        dang = np.radians(180 / self.h)
        cos_el = np.repeat(np.cos(np.radians(el)), self.w)
        t = np.where(wall, t, 0.0)
        area = t**2 * cos_el * dang * dang / self.cos_inc
        self.area = area  # mm^2 of wall per pixel
        self.footprint = np.where(wall, t * dang / np.maximum(self.cos_inc, 0.2), 1.0)
        self.idx = np.flatnonzero(wall)
        # blocks of pixels for culling: unit mean direction and angular radius
        rel = np.where(wall[:, None], world - self.centre, 0.0)
        self.dirs = np.zeros_like(rel)
        self.dirs[wall] = rel[wall] / np.linalg.norm(rel[wall], axis=1, keepdims=True)
        bh, bw = -(-self.h // BLOCK), -(-self.w // BLOCK)
        rows = np.arange(self.h * self.w) // self.w
        cols = np.arange(self.h * self.w) % self.w
        self.block_of = (rows // BLOCK) * bw + cols // BLOCK
        nb = bh * bw
        bd = np.zeros((nb, 3))
        for c in range(3):
            bd[:, c] = np.bincount(self.block_of[wall], weights=self.dirs[wall, c], minlength=nb)
        norm = np.linalg.norm(bd, axis=1)
        self.block_valid = norm > 0
        bd[self.block_valid] /= norm[self.block_valid, None]
        self.block_dir = bd
        order = np.argsort(self.block_of[wall], kind="stable")
        self.sorted_idx = self.idx[order]
        blk = self.block_of[self.sorted_idx]
        self.block_start = np.searchsorted(blk, np.arange(nb + 1))
        cosang = np.einsum("ij,ij->i", self.dirs[self.sorted_idx], bd[blk])
        ang = np.arccos(np.clip(cosang, -1, 1))
        rad = np.zeros(nb)
        nonempty = np.flatnonzero(np.diff(self.block_start) > 0)
        if len(nonempty):
            rad[nonempty] = np.maximum.reduceat(ang, self.block_start[nonempty])
        self.block_rad = rad

    def albedo(self, cube: CubeMap) -> np.ndarray:
        """RGB uint8 (H, W, 3) albedo atlas (black outside the wall)."""
        img = np.zeros((self.h * self.w, 3), np.float32)
        rgb, _ = cube.sample(self.material[self.wall], self.footprint[self.wall])
        img[self.wall] = rgb
        return np.clip(img + 0.5, 0, 255).astype(np.uint8).reshape(self.h, self.w, 3)

    def candidates(self, frame_dirs: np.ndarray) -> np.ndarray:
        """Atlas pixel indices possibly seen by a frame whose wall points have these directions
        (unit vectors from the barycentre)."""
        m = frame_dirs.mean(0)
        m /= np.linalg.norm(m)
        ang = np.arccos(np.clip(frame_dirs @ m, -1, 1)).max() + np.radians(1.0)
        bang = np.arccos(np.clip(self.block_dir @ m, -1, 1))
        sel = np.flatnonzero(self.block_valid & (bang <= ang + self.block_rad))
        if not len(sel):
            return np.zeros(0, np.int64)
        parts = [self.sorted_idx[self.block_start[b]:self.block_start[b + 1]] for b in sel]
        return np.concatenate(parts)

    def visible(self, camera: Camera, rot: np.ndarray, centre: np.ndarray, t_map: np.ndarray,
                frame_dirs: np.ndarray, max_radius: float = np.inf) -> np.ndarray:
        """Atlas pixel indices of wall points inside the image and not occluded.

        ``max_radius`` (largest undistorted normalised radius of the image) keeps points far
        outside the field of view away from the distortion polynomial."""
        cand = self.candidates(frame_dirs)
        if not len(cand):
            return cand
        p = self.world[cand]
        xc = rotate(p - centre, rot.T)
        z = np.maximum(xc[:, 2], 1e-9)
        front = (xc[:, 2] > 1e-6) & (np.hypot(xc[:, 0], xc[:, 1]) <= 1.02 * max_radius * z)
        cand, xc, p = cand[front], xc[front], p[front]
        uv = project_points(camera, xc)
        col = np.rint(uv[:, 0]).astype(np.int64)
        row = np.rint(uv[:, 1]).astype(np.int64)
        inside = ((uv[:, 0] >= -0.5) & (uv[:, 0] < camera.width - 0.5)
                  & (uv[:, 1] >= -0.5) & (uv[:, 1] < camera.height - 0.5))
        cand, p, col, row = cand[inside], p[inside], col[inside], row[inside]
        col = np.clip(col, 0, camera.width - 1)
        row = np.clip(row, 0, camera.height - 1)
        t_pix = t_map[row, col]
        dist = np.linalg.norm(p - centre, axis=1)
        ok = np.isfinite(t_pix) & (dist <= t_pix * 1.01 + 0.5)
        return cand[ok]

    def seen_fraction(self, seen: np.ndarray) -> float:
        return float(self.area[seen].sum() / self.area[self.wall].sum())

    def lesion_pixel(self, world: np.ndarray) -> tuple[float, float]:
        az, el = az_el(world - self.centre)
        return float(az), float(el)
