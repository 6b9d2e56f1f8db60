"""Painting the atlas from the registered frames (the two passes of the ``atlas`` stage).

First pass (survey): per frame, its depth map of the mesh, sharpness and coarse samples of the
wall it sees, for the exposure model and the robust per-cell brightness. Second pass: every
frame adds its exposure-corrected colours to the atlas pixels it sees, two-band blended, glints
down-weighted; pixels no frame shows free of glints are inpainted. Clipped pixels (the
preprocess stage's ``clipped/`` masks) are censored: a sample whose footprint holds one counts
for nothing, and wall that no frame shows free of them is left unseen.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from cystomap.atlas.config import AtlasConfig
from cystomap.atlas.projection import SurfaceRays
from cystomap.atlas.texture import (
    Photometry,
    View,
    ViewGeometry,
    WallSamples,
    _covariates,
    brightness_outlier_weight,
    cell_reference,
    fit_photometry,
    glint_weight,
    load_image,
    pyramid,
    sample_mip,
    sharpness,
    view_weights,
)
from cystomap.errors import InputError, StageError
from cystomap.parallel import ordered_map

log = logging.getLogger(__name__)

SURVEY_LEVELS = 6  # pyramid levels below the frame that pass 1's coarse samples may use


@dataclass
class PaintResult:
    colour: np.ndarray  # (H·W, 3) float RGB 0..255
    n_views: np.ndarray  # (H·W,) frames seeing each pixel
    photometry: Photometry
    contributing: int
    n_photometric_obs: int
    n_inpainted: int = 0
    n_clipped_only: int = 0  # atlas pixels every frame showed clipped (left unseen)


def paint(views: list[View], mask: np.ndarray, wall: WallSamples, rays: SurfaceRays,
          cfg: AtlasConfig) -> PaintResult:
    """Two passes over the frames: exposure model from the overlaps, then blending."""
    settings = cfg.texture_settings()
    geo = ViewGeometry(mask, settings)
    n_px = len(wall.hit)
    cells = np.flatnonzero(wall.hit[wall.cell_pixel])
    cell_px = wall.cell_pixel[cells]
    cell_size = np.where(np.isfinite(wall.cell_radius[cells]), wall.cell_radius[cells], 0) * 1.4

    def read(view: View) -> np.ndarray:
        img = load_image(view.path)
        if img.shape[:2] != mask.shape:
            raise InputError(f"{view.path}: size {img.shape[1]}x{img.shape[0]} differs from the "
                             f"mask {mask.shape[1]}x{mask.shape[0]}")
        return img

    def with_glint_weight(img: np.ndarray, view: View) -> np.ndarray:
        """BGR + a 4th channel: the glint weight (255 everywhere when glint_rel is 0); with the
        preprocess stage's mask of clipped pixels, a 5th: 255 where the pixel is not clipped
        (a pyramid level's sample is then 255 only if no clipped pixel is under it)."""
        import cv2

        bgra = cv2.cvtColor(img, cv2.COLOR_BGR2BGRA)
        if cfg.glint_rel > 0:
            bgra[..., 3] = glint_weight(img, mask, cfg.glint_rel)
        clipped = read_clipped(view, mask.shape)
        if clipped is None:
            return bgra
        return np.dstack([bgra, np.where(clipped, 0, 255).astype(np.uint8)])

    def footprint(i: int, depth: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray],
                                                     np.ndarray, np.ndarray] | None:
        """Atlas pixels frame ``i`` shows, their view geometry, and the pyramid level of each
        one's footprint (``level``) and of its coarse cell's (``coarse``); None if none."""
        view = views[i]
        px = np.sort(wall.candidates(view))  # raster order: cache-friendly gathers/scatters
        if len(px) == 0:
            return None
        o = geo.observe(view, wall, px, depth)
        ok = o["ok"]
        if not ok.any():
            return None
        px = px[ok]
        oo = {k: a[ok] for k, a in o.items()}
        # footprint of an atlas pixel in image pixels → pyramid level (anti-aliasing)
        foot = np.float32(view.K[0, 0]) * np.sqrt(pix_area[px] * np.clip(oo["cos"], 0.05, 1)) \
            / oo["dist"]
        level = np.log2(np.maximum(foot, 1.0))
        coarse = np.log2(np.maximum(np.float32(view.K[0, 0]) * cell_size_px[px] / oo["dist"],
                                    1.0))
        return px, oo, level, coarse

    def blend_levels(level: np.ndarray, coarse: np.ndarray) -> int:
        """Pyramid levels below the frame that pass 2 samples from (its coarsest footprint)."""
        return int(np.ceil(max(level.max(), coarse.max()))) + 1

    def blend_pyramid(full: list[np.ndarray], level: np.ndarray,
                      coarse: np.ndarray) -> list[np.ndarray | None]:
        """The levels of the frame's pyramid ``full`` that pass 2 samples; those finer than
        any it samples are None, so that a frame seen from afar keeps only the coarse levels
        it is blended from."""
        pyr: list[np.ndarray | None] = list(full[:blend_levels(level, coarse) + 1])
        finest = int(np.clip(np.rint(min(level.min(), coarse.min())), 0, len(pyr) - 1))
        return [None] * finest + pyr[finest:]

    # per pixel: its coarse cell (for the reference brightness and the cell footprint)
    w_atlas = cfg.width
    nbx = -(-w_atlas // cfg.block)
    pix = np.arange(n_px)
    cell_of = ((pix // w_atlas) // cfg.block) * nbx + (pix % w_atlas) // cfg.block
    cell_size_px = (np.where(np.isfinite(wall.cell_radius), wall.cell_radius, 0) * 1.4)[cell_of]
    cell_size_px = cell_size_px.astype(np.float32)
    del pix
    pix_area = wall.area.astype(np.float32)

    # ---- pass 1: depth maps, sharpness, coarse observations for the exposure model; each
    # frame's pyramid from the finest level pass 2 samples is kept while within the budget
    def survey(i: int) -> dict[str, Any]:
        view = views[i]
        img = read(view)
        depth = geo.depth_map(view, rays)
        out: dict[str, Any] = {"depth": depth, "sharp": sharpness(img, mask)}
        img4 = with_glint_weight(img, view)
        fp = footprint(i, depth)
        full = pyramid(img4, SURVEY_LEVELS if fp is None
                       else max(SURVEY_LEVELS, blend_levels(fp[2], fp[3])))
        if fp is not None:
            out["pyramid"] = blend_pyramid(full, fp[2], fp[3])
        o = geo.observe(view, wall, cell_px, depth)
        ok = o["ok"]
        if ok.any():
            oo = {k: a[ok] for k, a in o.items()}
            level = np.log2(np.maximum(view.K[0, 0] * cell_size[ok] / oo["dist"], 1.0))
            bgrw = sample_mip(full[:SURVEY_LEVELS + 1], oo["u"], oo["v"], level)
            grey = (bgrw[:, 0] + bgrw[:, 1] + bgrw[:, 2]) / 3
            out.update(cell=cells[ok], obs=oo, logi=np.log(grey + 1.0),
                       w=view_weights(oo, view, settings, 1.0, 1.0) * bgrw[:, 3] / 255.0
                       * unclipped(bgrw))
        return out

    budget = cfg.frame_cache_mb * 2**20
    cached_bytes = 0

    def keep_within_budget(sv: dict[str, Any]) -> dict[str, Any]:
        nonlocal cached_bytes
        if "pyramid" in sv:
            size = sum(a.nbytes for a in sv["pyramid"] if a is not None)
            if cached_bytes + size > budget:
                del sv["pyramid"]  # read again in pass 2
            else:
                cached_bytes += size
        return sv

    t0 = time.perf_counter()
    surveys = [keep_within_budget(sv)
               for sv in ordered_map(survey, range(len(views)), cfg.threads)]
    depths = [sv["depth"] for sv in surveys]
    pyramids = [sv.pop("pyramid", None) for sv in surveys]
    sharp = np.array([sv["sharp"] for sv in surveys])
    observed = [i for i, sv in enumerate(surveys) if "cell" in sv]
    log.info("pass 1 (depth maps, exposure samples) over %d frames: %.1f s; %d frame pyramids "
             "kept (%.1f MB)", len(views), time.perf_counter() - t0,
             sum(p is not None for p in pyramids), cached_bytes / 2**20)
    dist_ref = (float(np.median(np.concatenate([surveys[i]["obs"]["dist"] for i in observed])))
                if observed else 1.0)
    med_sharp = float(np.median(sharp[sharp > 0])) if (sharp > 0).any() else 1.0
    sharp_rel = np.clip(sharp / max(med_sharp, 1e-12), 0.1, 4.0)
    n_obs = int(sum(len(surveys[i]["cell"]) for i in observed))
    n_cells = len(wall.cell_pixel)
    photometry = Photometry.identity(len(views), dist_ref)
    ref_px: np.ndarray | None = None  # robust log brightness of each coarse cell
    if n_obs:
        o_cell = np.concatenate([surveys[i]["cell"] for i in observed])
        o_frame = np.concatenate([np.full(len(surveys[i]["cell"]), i) for i in observed])
        o_logi = np.concatenate([surveys[i]["logi"] for i in observed]).astype(np.float64)
        o_cov = np.concatenate([_covariates(surveys[i]["obs"], views[i], dist_ref)
                                for i in observed]).astype(np.float64)
        o_w = np.concatenate([surveys[i]["w"] for i in observed]).astype(np.float64) + 1e-6
        if cfg.exposure != "none":
            photometry = fit_photometry(o_cell, o_frame, o_logi, o_cov, o_w, len(views),
                                        dist_ref, illumination=cfg.exposure == "model")
            log.info("photometry: log gains %.2f…%.2f, beta %s (%d observations)",
                     photometry.gains.min(), photometry.gains.max(),
                     np.round(photometry.beta, 3).tolist(), n_obs)
        if cfg.outlier_rel > 0:
            ref_px = cell_reference(o_cell, o_frame, o_logi, o_cov, o_w, photometry,
                                    n_cells).astype(np.float32)
    del surveys
    # ---- pass 2: blend

    def colours(i: int) -> tuple[np.ndarray, ...] | None:
        view = views[i]
        pyr = pyramids[i]
        pyramids[i] = None  # free as we go
        fp = footprint(i, depths[i])
        if fp is None:
            return None
        px, oo, level, coarse = fp
        if pyr is None:
            pyr = blend_pyramid(pyramid(with_glint_weight(read(view), view),
                                        blend_levels(level, coarse)), level, coarse)
        wt = view_weights(oo, view, settings, float(sharp_rel[i]), dist_ref)
        bgrw = sample_mip(pyr, oo["u"], oo["v"], level)
        corr = photometry.correction(i, oo, view)
        bgr = bgrw[:, :3] * corr[:, None]
        usable = unclipped(bgrw)
        clean = np.maximum(bgrw[:, 3] / np.float32(255.0), np.float32(1e-3)) * usable
        if ref_px is not None:
            ref = ref_px[cell_of[px]]
            known = np.isfinite(ref)
            lum = sample_mip(pyr, oo["u"][known], oo["v"][known], coarse[known])
            fair = unclipped(lum) > 0  # a clipped cell's brightness says nothing
            known[known] = fair
            lum = lum[fair, :3]
            grey = (lum[:, 0] + lum[:, 1] + lum[:, 2]) / 3
            ratio = (grey + 1.0) * corr[known] / np.exp(ref[known])
            clean[known] *= brightness_outlier_weight(ratio, cfg.outlier_rel)
        wt = wt * clean
        return px, wt, wt ** np.float32(cfg.detail_power), bgr, clean, usable > 0

    t0 = time.perf_counter()
    # rows: weight, weight·R, weight·G, weight·B (soft weights, then detail weights)
    soft_acc = np.zeros((4, n_px), np.float32)
    det_acc = np.zeros((4, n_px), np.float32)
    n_views = np.zeros(n_px, np.uint16)
    best_clean = np.zeros(n_px, np.float32)
    shown_unclipped = np.zeros(n_px, bool)
    contributing = 0
    for res in ordered_map(colours, range(len(views)), cfg.threads):
        if res is None:
            continue
        px, wt, wd, bgr, clean, usable = res
        contributing += 1
        n_views[px] += 1
        shown_unclipped[px[usable]] = True
        best_clean[px] = np.maximum(best_clean[px], clean)
        for acc, ww in ((soft_acc, wt), (det_acc, wd)):
            acc[0, px] += ww
            for ch in range(3):
                acc[1 + ch, px] += ww * bgr[:, 2 - ch]  # BGR → RGB
    log.info("pass 2 (blending) over %d frames: %.1f s", len(views), time.perf_counter() - t0)
    # wall that every frame showing it showed clipped has no colour to give: not seen
    clipped_only = (n_views > 0) & ~shown_unclipped
    n_clipped_only = int(clipped_only.sum())
    if n_clipped_only:
        log.info("%.2f%% of the seen atlas pixels were shown clipped by every frame: left unseen",
                 100 * n_clipped_only / max(int(np.count_nonzero(n_views)), 1))
        n_views[clipped_only] = 0
    seen = n_views > 0
    soft = (soft_acc[1:] / np.maximum(soft_acc[0], 1e-30)).T
    det = (det_acc[1:] / np.maximum(det_acc[0], 1e-30)).T
    ok_det = seen & (det_acc[0] > 0)
    det[~ok_det] = soft[~ok_det]
    if cfg.base_sigma_px > 0 and cfg.detail_power > 1:
        h, w = cfg.height, cfg.width
        m = seen.reshape(h, w)
        low_soft = masked_blur(soft.reshape(h, w, 3), m, cfg.base_sigma_px)
        low_det = masked_blur(det.reshape(h, w, 3), m, cfg.base_sigma_px)
        colour = (low_soft + det.reshape(h, w, 3) - low_det).reshape(-1, 3)
    else:
        colour = det if cfg.detail_power > 1 else soft
    colour[~seen] = 0
    n_inpainted = 0
    if cfg.inpaint_below > 0:
        glinted = seen & (best_clean < cfg.inpaint_below)
        n_inpainted = int(glinted.sum())
        if n_inpainted:
            colour = inpaint(colour, glinted, seen, cfg.height, cfg.width)
    return PaintResult(colour, n_views, photometry, contributing, n_obs, n_inpainted,
                       n_clipped_only)


def read_clipped(view: View, shape: tuple[int, ...]) -> np.ndarray | None:
    """The preprocess stage's mask of ``view``'s clipped pixels (bool), None without one."""
    import cv2

    if view.clipped is None:
        return None
    clipped = cv2.imread(str(view.clipped), cv2.IMREAD_GRAYSCALE)
    if clipped is None or clipped.shape != shape:
        raise InputError(f"{view.clipped}: unreadable, or not of the frame's size "
                         f"{shape[1]}x{shape[0]}")
    return clipped > 0


def drop_overexposed(views: list[View], mask: np.ndarray, max_clipped: float) -> list[View]:
    """``views`` without those whose clipped-pixel mask covers more than ``max_clipped`` of
    the field of view ``mask``."""
    if max_clipped >= 1:
        return views
    inside = max(int(np.count_nonzero(mask)), 1)
    kept, dropped = [], []
    for view in views:
        clipped = read_clipped(view, mask.shape)
        if clipped is not None:
            if np.count_nonzero(clipped & mask) > max_clipped * inside:
                dropped.append(view.name)
                continue
        kept.append(view)
    if dropped:
        log.info("%d of %d frames more than %.0f%% clipped (overexposed) are not painted: %s",
                 len(dropped), len(views), 100 * max_clipped, ", ".join(dropped[:8])
                 + (", ..." if len(dropped) > 8 else ""))
    if not kept:
        raise StageError(f"every one of the {len(views)} registered frames is more than "
                         f"{100 * max_clipped:.0f}% clipped (atlas.max_clipped): nothing to "
                         "paint the atlas from")
    return kept


def unclipped(samples: np.ndarray) -> np.ndarray:
    """1 where a sample (of :func:`with_glint_weight`'s image) has no clipped pixel under its
    footprint (its 5th channel still 255), else 0; all 1 without that channel. A partly
    clipped footprint is censored whole: its unclipped part is its darkest (vessels, say),
    no fair sample of the wall's colour."""
    if samples.shape[1] < 5:
        return np.ones(len(samples), np.float32)
    return (samples[:, 4] >= np.float32(254.5)).astype(np.float32)


def inpaint(colour: np.ndarray, holes: np.ndarray, seen: np.ndarray, h: int, w: int) -> np.ndarray:
    """Fill ``holes`` (flat pixel mask) from the seen pixels around them (Telea, wrapping)."""
    import cv2

    pad = 16
    base = colour.copy()
    if (~seen).any():  # unseen pixels are no source: give them the mean colour, not black
        base[~seen] = colour[seen & ~holes].mean(axis=0) if (seen & ~holes).any() else 128
    img = np.clip(np.rint(base), 0, 255).astype(np.uint8).reshape(h, w, 3)
    holes2 = holes.reshape(h, w).astype(np.uint8)
    img = cv2.copyMakeBorder(img, 0, 0, pad, pad, cv2.BORDER_WRAP)
    holes2 = cv2.copyMakeBorder(holes2, 0, 0, pad, pad, cv2.BORDER_WRAP)
    filled = cv2.inpaint(img, holes2, 5, cv2.INPAINT_TELEA)[:, pad:-pad].reshape(-1, 3)
    out = colour.copy()
    out[holes] = filled[holes]
    return out


def masked_blur(img: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised Gaussian blur over ``mask`` (wrapping around in azimuth)."""
    import cv2

    pad = max(1, math.ceil(3 * sigma))
    m = mask.astype(np.float32)
    x = img.astype(np.float32) * m[..., None]

    def blur(a: np.ndarray) -> np.ndarray:
        a = cv2.copyMakeBorder(a, 0, 0, pad, pad, cv2.BORDER_WRAP)
        a = cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        return a[:, pad:-pad]

    num = blur(x)
    den = blur(m)
    return num / np.maximum(den, 1e-6)[..., None]
