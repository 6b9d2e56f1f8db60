"""Video decoding and field-of-view detection, shared by the ``frames`` and ``preprocess`` stages.

Endoscope images usually show the scene inside a circle or an octagon surrounded by black; the
lit area (the field of view, FOV) is found from the data: a high temporal percentile of many
frames, thresholded relative to its own bright level, largest connected component, convex hull
(the optics' FOV is convex, so dark lumen areas inside it are filled). Overlaid text in the
border is a separate component and is dropped.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cystomap.errors import InputError
from cystomap.parallel import ordered_map as ordered_map  # re-exported: preprocess, frames

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VideoInfo:
    """What the container says about a video (frame_count and fps are hints, may be 0)."""

    path: Path
    width: int
    height: int
    fps: float
    frame_count: int


def open_video(path: str | Path) -> tuple[cv2.VideoCapture, VideoInfo]:
    """Open ``path`` with the FFmpeg backend; :class:`InputError` if missing or not a video."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a directory, not a video file")
    if not path.is_file():
        raise InputError(f"{path}: video file not found")
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        cap.release()
        raise InputError(f"{path}: cannot open as a video (unreadable or not a video file)")
    width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
    height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    fps = float(cap.get(cv2.CAP_PROP_FPS))
    if not math.isfinite(fps) or fps <= 0 or fps > 1000:
        fps = 0.0
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    return cap, VideoInfo(path, width, height, fps, max(count, 0))


def iter_frames(path: str | Path) -> Iterator[tuple[int, float, np.ndarray]]:
    """Yield ``(index, time_s, bgr)`` for every decodable frame, streaming."""
    cap, info = open_video(path)
    try:
        index = 0
        while True:
            ok, frame = cap.read()
            if not ok or frame is None:
                break
            yield index, frame_time(cap, index, info.fps), frame
            index += 1
    finally:
        cap.release()


def frame_time(cap: cv2.VideoCapture, index: int, fps: float) -> float:
    """Timestamp of the frame just read, in seconds (index / fps when the container has no fps)."""
    if fps > 0:
        return index / fps
    msec = float(cap.get(cv2.CAP_PROP_POS_MSEC))
    return msec / 1000.0 if math.isfinite(msec) and msec >= 0 else float(index)


def temporal_std(samples: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """Per-pixel standard deviation over a sequence of equally sized grey images (float32)."""
    s1: np.ndarray | None = None
    s2: np.ndarray | None = None
    for sample in samples:
        f = np.asarray(sample, dtype=np.float32)
        s1 = f.copy() if s1 is None else s1 + f
        s2 = f * f if s2 is None else s2 + f * f
    if s1 is None or s2 is None:
        raise ValueError("no samples")
    n = float(len(samples))
    return np.sqrt(np.maximum(s2 / n - (s1 / n) ** 2, 0.0))


def fov_mask(
    level: np.ndarray, variation: np.ndarray | None = None, rel_threshold: float = 0.15,
    min_share: float = 0.05, full_share: float = 0.97,
) -> np.ndarray | None:
    """Field-of-view mask (uint8, 255 = inside) from a per-pixel brightness image ``level``.

    ``level`` should be a high temporal percentile (e.g. the 75th) of grey frames, so the FOV is
    bright there and the black border stays near zero. A pixel is lit above ``rel_threshold``
    times the image's 99th percentile. With ``variation`` (the per-pixel temporal std of the
    same frames), lit pixels must also change over time, which drops static overlays (text,
    logos) touching the FOV; ignored when that would leave too little (a still camera).
    The largest lit component's convex hull is the FOV. Returns a full mask when it covers
    nearly the whole image (share > ``full_share``), and None when no plausible FOV is found
    (share below ``min_share``: e.g. an all-dark video); the caller decides what to do then.
    """
    level = np.asarray(level, dtype=np.float32)
    h, w = level.shape
    if h < 4 or w < 4:
        return np.full((h, w), 255, np.uint8)
    level = cv2.GaussianBlur(level, (0, 0), 1.0)
    high = float(np.percentile(level, 99))
    if high <= 0:
        return None
    lit = level > rel_threshold * high
    candidates = [lit]
    if variation is not None and lit.any():
        variation = np.asarray(variation, dtype=np.float32)
        moving = lit & (variation > 0.1 * float(np.median(variation[lit])))
        candidates.insert(0, moving)
    for candidate in candidates:
        mask = _hull_of_largest(candidate.astype(np.uint8), min_share)
        if mask is not None:
            break
    else:
        return None
    share = float(np.count_nonzero(mask)) / (h * w)
    if share > full_share:
        return np.full((h, w), 255, np.uint8)
    return mask


def static_pixels(
    tstd: np.ndarray | None, inside: np.ndarray, rel: float, max_share: float = 0.1
) -> np.ndarray | None:
    """Pixels of the FOV (bool ``inside``) that hardly change over a set of frames: temporal std
    ``tstd`` below ``rel`` times its median inside, grown by 3 px (overlaid text, logos, dirt on
    the lens). Their crisp edges would pass for sharpness and their corners for a scene that
    does not move. None when ``tstd`` is None or ``rel`` is 0, and when more than ``max_share``
    of the FOV is static (a still camera: then nothing is excluded)."""
    if tstd is None or rel <= 0 or not inside.any():
        return None
    typical = float(np.median(tstd[inside]))
    if typical <= 0:
        return None
    static = (inside & (tstd < rel * typical)).astype(np.uint8)
    static = cv2.dilate(static, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))) > 0
    static &= inside
    if np.count_nonzero(static) > max_share * np.count_nonzero(inside):
        return None
    return static


def _hull_of_largest(binary: np.ndarray, min_share: float) -> np.ndarray | None:
    h, w = binary.shape
    k = max(3, round(min(h, w) / 60) | 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    if n <= 1:
        return None
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    if stats[best, cv2.CC_STAT_AREA] < min_share * h * w:
        return None
    comp = (labels == best).astype(np.uint8)
    contours, _ = cv2.findContours(comp, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    hull = cv2.convexHull(np.concatenate(contours))
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, hull, 255)
    return mask


def lit_extent(mask: np.ndarray) -> int:
    """Longest side (px) of the bounding box of the lit pixels of ``mask`` (> 127); the
    image's longest side when none is lit."""
    ys, xs = np.nonzero(mask > 127)
    if len(xs) == 0:
        return max(mask.shape[:2])
    return int(max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1))


def erode(mask: np.ndarray, px: int) -> np.ndarray:
    """Shrink a 0/255 mask by ``px`` pixels away from its rim inside the image (where the FOV is
    cut by the image edge, the edge is not a rim and is not eroded; a full mask stays full)."""
    if px <= 0:
        return mask
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    return cv2.erode(mask, kernel, borderType=cv2.BORDER_REPLICATE)


def fit_circle(mask: np.ndarray) -> tuple[float, float, float] | None:
    """Least-squares circle (cx, cy, r) through the FOV rim, ignoring rim points on the image edge
    (so a circle cut by the frame is fitted correctly). None if too little rim is visible."""
    h, w = mask.shape
    contours, _ = cv2.findContours((mask > 0).astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    pts = np.concatenate(contours).reshape(-1, 2).astype(np.float64)
    inner = (pts[:, 0] > 1) & (pts[:, 0] < w - 2) & (pts[:, 1] > 1) & (pts[:, 1] < h - 2)
    pts = pts[inner]
    if len(pts) < 20:
        return None
    # Kasa fit: x² + y² = 2 a x + 2 b y + c
    a_mat = np.column_stack([2 * pts[:, 0], 2 * pts[:, 1], np.ones(len(pts))])
    rhs = (pts**2).sum(axis=1)
    (a, b, c), *_ = np.linalg.lstsq(a_mat, rhs, rcond=None)
    r2 = c + a * a + b * b
    if r2 <= 0:
        return None
    # contour pixels lie on the last inside pixel: the edge is half a pixel further out
    return float(a), float(b), float(math.sqrt(r2)) + 0.5


def circle_mask(shape: tuple[int, int], cx: float, cy: float, r: float) -> np.ndarray:
    """0/255 mask of the pixels whose centres lie within ``r`` of (cx, cy)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    return np.where((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r, 255, 0).astype(np.uint8)
