"""``regions.png``: the atlas with the standard bladder regions drawn as a labelled grid."""

from __future__ import annotations

import math

import numpy as np

from cystomap.anatomy import DOME_CAP_DEG, NECK_CAP_DEG, WALL_SECTORS, Anatomy
from cystomap.atlas.projection import Projection

ORIENTATION_NOTE = (
    "anatomical (cystomap.anatomy): neck at the bottom row, dome at the top row; the wall "
    "seen from inside as when facing the patient: posterior wall in the centre column, the "
    "patient's right wall to its left, the left wall to its right, anterior wall at both "
    "edges; column = clock position seen from the neck (12 = anterior, 3 = patient's left)")
LEGEND = ("DOME top, NECK bottom; seen from inside, facing the patient: patient's RIGHT "
          "on the left, LEFT on the right", "columns: clock position seen from the neck, "
          "12 = anterior (at the edges), 6 = posterior (centre)")
GRID = (255, 255, 255)
TEXT = (255, 255, 0)


def _az(hours: float) -> float:
    """Atlas azimuth (radians) of a clock position (anatomical atlas axes)."""
    return math.radians(180.0 - 30.0 * hours)


def region_overlay(rgba: np.ndarray, proj: Projection, anatomy: Anatomy,
                   anatomical: bool = True) -> np.ndarray:
    """RGB atlas (unseen dark grey) with the region grid, names, clock ticks and a legend.

    ``anatomical``: the atlas axes are :func:`cystomap.anatomy.atlas_axes` (grid lines are
    straight); otherwise each pixel's region is looked up and the borders drawn.
    """
    import cv2

    h, w = rgba.shape[:2]
    img = rgba[..., :3].copy()
    img[rgba[..., 3] == 0] = 40
    img = np.ascontiguousarray(img)
    scale = max(0.4, h / 1024)
    thick = max(1, round(2 * scale))
    font = cv2.FONT_HERSHEY_SIMPLEX

    def put(text: str, x: float, y: float, size: float = 0.9, colour=TEXT) -> None:
        fs = size * scale
        (tw, th), _ = cv2.getTextSize(text, font, fs, thick)
        org = (round(x - tw / 2), round(y + th / 2))
        for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):  # a dark outline, same advance
            cv2.putText(img, text, (org[0] + dx, org[1] + dy), font, fs, (0, 0, 0), thick,
                        cv2.LINE_AA)
        cv2.putText(img, text, org, font, fs, colour, thick, cv2.LINE_AA)

    if anatomical:
        _, row_neck = proj.angles_to_pixel(0.0, math.radians(NECK_CAP_DEG - 90.0))
        _, row_dome = proj.angles_to_pixel(0.0, math.radians(90.0 - DOME_CAP_DEG))
        y_neck, y_dome = float(row_neck), float(row_dome)
        for y in (y_neck, y_dome):
            cv2.line(img, (0, round(y)), (w - 1, round(y)), GRID, thick, cv2.LINE_AA)
        for _, start, _ in WALL_SECTORS:
            x, _ = proj.angles_to_pixel(_az(start), 0.0)
            cv2.line(img, (round(float(x)), round(y_dome)), (round(float(x)), round(y_neck)),
                     GRID, thick, cv2.LINE_AA)
        for name, start, end in WALL_SECTORS:
            mid = (start + (end - start) % 12 / 2) % 12
            x, _ = proj.angles_to_pixel(_az(mid), 0.0)
            xs = [float(x)] if name != "anterior wall" else [w * 0.06, w * 0.94]
            for xx in xs:
                put(name.upper(), xx, (y_neck + y_dome) / 2)
        put("DOME", w / 2, max(y_dome / 2, 90 * scale))
        put("TRIGONE / NECK", w / 2, (y_neck + h) / 2)
        for hour in range(1, 13):
            x, _ = proj.angles_to_pixel(_az(hour), 0.0)
            for xx in ([float(x)] if hour != 12 else [0.0, w - 1.0]):
                cv2.line(img, (round(xx), round(y_neck) - round(8 * scale)),
                         (round(xx), round(y_neck) + round(8 * scale)), GRID, thick)
                put(str(hour), min(max(xx, 14 * scale), w - 14 * scale),
                    y_neck + 22 * scale, 0.7, GRID)
    else:
        names = anatomy.regions(proj.grid_directions().reshape(-1, 3) + proj.barycentre)
        codes = np.unique(names, return_inverse=True)[1].reshape(h, w).astype(np.uint8)
        edge = (cv2.morphologyEx(codes, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0)
        img[edge] = GRID
    for i, line in enumerate(LEGEND):
        put(line, w / 2, (22 + 30 * i) * scale, 0.8, GRID)
    return img
