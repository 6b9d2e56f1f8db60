"""Albedo of the bladder wall: a cube map over material directions, baked procedurally.

The texture is attached to the material (session-1 position of the wall), indexed by the
direction from the session-1 barycentre, so it is seamless (no azimuth seam, no pole pinch)
and moves with the wall when session 2 is deformed.

Layout: six faces (+x, -x, +y, -y, +z, -z) of ``n`` texels with a margin of ``MARGIN``
texels holding the neighbouring faces' content (so bilinear filtering never crosses a face
edge), tiled 3 across x 2 down. Mipmaps: level l has faces of n >> l texels (2x2 box
averages of level l - 1, down to MIN_MIP_FACE) with margins refilled from the neighbouring
faces; every level lives in one packed image. Sampling prefilters by the pixel's footprint on
the wall (see CubeMap.sample): a native low-resolution render matches a downsized
high-resolution one instead of aliasing or blurring the fine texture.

Contents: pink-orange mucosa with low-frequency colour variation (3-D functions of the wall
point), mottling (3-D noise), deep (blurred, purplish) and superficial (sharp, dark red)
branching vessels drawn as polylines on every face they cross, and fine grain at
``texture_detail_mm``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from cystomap.phantom.config import TEXTURE_FAMILIES as FAMILY_NAMES
from cystomap.phantom.config import PhantomConfig
from cystomap.phantom.geometry import STREAM_TEXTURE, Bladder, rng, unit

log = logging.getLogger(__name__)

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
MUCOSA_RGB = np.array([0.90, 0.62, 0.50], dtype=np.float32)
PALE_RGB = np.array([0.94, 0.76, 0.66], dtype=np.float32)  # pale, less vascular patches
VESSEL_RGB = np.array([0.60, 0.15, 0.13], dtype=np.float32)
DEEP_TINT = np.array([0.10, 0.32, 0.24], dtype=np.float32)  # darkening of R, G, B by deep vessels
STREAM_FAMILY = 7


@dataclass(frozen=True)
class TextureParams:
    """Parameters of the procedural mucosa; the defaults are the built-in phantom's wall."""

    mucosa_rgb: tuple[float, float, float] = (0.90, 0.62, 0.50)
    vessel_rgb: tuple[float, float, float] = (0.60, 0.15, 0.13)
    deep_tint: tuple[float, float, float] = (0.10, 0.32, 0.24)  # darkening by deep vessels
    mottle_scale: float = 1.0  # multiplies the blotch (2.5 mm) and mottle grid spacings
    mottle_contrast: float = 1.0  # multiplies the blotch (1.5 %) and mottle (1.2 %) amplitudes
    vessel_density: float = 1.0  # multiplies the number of vessel trunks (one per 700 mm2)
    grain: float = 0.025  # relative std of the fine grain
    grain_scale: float = 1.0  # grain blur in units of texture_detail_mm / 2

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


#: texture families: per parameter a (low, high) range, drawn uniformly per subject (seed);
#: colours: a base RGB and the half-width of a uniform jitter per channel
TEXTURE_FAMILIES: dict[str, dict] = {
    # A: pink mucosa, fine mottling, the default vessel network (closest to the default wall)
    "A": {"mucosa_rgb": ((0.90, 0.62, 0.50), 0.02), "vessel_rgb": ((0.60, 0.15, 0.13), 0.04),
          "deep_tint": ((0.10, 0.32, 0.24), 0.02), "mottle_scale": (0.8, 1.25),
          "mottle_contrast": (0.8, 1.5), "vessel_density": (0.8, 1.3), "grain": (0.02, 0.03),
          "grain_scale": (0.8, 1.2)},
    # B: pale mucosa, coarse strong blotches, sparse faint vessels, little grain
    "B": {"mucosa_rgb": ((0.93, 0.73, 0.63), 0.02), "vessel_rgb": ((0.72, 0.30, 0.28), 0.04),
          "deep_tint": ((0.06, 0.20, 0.16), 0.02), "mottle_scale": (1.8, 3.0),
          "mottle_contrast": (1.5, 3.0), "vessel_density": (0.3, 0.6), "grain": (0.01, 0.02),
          "grain_scale": (1.5, 2.5)},
    # C: red (inflamed) mucosa, fine strong mottling, dense dark vessels, strong grain
    "C": {"mucosa_rgb": ((0.88, 0.50, 0.42), 0.02), "vessel_rgb": ((0.50, 0.08, 0.10), 0.04),
          "deep_tint": ((0.14, 0.38, 0.30), 0.02), "mottle_scale": (0.5, 0.8),
          "mottle_contrast": (2.0, 3.5), "vessel_density": (1.5, 2.2), "grain": (0.035, 0.05),
          "grain_scale": (0.8, 1.2)},
}


assert set(TEXTURE_FAMILIES) == set(FAMILY_NAMES)


def texture_params(cfg: PhantomConfig) -> TextureParams:
    """The subject's texture: the default wall, or drawn from ``cfg.texture_family`` (seeded)."""
    if not cfg.texture_family:
        return TextureParams()
    fam = TEXTURE_FAMILIES[cfg.texture_family]
    g = rng(cfg, STREAM_FAMILY)
    out = {}
    for key in ("mucosa_rgb", "vessel_rgb", "deep_tint", "mottle_scale", "mottle_contrast",
                "vessel_density", "grain", "grain_scale"):
        spec = fam[key]
        if isinstance(spec[0], tuple):
            base, jit = spec
            out[key] = tuple(float(np.clip(b + g.uniform(-jit, jit), 0.0, 1.0)) for b in base)
        else:
            out[key] = float(g.uniform(*spec))
    return TextureParams(**out)


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


def cast(scene, origins: np.ndarray, dirs: np.ndarray, nthreads: int = 0) -> dict[str, np.ndarray]:
    """Cast rays (float32) and return numpy arrays of t_hit, primitive_ids, primitive_uvs."""
    import open3d as o3d

    rays = np.empty((len(dirs), 6), np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = dirs
    ans = scene.cast_rays(o3d.core.Tensor(rays), nthreads=nthreads)
    return {"t_hit": ans["t_hit"].numpy(), "primitive_ids": ans["primitive_ids"].numpy(),
            "primitive_uvs": ans["primitive_uvs"].numpy()}


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


# ----------------------------------------------------------------------------------------
# procedural content


@dataclass
class Waves:
    """Sum of plane waves cos(k.x + phase) in 3-D (a smooth random field, mm input)."""

    k: np.ndarray
    amp: np.ndarray
    phase: np.ndarray

    @classmethod
    def random(cls, g: np.random.Generator, n: int, wavelength_mm: tuple[float, float],
               std: float) -> Waves:
        lam = g.uniform(*wavelength_mm, size=n)
        k = unit(g.normal(size=(n, 3))) * (2 * np.pi / lam)[:, None]
        amp = g.normal(size=n) * std * math.sqrt(2.0 / n)
        return cls(k, amp, g.uniform(0, 2 * np.pi, size=n))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        out = np.zeros(len(x), np.float64)
        for k, a, p in zip(self.k, self.amp, self.phase, strict=True):
            out += a * np.cos(x @ k + p)
        return out


class NoiseVolume:
    """Gaussian-smoothed white noise on a 3-D grid, unit std, sampled trilinearly (mm input)."""

    def __init__(self, g: np.random.Generator, lo: np.ndarray, hi: np.ndarray, spacing: float,
                 sigma_cells: float) -> None:
        from scipy.ndimage import gaussian_filter

        self.lo = lo
        self.spacing = spacing
        shape = tuple(int(v) for v in np.ceil((hi - lo) / spacing) + 2)
        vol = g.standard_normal(shape, dtype=np.float32)
        vol = gaussian_filter(vol, sigma_cells, mode="wrap")
        vol /= vol.std()
        self.vol = vol

    def __call__(self, x: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        c = ((x - self.lo) / self.spacing).T
        return map_coordinates(self.vol, c, order=1, mode="nearest")


@dataclass
class Vessels:
    """Vessel segments on the unit sphere of material directions."""

    p0: np.ndarray
    p1: np.ndarray
    width_mm: np.ndarray
    deep: np.ndarray  # bool
    fade: np.ndarray  # opacity factor along the vessel (0 at its ends)

    def __len__(self) -> int:
        return len(self.width_mm)


def _rotate_tangent(h: np.ndarray, p: np.ndarray, angle: np.ndarray) -> np.ndarray:
    return h * np.cos(angle)[:, None] + np.cross(p, h) * np.sin(angle)[:, None]


def grow_vessels(g: np.random.Generator, radius: RadiusTable, area_mm2: float,
                 min_width_mm: float, density: float = 1.0) -> Vessels:
    """Branching random walks on the wall (trunks ~1 mm wide, branches down to min width);
    ``density`` multiplies the number of trunks."""
    n0 = max(6, round(area_mm2 / 700.0)) if density == 1.0 else max(3, round(area_mm2 * density / 700.0))
    p = unit(g.normal(size=(n0, 3)))
    h = unit(np.cross(p, unit(g.normal(size=(n0, 3)))))
    width = np.exp(g.uniform(np.log(max(0.3, min_width_mm)), np.log(1.1), size=n0))
    length = g.uniform(40, 110, size=n0) * np.sqrt(width)
    deep = g.random(n0) < 0.5
    segs: list[tuple[np.ndarray, ...]] = []
    generation = 0
    max_vessels = 60000
    total = n0
    while len(p) and generation < 12:
        curv = g.normal(0, 0.015, size=len(p))
        sigma = 0.10 + 0.30 * np.clip(0.6 - width, 0, 0.6)  # thin vessels are more tortuous
        travelled = np.zeros(len(p))
        w_start = width.copy()
        alive = np.ones(len(p), bool)
        kids: list[tuple[np.ndarray, ...]] = []
        spacing = np.clip(16.0 * width, 4.0, 14.0)
        while alive.any():
            i = np.flatnonzero(alive)
            frac = travelled[i] / length[i]
            w_now = w_start[i] * (1 - 0.6 * frac)
            step = np.clip(1.5 * w_now, 0.25, 1.0)
            rad = radius(p[i])
            p_new = unit(p[i] + h[i] * (step / rad)[:, None])
            hn = h[i] - np.einsum("ij,ij->i", h[i], p_new)[:, None] * p_new
            hn = unit(hn)
            turn = curv[i] * step + sigma[i] * np.sqrt(step) * g.standard_normal(len(i))
            hn = _rotate_tangent(hn, p_new, turn)
            # vessels emerge from / dive into the deeper tissue: fade in and out
            fade = np.clip(frac / 0.12, 0, 1) * np.clip((1 - frac) / 0.15, 0, 1)
            fade = fade * fade * (3 - 2 * fade)
            segs.append((p[i].copy(), p_new, w_now, deep[i], fade))
            p[i], h[i] = p_new, hn
            travelled[i] += step
            alive[i] = travelled[i] < length[i]
            # branching
            b = g.random(len(i)) < step / spacing[i]
            if b.any() and total < max_vessels:
                j = i[b]
                nb = len(j)
                ang = g.uniform(0.45, 1.3, size=nb) * g.choice([-1.0, 1.0], size=nb)
                cw = w_now[b] * g.uniform(0.45, 0.8, size=nb)
                keep = cw >= min_width_mm
                if keep.any():
                    j, ang, cw = j[keep], ang[keep], cw[keep]
                    ch = _rotate_tangent(h[j], p[j], ang)
                    cl = np.clip(g.uniform(12, 50, size=len(j)) * cw, 2.0, None)
                    cd = deep[j] & (cw > 0.25)
                    kids.append((p[j].copy(), ch, cw, cl, cd))
                    total += len(j)
        if not kids:
            break
        p = np.concatenate([k[0] for k in kids])
        h = np.concatenate([k[1] for k in kids])
        width = np.concatenate([k[2] for k in kids])
        length = np.concatenate([k[3] for k in kids])
        deep = np.concatenate([k[4] for k in kids])
        generation += 1
    return Vessels(*(np.concatenate([s[k] for s in segs]) for k in range(5)))


def draw_vessels(canvas: np.ndarray, face: int, n: int, vessels: Vessels, sel: np.ndarray,
                 radius: RadiusTable, opacity: np.ndarray) -> None:
    """Draw the selected segments into one face tile (uint8 canvas; value = opacity)."""
    k, sign = face // 2, (-1.0 if face % 2 else 1.0)
    p0, p1 = vessels.p0[sel], vessels.p1[sel]
    dn0, dn1 = sign * p0[:, k], sign * p1[:, k]
    ok = (dn0 > 0.45) & (dn1 > 0.45)
    if not ok.any():
        return
    p0, p1, dn0, dn1 = p0[ok], p1[ok], dn0[ok], dn1[ok]
    width = vessels.width_mm[sel][ok]
    alpha = opacity[ok]
    tile = n + 2 * MARGIN

    def px(p, dn):
        s = p[:, (k + 1) % 3] / dn
        t = p[:, (k + 2) % 3] / dn
        return MARGIN + (s + 1) * (0.5 * n) - 0.5, MARGIN + (t + 1) * (0.5 * n) - 0.5

    x0, y0 = px(p0, dn0)
    x1, y1 = px(p1, dn1)
    lo, hi = -8.0, tile + 8.0
    inside = ((np.minimum(x0, x1) < hi) & (np.maximum(x0, x1) > lo)
              & (np.minimum(y0, y1) < hi) & (np.maximum(y0, y1) > lo))
    if not inside.any():
        return
    x0, y0, x1, y1 = x0[inside], y0[inside], x1[inside], y1[inside]
    width, alpha, dn0 = width[inside], alpha[inside], dn0[inside]
    texel = radius(p0[inside]) * (2.0 / n) * dn0**1.5
    wpx = width / texel
    thick = np.maximum(1, np.round(wpx)).astype(int)
    value = np.clip(alpha * np.minimum(wpx, 1.0) * 255, 0, 255)
    vq = (np.round(value / 8) * 8).clip(0, 255).astype(int)
    shift = 4
    pts = np.stack([x0, y0, x1, y1], 1) * (1 << shift)
    pts = np.round(pts).astype(np.int32).reshape(-1, 2, 2)
    order = np.lexsort((thick, vq))
    keys = np.stack([vq[order], thick[order]], 1)
    starts = np.flatnonzero(np.r_[True, (np.diff(keys, axis=0) != 0).any(1)])
    ends = np.r_[starts[1:], len(order)]
    for a, b in zip(starts, ends, strict=True):
        if keys[a, 0] == 0:
            continue
        idx = order[a:b]
        cv2.polylines(canvas, list(pts[idx]), False, int(keys[a, 0]), int(keys[a, 1]),
                      cv2.LINE_AA, shift)


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


def build_mucosa(cfg: PhantomConfig, bladder: Bladder, scene) -> CubeMap:
    """Bake the session-independent mucosa texture (session-1 bladder and scene)."""
    t0 = time.perf_counter()
    g = rng(cfg, STREAM_TEXTURE)
    centre = np.zeros(3)
    radius = RadiusTable(scene, centre)
    max_r = float(np.linalg.norm(bladder.wall_vertices, axis=1).max())
    n = face_size(cfg, max_r)
    tile = n + 2 * MARGIN
    lo = bladder.vertices.min(0) - 4.0
    hi = bladder.vertices.max(0) + 4.0
    detail = cfg.texture_detail_mm
    tp = texture_params(cfg)
    mucosa_rgb = np.array(tp.mucosa_rgb, dtype=np.float32)
    vessel_rgb = np.array(tp.vessel_rgb, dtype=np.float32)
    deep_tint = np.array(tp.deep_tint, dtype=np.float32)
    # smooth 3-D fields (functions of the session-1 wall point, so seamless across faces)
    bright = Waves.random(g, 12, (18.0, 90.0), 0.035)
    pink = Waves.random(g, 10, (25.0, 80.0), 1.0)
    pale = Waves.random(g, 10, (30.0, 100.0), 1.0)
    blotch = NoiseVolume(g, lo, hi, 2.5 * tp.mottle_scale, 1.6)
    mottle = NoiseVolume(g, lo, hi, max(1.0, 2.0 * detail) * tp.mottle_scale, 1.2)
    vessels = grow_vessels(g, radius, bladder.wall_area_mm2, max(detail, 0.06), tp.vessel_density)
    deep_sel = vessels.deep
    deep_op = 0.5 * vessels.fade
    sup_op = np.clip(0.2 + 0.6 * vessels.width_mm, 0.25, 0.8) * vessels.fade
    seg_mm = np.linalg.norm(vessels.p1 - vessels.p0, axis=1) * radius(vessels.p0)
    log.info("texture: %d texels per face, %d vessel segments (%.1f m)", n, len(vessels),
             float(seg_mm.sum()) / 1000)
    level0 = np.zeros((2 * tile, 3 * tile, 3), np.uint8)
    t2 = tile // 4
    gloss = np.zeros((2 * t2, 3 * t2), np.float32)
    for face in range(6):
        # level 4: smooth colour variation
        d4, _ = _face_grid(face, n, 4, 2)
        w4, _, _ = surface_points(scene, bladder, centre, d4)
        miss = ~np.isfinite(w4[:, 0])
        w4[miss] = d4[miss] * radius(d4[miss])[:, None]
        smooth = np.stack([bright(w4), 1 / (1 + np.exp(-(pink(w4) - 1.0) * 3.0)),
                           np.clip(pale(w4) - 0.3, 0, 1.0)], -1).astype(np.float32)
        side4 = round(math.sqrt(len(d4)))
        d2, side2 = _face_grid(face, n, 2, 2)
        sm = _upsample(smooth.reshape(side4, side4, 3), 4, 2, side2, start=-2)
        # level 2: mottling, gloss (grid extended by 2 texels for the final upsampling)
        w2, _, _ = surface_points(scene, bladder, centre, d2)
        miss = ~np.isfinite(w2[:, 0])
        w2[miss] = d2[miss] * radius(d2[miss])[:, None]
        bl = blotch(w2).reshape(side2, side2)
        mo = mottle(w2).reshape(side2, side2)
        if tp.mottle_contrast == 1.0:
            b = sm[..., 0] + 0.015 * bl + 0.012 * mo
        else:
            b = sm[..., 0] + (0.015 * tp.mottle_contrast) * bl + (0.012 * tp.mottle_contrast) * mo
        col = np.empty((side2, side2, 3), np.float32)
        for c, (kp, pale_c) in enumerate(zip((0.0, 0.16, 0.12), PALE_RGB, strict=True)):
            x = mucosa_rgb[c] * (1 + b) * (1 - kp * sm[..., 1])
            col[..., c] = x + (pale_c - x) * (0.4 * sm[..., 2])
        gl = np.clip((mo - 1.2) / 0.5, 0, 1) * np.clip(1 + 0.5 * bl, 0, 1)
        r0, c0 = (face // 3) * t2, (face % 3) * t2
        gloss[r0:r0 + t2, c0:c0 + t2] = gl[2:-2, 2:-2]
        col = _upsample(col, 4, 2, tile)
        # vessels: deep (blurred, purplish darkening) then superficial (dark red)
        texel_mm = float(np.median(radius(d2))) * 2.0 / n
        canvas = np.zeros((tile, tile), np.uint8)
        draw_vessels(canvas, face, n, vessels, deep_sel, radius, deep_op[deep_sel])
        deep = cv2.GaussianBlur(canvas, (0, 0), 0.45 / texel_mm).astype(np.float32)
        canvas[:] = 0
        draw_vessels(canvas, face, n, vessels, ~deep_sel, radius, sup_op[~deep_sel])
        sup = cv2.GaussianBlur(canvas, (0, 0), 0.6).astype(np.float32)
        sup *= 1 / 255
        # fine grain (independent per face: white noise at texture_detail_mm)
        grain = g.standard_normal((tile, tile), dtype=np.float32)
        sg = max(0.5, 0.5 * detail / texel_mm * tp.grain_scale)
        grain = cv2.GaussianBlur(grain, (0, 0), sg)
        grain *= tp.grain / max(float(grain[::7, ::7].std()), 1e-6)
        grain += 1
        planes = []
        for c in range(3):
            x = col[..., c]
            x *= 1 - (deep_tint[c] / 255) * deep
            x += (vessel_rgb[c] - x) * sup
            x *= grain
            planes.append(x)
        col = cv2.merge(planes)
        blur = 0.35 * detail / texel_mm
        if blur > 0.7:
            col = cv2.GaussianBlur(col, (0, 0), blur)
        r0, c0 = (face // 3) * tile, (face % 3) * tile
        level0[r0:r0 + tile, c0:c0 + tile] = cv2.convertScaleAbs(col, alpha=255.0)
    cube = CubeMap([level0], n, gloss, params=tp)
    log.info("texture baked in %.1f s", time.perf_counter() - t0)
    if cfg.texture_mode == "mosaic":
        cube = build_mosaic(cfg, cube, radius)
    return cube


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
