"""The phantom's ground truth of one session, and the geometry shared by the scores.

A truth directory holds ``truth.json``, ``poses.csv``, ``camera.json``, ``surface.ply``,
``seen.png``, ``albedo.png`` and ``lesions.csv`` (formats in the module ``cystomap.evaluate``).
``truth.json`` and ``poses.csv`` are read up front; the others when a score needs them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cystomap.camera import Camera
from cystomap.errors import InputError
from cystomap.geometry.raycast import MeshRays
from cystomap.geometry.trimesh import triangle_areas
from cystomap.io.ply import read_mesh as read_triangle_mesh
from cystomap.outputs import read_json_object

log = logging.getLogger(__name__)

POSE_COLUMNS = ("frame", "qw", "qx", "qy", "qz", "tx", "ty", "tz")
LESION_COLUMNS = ("id", "x", "y", "z", "diameter_mm")
TRUTH_KEYS = ("n_frames", "barycentre", "extent_mm", "seen_fraction")


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh as plain arrays (vertices Nx3 float64, triangles Mx3 int)."""

    vertices: np.ndarray
    triangles: np.ndarray

    def transformed(self, sim3: Any) -> Mesh:
        return Mesh(sim3.apply(self.vertices), self.triangles)

    @property
    def triangle_areas(self) -> np.ndarray:
        return triangle_areas(self.vertices, self.triangles)


@dataclass(frozen=True)
class Truth:
    """Ground truth of one session; files other than truth.json and poses.csv load lazily."""

    directory: Path
    meta: dict[str, Any]
    frames: np.ndarray  # (N,) int, frame index of each row of poses.csv
    rotations: np.ndarray  # (N, 3, 3) camera-to-world
    centres: np.ndarray  # (N, 3) camera centres, mm

    @property
    def n_frames(self) -> int:
        return int(self.meta["n_frames"])

    @property
    def bad_frames(self) -> frozenset[int]:
        return frozenset(int(f) for f in self.meta.get("bad_frames") or ())

    @property
    def barycentre(self) -> np.ndarray:
        return np.asarray(self.meta["barycentre"], dtype=np.float64)

    @property
    def extent_mm(self) -> float:
        return float(self.meta["extent_mm"])

    @property
    def seen_fraction(self) -> float:
        return float(self.meta["seen_fraction"])

    def in_opening(self, points: np.ndarray) -> np.ndarray:
        """Whether each point lies, seen from the barycentre, in the cone of an opening of the
        wall (truth.json ``aperture``: azimuth_deg, elevation_deg, angular_radius_deg), where
        the true surface is open and a closed reconstruction must bridge the gap."""
        ap = self.meta.get("aperture")
        d = np.asarray(points, dtype=np.float64) - self.barycentre
        if not isinstance(ap, dict) or not {"azimuth_deg", "elevation_deg",
                                             "angular_radius_deg"} <= ap.keys():
            return np.zeros(len(d), dtype=bool)
        az, el = np.radians(float(ap["azimuth_deg"])), np.radians(float(ap["elevation_deg"]))
        axis = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cos = d @ axis / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        return cos > np.cos(np.radians(float(ap["angular_radius_deg"])))

    @cached_property
    def camera(self) -> Camera:
        return Camera.load(self._file("camera.json"))

    @cached_property
    def surface(self) -> Mesh:
        return read_mesh(self._file("surface.ply"))

    @cached_property
    def seen(self) -> np.ndarray:
        """Boolean equirectangular mask about the barycentre: True = seen by a frame."""
        return read_equirect(self._file("seen.png"), grey=True) > 127

    @cached_property
    def albedo(self) -> np.ndarray:
        """Grey equirectangular albedo (float, 0..255) on the grid of ``seen``."""
        img = read_equirect(self._file("albedo.png"), grey=True)
        if img.shape != self.seen.shape:
            raise InputError(
                f"{self.directory / 'albedo.png'}: size {img.shape[1]}x{img.shape[0]} differs from "
                f"seen.png {self.seen.shape[1]}x{self.seen.shape[0]}"
            )
        return img

    @cached_property
    def lesions(self) -> pd.DataFrame:
        path = self._file("lesions.csv")
        df = read_csv(path, LESION_COLUMNS)
        if (df["diameter_mm"] <= 0).any():
            raise InputError(f"{path}: diameter_mm must be positive")
        return df

    def _file(self, name: str) -> Path:
        path = self.directory / name
        if not path.is_file():
            raise InputError(f"truth file {path} not found (the phantom writes it per session)")
        return path


def load_truth(directory: str | Path) -> Truth:
    """Read ``truth.json`` and ``poses.csv`` of a truth directory; check their contents."""
    directory = Path(directory)
    meta_path = directory / "truth.json"
    if not meta_path.is_file():
        raise InputError(f"truth file {meta_path} not found (is {directory} a truth directory?)")
    meta = read_json_object(meta_path)
    missing = [k for k in TRUTH_KEYS if k not in meta]
    if missing:
        raise InputError(f"{meta_path}: missing key(s) {', '.join(missing)}")
    if np.asarray(meta["barycentre"]).shape != (3,):
        raise InputError(f"{meta_path}: barycentre must be [x, y, z]")
    poses_path = directory / "poses.csv"
    if not poses_path.is_file():
        raise InputError(f"truth file {poses_path} not found")
    df = read_csv(poses_path, POSE_COLUMNS)
    if df["frame"].duplicated().any():
        raise InputError(f"{poses_path}: duplicate frame indices")
    q = df[["qw", "qx", "qy", "qz"]].to_numpy(np.float64)
    norm = np.linalg.norm(q, axis=1)
    if (np.abs(norm - 1) > 1e-3).any():
        raise InputError(f"{poses_path}: quaternions must be unit length (w, x, y, z)")
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_quat(q / norm[:, None], scalar_first=True).as_matrix()
    return Truth(
        directory=directory,
        meta=meta,
        frames=df["frame"].to_numpy(np.int64),
        rotations=rot.reshape(-1, 3, 3),
        centres=df[["tx", "ty", "tz"]].to_numpy(np.float64),
    )


def read_csv(path: Path, required: tuple[str, ...]) -> pd.DataFrame:
    """A CSV with the ``required`` numeric columns (InputError naming the file otherwise)."""
    try:
        df = pd.read_csv(path)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise InputError(f"{path}: cannot read CSV ({exc})") from exc
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise InputError(
            f"{path}: missing column(s) {', '.join(missing)}; "
            f"found {', '.join(df.columns) or 'none'}"
        )
    for c in required:
        if c == "id":
            continue
        try:
            df[c] = pd.to_numeric(df[c])
        except (ValueError, TypeError) as exc:
            raise InputError(f"{path}: column {c} is not numeric ({exc})") from exc
    return df


def read_mesh(path: Path) -> Mesh:
    """Triangles of a PLY (or other open3d-readable) mesh; InputError if unreadable or empty."""
    return Mesh(*read_triangle_mesh(path))


def read_equirect(path: Path, grey: bool = False) -> np.ndarray:
    """An equirectangular image (width = 2 × height) as float; grey = mean of the colour channels.

    A colour image is returned as (H, W, C) in the file's channel order, alpha included.
    """
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: cannot read image")
    h, w = img.shape[:2]
    if w != 2 * h:
        raise InputError(f"{path}: equirectangular image must be 2:1 (width:height), got {w}x{h}")
    scale = 255.0 / 65535.0 if img.dtype == np.uint16 else 1.0  # 16-bit to the 8-bit scale
    img = img.astype(np.float64) * scale
    if grey and img.ndim == 3:
        img = img[..., : min(3, img.shape[2])].mean(axis=2)
    return img


def equirect_directions(height: int, width: int) -> np.ndarray:
    """Unit directions (H, W, 3) of the pixel centres of an equirectangular grid."""
    az = np.radians(-180.0 + (np.arange(width) + 0.5) * 360.0 / width)
    el = np.radians(90.0 - (np.arange(height) + 0.5) * 180.0 / height)
    az, el = np.meshgrid(az, el)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def equirect_pixels(
    directions: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) of the pixel containing each direction (need not be unit length)."""
    row, col = equirect_coords(directions, height, width)
    col_i = np.floor(col + 0.5).astype(np.int64) % width
    row_i = np.clip(np.floor(row + 0.5).astype(np.int64), 0, height - 1)
    return row_i, col_i


def equirect_coords(
    directions: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """Continuous (row, column) of each direction, pixel centres at integers."""
    d = np.asarray(directions, dtype=np.float64)
    az = np.arctan2(d[..., 1], d[..., 0])
    el = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
    return (math.pi / 2 - el) / math.pi * height - 0.5, (az + math.pi) / (2 * math.pi) * width - 0.5


def sample_surface(mesh: Mesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniformly distributed over the mesh area."""
    areas = mesh.triangle_areas
    total = areas.sum()
    if not total > 0:
        raise InputError("mesh has zero area")
    tri = rng.choice(len(areas), size=n, p=areas / total)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a, b, c = (mesh.vertices[mesh.triangles[tri, i]] for i in range(3))
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


class SurfaceQuery(MeshRays):
    """Distances to, and rays onto, a mesh (open3d RaycastingScene, float32 about ``origin``)."""

    def __init__(self, mesh: Mesh, origin: np.ndarray | None = None) -> None:
        super().__init__(mesh.vertices, mesh.triangles,
                         np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64))
        self.mesh = mesh
