"""COLMAP models: where they are, reading them with pycolmap, their registered images' poses."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cystomap.errors import InputError

MODEL_FILES = ("cameras", "images", "points3D")


def is_model_dir(path: Path) -> bool:
    """Whether ``path`` holds a COLMAP model (binary or text)."""
    path = Path(path)
    return all((path / f"{n}.bin").is_file() or (path / f"{n}.txt").is_file() for n in MODEL_FILES)


def find_model_dir(sfm_dir: Path) -> Path | None:
    """The directory holding the COLMAP model (``sfm_dir`` itself or one level below)."""
    for d in (sfm_dir, *sorted(p for p in sfm_dir.glob("*") if p.is_dir())):
        if is_model_dir(d):
            return d
    return None


def model_dirs(path: Path) -> list[Path]:
    """``path`` when it is a model, else its sub-directories that are (sorted); [] if none."""
    path = Path(path)
    if not path.is_dir():
        return []
    if is_model_dir(path):
        return [path]
    return sorted(p for p in path.iterdir() if p.is_dir() and is_model_dir(p))


def read_model(model_dir: Path, what: str | None = None) -> Any:
    """``pycolmap.Reconstruction`` of one model directory; InputError if unreadable.

    ``what`` starts the error message (default: the directory).
    """
    import pycolmap

    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises plain RuntimeError / ValueError
        raise InputError(f"{what or model_dir}: cannot read the COLMAP model ({exc})") from exc


def load_reconstruction(sfm_dir: Path) -> Any:
    """The COLMAP model of ``sfm_dir`` (itself or its first sub-model) as a Reconstruction."""
    model = find_model_dir(Path(sfm_dir))
    if model is None:
        raise InputError(f"{sfm_dir}: no COLMAP model (cameras.bin, images.bin, points3D.bin)")
    return read_model(model)


def registered_images(rec: Any) -> list[Any]:
    """The images of ``rec`` that have a pose, in name order."""
    return sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)


def world_to_camera(image: Any) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (3, 3) and translation (3,) of a pycolmap image's world → camera pose."""
    cfw = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return (np.asarray(cfw.rotation.matrix(), dtype=np.float64),
            np.asarray(cfw.translation, dtype=np.float64).reshape(3))


def camera_centres(images: list[Any]) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world rotations (N, 3, 3) and camera centres (N, 3) of posed images."""
    rots, cens = [], []
    for im in images:
        r, t = world_to_camera(im)
        rots.append(r.T)
        cens.append(-r.T @ t)
    return np.array(rots).reshape(-1, 3, 3), np.array(cens).reshape(-1, 3)
