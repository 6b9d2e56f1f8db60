"""Scores of the surface mesh and of the 2-D atlas against the true wall."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.errors import InputError
from cystomap.evaluate.config import EvalConfig
from cystomap.evaluate.trajectory import Sim3
from cystomap.evaluate.truth import (
    SurfaceQuery,
    Truth,
    equirect_coords,
    equirect_directions,
    equirect_pixels,
    read_equirect,
    read_mesh,
    sample_surface,
)
from cystomap.images import sample_bilinear
from cystomap.outputs import read_json_object

log = logging.getLogger(__name__)


def score_surface(truth: Truth, mesh_ply: Path, sim3: Sim3, cfg: EvalConfig) -> dict[str, Any]:
    """Accuracy and completeness of a mesh given in the model frame (``sim3``: model → truth).

    accuracy: distances from points sampled on the reconstructed mesh to the true surface,
    leaving out the part that bridges an opening of the true wall (the aperture into the
    urethra, where a closed mesh must differ from the open truth; ``Truth.in_opening``), which
    is scored on its own (``closure_*``); completeness: share of points sampled on the seen
    part of the true wall (``seen.png`` about the truth barycentre) lying within
    ``cfg.completeness_threshold_mm`` of the mesh.
    """
    rng = np.random.default_rng(cfg.seed)
    recon = read_mesh(mesh_ply).transformed(sim3)
    true_mesh = truth.surface
    origin = truth.barycentre
    rec_pts = sample_surface(recon, cfg.surface_samples, rng)
    acc_all = SurfaceQuery(true_mesh, origin).distance(rec_pts)
    opening = truth.in_opening(rec_pts)
    acc = acc_all[~opening] if (~opening).any() else acc_all
    true_pts = sample_surface(true_mesh, cfg.surface_samples, rng)
    seen = seen_at(truth, true_pts)
    dist = SurfaceQuery(recon, origin).distance(true_pts)
    close = dist <= cfg.completeness_threshold_mm
    scores = {
        "n_samples": cfg.surface_samples,
        "accuracy_mean_mm": float(acc.mean()),
        "accuracy_median_mm": float(np.median(acc)),
        "accuracy_p90_mm": float(np.percentile(acc, 90)),
        "accuracy_within_2mm": float((acc <= 2.0).mean()),
        "accuracy_mean_mm_with_closure": float(acc_all.mean()),
        "closure_share": float(opening.mean()),
        "closure_mean_mm": float(acc_all[opening].mean()) if opening.any() else None,
        "completeness_threshold_mm": cfg.completeness_threshold_mm,
        "completeness": float(close[seen].mean()) if seen.any() else None,
        "completeness_whole_wall": float(close.mean()),
        "seen_share_of_samples": float(seen.mean()),
        "area_mm2": float(recon.triangle_areas.sum()),
        "area_ratio": float(recon.triangle_areas.sum() / true_mesh.triangle_areas.sum()),
    }
    log.info("%s: accuracy %.3f mm (mean), completeness %s", mesh_ply, scores["accuracy_mean_mm"],
             scores["completeness"])
    return scores


def seen_at(truth: Truth, points: np.ndarray) -> np.ndarray:
    """Whether each point of the true wall is seen, from ``seen.png`` about the barycentre."""
    mask = truth.seen
    row, col = equirect_pixels(points - truth.barycentre, *mask.shape)
    return mask[row, col]


def read_atlas_json(atlas_dir: Path) -> dict[str, Any]:
    return read_json_object(atlas_dir / "atlas.json")


def score_atlas(
    truth: Truth, atlas_dir: Path, sim3: Sim3 | None, cfg: EvalConfig
) -> dict[str, Any]:
    """Coverage claimed in atlas.json against the truth; with atlas.png and a Sim(3), its mask.

    The atlas image is compared on the truth's equirectangular grid: each truth pixel's ray from
    the truth barycentre hits the true wall at X; X is taken into the model frame and looked up
    in atlas.png from the atlas barycentre. Pixels are weighted by the wall area they cover.
    A pixel of atlas.png counts as painted when its alpha (if any) or any colour is non-zero.
    """
    meta = read_atlas_json(atlas_dir)
    out: dict[str, Any] = {}
    true_pct = 100.0 * truth.seen_fraction
    if "coverage_percent" in meta:
        try:
            pct = float(meta["coverage_percent"])
        except (TypeError, ValueError) as exc:
            msg = f"{atlas_dir / 'atlas.json'}: coverage_percent is not a number"
            raise InputError(msg) from exc
        out.update(coverage_percent=pct, coverage_percent_true=true_pct,
                   coverage_error_pp=pct - true_pct, coverage_abs_error_pp=abs(pct - true_pct))
    else:
        log.warning("%s: no coverage_percent; coverage not scored", atlas_dir / "atlas.json")
    png = atlas_dir / "atlas.png"
    if sim3 is None or not png.is_file() or "barycentre" not in meta:
        why = ("no alignment" if sim3 is None else "no atlas.png" if not png.is_file()
               else "no barycentre in atlas.json")
        log.warning("%s: atlas image not scored (%s)", atlas_dir, why)
        return out
    atlas_b = np.asarray(meta["barycentre"], dtype=np.float64)
    if atlas_b.shape != (3,):
        raise InputError(f"{atlas_dir / 'atlas.json'}: barycentre must be [x, y, z]")
    axes = np.asarray(meta.get("axes", np.eye(3)), dtype=np.float64)
    out.update(_score_atlas_image(truth, read_equirect(png), atlas_b, sim3, cfg, axes))
    return out


def _score_atlas_image(
    truth: Truth, atlas: np.ndarray, atlas_b: np.ndarray, sim3: Sim3, cfg: EvalConfig,
    axes: np.ndarray | None = None,
) -> dict[str, Any]:
    seen = truth.seen
    h, w = seen.shape
    dirs = equirect_directions(h, w).reshape(-1, 3)
    query = SurfaceQuery(truth.surface, truth.barycentre)
    t, tri = query.cast(truth.barycentre, dirs)
    hit = tri >= 0
    if not hit.any():
        raise InputError(f"{truth.directory}: rays from the barycentre miss surface.ply")
    cos_inc = np.abs(np.einsum("ij,ij->i", query.triangle_normals(tri[hit]), dirs[hit]))
    el = np.arcsin(np.clip(dirs[hit, 2], -1, 1))
    weight = np.zeros(len(dirs))
    weight[hit] = t[hit] ** 2 * np.cos(el) / np.maximum(cos_inc, cfg.atlas_min_cos_incidence)
    wall = truth.barycentre + t[hit, None] * dirs[hit]
    in_model = sim3.inverse().apply(wall)
    if axes is not None:  # atlas frame (atlas.json "axes": q = axes @ (p - barycentre))
        in_model = (in_model - atlas_b) @ axes.T + atlas_b
    row, col = equirect_pixels(in_model - atlas_b, *atlas.shape[:2])
    px = atlas[row, col]
    # bilinear, for the image comparison
    smooth = sample_bilinear(atlas.astype(np.float32),
                             *equirect_coords(in_model - atlas_b, *atlas.shape[:2])[::-1], wrap_columns=True)
    if atlas.ndim == 2:
        painted_hit, grey_hit = px > 0, px
    elif atlas.shape[2] in (2, 4):
        painted_hit = px[:, -1] > 0
        grey_hit = px[:, :-1].mean(axis=1)
    else:
        painted_hit, grey_hit = (px > 0).any(axis=1), px.mean(axis=1)
    painted = np.zeros(len(dirs), dtype=bool)
    painted[hit] = painted_hit
    s = seen.reshape(-1) & hit
    both = s & painted
    w_seen, w_painted = float(weight[s].sum()), float(weight[painted].sum())
    w_both, w_union = float(weight[both].sum()), float(weight[s | painted].sum())
    out: dict[str, Any] = {
        "painted_percent": 100.0 * w_painted / float(weight.sum()),
        "mask_recall": w_both / w_seen if w_seen > 0 else None,
        "mask_precision": w_both / w_painted if w_painted > 0 else None,
        "mask_iou": w_both / w_union if w_union > 0 else None,
    }
    grey = np.zeros(len(dirs))
    grey[hit] = grey_hit
    albedo = truth.albedo.reshape(-1)
    if both.sum() >= 3 and grey[both].std() > 0 and albedo[both].std() > 0:
        out["albedo_correlation"] = float(np.corrcoef(grey[both], albedo[both])[0, 1])
    else:
        out["albedo_correlation"] = None
    resampled = np.zeros(len(dirs))
    resampled[hit] = smooth[:, 0] if atlas.ndim == 2 else (
        smooth[:, :-1].mean(axis=1) if atlas.shape[2] in (2, 4) else smooth.mean(axis=1))
    out.update(_image_similarity(truth.albedo, resampled.reshape(h, w), both.reshape(h, w),
                                 weight.reshape(h, w)))
    return out


def _image_similarity(
    albedo: np.ndarray, atlas: np.ndarray, mask: np.ndarray, weight: np.ndarray
) -> dict[str, Any]:
    """How well the atlas (resampled onto the truth grid) reproduces the true albedo.

    Only where the wall is seen and painted, away from the mask's border by the SSIM window,
    averaged with the wall-area weights. The atlas is in arbitrary exposure units, so it is
    first scaled by the least-squares gain to the albedo (one number for the whole image:
    local contrast, blur and ghosting are still scored).

    - ``ssim``: SSIM (Wang et al. 2004; Gaussian window σ = 1.5 px) on the 0..255 scale.
      Lenient on a low-contrast wall, whose variance is small next to SSIM's constants, so also
    - ``ssim_stretched``: the same with the data range set to the albedo's own 1st-99th
      percentile range on the scored area (as if both images were contrast-stretched);
    - ``detail_correlation``: correlation of the high-pass parts (minus a Gaussian blur of
      σ = 8 px): vessels and grain in the right place, blind to slow shading differences;
    - ``sharpness_ratio``: mean gradient magnitude of the atlas over that of the albedo
      (1 = as sharp; blur or ghosting lowers it, noise raises it).
    """
    import cv2
    from skimage.metrics import structural_similarity

    inner = cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    if inner.sum() < 100:
        return {k: None for k in ("ssim", "ssim_stretched", "detail_correlation", "sharpness_ratio")}
    a, b = albedo[inner], atlas[inner]
    gain = float((a * b).sum() / max((b * b).sum(), 1e-12))
    scaled = np.clip(atlas * gain, 0, 255)
    wts = weight[inner]
    out: dict[str, Any] = {"exposure_gain": gain}
    lo, hi = np.percentile(a, [1, 99])
    for key, data_range in (("ssim", 255.0), ("ssim_stretched", max(float(hi - lo), 1.0))):
        _, ssim_map = structural_similarity(albedo, scaled, data_range=data_range, full=True,
                                            gaussian_weights=True, sigma=1.5,
                                            use_sample_covariance=False)
        out[key] = float(np.average(ssim_map[inner], weights=wts))

    def high_pass(img: np.ndarray) -> np.ndarray:
        img = img.astype(np.float32)
        return (img - cv2.GaussianBlur(img, (0, 0), 8.0))[inner]

    def gradient(img: np.ndarray) -> np.ndarray:
        img = img.astype(np.float32)
        gx, gy = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
        return np.hypot(gx, gy)[inner]

    ha, hb = high_pass(albedo), high_pass(scaled)
    out["detail_correlation"] = (float(np.corrcoef(ha, hb)[0, 1])
                                 if ha.std() > 0 and hb.std() > 0 else None)
    g_true = float(np.average(gradient(albedo), weights=wts))
    out["sharpness_ratio"] = (float(np.average(gradient(scaled), weights=wts)) / g_true
                              if g_true > 0 else None)
    return out
