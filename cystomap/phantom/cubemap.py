"""The cube-map texture of the phantom wall: layout, mipmaps and footprint-filtered sampling.

Six faces (+x, -x, +y, -y, +z, -z) of ``n`` texels with a margin of ``MARGIN`` texels holding
the neighbouring faces' content, tiled 3 across x 2 down; level l of the mipmaps has faces of
``n >> l`` texels, every level packed into one image (see :mod:`cystomap.phantom.texture` for
what is baked into it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from cystomap.phantom.config import PhantomConfig
from cystomap.phantom.geometry import unit

if TYPE_CHECKING:
    from cystomap.phantom.mosaic import Mosaic
    from cystomap.phantom.texture import TextureParams

MARGIN = 8  # level-0 margin (texels), drawn by the baker
MIP_MARGIN = 2  # smallest margin of a coarser level (texels of that level)
MIN_MIP_FACE = 8  # the coarsest level has faces of at least this many texels
MAX_FOOTPRINT_STRETCH = 10.0  # oblique incidence: footprint at most 10x longer than wide
# texture taps per pixel, spread along the longer edge of its footprint on the wall
ANISO_TAPS = 2
# level-of-detail bias: trilinear mipmapping blurs more than the pixel's box (its filter is
# about 1.5x wider). Against a 2560x1440 render downsized, native 640x360 renders match best
# at -0.25 (fine-band energy 1.03x, correlation 0.978; 0: 0.91x, 0.965; -0.5: 1.14x, i.e.
# some aliasing, 0.978), 320x180 ones at -0.5 to -0.75 (-0.25: 0.87x, 0.965)
LOD_BIAS = -0.25


def face_st(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Face index, face coordinates s, t in [-1, 1], and |d_major| / |d| for directions ``d``.

    Face 2k (+) / 2k+1 (-) is the one whose normal is ± axis k; s = d[k+1] / |d[k]|,
    t = d[k+2] / |d[k]| (indices mod 3). ``d`` need not be normalised.
    """
    a = np.abs(d)
    k = a.argmax(axis=1)
    rows = np.arange(len(d))
    major = a[rows, k]
    neg = d[rows, k] < 0
    face = 2 * k + neg
    s = d[rows, (k + 1) % 3] / major
    t = d[rows, (k + 2) % 3] / major
    dn = major / np.sqrt(np.einsum("ij,ij->i", d, d))
    return face, s, t, dn


def face_dirs(face: int, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Unnormalised directions of face coordinates (inverse of face_st)."""
    k, sign = face // 2, (-1.0 if face % 2 else 1.0)
    d = np.empty((*np.broadcast(s, t).shape, 3), dtype=np.float64)
    d[..., k] = sign
    d[..., (k + 1) % 3] = s
    d[..., (k + 2) % 3] = t
    return d


@dataclass
class CubeMap:
    """Mipmapped RGB cube map (uint8) plus a gloss map at level-2 resolution.

    ``levels[0]`` is the baked layout (faces of ``n`` texels, margin ``MARGIN``); level l has
    faces of ``n >> l`` texels (2x2 box averages of level l - 1) and a margin of
    ``margins[l]`` texels filled from the neighbouring faces, down to ``MIN_MIP_FACE``. All
    levels live in one image (``packed``; ``levels`` are views into it) so one remap per
    level of detail samples every pixel whatever its level.
    """

    levels: list[np.ndarray]
    n: int
    gloss: np.ndarray | None = None  # float32 layout at level 2, values in [0, 1]
    mosaic: Mosaic | None = None  # the tiles, when the wall is a mosaic
    params: TextureParams | None = None  # the procedural texture's parameters

    def __post_init__(self) -> None:
        self.rebuild_mips()

    @property
    def tile(self) -> int:
        return self.n + 2 * MARGIN

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    def texel_mm(self, radius: np.ndarray, dn: np.ndarray) -> np.ndarray:
        """Approximate size of a level-0 texel on the wall at material radius and ``dn``."""
        return radius * (2.0 / self.n) * dn**1.5

    def rebuild_mips(self) -> None:
        """(Re)build levels 1… from level 0 (after painting into it)."""
        base = self.levels[0]
        sizes = [self.n]
        while sizes[-1] % 2 == 0 and sizes[-1] // 2 >= MIN_MIP_FACE:
            sizes.append(sizes[-1] // 2)
        margins = [MARGIN] + [max(MARGIN >> lv, MIP_MARGIN) for lv in range(1, len(sizes))]
        tiles = [s + 2 * m for s, m in zip(sizes, margins, strict=True)]
        offsets = [(0, 0)]
        x = 0
        for tl in tiles[1:]:
            offsets.append((x, 2 * tiles[0]))
            x += 3 * tl
        height = 2 * tiles[0] + (2 * tiles[1] if len(tiles) > 1 else 0)
        packed = np.zeros((height, max(3 * tiles[0], x), 3), np.uint8)
        packed[:2 * tiles[0], :3 * tiles[0]] = base
        levels = [packed[:2 * tiles[0], :3 * tiles[0]]]
        m0, n0 = margins[0], sizes[0]
        inner = [base[(f // 3) * tiles[0] + m0:(f // 3) * tiles[0] + m0 + n0,
                      (f % 3) * tiles[0] + m0:(f % 3) * tiles[0] + m0 + n0] for f in range(6)]
        for lv in range(1, len(sizes)):
            n, m, tl = sizes[lv], margins[lv], tiles[lv]
            ox, oy = offsets[lv]
            view = packed[oy:oy + 2 * tl, ox:ox + 3 * tl]
            inner = [cv2.resize(a, (n, n), interpolation=cv2.INTER_AREA) for a in inner]
            stacked = np.concatenate(inner, axis=0)  # faces on top of each other
            i = np.arange(tl)
            ring = ((i[:, None] < m) | (i[:, None] >= m + n) | (i[None, :] < m) | (i[None, :] >= m + n))
            rr, cc = np.nonzero(ring)
            sc = ((cc - m) + 0.5) * (2.0 / n) - 1.0
            tc = ((rr - m) + 0.5) * (2.0 / n) - 1.0
            for f in range(6):
                r0, c0 = (f // 3) * tl, (f % 3) * tl
                view[r0 + m:r0 + m + n, c0 + m:c0 + m + n] = inner[f]
                g, s2, t2, _ = face_st(face_dirs(f, sc, tc))
                xs = np.clip((s2 + 1) * (0.5 * n) - 0.5, 0, n - 1)
                ys = np.clip((t2 + 1) * (0.5 * n) - 0.5, 0, n - 1) + g * n
                vals = _remap_points(stacked, xs, ys)
                view[r0 + rr, c0 + cc] = np.clip(vals + 0.5, 0, 255).astype(np.uint8)
            levels.append(view)
        self.levels = levels
        self.packed = packed
        # packed-image coordinates of face point (s, t) at level l: (bx + s * half, by + t * half)
        # with bx, by at index 6 l + face, half at index l
        self._half = np.array([0.5 * sz for sz in sizes], np.float32)
        self._bx = np.array([offsets[lv][0] + (f % 3) * tiles[lv] + margins[lv] - 0.5 + 0.5 * sizes[lv]
                             for lv in range(len(sizes)) for f in range(6)], np.float32)
        self._by = np.array([offsets[lv][1] + (f // 3) * tiles[lv] + margins[lv] - 0.5 + 0.5 * sizes[lv]
                             for lv in range(len(sizes)) for f in range(6)], np.float32)

    def lod(self, footprint_mm: np.ndarray, radius: np.ndarray, dn: np.ndarray) -> np.ndarray:
        """Level of detail of an isotropic footprint (mm on the wall)."""
        return np.log2(np.maximum(footprint_mm / self.texel_mm(radius, dn), 1e-6)).astype(np.float32)

    def sample(self, points: np.ndarray, footprint_mm: np.ndarray | None = None,
               with_gloss: bool = False, axes: tuple[np.ndarray, np.ndarray] | None = None
               ) -> tuple[np.ndarray, np.ndarray | None]:
        """Albedo (float32 0..255, RGB) at material points (n, 3), prefiltered.

        ``axes``: the two edge vectors (3, n) of each pixel's footprint on the wall in material
        coordinates (mm), e.g. from ray differentials → anisotropic filtering: ANISO_TAPS
        trilinear taps spread evenly along the longer edge (each covering an equal share of
        it), at the level of detail of ``max(longer / ANISO_TAPS, shorter)`` (+ LOD_BIAS),
        i.e. supersampling along the footprint's stretch. ``footprint_mm``: an isotropic
        footprint size (mm) → one trilinear tap. Neither: bilinear at level 0.
        """
        pts = np.ascontiguousarray(points, dtype=np.float32)
        count = len(pts)
        fr = _FaceFrame(pts)
        half = 0.5 * self.n
        spread = None
        if axes is not None and count:
            ds1, dt1 = fr.differential(axes[0])
            ds2, dt2 = fr.differential(axes[1])
            # the taps spread along the longer footprint edge; their level of detail covers
            # the rest of the footprint (the shorter edge, or the long one's share)
            la = ds1 * ds1
            la += dt1 * dt1
            lb = ds2 * ds2
            lb += dt2 * dt2
            c = (la >= lb).astype(np.float32)
            major = np.sqrt(np.maximum(la, lb))
            minor = np.sqrt(np.minimum(la, lb))
            taps = ANISO_TAPS
            if taps > 1:
                ex = ds2 + c * (ds1 - ds2)
                ey = dt2 + c * (dt1 - dt2)
                spread = (ex * (1.0 / taps), ey * (1.0 / taps))  # face units between taps
            width = np.maximum(major * (1.0 / taps), np.maximum(minor, major * (1.0 / MAX_FOOTPRINT_STRETCH)))
            width *= half
            np.maximum(width, 1e-6, out=width)
            lod = np.log2(width)
        elif footprint_mm is not None:
            dn = fr.dn
            lod = self.lod(np.asarray(footprint_mm, np.float32), fr.abs_major / dn, dn)
        else:
            lod = np.zeros(count, np.float32)
        top = self.n_levels - 1
        lod = np.clip(lod + LOD_BIAS, 0, top).astype(np.float32)
        lo = np.minimum(lod.astype(np.int32), max(top - 1, 0))
        frac = lod - lo.astype(np.float32)
        key = lo * 6 + fr.face
        scale_lo = np.exp2(-lo.astype(np.float32)) * half  # = self._half[lo]
        x_lo = np.take(self._bx, key) + fr.s * scale_lo
        y_lo = np.take(self._by, key) + fr.t * scale_lo
        use_hi = top > 0 and bool((frac > 0).any())
        if use_hi:
            key += 6
            x_hi = np.take(self._bx, key) + fr.s * (0.5 * scale_lo)
            y_hi = np.take(self._by, key) + fr.t * (0.5 * scale_lo)
        if spread is None:
            shifts = [0.0]
        else:
            sx, sy = spread[0] * scale_lo, spread[1] * scale_lo
            shifts = [k - 0.5 * (ANISO_TAPS - 1) for k in range(ANISO_TAPS)]
        out = None
        for k in shifts:
            if k == 0.0:
                a = _remap_points(self.packed, x_lo, y_lo)
            else:
                a = _remap_points(self.packed, x_lo + k * sx, y_lo + k * sy)
            if use_hi:
                if k == 0.0:
                    b = _remap_points(self.packed, x_hi, y_hi)
                else:
                    b = _remap_points(self.packed, x_hi + (0.5 * k) * sx, y_hi + (0.5 * k) * sy)
                b -= a
                b *= frac[:, None]
                a += b
            if out is None:
                out = a
            else:
                out += a
        if len(shifts) > 1:
            out *= 1.0 / len(shifts)
        gloss = None
        if with_gloss and self.gloss is not None:
            key0 = fr.face
            x0 = np.take(self._bx, key0) + fr.s * half
            y0 = np.take(self._by, key0) + fr.t * half
            gloss = _remap_points(self.gloss, x0 * 0.25 - 0.375, y0 * 0.25 - 0.375)[:, 0]
        return out, gloss


class _FaceFrame:
    """Cube face, face coordinates and their derivatives for many material points (fast:
    per-point component selection by 0/1 masks instead of gathers)."""

    def __init__(self, pts: np.ndarray) -> None:
        p = np.ascontiguousarray(pts.T, dtype=np.float32)
        a = np.abs(p)
        # major axis k = argmax |p| (first maximum), as face_st
        m1 = (a[1] > a[0]) & (a[1] >= a[2])
        m2 = (a[2] > a[0]) & (a[2] > a[1])
        self.masks = (1 - (m1 | m2)).astype(np.float32), m1.astype(np.float32), m2.astype(np.float32)
        major = self._pick(p, 0)
        self.face = (2 * (m1.astype(np.int64) + 2 * m2)) + (major < 0)
        self.abs_major = np.abs(major)
        self.inv_abs = 1.0 / self.abs_major
        self.inv = 1.0 / major
        self.s = self._pick(p, 1)
        self.s *= self.inv_abs
        self.t = self._pick(p, 2)
        self.t *= self.inv_abs
        self._p = p

    def _pick(self, v: np.ndarray, shift: int) -> np.ndarray:
        """Component (k + shift) % 3 of each column of ``v`` (3, n)."""
        m0, m1, m2 = self.masks
        out = v[shift % 3] * m0
        out += v[(shift + 1) % 3] * m1
        out += v[(shift + 2) % 3] * m2
        return out

    @property
    def dn(self) -> np.ndarray:
        """|major component| / |p|."""
        p = self._p
        return self.abs_major / np.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])

    def differential(self, dp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Change of (s, t) for small material displacements ``dp`` (3, n)."""
        dp = np.asarray(dp, dtype=np.float32)
        dk = self._pick(dp, 0)
        dk *= self.inv
        ds = self._pick(dp, 1)
        ds *= self.inv_abs
        ds -= self.s * dk
        dt = self._pick(dp, 2)
        dt *= self.inv_abs
        dt -= self.t * dk
        return ds, dt


def _remap_points(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """cv2.remap for a flat list of points; returns (n, channels) float32."""
    n = len(x)
    width = 1024
    rows = -(-n // width)
    if n == rows * width:
        mx = np.ascontiguousarray(x, np.float32)
        my = np.ascontiguousarray(y, np.float32)
    else:
        mx = np.zeros(rows * width, np.float32)
        my = np.zeros(rows * width, np.float32)
        mx[:n], my[:n] = x, y
    r = cv2.remap(img, mx.reshape(rows, width), my.reshape(rows, width), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE)
    r = r.reshape(rows * width, -1)[:n]
    return r.astype(np.float32)


def face_size(cfg: PhantomConfig, max_radius: float) -> int:
    """Texels per face edge: the finest texel (face centre, farthest wall) <= ~detail / 1.2."""
    if cfg.cube_face_px:
        return cfg.cube_face_px
    need = 2 * max_radius / (cfg.texture_detail_mm / 1.2)
    n = 256
    while n < need and n < 2048:
        n *= 2
    return n


def _face_grid(face: int, n: int, level: int, ext: int) -> tuple[np.ndarray, int]:
    """Unit directions of the level-``level`` texel centres of a face tile, extended by
    ``ext`` texels on each side (rows = t, columns = s); also the side length."""
    tile = (n + 2 * MARGIN) >> level
    f = 1 << level
    i = np.arange(-ext, tile + ext)
    xf = f * i + (f - 1) / 2  # level-0 pixel position of the texel centres
    sc = ((xf - MARGIN) + 0.5) * (2.0 / n) - 1.0
    d = unit(face_dirs(face, sc[None, :], sc[:, None]).reshape(-1, 3))
    return d, len(i)


def _upsample(arr: np.ndarray, factor: int, ext: int, size: int, start: int = 0) -> np.ndarray:
    """Upsample a grid from _face_grid(ext) by ``factor`` (cv2 pixel-centre convention) and
    crop ``size`` texels from index ``start`` of the finer grid (negative = into its margin)."""
    h, w = arr.shape[:2]
    up = cv2.resize(arr, (w * factor, h * factor), interpolation=cv2.INTER_LINEAR)
    o = ext * factor + start
    return up[o:o + size, o:o + size]
