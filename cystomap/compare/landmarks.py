"""Find back: landmarks marked in session A carried into session B.

A landmark is given either as a pixel of A's atlas (``col``, ``row``; continuous, pixel
centres at integers) or as a point of A's model frame (``x``, ``y``, ``z``). Atlas pixels go
to A's wall (ray from A's barycentre to A's mesh); the point goes through the A → B warp
(similarity + thin-plate spline) and is put on B's wall along its direction from B's
barycentre; it is reported in B's model frame and as a pixel of B's atlas.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.atlas.projection import pixel_to_point
from cystomap.errors import InputError

LANDMARK_COLUMNS = ("name", "source", "a_col", "a_row", "a_x", "a_y", "a_z", "x", "y", "z",
                    "azimuth_deg", "elevation_deg", "atlas_col", "atlas_row",
                    "off_wall_mm", "status")


@dataclass(frozen=True)
class Landmark:
    """A site marked in session A: an atlas pixel (col, row) or a model point (x, y, z)."""

    name: str
    col: float | None = None
    row: float | None = None
    point: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        pixel = self.col is not None and self.row is not None
        if pixel == (self.point is not None):
            raise InputError(f"landmark {self.name!r}: give either col and row (atlas pixel) "
                             "or x, y, z (model point)")


def as_landmark(item: Any, index: int) -> Landmark:
    """A :class:`Landmark` from a Landmark, a mapping (name, col/row or x/y/z) or a tuple
    (col, row) / (x, y, z)."""
    if isinstance(item, Landmark):
        return item
    name = f"L{index + 1}"
    if isinstance(item, Mapping):
        name = str(item.get("name") or name)
        try:
            if item.get("x") not in (None, "") and item.get("col") in (None, ""):
                return Landmark(name, point=(float(item["x"]), float(item["y"]),
                                             float(item["z"])))
            return Landmark(name, col=float(item["col"]), row=float(item["row"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"landmark {name!r}: needs col, row or x, y, z ({exc})") from exc
    values = tuple(item)
    if len(values) == 2:
        return Landmark(name, col=float(values[0]), row=float(values[1]))
    if len(values) == 3:
        return Landmark(name, point=(float(values[0]), float(values[1]), float(values[2])))
    raise InputError(f"landmark {index + 1}: expected (col, row) or (x, y, z), got {item!r}")


def read_landmarks(path: Path) -> list[Landmark]:
    """Landmarks from a CSV with columns name and col, row or x, y, z (per row)."""
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise InputError(f"{path}: cannot read landmarks ({exc})") from exc
    return [as_landmark(r, i) for i, r in enumerate(rows)]


def map_landmarks(landmarks: Iterable[Any], atlas_a: Any, atlas_b: Any,
                  registration: Any) -> list[dict[str, Any]]:
    """One output row per landmark (see :data:`LANDMARK_COLUMNS`)."""
    items = [as_landmark(x, i) for i, x in enumerate(landmarks)]
    rows: list[dict[str, Any]] = []
    for lm in items:
        row: dict[str, Any] = {k: "" for k in LANDMARK_COLUMNS}
        row["name"] = lm.name
        if lm.point is not None:
            row["source"] = "point"
            pa = np.asarray(lm.point, dtype=np.float64)
        else:
            row["source"] = "atlas"
            row["a_col"], row["a_row"] = lm.col, lm.row
            pts, hit = pixel_to_point(atlas_a.proj, atlas_a.rays, [lm.col], [lm.row])
            if not hit[0]:
                row["status"] = "not on A's wall (ray misses A's mesh)"
                rows.append(row)
                continue
            pa = pts[0]
        row["a_x"], row["a_y"], row["a_z"] = (float(v) for v in pa)
        if registration is None or not registration.registered:
            row["status"] = "not registered"
            rows.append(row)
            continue
        pb = registration.warp_ab(pa[None])[0]
        proj = atlas_b.proj
        d = pb - proj.barycentre
        d = d / max(float(np.linalg.norm(d)), 1e-12)
        t, _ = atlas_b.rays.cast(proj.barycentre, d[None])
        if not np.isfinite(t[0]):
            row["status"] = "not on B's wall (ray misses B's mesh)"
            rows.append(row)
            continue
        wall = proj.barycentre + t[0] * d
        col, r = proj.point_to_pixel(wall[None])
        q = proj.axes @ d
        row.update(x=float(wall[0]), y=float(wall[1]), z=float(wall[2]),
                   azimuth_deg=math.degrees(math.atan2(q[1], q[0])),
                   elevation_deg=math.degrees(math.atan2(q[2], math.hypot(q[0], q[1]))),
                   atlas_col=float(col[0]), atlas_row=float(r[0]),
                   off_wall_mm=float(np.linalg.norm(pb - wall)), status="ok")
        rows.append(row)
    return rows
