"""Image file helpers shared by the stages."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from cystomap.errors import StageError


def imwrite_rgb(path: Path, img: np.ndarray) -> None:
    """Write an RGB or RGBA (or grey) array with OpenCV, which expects BGR(A)."""
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    elif img.ndim == 3:
        img = img[..., ::-1]
    if not cv2.imwrite(str(path), np.ascontiguousarray(img)):
        raise StageError(f"cannot write {path}")
