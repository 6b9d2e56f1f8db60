"""The phantom's "mosaic" texture mode: the baked mucosa cut into patches, each rotated,
stretched and tinted, tiled over the wall (a texture without the procedural one's statistics)."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from cystomap.phantom.config import PhantomConfig
from cystomap.phantom.cubemap import CubeMap, _face_grid
from cystomap.phantom.geometry import rng, unit
from cystomap.phantom.wall_rays import RadiusTable

log = logging.getLogger(__name__)


STREAM_MOSAIC = 6
MOSAIC_SPACING = 0.6  # tile spacing on the wall / patch edge (cells stay inside their patch)
MOSAIC_STRETCH = 0.25  # log-stretch per patch axis, uniform in [-this, this]
MOSAIC_TINT = 0.04  # std of the log-gain per colour channel of a tile
MOSAIC_MAX_PATCH_PX = 1024


def tangent_frame(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (e1, e2) of unit normals (n, 3), right-handed with the normal."""
    ref = np.where(np.abs(normal[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = unit(np.cross(normal, ref))
    return e1, np.cross(normal, e1)


@dataclass
class Mosaic:
    """Tiles of a mosaic wall: tile k shows patch ``patch[k]`` centred at wall point
    ``centre[k]`` (tangent frame e1, e2 about the radial direction), the patch mirrored in its
    first axis when ``mirror[k]``, stretched by ``stretch[k]`` along its axes, rotated by
    ``angle[k]`` (rad, from e1 towards e2) and its RGB multiplied by ``tint[k]``. Each texel
    belongs to the tile whose direction is nearest its own (cells on the sphere of directions).
    """

    patches: list[np.ndarray]  # float32 (px, px, 3), 0..255
    patch_mm: float
    centre: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    patch: np.ndarray
    angle: np.ndarray
    mirror: np.ndarray
    stretch: np.ndarray
    tint: np.ndarray
    source: np.ndarray  # (n_patches, 3) wall points the patches were cut from

    def cell(self, points: np.ndarray) -> np.ndarray:
        """Index of the tile showing each wall point (nearest tile direction)."""
        from scipy.spatial import cKDTree

        if not hasattr(self, "_tree"):
            self._tree = cKDTree(unit(self.centre))
        return self._tree.query(unit(np.asarray(points, np.float64)))[1]

    def __len__(self) -> int:
        return len(self.patch)

    def wall_offsets(self, k: int, xy: np.ndarray) -> np.ndarray:
        """Wall points (3-D) of patch coordinates ``xy`` (mm from the patch centre) in tile k."""
        x = xy[:, 0] * (-1.0 if self.mirror[k] else 1.0) * self.stretch[k, 0]
        y = xy[:, 1] * self.stretch[k, 1]
        c, s = math.cos(self.angle[k]), math.sin(self.angle[k])
        u, v = c * x - s * y, s * x + c * y
        return self.centre[k] + u[:, None] * self.e1[k] + v[:, None] * self.e2[k]

    def to_dict(self) -> dict:
        return {"patches": len(self.patches), "patch_mm": self.patch_mm, "tiles": len(self),
                "tiles_per_patch": np.bincount(self.patch, minlength=len(self.patches)).tolist(),
                "patch_px": int(self.patches[0].shape[0]),
                "sources": np.round(self.source, 3).tolist()}


def build_mosaic(cfg: PhantomConfig, source: CubeMap, radius: RadiusTable) -> CubeMap:
    """Re-tile the wall with ``cfg.mosaic_patches`` square patches cut from ``source``.

    Patches (``cfg.mosaic_patch_mm`` on a side) are sampled from the procedural texture on the
    tangent planes of random wall points; tiles are laid on a Fibonacci lattice of directions
    about MOSAIC_SPACING patch edges apart at the farthest wall, each with a random patch,
    rotation, mirroring, anisotropic stretch and tint. The gloss map is kept.
    """
    from cystomap.phantom.geometry import fibonacci_sphere

    t0 = time.perf_counter()
    g = rng(cfg, STREAM_MOSAIC)
    n = source.n
    size = cfg.mosaic_patch_mm
    probe = fibonacci_sphere(2000)
    r_probe = radius(probe)
    texel_mm = float(np.median(r_probe)) * 2.0 / n
    px = int(min(MOSAIC_MAX_PATCH_PX, max(16, math.ceil(size / texel_mm))))
    # patches: tangent-plane samples of the procedural texture around random wall points
    src_dirs = unit(g.normal(size=(cfg.mosaic_patches, 3)))
    src = src_dirs * radius(src_dirs)[:, None]
    se1, se2 = tangent_frame(src_dirs)
    a = ((np.arange(px) + 0.5) / px - 0.5) * size
    gx, gy = np.meshgrid(a, a)  # rows = second axis
    patches = []
    for i in range(cfg.mosaic_patches):
        pts = src[i] + gx.reshape(-1, 1) * se1[i] + gy.reshape(-1, 1) * se2[i]
        col, _ = source.sample(pts)
        patches.append(np.ascontiguousarray(col.reshape(px, px, 3), np.float32))
    # tiles
    spacing_rad = MOSAIC_SPACING * size / float(r_probe.max())
    n_tiles = max(cfg.mosaic_patches, math.ceil(4 * math.pi / (0.866 * spacing_rad**2)))
    tdir = fibonacci_sphere(n_tiles)
    tdir = unit(tdir @ _random_rotation(g).T)
    centre = tdir * radius(tdir)[:, None]
    e1, e2 = tangent_frame(tdir)
    mosaic = Mosaic(
        patches, size, centre, e1, e2,
        patch=g.integers(0, cfg.mosaic_patches, size=n_tiles),
        angle=g.uniform(0, 2 * math.pi, size=n_tiles),
        mirror=g.random(n_tiles) < 0.5,
        stretch=np.exp(g.uniform(-MOSAIC_STRETCH, MOSAIC_STRETCH, size=(n_tiles, 2))),
        tint=np.exp(g.normal(0, MOSAIC_TINT, size=(n_tiles, 3))),
        source=src,
    )
    tile = source.tile
    level0 = np.empty_like(source.levels[0])
    chunk = 1 << 20  # texels at a time (bounded memory at 2048 texels per face)
    for face in range(6):
        dirs, side = _face_grid(face, n, 0, 0)
        out = np.empty((len(dirs), 3), np.float32)
        for j in range(0, len(dirs), chunk):
            d = dirs[j:j + chunk]
            k = mosaic.cell(d)
            rel = d * radius(d)[:, None] - centre[k]
            u = np.einsum("ij,ij->i", rel, e1[k])
            v = np.einsum("ij,ij->i", rel, e2[k])
            c, s = np.cos(mosaic.angle[k]), np.sin(mosaic.angle[k])
            x = (c * u + s * v) / mosaic.stretch[k, 0]
            y = (-s * u + c * v) / mosaic.stretch[k, 1]
            x = np.where(mosaic.mirror[k], -x, x)
            mx = ((x / size + 0.5) * px - 0.5).astype(np.float32)
            my = ((y / size + 0.5) * px - 0.5).astype(np.float32)
            part = np.empty((len(d), 3), np.float32)
            pid = mosaic.patch[k]
            for i in range(cfg.mosaic_patches):
                sel = np.flatnonzero(pid == i)
                if len(sel):
                    part[sel] = _remap_reflect(patches[i], mx[sel], my[sel])
            part *= mosaic.tint[k].astype(np.float32)
            out[j:j + chunk] = part
        r0, c0 = (face // 3) * tile, (face % 3) * tile
        level0[r0:r0 + tile, c0:c0 + tile] = np.clip(out + 0.5, 0, 255).astype(np.uint8).reshape(side, side, 3)
    cube = CubeMap([level0], n, source.gloss, mosaic, source.params)
    log.info("mosaic: %d tiles of %d patches (%d px, %.1f mm) in %.1f s", n_tiles,
             cfg.mosaic_patches, px, size, time.perf_counter() - t0)
    return cube


def _random_rotation(g: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(g.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def _remap_reflect(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup of points in ``img`` with mirrored borders; (n, channels) float32."""
    n = len(x)
    width = 1024
    rows = -(-n // width)
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    mx[:n], my[:n] = x, y
    r = cv2.remap(img, mx.reshape(rows, width), my.reshape(rows, width), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REFLECT_101)
    return r.reshape(rows * width, -1)[:n]
