"""Small seeded synthetic videos and images for the frames / preprocess tests."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from cystomap.video import iter_frames

WIDTH, HEIGHT = 320, 180


def texture(height: int, width: int, seed: int = 0, contrast: float = 1.0,
            detail: tuple[float, float] | None = None) -> np.ndarray:
    """A colour, mucosa-like texture (multi-scale blobs and thin 'vessels'), uint8 BGR.

    ``detail`` = (left, right) scales the fine structure (small blobs and vessels) linearly
    across the width: e.g. (1, 0.1) goes from vessel-rich mucosa to a smooth, featureless patch,
    everything in focus.
    """
    rng = np.random.default_rng(seed)
    acc = np.zeros((height, width), np.float32)
    ramp = None if detail is None else np.linspace(*detail, width, dtype=np.float32)[None, :]
    for sigma, weight in ((12.0, 1.0), (4.0, 0.7), (1.5, 0.5)):
        noise = rng.standard_normal((height, width)).astype(np.float32)
        noise = cv2.GaussianBlur(noise, (0, 0), sigma)
        layer = weight * noise / (noise.std() + 1e-6)
        acc += layer if ramp is None or sigma > 10 else layer * ramp
    vessels = np.zeros((height, width), np.uint8)
    for _ in range(max(4, width * height // 4000)):
        pts = np.cumsum(rng.normal(0, 6, (12, 2)), axis=0) + rng.uniform((0, 0), (width, height))
        cv2.polylines(vessels, [pts.astype(np.int32).reshape(-1, 1, 2)], False, 255, 1,
                      cv2.LINE_AA)
    lines = vessels.astype(np.float32) if ramp is None else vessels.astype(np.float32) * ramp
    acc = acc / (acc.std() + 1e-6) - 1.2 * lines / 255
    grey = 128 + 40 * contrast * acc
    bgr = np.stack([0.55 * grey, 0.65 * grey, 1.0 * grey + 20], axis=-1)
    return np.clip(bgr, 0, 255).astype(np.uint8)


def write_video(path: Path, frames: list[np.ndarray], fps: float = 25.0) -> Path:
    """Write BGR frames with cv2.VideoWriter (mp4v)."""
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    assert writer.isOpened(), f"cannot write {path}"
    for f in frames:
        writer.write(np.ascontiguousarray(f))
    writer.release()
    return path


def circle_border(frame: np.ndarray, cx: float, cy: float, r: float) -> np.ndarray:
    """Black out everything outside the circle (an endoscope's round field of view)."""
    h, w = frame.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    out = frame.copy()
    out[(xx - cx) ** 2 + (yy - cy) ** 2 > r * r] = 0
    return out


def pan_frames(
    n: int, speed: float = 4.0, size: tuple[int, int] = (WIDTH, HEIGHT), seed: int = 0,
    replace: Mapping[int, str] | None = None, circle: tuple[float, float, float] | None = None,
    detail: tuple[float, float] | None = None, jumps: Mapping[int, float] | None = None,
) -> list[np.ndarray]:
    """``n`` frames panning right over a texture at ``speed`` px/frame.

    ``replace`` maps frame index to a defect: "blur" (Gaussian sigma 3), "black", "white",
    "dup" (exact copy of the previous frame). ``circle`` = (cx, cy, r) blacks out the outside.
    ``detail`` is passed to :func:`texture` (its fine structure fading along the pan).
    ``jumps`` maps frame index to an extra leap in px from that frame on (the camera moving
    too fast for frame-to-frame tracking).
    """
    w, h = size
    jumps = jumps or {}
    big = texture(h, w + int(np.ceil(speed * n + sum(jumps.values()))) + 2, seed,
                  detail=detail)
    frames = []
    for i in range(n):
        x = speed * i + sum(v for k, v in jumps.items() if k <= i)
        m = np.float32([[1, 0, -x], [0, 1, 0]])
        f = cv2.warpAffine(big, m, (w, h), flags=cv2.INTER_LINEAR)
        kind = (replace or {}).get(i)
        if kind == "blur":
            f = cv2.GaussianBlur(f, (0, 0), 3.0)
        elif kind == "black":
            f = np.zeros_like(f)
        elif kind == "white":
            f = np.full_like(f, 255)
        elif kind == "dup":
            f = frames[-1].copy()
        elif kind is not None:
            raise ValueError(kind)
        if circle is not None and kind != "dup":
            f = circle_border(f, *circle)
        frames.append(f)
    return frames


def decode_all(path: Path) -> list[np.ndarray]:
    return [f for _, _, f in iter_frames(path)]


# ------------------------------------------------------------------ images for preprocess


def grid_image(height: int, width: int, step: int = 20) -> np.ndarray:
    """A smooth dark-line grid on light grey (BGR), lines every ``step`` px, slightly blurred."""
    img = np.full((height, width), 200, np.uint8)
    for x in range(step // 2, width, step):
        cv2.line(img, (x, 0), (x, height - 1), 40, 2)
    for y in range(step // 2, height, step):
        cv2.line(img, (0, y), (width - 1, y), 40, 2)
    img = cv2.GaussianBlur(img, (0, 0), 1.2)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def distort(image: np.ndarray, k: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """What a camera with intrinsics ``k`` and OpenCV distortion ``dist`` sees, given the ideal
    pinhole image ``image`` (same intrinsics, no distortion): for every distorted pixel find its
    undistorted position (cv2.undistortPoints, iterated) and sample the ideal image there."""
    h, w = image.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    pts = np.stack([xx.ravel(), yy.ravel()], axis=-1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
        und = cv2.undistortPointsIter(pts, k, dist, None, k, criteria)
    else:  # OpenCV 5: undistortPoints takes the criteria
        und = cv2.undistortPoints(pts, k, dist, R=None, P=k, criteria=criteria)
    und = und.reshape(h, w, 2).astype(np.float32)
    return cv2.remap(image, und[..., 0], und[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def vignette(image: np.ndarray, strength: float = 0.7, center: tuple[float, float] | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Multiply by a smooth radial falloff (1 at ``center``, 1-strength at the far corner)."""
    h, w = image.shape[:2]
    cx, cy = center if center is not None else ((w - 1) / 2, (h - 1) / 2)
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / max(
        (cx**2 + cy**2), ((w - cx) ** 2 + (h - cy) ** 2))
    falloff = (1.0 - strength * r2).astype(np.float32)
    out = np.clip(image.astype(np.float32) * falloff[..., None], 0, 255).astype(np.uint8)
    return out, falloff


def scope_frames(n: int = 60, size: tuple[int, int] = (WIDTH, HEIGHT), seed: int = 7,
                 blurred: tuple[int, ...] = (), dimmed: tuple[int, ...] = (),
                 contrast: float = 0.5) -> list[np.ndarray]:
    """A harder, cystoscopy-like sequence: low-contrast texture seen through a round FOV with
    overlaid text (a time stamp in the corner, "REC" inside the FOV), rotating (with tremor),
    zooming in and drifting; vignetting, sensor noise and moving specular glints. Frames in
    ``blurred`` are defocused (sigma 2.5), frames in ``dimmed`` are at a tenth of the
    brightness (a light dip)."""
    w, h = size
    rng = np.random.default_rng(seed)
    big = texture(2 * h + 4 * n, 2 * w + 4 * n, seed=seed, contrast=contrast)
    frames = []
    for i in range(n):
        angle = 1.0 * i + 2.0 * np.sin(i / 4)
        cx, cy = big.shape[1] / 2 + 2.0 * i, big.shape[0] / 2 + 1.0 * i
        m = cv2.getRotationMatrix2D((cx, cy), angle, 1.0 + 0.006 * i)
        m[:, 2] += (w / 2 - cx, h / 2 - cy)
        f = cv2.warpAffine(big, m, (w, h), flags=cv2.INTER_LINEAR)
        f, _ = vignette(f, 0.5)
        for _ in range(4):
            p = (int(rng.uniform(0.2 * w, 0.8 * w)), int(rng.uniform(0.2 * h, 0.8 * h)))
            cv2.circle(f, p, int(rng.integers(1, 4)), (255, 255, 255), -1)
        f = np.clip(f.astype(np.float32) + rng.normal(0, 3.0, f.shape), 0, 255).astype(np.uint8)
        if i in blurred:
            f = cv2.GaussianBlur(f, (0, 0), 2.5)
        if i in dimmed:
            f = (f * 0.1).astype(np.uint8)
        f = circle_border(f, w / 2, h / 2, 0.45 * w)
        cv2.putText(f, f"00:{i:02d}", (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    (255, 255, 255), 1)  # time stamp in the black corner
        cv2.putText(f, "REC", (w // 2 - 12, h // 5), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (255, 255, 255), 1)  # a static overlay inside the FOV
        frames.append(f)
    return frames
