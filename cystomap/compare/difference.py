"""Session A's texture in session B's atlas frame, illumination matching, colour difference.

For every pixel of the comparison grid (session B's atlas projection at a resolution of
about ``grid_mm`` on the wall): B's atlas pixel → B's wall point (ray from B's barycentre to B's mesh) → the
B → A warp (similarity + thin-plate spline) → A's atlas pixel (direction from A's barycentre)
→ A's colour (:func:`warp_points`, :class:`AtlasSampler`); a dense optical-flow correction
(:func:`refine_flow`) then removes the misalignment the spline leaves. Only the wall both
sessions saw (painted from at least ``min_views`` frames, not within ``edge_margin_mm`` of
the edge of either coverage) is compared.

Illumination and colour: A's colours are quantile-matched to B's per channel on the jointly
seen wall (global gain, offset and tone curve), then a smooth per-channel gain field
(normalised Gaussian of ``illumination_mm``) removes slow exposure differences; pixels
already flagged as changed are left out of that field (two passes), so it does not absorb
lesions.

The colour difference B − A is smoothed on the wall (Gaussian of ``smooth_mm``, anisotropic
in the atlas so that it is isotropic in mm): registration jitter of fine texture (vessels)
gives differences of both signs that cancel, a coloured patch does not. Its robust colour
covariance on the jointly seen wall (trimmed re-weighting from a MAD start) whitens it; the
whitened length (Mahalanobis distance) is the per-pixel significance in noise units. A
difference of sharpness between the atlases is tolerated (``blur_tolerance_mm``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.atlas.projection import Projection, SurfaceRays
from cystomap.compare.grid import Grid, blur_mm, erode_mm, masked_blur_mm, wrap_pad
from cystomap.compare.grid import wall_grid as wall_grid  # re-exported (stage, tests)
from cystomap.errors import InputError
from cystomap.io.ply import read_mesh
from cystomap.parallel import ordered_map
from cystomap.stats import stable_argsort

log = logging.getLogger(__name__)

CHI3_MEDIAN = 1.5382  # median of the chi distribution with 3 degrees of freedom


# --------------------------------------------------------------------------- inputs


@dataclass
class SessionAtlas:
    """One session's atlas (RGBA), its projection, and its mesh for ray casting."""

    atlas_dir: Path
    proj: Projection
    rgba: np.ndarray  # (H, W, 4) uint8 RGBA
    vertices: np.ndarray
    faces: np.ndarray
    rays: SurfaceRays
    views: np.ndarray | None = None  # (H, W) frames seeing each pixel (from coverage.png)

    @classmethod
    def load(cls, atlas_dir: Path, mesh_ply: Path) -> SessionAtlas:
        import json

        import cv2

        atlas_dir = Path(atlas_dir)
        meta_path, png = atlas_dir / "atlas.json", atlas_dir / "atlas.png"
        for p in (meta_path, png):
            if not p.is_file():
                raise InputError(f"{p} not found (run the atlas stage first)")
        try:
            proj = Projection.from_json(json.loads(meta_path.read_text()))
        except (ValueError, KeyError, TypeError) as exc:
            raise InputError(f"{meta_path}: not an atlas contract ({exc})") from exc
        img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"{png}: cannot read image")
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGRA)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2BGRA)
        rgba = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
        if rgba.shape[:2] != (proj.height, proj.width):
            raise InputError(f"{png}: size {rgba.shape[1]}x{rgba.shape[0]} differs from "
                             f"atlas.json ({proj.width}x{proj.height})")
        verts, faces = read_mesh(Path(mesh_ply))
        meta = json.loads(meta_path.read_text())
        views = read_views(atlas_dir / "coverage.png", meta, rgba.shape[:2])
        return cls(atlas_dir, proj, rgba, verts, faces, SurfaceRays(verts, faces, proj.barycentre),
                   views)

    def scaled(self, scale: float, min_views: int = 0) -> tuple[Projection, np.ndarray]:
        """The projection and RGBA (float; alpha 0..1 = share of the pixel seen, by at least
        ``min_views`` frames when the coverage is known) at ``scale``."""
        import cv2

        p = self.proj
        w, h = max(16, round(p.width * scale)), max(8, round(p.height * scale))
        proj = Projection(p.kind, w, h, p.barycentre, p.axes)
        rgba = self.rgba.astype(np.float32)
        if min_views > 1 and self.views is not None:
            rgba[..., 3] *= self.views >= min_views
        rgba[..., :3] *= rgba[..., 3:4] / 255.0  # premultiplied: unseen colour does not bleed
        if (w, h) != (p.width, p.height):
            interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
            rgba = cv2.resize(rgba, (w, h), interpolation=interp)
        alpha = rgba[..., 3] / 255.0
        rgb = rgba[..., :3] / np.maximum(alpha, 1e-6)[..., None]
        return proj, np.dstack([rgb, alpha]).astype(np.float32)


def read_views(path: Path, meta: dict[str, Any], shape: tuple[int, int]) -> np.ndarray | None:
    """Frames seeing each atlas pixel, decoded from coverage.png (atlas stage contract: black =
    unseen, else viridis of grey 40 + 215 · min(n / max_views, 1)); None when unavailable."""
    import cv2

    if not path.is_file():
        return None
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None or img.shape[:2] != shape:
        log.warning("%s: unreadable or not of the atlas size; view counts not used", path)
        return None
    spec = meta.get("coverage", {}).get("coverage_png", {})
    if spec.get("colormap", "viridis") != "viridis":
        return None
    max_views = float(spec.get("max_views", 20))
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)
    lut = lut[:, 0, :].astype(np.int32)  # BGR per grey level
    key = (img[..., 0].astype(np.int32) << 16) | (img[..., 1].astype(np.int32) << 8) | img[..., 2]
    uniq, inv = np.unique(key.ravel(), return_inverse=True)
    cols = np.stack([(uniq >> 16) & 255, (uniq >> 8) & 255, uniq & 255], axis=1)
    d = ((cols[:, None, :] - lut[None, :, :]) ** 2).sum(axis=2)
    grey = d.argmin(axis=1)
    n = np.clip(np.rint((grey - 40) / 215.0 * max_views), 1, None)
    n[uniq == 0] = 0  # black
    return n[inv].reshape(shape).astype(np.float32)


# --------------------------------------------------------------------------- warping A


@dataclass
class AtlasSampler:
    """Session A's atlas (RGBA float, alpha 0..1) at the comparison scale, wrap-padded."""

    proj: Projection
    padded: np.ndarray
    pad: int

    @classmethod
    def of(cls, atlas: SessionAtlas, scale: float, min_views: int = 0,
           pad: int = 4) -> AtlasSampler:
        proj, rgba = atlas.scaled(scale, min_views)
        return cls(proj, wrap_pad(rgba, pad), pad)

    def pixel_maps(self, points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """(H, W, 2) float32 (col, row) of A-frame ``points`` in the padded atlas."""
        col, row = self.proj.point_to_pixel(points)
        col = np.mod(col + 0.5, self.proj.width) - 0.5 + self.pad
        return np.dstack([col.reshape(shape), row.reshape(shape)]).astype(np.float32)

    def sample(self, maps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """RGB (H, W, 3) and seen share (H, W) at ``maps``."""
        import cv2

        out = cv2.remap(self.padded, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return out[..., :3], out[..., 3]


def warp_points(grid: Grid, warp_ba: Any, step: int = 4) -> np.ndarray:
    """A-frame points (H·W, 3) of the grid's pixels through the B → A warp.

    The spline part of the warp is evaluated every ``step`` pixels and interpolated (it is
    smooth); the similarity is applied at every pixel. Pixels whose ray misses B's mesh use
    the point at the median radius in their direction.
    """
    import cv2

    h, w = grid.shape
    pts = grid.points.reshape(-1, 3)
    hit = grid.hit.reshape(-1)
    radius = float(np.nanmedian(np.linalg.norm(pts[hit] - grid.proj.barycentre, axis=1)))
    dirs = grid.proj.grid_directions().reshape(-1, 3)
    filled = np.where(hit[:, None], pts, grid.proj.barycentre + radius * dirs)
    out = warp_ba.transform.apply(filled)
    if warp_ba.spline is not None:
        rows = np.arange(0, h, step)
        cols = np.arange(0, w, step)
        coarse = filled.reshape(h, w, 3)[rows][:, cols].reshape(-1, 3)
        disp = (warp_ba(coarse) - warp_ba.transform.apply(coarse)).reshape(len(rows), len(cols), 3)
        disp = np.concatenate([disp, disp[:, :1]], axis=1).astype(np.float32)  # wrap column
        # coarse column k is pixel k·step; the appended column (pixel ≈ w) wraps to column 0
        mx, my = np.meshgrid(np.arange(w, dtype=np.float32) / step,
                             np.arange(h, dtype=np.float32) / step)
        full = cv2.remap(disp, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out = out + full.reshape(-1, 3)
    return out


LUMA = np.array([0.299, 0.587, 0.114], np.float32)  # Rec. 601 luma weights (RGB)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Luma of RGB colours (..., 3) -> (...)."""
    return rgb @ LUMA


def lab(rgb: np.ndarray) -> np.ndarray:
    """CIE L*a*b* (D65) of RGB colours (..., 3) on 0..255 (clipped) -> (..., 3)."""
    import cv2

    rgb = np.asarray(rgb, dtype=np.float32)
    flat = np.clip(rgb.reshape(1, -1, 3) / 255.0, 0, 1)
    return cv2.cvtColor(flat, cv2.COLOR_RGB2Lab).reshape(rgb.shape)


def _grey(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(luminance(rgb)), 0, 255).astype(np.uint8)


def refine_flow(grid: Grid, b_rgb: np.ndarray, a_rgb: np.ndarray, joint: np.ndarray,
                smooth_mm: float, max_mm: float, min_luminance: float,
                ) -> tuple[np.ndarray, dict[str, Any]]:
    """Dense residual alignment (H, W, 2), in grid pixels: B's pixel x shows A's content at
    x + flow(x).

    DIS optical flow both ways on the grey images (A tone-matched to B first, on the wall
    both show as wall: :func:`shown_as_wall` of ``min_luminance``); vectors that
    fail the forward-backward check (1 px) are dropped, the rest smoothed on the wall
    (normalised Gaussian of ``smooth_mm``) and clipped at ``max_mm``, so only a smooth
    correction of the spline remains: new texture (a lesion) has no counterpart to flow to
    and cannot be explained away at that scale.
    """
    import cv2

    h, w = joint.shape
    a_q, _ = quantile_match(a_rgb, b_rgb, shown_as_wall(a_rgb, b_rgb, joint, min_luminance),
                            area=grid.area)
    gb = _grey(b_rgb)
    ga = np.where(joint, _grey(a_q), gb).astype(np.uint8)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    fwd = dis.calc(gb, ga, None)
    bwd = dis.calc(ga, gb, None)
    mx, my = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    back = cv2.remap(bwd, mx + fwd[..., 0], my + fwd[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    good = joint & (np.linalg.norm(fwd + back, axis=2) < 1.0)
    if good.sum() < 100:
        return np.zeros((h, w, 2), np.float32), {"flow": False, "reason": "no consistent flow"}
    # flow in mm → smooth → back to pixels (pixel size varies along the rows)
    sx = grid.mm_per_px_x[:, None].astype(np.float32)
    sy = np.float32(grid.mm_per_px_y)
    f_mm = np.dstack([fwd[..., 0] * sx, fwd[..., 1] * sy])
    f_mm = masked_blur_mm(f_mm, good, grid, smooth_mm)
    mag = np.linalg.norm(f_mm, axis=2)
    f_mm *= np.minimum(1.0, max_mm / np.maximum(mag, 1e-9))[..., None]
    flow = np.dstack([f_mm[..., 0] / sx, f_mm[..., 1] / sy]).astype(np.float32)
    mag = np.linalg.norm(f_mm, axis=2)[joint]
    return flow, {"flow": True, "consistent_share": float(good[joint].mean()),
                  "correction_mm": {"median": float(np.median(mag)),
                                    "p90": float(np.percentile(mag, 90)),
                                    "max": float(mag.max())}}


def compose(points: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``points(x + flow(x))``: (H, W, 3) A-frame points resampled along the flow (smooth in
    3-D, unlike atlas pixel coordinates, which jump at A's seam; B's seam wraps)."""
    import cv2

    h, w = flow.shape[:2]
    pad = 8
    src = wrap_pad(points.astype(np.float32), pad)
    mx, my = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(src, mx + flow[..., 0] + pad, my + flow[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).astype(np.float64)


# --------------------------------------------------------------------------- photometry


def weighted_percentile(x: np.ndarray, weights: np.ndarray | None, q: np.ndarray) -> np.ndarray:
    """Percentiles ``q`` (0-100) of ``x`` weighted by ``weights`` (None: unweighted)."""
    if weights is None:
        return np.percentile(x, q)
    order = stable_argsort(x)
    xs, ws = x[order], np.asarray(weights, np.float64)[order]
    c = np.cumsum(ws) - 0.5 * ws
    return np.interp(np.asarray(q) / 100.0 * float(ws.sum()), c, xs)


def shown_as_wall(a: np.ndarray, b: np.ndarray, mask: np.ndarray, min_luminance: float,
                  ) -> np.ndarray:
    """``mask`` without the pixels either session shows darker than ``min_luminance`` times
    its median luminance on ``mask``: an opening (the neck, the urethra, an orifice), not
    wall. How much of an opening each session shows differs, so a tone curve fitted over
    it maps the darkest wall of one session (its vessels) onto the other's lumen."""
    out = mask.copy()
    for rgb in (a, b):
        lum = luminance(rgb)
        out &= lum >= min_luminance * float(np.median(lum[mask]))
    return out if out.sum() >= 100 else mask


def quantile_match(a: np.ndarray, b: np.ndarray, mask: np.ndarray, n_q: int = 257,
                   area: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, list[dict[str, float]]]:
    """A's channels mapped monotonically so their distribution on ``mask`` matches B's: by
    wall ``area`` when given (atlas pixels crowd towards the poles: a change there would
    otherwise weigh in the tone curve as if it were several times its size). Values below
    the sample's darkest are scaled in proportion (an opening left out of ``mask`` stays
    dark), values above its brightest clamped."""
    out = np.empty_like(a, dtype=np.float32)
    q = np.linspace(0, 100, n_q)
    info = []
    wa = None if area is None else area[mask]
    for c in range(a.shape[2]):
        qa = weighted_percentile(a[..., c][mask], wa, q)
        qb = weighted_percentile(b[..., c][mask], wa, q)
        qa = np.maximum.accumulate(qa + np.arange(n_q) * 1e-6)  # strictly increasing
        x = a[..., c]
        out[..., c] = np.where(x < qa[0], x * (qb[0] / max(float(qa[0]), 1e-6)),
                               np.interp(x, qa, qb))
        slope = np.polyfit(qa[16:-16], qb[16:-16], 1)
        info.append({"gain": float(slope[0]), "offset": float(slope[1])})
    return out, info


def robust_covariance(x: np.ndarray, iterations: int = 5) -> np.ndarray:
    """Covariance of the bulk of ``x`` (n, d): MAD start, then trimmed re-weighting.

    Each round keeps the points within the 97.5 % chi-square quantile of the current
    Mahalanobis distance and rescales for the trimmed tails (consistency factor for a
    Gaussian), so a few changed areas do not inflate the noise estimate.
    """
    from scipy.stats import chi2

    d = x.shape[1]
    med = np.median(x, axis=0)
    mad = 1.4826 * np.median(np.abs(x - med), axis=0)
    cov = np.diag(np.maximum(mad, 1e-6) ** 2)
    centre = med
    cut = chi2.ppf(0.975, d)
    # consistency: E[r² | r² < cut] / d for a Gaussian
    factor = chi2.cdf(cut, d + 2) / chi2.cdf(cut, d)
    for _ in range(iterations):
        inv = np.linalg.inv(cov)
        dx = x - centre
        r2 = ((dx @ inv) * dx).sum(axis=1)
        keep = r2 < cut
        if keep.sum() < 10 * d:
            break
        centre = x[keep].mean(axis=0)
        cov = np.cov(x[keep].T) / factor
    return cov


@dataclass
class Difference:
    """Everything the change detection needs, on the comparison grid."""

    grid: Grid
    b_rgb: np.ndarray  # (H, W, 3) float 0..255, B's colours
    a_rgb: np.ndarray  # (H, W, 3) A's colours warped into B's frame, illumination-matched
    joint: np.ndarray  # (H, W) bool, jointly seen (edge margin removed)
    delta: np.ndarray  # (H, W, 3) B − A (unsmoothed), 0 outside joint
    delta_smooth: np.ndarray  # (H, W, 3) smoothed on the wall
    significance: np.ndarray  # (H, W) Mahalanobis length of delta_smooth, 0 outside joint
    covariance: np.ndarray  # (3, 3) robust noise covariance of delta_smooth
    info: dict[str, Any]
    # (H, W) larger of the two sessions' distances to their nearest SfM point (set by the stage)
    point_distance: np.ndarray | None = None
    # (H, W) wall B's atlas shows (from any number of frames; A may not have seen it), and
    # B's colours smoothed (smooth_mm) over it; set by painted_b
    b_seen: np.ndarray | None = None
    b_smooth: np.ndarray | None = None
    # (H, W) wall A saw, beyond its edge margin (compared unless B did not see it)
    a_interior: np.ndarray | None = None
    # (H, W) significance of the part of the smoothed difference that no brightness change
    # (a gain along B's colour) explains, and the whitened size of the brightness part
    # (both only with neck_chroma)
    significance_colour: np.ndarray | None = None
    brightness: np.ndarray | None = None


def compute_difference(grid: Grid, b_rgb: np.ndarray, b_seen: np.ndarray, a_rgb: np.ndarray,
                       a_seen: np.ndarray, cfg: Any,
                       hint: Callable[[np.ndarray, np.ndarray], np.ndarray],
                       neck_angle: np.ndarray | None = None) -> Difference:
    """Illumination-matched, smoothed and whitened colour difference B − A on the grid.

    ``hint(significance, joint)`` gives the wall (bool mask) that counts as changed when the
    illumination field is re-estimated without it (second pass).

    Resolution tolerance (``blur_tolerance_mm``): the two atlases are painted from frames at
    different distances, so the same vessel can be sharper in one. The significance is the
    smallest over comparing B with A, B with A blurred (σ = t/2, t) and A with B blurred: a
    difference of focus is explained away, a new coloured patch is not.

    ``neck_angle`` (each pixel's angle to the bladder neck, degrees): A's colours are also
    matched to B's ring by ring around the neck (:func:`cystomap.compare.neck.ring_ratio`).
    """
    joint_raw = grid.hit & b_seen & a_seen
    if joint_raw.sum() < 100:
        raise InputError("the sessions share (almost) no seen wall after co-registration")
    joint = erode_mm(joint_raw, grid, cfg.edge_margin_mm)
    if joint.sum() < 100:
        joint = joint_raw
    # the tone curve from wall both sessions show as wall (not the openings)
    wall = shown_as_wall(a_rgb, b_rgb, joint, cfg.min_luminance_a)
    a_q, tone = quantile_match(a_rgb, b_rgb, wall, area=grid.area)
    exclude = np.zeros_like(joint)
    info: dict[str, Any] = {"tone_match": tone}
    a_n = a_q
    t = cfg.blur_tolerance_mm
    blurs = [0.0] + ([t / 2, t] if t > 0 else [])
    sm = cfg.smooth_mm
    # B's smoothed colours do not depend on the illumination field: once for both rounds
    threads = int(getattr(cfg, "threads", 1))

    def blurred(img: np.ndarray, mask: np.ndarray, sigmas: list[float]) -> list[np.ndarray]:
        return list(ordered_map(lambda s: masked_blur_mm(img, mask, grid, s), sigmas, threads))

    sb = blurred(b_rgb, joint, [math.hypot(sm, x) for x in blurs])
    for round_ in range(2):
        if cfg.illumination_mm > 0:
            use = joint & ~exclude
            lb, la = ordered_map(
                lambda img, use=use: masked_blur_mm(np.log(img + 8.0), use, grid,
                                                    cfg.illumination_mm),
                (b_rgb, a_q), threads)
            a_n = np.clip((a_q + 8.0) * np.exp(lb - la) - 8.0, 0, 255)
        if neck_angle is not None:
            from cystomap.compare.neck import ring_ratio

            factor, info["neck_ratio"] = ring_ratio(b_rgb, a_n, joint & ~exclude, grid,
                                                    neck_angle, 2 * sm)
            a_n = np.clip((a_n + 8.0) * factor - 8.0, 0, 255)
        delta = np.where(joint[..., None], b_rgb - a_n, 0.0).astype(np.float32)
        sa = blurred(a_n, joint, [math.hypot(sm, x) for x in blurs])
        smooth = sb[0] - sa[0]
        smooth[~joint] = 0
        x = smooth[joint]
        rng = np.random.default_rng(cfg.seed)
        # the noise of the wall, not of the atlas's pixels: drawn in proportion to their wall
        # area (pixels crowd towards the poles, a few square millimetres in hundreds of them)
        wa = grid.area[joint].astype(np.float64)
        sub = x[rng.choice(len(x), 200000, replace=True, p=wa / wa.sum())]
        cov = robust_covariance(sub.astype(np.float64))
        inv = np.linalg.inv(cov).astype(np.float32)

        def maha(d: np.ndarray, inv: np.ndarray = inv) -> np.ndarray:
            return np.sqrt(np.maximum(np.einsum("hwi,ij,hwj->hw", d, inv, d), 0))

        sig = maha(smooth)
        for k in range(1, len(blurs)):
            sig = np.minimum(sig, maha(sb[0] - sa[k]))
            sig = np.minimum(sig, maha(sb[k] - sa[0]))
        sig[~joint] = 0
        if round_ == 0 and cfg.illumination_mm > 0:
            # leave clearly changed wall (and a margin) out of the illumination field
            flagged = joint & hint(sig, joint)
            exclude = blur_mm(flagged.astype(np.float32), grid, 2 * cfg.illumination_mm / 5) > 0.02
            info["illumination_excluded_share"] = float(exclude[joint].mean())
        else:
            break
    area_joint = float(grid.area[joint].sum())
    info.update(
        joint_area_mm2=area_joint,
        joint_share_of_b_wall=area_joint / max(float(grid.area[grid.hit].sum()), 1e-9),
        noise_covariance=cov.tolist(),
        noise_sigma_rgb=np.sqrt(np.diag(cov)).tolist(),
        significance_median=float(np.median(sig[joint])),
        significance_mad=float(1.4826 * np.median(np.abs(sig[joint] - np.median(sig[joint])))),
        significance_note="whitened length of the smoothed colour difference (noise units; "
                          f"a chi(3) variable under Gaussian noise, median {CHI3_MEDIAN})",
        raw_difference_rms=float(np.sqrt(np.mean(delta[joint] ** 2))),
    )
    out = Difference(grid, b_rgb, a_n.astype(np.float32), joint, delta, smooth, sig, cov, info)
    out.a_interior = erode_mm(grid.hit & a_seen, grid, cfg.edge_margin_mm)
    if getattr(cfg, "neck_chroma", False):
        u = sb[0] / np.maximum(np.linalg.norm(sb[0], axis=-1, keepdims=True), 1e-6)
        sig_c, bright = None, None
        for k in range(len(blurs)):
            for d in ([smooth] if k == 0 else [sb[0] - sa[k], sb[k] - sa[0]]):
                c, g = gain_free(d, u, inv)
                sig_c = c if sig_c is None else np.minimum(sig_c, c)
                bright = g if bright is None else np.minimum(bright, g)
        sig_c[~joint] = 0
        bright[~joint] = 0
        out.significance_colour, out.brightness = sig_c, bright
    return out


def gain_free(d: np.ndarray, u: np.ndarray, inv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whitened length of the part of the differences ``d`` (H, W, 3) that no change of
    brightness along the colours' directions ``u`` (unit, H, W, 3) explains (the smallest
    Mahalanobis length of d - g·u over g: a chi(2) variable under Gaussian noise), and the
    whitened size of the brightness part |g| (a chi(1) one)."""
    d = d.astype(np.float32)
    di = d @ inv
    ui = u.astype(np.float32) @ inv
    full = np.einsum("hwi,hwi->hw", di, d)
    proj = np.einsum("hwi,hwi->hw", ui, d)
    uu = np.maximum(np.einsum("hwi,hwi->hw", ui, u), 1e-12)
    return (np.sqrt(np.maximum(full - proj ** 2 / uu, 0)),
            np.abs(proj) / np.sqrt(uu))


def painted_b(diff: Difference, rgba_b: np.ndarray, smooth_mm: float) -> None:
    """Set ``diff.b_seen`` / ``diff.b_smooth`` from B's atlas at the grid's size (RGBA, alpha
    0..1) painted from any number of frames: where a change is followed beyond the compared
    wall (see :mod:`cystomap.compare.changes`), one view of B is enough to see it."""
    grid = diff.grid
    seen = grid.hit & (rgba_b[..., 3] > 0.999)
    rgb = rgba_b[..., :3]
    diff.b_seen = seen
    diff.b_smooth = (masked_blur_mm(rgb, seen, grid, smooth_mm) if smooth_mm > 0
                     else rgb.astype(np.float32))


def difference_image(diff: Difference) -> np.ndarray:
    """RGB uint8 in the reference study's style: 50 % grey = no change, deviations = B − A.

    Unseen or not jointly seen wall is black.
    """
    img = np.clip(128.0 + diff.delta, 0, 255)
    img[~diff.joint] = 0
    return np.rint(img).astype(np.uint8)
