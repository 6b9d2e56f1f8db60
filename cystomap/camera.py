"""Pinhole camera with OpenCV distortion, as configured under ``cameras:``.

Conventions used throughout cystomap: OpenCV camera axes (x right, y down, z forward),
pixel centres at integer coordinates, distances in millimetres, poses camera-to-world.

COLMAP (the sfm stage's model) puts the *corner* of the first pixel at 0, so its pixel centres
and principal point are 0.5 px larger. The functions at the end of this module are the one place
where the two conventions meet: :func:`colmap_params` writes a :class:`Camera` into COLMAP,
:func:`opencv_calibration` reads a COLMAP camera back as an OpenCV ``K`` (for the image size at
hand), :func:`colmap_to_opencv_xy` / :func:`opencv_to_colmap_xy` convert keypoints.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.errors import InputError

DIST_KEYS = ("k1", "k2", "p1", "p2", "k3")
#: Parameters of the COLMAP camera models cystomap reads and writes (all with OpenCV's
#: distortion: SIMPLE_RADIAL's k is k1, RADIAL's k1, k2 and OPENCV's k1, k2, p1, p2 are
#: OpenCV's coefficients of the same names).
COLMAP_PARAMS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}


@dataclass(frozen=True)
class Camera:
    """Intrinsics of one camera; ``dist`` holds OpenCV's (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    calibrated: bool = True
    name: str = field(default="camera", compare=False)

    @classmethod
    def from_fov(
        cls, width: int, height: int, diagonal_fov_deg: float, name: str = "camera"
    ) -> Camera:
        """An uncalibrated camera: square pixels, centred principal point, no distortion."""
        if not 1.0 < diagonal_fov_deg < 179.0:
            raise InputError(f"camera {name!r}: diagonal_fov_deg={diagonal_fov_deg} is not in (1, 179)")
        f = 0.5 * math.hypot(width, height) / math.tan(math.radians(diagonal_fov_deg) / 2)
        return cls(width, height, f, f, (width - 1) / 2, (height - 1) / 2, calibrated=False, name=name)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], name: str = "camera") -> Camera:
        """Build from a ``cameras:`` entry: full calibration, or ``diagonal_fov_deg`` only."""
        try:
            width, height = int(cfg["width"]), int(cfg["height"])
        except KeyError as exc:
            raise InputError(f"camera {name!r}: missing key {exc.args[0]!r}") from None
        if width <= 0 or height <= 0:
            raise InputError(f"camera {name!r}: width and height must be positive")
        if all(k in cfg for k in ("fx", "fy", "cx", "cy")):
            dist = tuple(float(cfg.get(k, 0.0)) for k in DIST_KEYS)
            return cls(width, height, float(cfg["fx"]), float(cfg["fy"]), float(cfg["cx"]),
                       float(cfg["cy"]), dist, calibrated=True, name=name)  # type: ignore[arg-type]
        if "diagonal_fov_deg" in cfg:
            return cls.from_fov(width, height, float(cfg["diagonal_fov_deg"]), name=name)
        raise InputError(
            f"camera {name!r}: give either fx, fy, cx, cy (and optionally {', '.join(DIST_KEYS)})"
            " or diagonal_fov_deg"
        )

    @classmethod
    def from_colmap(
        cls, model: str, width: int, height: int, params: Any, name: str = "camera",
        calibrated: bool = True,
    ) -> Camera:
        """The camera of COLMAP ``model`` with ``params`` (COLMAP's convention: pixel corner at
        0, so its principal point is 0.5 px off OpenCV's)."""
        if model not in COLMAP_PARAMS:
            raise InputError(f"camera {name!r}: COLMAP model {model} is not one of "
                             f"{', '.join(COLMAP_PARAMS)}")
        v = dict(zip(COLMAP_PARAMS[model], (float(p) for p in params), strict=True))
        fx, fy = v.get("fx", v.get("f", 0.0)), v.get("fy", v.get("f", 0.0))
        dist = (v.get("k1", v.get("k", 0.0)), v.get("k2", 0.0), v.get("p1", 0.0),
                v.get("p2", 0.0), 0.0)
        return cls(int(width), int(height), fx, fy, v["cx"] - COLMAP_PIXEL_OFFSET, v["cy"] - COLMAP_PIXEL_OFFSET, dist,
                   calibrated=calibrated, name=name)

    def colmap_params(self, model: str) -> tuple[float, ...]:
        """Parameters of COLMAP ``model`` for this camera (inverse of :meth:`from_colmap`;
        a model without some coefficient drops it: one focal length is the mean of fx, fy)."""
        if model not in COLMAP_PARAMS:
            raise InputError(f"COLMAP camera model {model} is not one of {', '.join(COLMAP_PARAMS)}")
        v = {"f": 0.5 * (self.fx + self.fy), "fx": self.fx, "fy": self.fy,
             "cx": self.cx + COLMAP_PIXEL_OFFSET, "cy": self.cy + COLMAP_PIXEL_OFFSET, "k": self.dist[0],
             **dict(zip(DIST_KEYS, self.dist, strict=True))}
        return tuple(float(v[n]) for n in COLMAP_PARAMS[model])

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.dist)

    @property
    def diagonal_fov_deg(self) -> float:
        """Diagonal field of view of the pinhole model (distortion ignored)."""
        half_x = max(self.cx, self.width - 1 - self.cx) + 0.5
        half_y = max(self.cy, self.height - 1 - self.cy) + 0.5
        return math.degrees(2 * math.atan(math.hypot(half_x / self.fx, half_y / self.fy)))

    def scaled(self, factor: float) -> Camera:
        """The same camera for images resized by ``factor`` (pixel-centre convention kept)."""
        w, h = round(self.width * factor), round(self.height * factor)
        sx, sy = w / self.width, h / self.height
        return replace(
            self, width=w, height=h, fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
        )

    def without_distortion(self) -> Camera:
        return replace(self, dist=(0.0, 0.0, 0.0, 0.0, 0.0))

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project Nx3 points in camera coordinates to Nx2 pixels (with distortion)."""
        import cv2

        pts = np.ascontiguousarray(points_cam, dtype=np.float64).reshape(-1, 1, 3)
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist_array)
        return uv.reshape(-1, 2)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.update(zip(DIST_KEYS, self.dist, strict=True))
        del d["dist"]
        d["diagonal_fov_deg"] = round(self.diagonal_fov_deg, 4)
        return d

    def save(self, path: str | os.PathLike[str]) -> Path:
        from cystomap.outputs import write_json

        return write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Camera:
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"{path}: cannot read camera JSON ({exc})") from exc
        cam = cls.from_config(d, name=str(d.get("name", path.stem)))
        return replace(cam, calibrated=bool(d.get("calibrated", True)))


# --------------------------------------------------------------------------- COLMAP <-> OpenCV

COLMAP_PIXEL_OFFSET = 0.5  # COLMAP coordinate of the centre of pixel 0 (OpenCV: 0)


def colmap_params(camera: Camera, model: str = "PINHOLE") -> tuple[float, ...]:
    """Parameters of COLMAP ``model`` (PINHOLE, SIMPLE_PINHOLE, or a model with distortion such
    as RADIAL) of ``camera`` in COLMAP's convention (principal point + 0.5)."""
    return camera.colmap_params(model)


def opencv_calibration(colmap_camera: Any, width: int | None = None,
                       height: int | None = None) -> np.ndarray:
    """OpenCV ``K`` (pixel centres at integers) of a pycolmap camera, for its images resized
    to ``width`` x ``height`` (default: the camera's own size)."""
    k = np.asarray(colmap_camera.calibration_matrix(), dtype=np.float64).copy()
    sx = 1.0 if width is None else width / colmap_camera.width
    sy = 1.0 if height is None else height / colmap_camera.height
    # COLMAP coordinates scale with the image (corner at 0); then shift to pixel centres
    k[0, 0] *= sx
    k[1, 1] *= sy
    k[0, 1] *= sx
    k[0, 2] = k[0, 2] * sx - COLMAP_PIXEL_OFFSET
    k[1, 2] = k[1, 2] * sy - COLMAP_PIXEL_OFFSET
    return k


def colmap_to_opencv_xy(xy: np.ndarray, sx: float = 1.0, sy: float = 1.0) -> np.ndarray:
    """(N, 2) COLMAP image coordinates -> OpenCV pixels of the image resized by (sx, sy)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([xy[:, 0] * sx, xy[:, 1] * sy]) - COLMAP_PIXEL_OFFSET


def opencv_to_colmap_xy(xy: np.ndarray) -> np.ndarray:
    """(N, 2) OpenCV pixels (centres at integers) -> COLMAP image coordinates."""
    return np.asarray(xy, dtype=np.float64).reshape(-1, 2) + COLMAP_PIXEL_OFFSET
