"""Resize and undistortion of the preprocess stage: the maps computed once per session, the
undistorted pinhole camera, and the undistortion of pixel positions."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from cystomap.camera import Camera

if TYPE_CHECKING:
    from cystomap.preprocess import PreprocessConfig

__all__ = ["_Geometry", "undistort_points"]


class _Geometry:
    """Resize + undistortion maps and the undistorted pinhole camera."""

    def __init__(self, camera: Camera, cfg: PreprocessConfig, scale: float | None = None) -> None:
        """``scale`` (default ``cfg.scale``): output size / ``camera``'s size."""
        self.camera = camera
        self.scale = cfg.scale if scale is None else scale
        src = camera.scaled(self.scale) if self.scale != 1.0 else camera
        self.src = src
        self.width, self.height = src.width, src.height
        size = (src.width, src.height)
        k = src.K
        if cfg.new_camera == "same" or not camera.has_distortion:
            new_k = k
        else:
            new_k = _new_camera_matrix(k, src.dist_array, size, cfg.new_camera)
        self.out_camera = replace(
            src.without_distortion(), fx=float(new_k[0, 0]), fy=float(new_k[1, 1]),
            cx=float(new_k[0, 2]), cy=float(new_k[1, 2]),
        )
        self.maps: tuple[np.ndarray, np.ndarray] | None = None
        self.valid = np.full((self.height, self.width), 255, np.uint8)
        if camera.has_distortion:
            self.maps = cv2.initUndistortRectifyMap(k, src.dist_array, None, new_k, size,
                                                    cv2.CV_16SC2)
            ones = np.full((self.height, self.width), 255, np.uint8)
            warped = self.remap(ones, cv2.INTER_LINEAR)
            self.valid = np.where(warped >= 255, 255, 0).astype(np.uint8)

    def resize(self, image: np.ndarray) -> np.ndarray:
        if (image.shape[1], image.shape[0]) == (self.width, self.height):
            return image
        shrink = self.width < image.shape[1]
        return cv2.resize(image, (self.width, self.height),
                          interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)

    def remap(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        if self.maps is None:
            return image
        return cv2.remap(image, self.maps[0], self.maps[1], interpolation,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def undistort(self, image: np.ndarray) -> np.ndarray:
        return self.remap(self.resize(image))


def _new_camera_matrix(k: np.ndarray, dist: np.ndarray, size: tuple[int, int], mode: str
                       ) -> np.ndarray:
    """K scaled by one factor about the same principal point (square pixels stay square):
    "crop" = the largest scale at which every output pixel has a source pixel, "full" = the
    scale at which every source pixel lands in the output."""
    w, h = size
    n = 64
    xs, ys = np.linspace(-0.5, w - 0.5, n), np.linspace(-0.5, h - 0.5, n)
    border = np.concatenate([
        np.column_stack([xs, np.full(n, -0.5)]),
        np.column_stack([np.full(n, w - 0.5), ys]),
        np.column_stack([xs[::-1], np.full(n, h - 0.5)]),
        np.column_stack([np.full(n, -0.5), ys[::-1]]),
    ])
    und = undistort_points(border, k, dist)  # pixels of the same K without distortion
    cx, cy = k[0, 2], k[1, 2]
    dx, dy = und[:, 0] - cx, und[:, 1] - cy
    if mode == "full":
        lim_x = np.where(dx > 0, w - 0.5 - cx, cx + 0.5)
        lim_y = np.where(dy > 0, h - 0.5 - cy, cy + 0.5)
        with np.errstate(divide="ignore"):
            s = float(min((lim_x / np.abs(dx)).min(), (lim_y / np.abs(dy)).min()))
    else:
        polygon = und.astype(np.float32).reshape(-1, 1, 2)
        rect = border - (cx, cy)

        def inside(scale: float) -> bool:
            pts = rect / scale + (cx, cy)
            return all(cv2.pointPolygonTest(polygon, (float(x), float(y)), False) >= 0
                       for x, y in pts)

        lo, hi = 0.05, 20.0  # scale lo: output rect far larger than the source; hi: tiny
        for _ in range(40):
            mid = math.sqrt(lo * hi)
            lo, hi = (lo, mid) if inside(mid) else (mid, hi)
        s = hi
    new_k = k.copy()
    new_k[0, 0] *= s
    new_k[1, 1] *= s
    return new_k


def undistort_points(points: np.ndarray, k: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Undistorted pixel positions (same K) of distorted pixels ``points`` (N x 2), iterated to
    convergence (OpenCV's default 5 iterations are not enough for strong endoscope distortion)."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
        out = cv2.undistortPointsIter(pts, k, dist, None, k, criteria)
    else:  # OpenCV 5: undistortPoints takes the criteria
        out = cv2.undistortPoints(pts, k, dist, R=None, P=k, criteria=criteria)
    return out.reshape(-1, 2)
