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

This module bakes it (:func:`build_mucosa`); the cube map itself is
:mod:`cystomap.phantom.cubemap`, the procedural content :mod:`cystomap.phantom.vessels`, the
mosaic mode :mod:`cystomap.phantom.mosaic`, rays onto the wall :mod:`cystomap.phantom.wall_rays`.
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
from cystomap.phantom.cubemap import MARGIN, CubeMap, _face_grid, _upsample, face_size
from cystomap.phantom.geometry import STREAM_TEXTURE, Bladder, rng
from cystomap.phantom.mosaic import build_mosaic
from cystomap.phantom.vessels import NoiseVolume, Waves, draw_vessels, grow_vessels
from cystomap.phantom.wall_rays import RadiusTable, surface_points

log = logging.getLogger(__name__)

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
