"""The registered frames of a session: pose, intrinsics (OpenCV convention) and colour file.

The atlas paints from them; compare reads them again for photo-consistency and find-back.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cystomap.camera import opencv_calibration
from cystomap.errors import InputError
from cystomap.io.colmap import load_reconstruction, registered_images, world_to_camera

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class View:
    """One registered frame: world→camera pose, intrinsics, the colour image file and, if the
    preprocess stage wrote one, its mask of clipped pixels (255 = clipped)."""

    name: str
    rotation: np.ndarray  # (3, 3) world → camera
    translation: np.ndarray  # (3,)
    K: np.ndarray  # (3, 3) for the colour image's pixel grid
    width: int
    height: int
    path: Path
    clipped: Path | None = None

    @property
    def centre(self) -> np.ndarray:
        return -self.rotation.T @ self.translation

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        return points @ self.rotation.T + self.translation



def load_views(
    sfm_dir: Path, preprocessed_dir: Path, max_views: int = 0
) -> tuple[list[View], np.ndarray]:
    """Registered frames with their colour files, and the field-of-view mask (bool)."""
    import cv2

    from cystomap.sfm.intrinsics import frames_dir

    preprocessed_dir = frames_dir(sfm_dir, preprocessed_dir)  # undistorted if self-calibrated
    color_dir = preprocessed_dir / "color"
    clipped_dir = preprocessed_dir / "clipped"
    if not color_dir.is_dir():
        raise InputError(f"{color_dir}: preprocessed colour frames not found")
    rec = load_reconstruction(sfm_dir)
    images = registered_images(rec)
    if not images:
        raise InputError(f"{sfm_dir}: the COLMAP model has no registered image")
    mask_path = preprocessed_dir / "mask.png"
    mask = None
    if mask_path.is_file():
        mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise InputError(f"{mask_path}: cannot read image")
    views: list[View] = []
    missing: list[str] = []
    for im in images:
        path = color_dir / Path(im.name).name
        if not path.is_file():
            alt = sorted(color_dir.glob(Path(im.name).stem + ".*"))
            if not alt:
                missing.append(im.name)
                continue
            path = alt[0]
        if mask is None:
            first = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if first is None:
                raise InputError(f"{path}: cannot read image")
            mask = np.full(first.shape, 255, np.uint8)
        cam = rec.cameras[im.camera_id]
        model = str(cam.model.name if hasattr(cam.model, "name") else cam.model)
        if model not in ("PINHOLE", "SIMPLE_PINHOLE"):
            log.warning("%s: camera model %s; its distortion is ignored (frames should be "
                        "undistorted)", im.name, model)
        h, w = mask.shape
        k = opencv_calibration(cam, w, h)
        rot, trans = world_to_camera(im)
        clipped = clipped_dir / path.name
        views.append(View(im.name, rot, trans, k, w, h, path,
                          clipped if clipped.is_file() else None))
    if missing:
        log.warning("%s: %d registered frame(s) without a colour file, e.g. %s", color_dir,
                    len(missing), missing[0])
    if not views:
        raise InputError(f"{color_dir}: none of the {len(images)} registered frames is there")
    if max_views and len(views) > max_views:
        keep = np.unique(np.linspace(0, len(views) - 1, max_views).round().astype(int))
        views = [views[i] for i in keep]
    assert mask is not None
    return views, mask > 127
