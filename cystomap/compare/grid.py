"""The comparison grid on session B's wall and filters whose sizes are millimetres on it.

Used by :mod:`cystomap.compare.difference` (which re-exports ``Grid`` and ``wall_grid``) and
:mod:`cystomap.compare.changes`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cystomap.atlas.projection import Projection, SurfaceRays


@dataclass
class Grid:
    """The comparison grid: B's atlas projection, its wall points, normals and pixel areas."""

    proj: Projection
    points: np.ndarray  # (H, W, 3), NaN where the ray misses
    hit: np.ndarray  # (H, W) bool
    normals: np.ndarray  # (H, W, 3) outward
    area: np.ndarray  # (H, W) wall area of each pixel (model units²)
    mm_per_px_y: float  # typical wall length of one pixel along a column
    mm_per_px_x: np.ndarray  # (H,) typical wall length of one pixel along each row

    @property
    def shape(self) -> tuple[int, int]:
        return self.proj.height, self.proj.width


def wall_grid(proj: Projection, rays: SurfaceRays) -> Grid:
    h, w = proj.height, proj.width
    dirs = proj.grid_directions().reshape(-1, 3)
    t, tri = rays.cast(proj.barycentre, dirs)
    hit = tri >= 0
    pts = np.full((h * w, 3), np.nan)
    pts[hit] = proj.barycentre + t[hit, None] * dirs[hit]
    normals = np.zeros((h * w, 3))
    normals[hit] = rays.face_normals[tri[hit]]
    cos_b = np.abs(np.einsum("ij,ij->i", normals, dirs))
    solid = np.repeat(proj.pixel_solid_angle(), w)
    tt = np.where(hit, t, 0.0)
    area = np.where(hit, tt ** 2 * solid / np.maximum(cos_b, 0.1), 0.0)
    hit2 = hit.reshape(h, w)
    t2 = np.where(hit2, tt.reshape(h, w), np.nan)
    radius = float(np.nanmedian(t2)) if hit.any() else 1.0
    row_t = np.nanmedian(np.where(hit2, t2, np.nan), axis=1) if hit.any() else np.ones(h)
    row_t = np.where(np.isfinite(row_t), row_t, radius)
    rows = np.arange(h, dtype=np.float64)
    _, el = proj.pixel_to_angles(np.zeros(h), rows)
    _, el_a = proj.pixel_to_angles(0, rows - 0.5)
    _, el_b = proj.pixel_to_angles(0, rows + 0.5)
    mm_y = float(np.median(np.abs(el_a - el_b) * row_t))
    mm_x = row_t * np.cos(el) * (2 * math.pi / w)
    return Grid(proj, pts.reshape(h, w, 3), hit2, normals.reshape(h, w, 3), area.reshape(h, w),
                mm_y, np.maximum(mm_x, 1e-6 * mm_y))


def wrap_pad(a: np.ndarray, pad: int) -> np.ndarray:
    import cv2

    return cv2.copyMakeBorder(a, 0, 0, pad, pad, cv2.BORDER_WRAP)


def over_the_poles(a: np.ndarray, pad: int) -> np.ndarray:
    """``a`` (H, W, ...) padded by ``pad`` rows above and below with the wall beyond each pole:
    the rows next to it in reverse order, turned half-way round in azimuth (row -1 - i,
    column c is row i, column c + W/2)."""
    if pad <= 0:
        return a
    w = a.shape[1]
    top = np.roll(a[pad - 1::-1], w // 2, axis=1)
    bottom = np.roll(a[:-pad - 1:-1], w // 2, axis=1)
    return np.ascontiguousarray(np.concatenate([top, a, bottom], axis=0))


def _gauss_kernel(sigma: float) -> np.ndarray:
    r = max(1, math.ceil(3 * sigma))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / max(sigma, 1e-6)) ** 2)
    return (k / k.sum()).astype(np.float32)


def blur_mm(img: np.ndarray, grid: Grid, sigma_mm: float) -> np.ndarray:
    """Gaussian blur of ``sigma_mm`` on the wall: rows and columns in mm (wrapping in azimuth,
    and along the columns across the poles: :func:`over_the_poles`).

    Along a row the pixel length shrinks towards the poles, so rows are blurred in bands of
    similar pixel length (sigma in pixels within 10 %), capped at a quarter of the width.
    """
    import cv2

    if sigma_mm <= 0:
        return img.astype(np.float32)
    a = img.astype(np.float32)
    h, w = a.shape[:2]
    sy = sigma_mm / grid.mm_per_px_y
    ky = _gauss_kernel(sy)
    # along the columns the wall continues across each pole onto the opposite azimuth
    pad = min(len(ky) // 2, h)
    a = cv2.sepFilter2D(over_the_poles(a, pad), -1, np.ones(1, np.float32), ky,
                        borderType=cv2.BORDER_REFLECT)[pad:pad + h]
    sx = np.minimum(sigma_mm / grid.mm_per_px_x, w / 4.0)
    band = np.floor(np.log(np.maximum(sx, 0.3)) / math.log(1.1)).astype(int)
    out = np.empty_like(a)
    start = 0
    for r in range(1, h + 1):
        if r == h or band[r] != band[start]:
            s = float(np.median(sx[start:r]))
            k = _gauss_kernel(s)
            pad = min(len(k) // 2, w)
            block = wrap_pad(a[max(0, start - 1):min(h, r + 1)], pad)
            if pad >= w:  # kernel wider than the ring: plain mean along the row
                res = np.repeat(block.mean(axis=1, keepdims=True), block.shape[1], axis=1)
            else:
                res = cv2.sepFilter2D(block, -1, k, np.ones(1, np.float32),
                                      borderType=cv2.BORDER_REFLECT)
            res = res[:, pad:pad + w]
            off = start - max(0, start - 1)
            out[start:r] = res[off:off + (r - start)]
            start = r
    _blur_polar_caps(img.astype(np.float32), out, grid, sigma_mm)
    return out


# rows nearer a pole than this many sigmas are blurred on a plane tangent at the pole: there
# the separable blur along rows and columns is no Gaussian on the wall (the rows are circles
# of a few sigmas' circumference; it concentrated a 2 mm blur's mass 1.8-fold at 0.5 deg from
# the pole of a 40 mm sphere, and an 8 mm one 6-fold)
POLAR_SIGMAS = 6.0


def _blur_polar_caps(img: np.ndarray, out: np.ndarray, grid: Grid, sigma_mm: float) -> None:
    """Rows of ``out`` within ``POLAR_SIGMAS`` sigmas of either pole replaced by the Gaussian
    blur of ``img`` on the plane tangent there (azimuthal equidistant: distance from the pole
    along the wall and azimuth kept; its scale error at the support's edge, 10 sigmas, is
    at most 1 - sin(x)/x of that arc over the radius)."""
    import cv2

    h, w = img.shape[:2]
    proj = Projection(grid.proj.kind, w, h)
    rows = np.arange(h, dtype=np.float64)
    _, el = proj.pixel_to_angles(np.zeros(h), rows)
    eq = np.abs(el) < math.radians(30)
    radius = float(np.median(grid.mm_per_px_x[eq] * w / (2 * math.pi * np.cos(el[eq])))) \
        if eq.any() else grid.mm_per_px_y * h / math.pi
    step = grid.mm_per_px_y  # plane pixels as long as a row
    reach_mm = min((POLAR_SIGMAS + 4) * sigma_mm, 0.5 * math.pi * radius)
    cap_mm = min(POLAR_SIGMAS * sigma_mm, reach_mm - 2 * sigma_mm)
    n = math.ceil(reach_mm / step)
    xy = (np.arange(-n, n + 1, dtype=np.float32) * step)
    px, py = np.meshgrid(xy, xy)
    rho, az = np.hypot(px, py), np.arctan2(py, px)
    src = cv2.copyMakeBorder(img, 0, 0, 2, 2, cv2.BORDER_WRAP)  # columns wrap
    for sign in (1.0, -1.0):
        dist = radius * (0.5 * math.pi - sign * el)  # from this pole, along the wall
        cap = np.flatnonzero(dist < cap_mm)
        if not len(cap):
            continue
        col, row = proj.angles_to_pixel(az, sign * (0.5 * math.pi - rho / radius))
        plane = cv2.remap(src, (col + 2).astype(np.float32), row.astype(np.float32),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        plane = cv2.GaussianBlur(plane, (0, 0), sigma_mm / step, borderType=cv2.BORDER_REFLECT)
        caz, cel = proj.pixel_to_angles(np.arange(w, dtype=np.float64)[None, :],
                                        rows[cap][:, None])
        r_back = radius * (0.5 * math.pi - sign * cel)
        mx = (r_back * np.cos(caz) / step + n).astype(np.float32)
        my = (r_back * np.sin(caz) / step + n).astype(np.float32)
        back = cv2.remap(plane, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        out[cap] = back.reshape(out[cap].shape)


def masked_blur_mm(img: np.ndarray, mask: np.ndarray, grid: Grid, sigma_mm: float) -> np.ndarray:
    """Normalised convolution: the blur of ``img`` over ``mask`` only.

    Wide blurs (sigma over 8 pixels) run on a grid reduced by a power of two and are
    interpolated back (the result is smooth at that scale anyway).
    """
    import cv2

    m = mask.astype(np.float32)
    x = img.astype(np.float32) * (m[..., None] if img.ndim == 3 else m)
    h, w = mask.shape
    factor = 1
    while sigma_mm / (grid.mm_per_px_y * factor * 2) >= 4 and min(h, w) // (factor * 2) >= 16:
        factor *= 2
    if factor > 1:
        small = (max(1, w // factor), max(1, h // factor))
        x = cv2.resize(x, small, interpolation=cv2.INTER_AREA)
        m = cv2.resize(m, small, interpolation=cv2.INTER_AREA)
        g = _reduced(grid, factor, small)
    else:
        g = grid
    num = blur_mm(x, g, sigma_mm)
    den = np.maximum(blur_mm(m, g, sigma_mm), 1e-6)
    out = num / (den[..., None] if num.ndim == 3 else den)
    if factor > 1:
        out = cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)
    return out


def _reduced(grid: Grid, factor: int, size: tuple[int, int]) -> Grid:
    """The pixel scales of ``grid`` reduced by ``factor`` (only what blur_mm needs)."""
    w, h = size
    rows = np.clip(((np.arange(h) + 0.5) * grid.shape[0] / h).astype(int), 0, grid.shape[0] - 1)
    mm_x = grid.mm_per_px_x[rows] * grid.shape[1] / w
    return Grid(grid.proj, np.empty((0, 0, 3)), np.empty((0, 0), bool), np.empty((0, 0, 3)),
                np.empty((0, 0)), grid.mm_per_px_y * grid.shape[0] / h, mm_x)


def erode_mm(mask: np.ndarray, grid: Grid, radius_mm: float) -> np.ndarray:
    """Erode ``mask`` by about ``radius_mm`` on the wall (blur-based, wrapping in azimuth)."""
    if radius_mm <= 0:
        return mask.copy()
    # a pixel survives when the mask covers (almost) all of a Gaussian of sigma r/2 around it
    cover = blur_mm(mask.astype(np.float32), grid, radius_mm / 2.0)
    return mask & (cover > 0.977)  # 2 sigma of a 1-D edge profile


def within_cone(dirs: np.ndarray, axes: np.ndarray, half_angle_deg: float) -> np.ndarray:
    """bool per unit direction ``dirs`` (..., 3): within ``half_angle_deg`` of any of ``axes``
    (k, 3 unit vectors); all False when there is no axis or the angle is 0."""
    axes = np.asarray(axes, np.float64).reshape(-1, 3)
    if not len(axes) or half_angle_deg <= 0:
        return np.zeros(np.shape(dirs)[:-1], bool)
    return (np.asarray(dirs) @ axes.T).max(axis=-1) > math.cos(math.radians(half_angle_deg))


def cone_mask(grid: Grid, directions: np.ndarray, half_angle_deg: float) -> np.ndarray:
    """(H, W) bool: wall pixels whose direction from B's barycentre lies within
    ``half_angle_deg`` of any of ``directions`` (k, 3; unit vectors in B's frame)."""
    return grid.hit & within_cone(grid.proj.grid_directions(), directions, half_angle_deg)
