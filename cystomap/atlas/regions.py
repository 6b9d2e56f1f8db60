"""``regions.png``: the atlas with the standard bladder regions drawn as a labelled grid."""

from __future__ import annotations

import math

import numpy as np

from cystomap.anatomy import DOME_CAP_DEG, NECK_CAP_DEG, WALL_SECTORS, Anatomy
from cystomap.atlas.projection import Projection, SurfaceRays

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


def region_grid(anatomy: Anatomy, rays: SurfaceRays,
                step_deg: float = 2.0) -> dict[str, list]:
    """The region borders and names on the wall (model frame), for the 3-D views.

    ``lines``: polylines (lists of [x, y, z]) where rays from the anatomical origin along the
    borders meet the mesh ``rays``: the neck and dome caps' circles and, between them, the
    wall sectors' meridians (a ray that misses, e.g. through an open aperture, breaks its
    line); ``labels``: ``{"text", "xyz"}`` per region, on the wall at its middle (the
    trigone/neck's half-way to the neck, at 6 o'clock: the neck itself is the aperture).
    """
    n, a, left = anatomy.neck, anatomy.anterior, anatomy.left

    def dirs(polar_deg: np.ndarray, hours: np.ndarray) -> np.ndarray:
        p, t = np.radians(polar_deg), np.radians(30.0 * hours)
        side = np.cos(t)[:, None] * a + np.sin(t)[:, None] * left
        return np.cos(p)[:, None] * n + np.sin(p)[:, None] * side

    def on_wall(d: np.ndarray) -> np.ndarray:
        t, _ = rays.cast(anatomy.origin, d)
        return anatomy.origin + np.where(np.isfinite(t), t, np.nan)[:, None] * d  # NaN: a miss

    def pieces(points: np.ndarray) -> list[list[list[float]]]:
        ok = np.isfinite(points).all(axis=1)
        out, cur = [], []
        for p, good in zip(points, ok, strict=True):
            if good:
                cur.append([round(float(x), 3) for x in p])
            elif cur:
                out.append(cur)
                cur = []
        if cur:
            out.append(cur)
        return [c for c in out if len(c) >= 2]

    k = max(8, math.ceil(360.0 / step_deg))
    ring = np.arange(k + 1) * (12.0 / k)  # closed: the last point is the first
    lines = []
    for polar in (NECK_CAP_DEG, 180.0 - DOME_CAP_DEG):
        lines += pieces(on_wall(dirs(np.full(len(ring), polar), ring)))
    m = max(2, math.ceil((180.0 - DOME_CAP_DEG - NECK_CAP_DEG) / step_deg))
    span = np.linspace(NECK_CAP_DEG, 180.0 - DOME_CAP_DEG, m + 1)
    for _, start, _ in WALL_SECTORS:
        lines += pieces(on_wall(dirs(span, np.full(len(span), start))))
    names, polar, hours = [], [], []
    for name, start, end in WALL_SECTORS:
        names.append(name)
        polar.append(90.0)
        hours.append((start + (end - start) % 12 / 2) % 12)
    names += ["trigone/neck", "dome"]
    polar += [NECK_CAP_DEG / 2, 180.0]
    hours += [6.0, 6.0]
    at = on_wall(dirs(np.array(polar), np.array(hours)))
    labels = [{"text": name, "xyz": [round(float(x), 3) for x in p]}
              for name, p in zip(names, at, strict=True) if np.isfinite(p).all()]
    return {"lines": lines, "labels": labels}
