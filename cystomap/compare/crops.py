"""Crops of a change for find-back: from both atlases and from the best frame of each session,
the change outlined in the colour of ``changes.png`` (the frame crops: :func:`cystomap.compare.findback.frame_crop`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cystomap.compare.images import HIGHLIGHT

CROP_MARGIN = 1.6  # a crop spans this many times the region's extent about its centroid


def spacing_px(uv: np.ndarray) -> float:
    """Distance between neighbouring projected points (the splat size): the 90th percentile
    of the nearest-neighbour distances, so that sparser directions (an atlas near a pole,
    a grazing view) are closed too."""
    from scipy.spatial import cKDTree

    if len(uv) < 2:
        return 1.0
    d, _ = cKDTree(uv).query(uv, k=2)
    return float(max(np.percentile(d[:, 1], 90), 0.5))


def crop_outlined(img: np.ndarray, centre: tuple[float, float], half: tuple[float, float],
                  uv: np.ndarray, out_px: int, wrap_columns: bool = False,
                  spacing: float | None = None) -> np.ndarray:
    """An ``out_px`` square RGB crop of ``img`` (RGB) about ``centre`` (col, row), ``half``
    (columns, rows) on each side (black outside the image; columns periodic with
    ``wrap_columns``), with the region made of the points ``uv`` (image pixels) outlined."""
    import cv2

    h, w = img.shape[:2]
    hx, hy = max(1, round(half[0])), max(1, round(half[1]))
    c0, r0 = round(centre[0]) - hx, round(centre[1]) - hy
    cols = np.arange(c0, c0 + 2 * hx + 1)
    rows = np.arange(r0, r0 + 2 * hy + 1)
    if wrap_columns:
        col_ok = np.ones(len(cols), bool)
        cols_src = np.mod(cols, w)
    else:
        col_ok = (cols >= 0) & (cols < w)
        cols_src = np.clip(cols, 0, w - 1)
    row_ok = (rows >= 0) & (rows < h)
    win = img[np.clip(rows, 0, h - 1)][:, cols_src, :3].copy()
    win[~row_ok] = 0
    win[:, ~col_ok] = 0
    mask = np.zeros(win.shape[:2], np.uint8)
    if len(uv):
        du = uv[:, 0] - c0
        if wrap_columns:
            du = np.mod(du + w / 2 - hx, w) - w / 2 + hx  # the nearest copy of each point
        iu, iv = np.rint(du).astype(int), np.rint(uv[:, 1] - r0).astype(int)
        inside = (iu >= 0) & (iu < mask.shape[1]) & (iv >= 0) & (iv < mask.shape[0])
        mask[iv[inside], iu[inside]] = 1
        s = spacing if spacing is not None else spacing_px(uv)
        r = max(1, math.ceil(s))
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, k)
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3)))
    shrink = win.shape[0] > out_px or win.shape[1] > out_px
    crop = cv2.resize(win, (out_px, out_px),
                      interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    if mask.any():
        m = cv2.resize(mask.astype(np.float32), (out_px, out_px),
                       interpolation=cv2.INTER_LINEAR)
        up = max(out_px / mask.shape[0], out_px / mask.shape[1])
        if up > 2:  # an enlarged crop: smooth the staircase of the source pixels
            m = cv2.GaussianBlur(m, (0, 0), up / 2)
        m = m > 0.5
        contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_SIMPLE)
        crop = np.ascontiguousarray(crop)
        cv2.drawContours(crop, contours, -1, HIGHLIGHT, max(1, out_px // 128), cv2.LINE_AA)
    return crop


def atlas_crop(atlas: Any, centroid: np.ndarray, points: np.ndarray, out_px: int) -> np.ndarray:
    """Crop of a session's atlas (SessionAtlas) about ``centroid`` with ``points`` outlined;
    columns widened by 1 / cos(elevation) so the crop is about square on the wall."""
    proj = atlas.proj
    col, row = proj.point_to_pixel(points)
    cc, cr = proj.point_to_pixel(centroid[None])
    cc, cr = float(cc[0]), float(cr[0])
    dc = np.mod(col - cc + proj.width / 2, proj.width) - proj.width / 2
    _, el = proj.pixel_to_angles(cc, cr)
    cos_el = max(math.cos(float(el)), 1e-3)
    extent = max(float(np.abs(row - cr).max()) if len(row) else 0.0,
                 float(np.abs(dc).max()) * cos_el if len(dc) else 0.0, 4.0)
    hy = min(CROP_MARGIN * extent, proj.height / 2)
    hx = min(hy / cos_el, proj.width / 2)
    rgb = atlas.rgba[..., :3].copy()
    rgb[atlas.rgba[..., 3] == 0] = 0
    uv = np.stack([col, row], axis=1)
    return crop_outlined(rgb, (cc, cr), (hx, hy), uv, out_px, wrap_columns=True)


