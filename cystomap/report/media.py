"""Images for the report: read, composite, downsample and embed as data URIs."""

from __future__ import annotations

import base64
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cystomap.errors import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Embedded:
    """One image ready for an ``<img>`` tag."""

    uri: str
    width: int
    height: int
    source: Path | None = None  # the full-size file it was made from

    @property
    def nbytes(self) -> int:
        return len(self.uri)


def read_rgba(path: Path) -> np.ndarray:
    """An image file as RGB or RGBA uint8 (16-bit scaled down, grey made RGB)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: cannot read image")
    if img.dtype != np.uint8:
        img = (img / 257).astype(np.uint8) if img.dtype == np.uint16 else img.astype(np.uint8)
    if img.ndim == 2:
        return np.dstack([img] * 3)
    order = [2, 1, 0, 3] if img.shape[2] == 4 else [2, 1, 0]
    return np.ascontiguousarray(img[..., order])


def over(img: np.ndarray, background: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """RGB uint8: an RGBA image's transparent pixels composited over ``background``."""
    if img.shape[2] != 4:
        return img
    alpha = img[..., 3:4].astype(np.float32) / 255.0
    bg = np.array(background, np.float32)
    return np.rint(img[..., :3] * alpha + bg * (1 - alpha)).astype(np.uint8)


def read_rgb(path: Path, background: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """An image file as RGB uint8; transparent pixels (alpha) composited over ``background``."""
    return over(read_rgba(path), background)


def downsample(rgb: np.ndarray, max_width: int) -> np.ndarray:
    """At most ``max_width`` pixels wide (area averaging), aspect kept; never upscaled."""
    import cv2

    h, w = rgb.shape[:2]
    if w <= max_width:
        return rgb
    new_h = max(1, round(h * max_width / w))
    return cv2.resize(rgb, (max_width, new_h), interpolation=cv2.INTER_AREA)


def encode(rgb: np.ndarray, jpeg_quality: int) -> tuple[str, bytes]:
    """(mime type, bytes): JPEG, or PNG when that is smaller (flat colours, lossless)."""
    import cv2

    bgr = np.ascontiguousarray(rgb[..., ::-1])
    ok_j, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality),
                                          cv2.IMWRITE_JPEG_OPTIMIZE, 1])
    ok_p, png = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not (ok_j and ok_p):
        raise InputError("cannot encode an image for the report")
    if len(png) <= len(jpg):
        return "image/png", png.tobytes()
    return "image/jpeg", jpg.tobytes()


def embed_array(rgb: np.ndarray, max_width: int, jpeg_quality: int, source: Path | None = None) -> Embedded:
    small = downsample(rgb, max_width)
    mime, data = encode(small, jpeg_quality)
    uri = f"data:{mime};base64," + base64.b64encode(data).decode("ascii")
    return Embedded(uri, int(small.shape[1]), int(small.shape[0]), source)


def embed_file(path: Path, max_width: int, jpeg_quality: int,
               background: tuple[int, int, int] = (0, 0, 0)) -> Embedded:
    """``path`` downsampled and encoded for the report (transparent areas over ``background``)."""
    return embed_array(read_rgb(path, background), max_width, jpeg_quality, Path(path))
