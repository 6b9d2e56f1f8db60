"""The pictures and tables the ``compare`` stage writes: atlases side by side, significance,
regions outlined on B's atlas and model, landmarks, CSV rows."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.compare.changes import Region
from cystomap.compare.config import CompareConfig
from cystomap.compare.difference import SessionAtlas
from cystomap.errors import StageError

HIGHLIGHT = (255, 40, 200)  # magenta: not a mucosa colour


def _rgb(rgba: np.ndarray, unseen: int = 0) -> np.ndarray:
    rgb = rgba[..., :3].copy()
    rgb[rgba[..., 3] == 0] = unseen
    return rgb


def side_by_side(rgba_a: np.ndarray, rgba_b: np.ndarray, gap: int = 8) -> np.ndarray:
    """A's atlas (left) and B's (right) at B's height, unseen black, a white gap between."""
    import cv2

    h = rgba_b.shape[0]
    a = _rgb(rgba_a)
    if a.shape[0] != h:
        a = cv2.resize(a, (round(a.shape[1] * h / a.shape[0]), h), interpolation=cv2.INTER_AREA)
    b = _rgb(rgba_b)
    sep = np.full((h, gap, 3), 255, np.uint8)
    img = np.hstack([a, sep, b])
    for text, x in (("A (earlier)", 10), ("B (later)", a.shape[1] + gap + 10)):
        cv2.putText(img, text, (x, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.9, (255, 255, 255), 2,
                    cv2.LINE_AA)
    return img


def significance_image(sig: np.ndarray, joint: np.ndarray, thr: float) -> np.ndarray:
    g = np.clip(sig / max(2 * thr, 1e-9) * 255, 0, 255).astype(np.uint8)
    img = np.dstack([g, g, g])
    above = joint & (sig > thr)
    img[above] = np.array([255, 0, 0], np.uint8)
    img[~joint] = 0
    return img


def region_masks(regions: list[Region], shape: tuple[int, int], proj_full: Any) -> np.ndarray:
    """(H, W) int32 labels (region id, 0 = none) at the full atlas size of ``proj_full``."""
    import cv2

    lab = np.zeros(shape[0] * shape[1], np.int32)
    for g in regions:
        lab[g.pixels] = g.id
    lab = lab.reshape(shape)
    if shape != (proj_full.height, proj_full.width):
        lab = cv2.resize(lab.astype(np.float32), (proj_full.width, proj_full.height),
                         interpolation=cv2.INTER_NEAREST).astype(np.int32)
    return lab


def _outline(mask: np.ndarray, width: int) -> np.ndarray:
    import cv2

    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * width + 1, 2 * width + 1))
    m = mask.astype(np.uint8)
    return (cv2.dilate(m, k) > 0) & ~(cv2.erode(m, k) > 0)


def outline_atlas(rgba: np.ndarray, labels: np.ndarray, regions: list[Region],
                  cfg: CompareConfig) -> np.ndarray:
    """B's atlas (unseen black) with each region outlined and numbered."""
    import cv2

    img = _rgb(rgba)
    edge = _outline(labels > 0, cfg.outline_px)
    img[edge] = HIGHLIGHT
    for g in regions:
        x, y = round(float(g.atlas_col)), round(float(g.atlas_row))
        r = max(6, round(float(math.sqrt(len(g.pixels)))))
        cv2.putText(img, str(g.id), (x + r, y - r), cv2.FONT_HERSHEY_SIMPLEX, 0.8,
                    (255, 255, 255), 3, cv2.LINE_AA)
        cv2.putText(img, str(g.id), (x + r, y - r), cv2.FONT_HERSHEY_SIMPLEX, 0.8, HIGHLIGHT,
                    2, cv2.LINE_AA)
    return img


def _write_model(path: Path, atlas_b: SessionAtlas, labels: np.ndarray,
                 cfg: CompareConfig) -> None:
    import cv2

    from cystomap.atlas.model import uv_unwrap, write_glb

    tex = _rgb(atlas_b.rgba, unseen=96).astype(np.float32)
    inside = labels > 0
    tex[inside] = 0.5 * tex[inside] + 0.5 * np.array(HIGHLIGHT, np.float32)
    tex[_outline(inside, cfg.outline_px)] = HIGHLIGHT
    tex = np.clip(np.rint(tex), 0, 255).astype(np.uint8)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(tex[..., ::-1]))
    if not ok:
        raise StageError("cannot encode the changes texture")
    tm = uv_unwrap(atlas_b.vertices, atlas_b.faces, atlas_b.proj)
    write_glb(path, tm, png.tobytes(), name="bladder wall, changes highlighted")


def draw_landmarks(rgba: np.ndarray, rows: list[dict[str, Any]]) -> np.ndarray:
    import cv2

    img = _rgb(rgba)
    for r in rows:
        if r.get("status") != "ok":
            continue
        x, y = round(float(r["atlas_col"])), round(float(r["atlas_row"]))
        cv2.drawMarker(img, (x, y), (0, 255, 255), cv2.MARKER_CROSS, 24, 3)
        cv2.putText(img, str(r["name"]), (x + 10, y - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.8,
                    (0, 255, 255), 2, cv2.LINE_AA)
    return img


def _write_csv(path: Path, columns: tuple[str, ...], rows: list[dict[str, Any]]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
