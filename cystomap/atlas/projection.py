"""Atlas projections: atlas pixel ↔ direction from the barycentre ↔ point on the wall.

Atlas frame: ``q = axes @ (p - barycentre)`` for a point ``p`` of the SfM frame (``axes``: rows
are the atlas x, y, z axes in SfM coordinates; the identity unless stated). A direction
``q / |q|`` has azimuth ``az = atan2(q_y, q_x)`` and elevation ``el = asin(q_z / |q|)``::

    direction(az, el) = (cos el · cos az, cos el · sin az, sin el)

Pixels: column ``col``, row ``row``, pixel centres at integers, ``col`` 0 at the left.

* ``equirectangular``: az = −180° + (col + ½)·360°/W, el = 90° − (row + ½)·180°/H
  (W = 2H by default).
* ``equal_area`` (Lambert cylindrical equal-area): az as above, sin el = 1 − (row + ½)·2/H:
  every pixel covers the same solid angle (4π / (W·H)).

A pixel maps to the wall point where the ray from the barycentre along its direction first
meets the surface mesh (the wall is star-shaped about the barycentre, so the map is one-to-one);
a wall point maps back through its direction. :func:`pixel_to_point` and :func:`point_to_pixel`
implement the two directions; continuous pixel coordinates are accepted and returned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cystomap.geometry.raycast import MeshRays

PROJECTIONS = ("equirectangular", "equal_area")


@dataclass(frozen=True)
class Projection:
    """One atlas grid: projection kind, size, centre and axes of the atlas frame."""

    kind: str
    width: int
    height: int
    barycentre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axes: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        if self.kind not in PROJECTIONS:
            raise ValueError(f"projection {self.kind!r} is not one of {', '.join(PROJECTIONS)}")
        if self.width < 2 or self.height < 2:
            raise ValueError(f"atlas size {self.width}x{self.height} is too small")
        object.__setattr__(self, "barycentre", np.asarray(self.barycentre, dtype=np.float64))
        axes = np.asarray(self.axes, dtype=np.float64)
        if axes.shape != (3, 3) or not np.allclose(axes @ axes.T, np.eye(3), atol=1e-6):
            raise ValueError("atlas axes must be a 3x3 rotation matrix")
        object.__setattr__(self, "axes", axes)

    # ---- pixel ↔ (azimuth, elevation), radians

    def pixel_to_angles(self, col: Any, row: Any) -> tuple[np.ndarray, np.ndarray]:
        col = np.asarray(col, dtype=np.float64)
        row = np.asarray(row, dtype=np.float64)
        az = -math.pi + (col + 0.5) * (2 * math.pi / self.width)
        if self.kind == "equirectangular":
            el = math.pi / 2 - (row + 0.5) * (math.pi / self.height)
        else:
            el = np.arcsin(np.clip(1.0 - (row + 0.5) * (2.0 / self.height), -1.0, 1.0))
        return az, el

    def angles_to_pixel(self, az: Any, el: Any) -> tuple[np.ndarray, np.ndarray]:
        az = np.asarray(az, dtype=np.float64)
        el = np.asarray(el, dtype=np.float64)
        col = (az + math.pi) * (self.width / (2 * math.pi)) - 0.5
        if self.kind == "equirectangular":
            row = (math.pi / 2 - el) * (self.height / math.pi) - 0.5
        else:
            row = (1.0 - np.sin(el)) * (self.height / 2.0) - 0.5
        return col, row

    # ---- pixel ↔ unit direction (SfM frame)

    def pixel_to_direction(self, col: Any, row: Any) -> np.ndarray:
        az, el = self.pixel_to_angles(col, row)
        q = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
        return q @ self.axes  # atlas frame → SfM frame (axesᵀ q)

    def direction_to_pixel(self, directions: Any) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(directions, dtype=np.float64) @ self.axes.T
        az = np.arctan2(q[..., 1], q[..., 0])
        el = np.arctan2(q[..., 2], np.hypot(q[..., 0], q[..., 1]))
        return self.angles_to_pixel(az, el)

    def point_to_pixel(self, points: Any) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (col, row) of SfM-frame points, through their direction from the centre."""
        return self.direction_to_pixel(np.asarray(points, dtype=np.float64) - self.barycentre)

    # ---- grids

    def grid_directions(self) -> np.ndarray:
        """(H, W, 3) unit directions of all pixel centres."""
        col, row = np.meshgrid(np.arange(self.width), np.arange(self.height))
        return self.pixel_to_direction(col, row)

    def pixel_solid_angle(self) -> np.ndarray:
        """(H,) solid angle (steradian) of the pixels of each row."""
        rows = np.arange(self.height, dtype=np.float64)
        _, el_top = self.pixel_to_angles(0, rows - 0.5)
        _, el_bot = self.pixel_to_angles(0, rows + 0.5)
        el_top = np.clip(el_top, -math.pi / 2, math.pi / 2)
        el_bot = np.clip(el_bot, -math.pi / 2, math.pi / 2)
        return (2 * math.pi / self.width) * (np.sin(el_top) - np.sin(el_bot))

    def uv(self, points: Any) -> np.ndarray:
        """Texture coordinates in [0, 1]² (u right, v down: glTF convention) of SfM points."""
        col, row = self.point_to_pixel(points)
        return np.stack([(col + 0.5) / self.width, (row + 0.5) / self.height], axis=-1)

    def to_json(self) -> dict[str, Any]:
        """The contract written to atlas.json (see the module docstring)."""
        if self.kind == "equirectangular":
            el_rule = "el = 90 - (row + 0.5) * 180 / height (degrees)"
            row_rule = "row = (90 - el) * height / 180 - 0.5"
        else:
            el_rule = "sin(el) = 1 - (row + 0.5) * 2 / height"
            row_rule = "row = (1 - sin(el)) * height / 2 - 0.5"
        return {
            "projection": self.kind,
            "width": self.width,
            "height": self.height,
            "barycentre": self.barycentre.tolist(),
            "axes": self.axes.tolist(),
            "contract": {
                "frame": "q = axes @ (p - barycentre) for an SfM-frame point p (mm)",
                "pixel_centres": "integer (col, row); col 0 = left, row 0 = top",
                "pixel_to_direction": "az = -180 + (col + 0.5) * 360 / width (degrees); "
                + el_rule + "; q = (cos el cos az, cos el sin az, sin el); d = axes^T q",
                "pixel_to_point": "p = barycentre + t d, t = distance to the first hit of the ray "
                "(barycentre, d) with the surface mesh",
                "point_to_pixel": "q = axes @ (p - barycentre); az = atan2(q_y, q_x); "
                "el = atan2(q_z, hypot(q_x, q_y)); col = (az + 180) * width / 360 - 0.5; "
                + row_rule,
                "code": "cystomap.atlas.projection.pixel_to_point / point_to_pixel",
            },
        }

    @classmethod
    def from_json(cls, meta: dict[str, Any]) -> Projection:
        return cls(str(meta["projection"]), int(meta["width"]), int(meta["height"]),
                   np.asarray(meta["barycentre"], float),
                   np.asarray(meta.get("axes", np.eye(3)), float))


#: ray queries on the wall mesh (the core wrapper, under the atlas's name)
SurfaceRays = MeshRays


def pixel_to_point(
    proj: Projection, surface: SurfaceRays, col: Any, row: Any
) -> tuple[np.ndarray, np.ndarray]:
    """Wall points (N, 3) of atlas pixels (continuous coordinates) and whether each ray hit."""
    col = np.asarray(col, dtype=np.float64).ravel()
    row = np.asarray(row, dtype=np.float64).ravel()
    d = proj.pixel_to_direction(col, row)
    t, _ = surface.cast(proj.barycentre, d)
    hit = np.isfinite(t)
    pts = np.full((len(d), 3), np.nan)
    pts[hit] = proj.barycentre + t[hit, None] * d[hit]
    return pts, hit


def point_to_pixel(proj: Projection, points: Any) -> tuple[np.ndarray, np.ndarray]:
    """Continuous (col, row) of wall points; integer parts (rounded) index atlas.png."""
    return proj.point_to_pixel(points)
