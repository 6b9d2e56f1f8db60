"""Small synthetic ground truth in the phantom's formats, and reconstructions with known errors.

Independent of ``cystomap.phantom``: an ellipsoidal wall, cameras inside it, a seen mask
(elevation < 30°, minus the azimuth wedge 0°…60°), a smooth albedo, and lesions on the wall.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pandas as pd
from scipy.spatial.transform import Rotation

from cystomap.camera import Camera

SEMI_AXES = np.array([40.0, 32.0, 36.0])
CENTRE = np.array([5.0, -3.0, 2.0])
GRID_H = 90
CAMERA = Camera(320, 240, 200.0, 200.0, 159.5, 119.5, name="fake")
#: (azimuth deg, elevation deg, diameter mm) of the lesions of session B.
LESIONS = ((-120.0, 0.0, 3.0), (-30.0, -20.0, 3.0), (90.0, 10.0, 6.0), (150.0, -50.0, 6.0),
           (-80.0, 20.0, 4.0))


@dataclass(frozen=True)
class Transform:
    """x ↦ s·R·x + t (the tests' own Sim(3), truth → reconstruction)."""

    s: float = 1.0
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.s * np.asarray(x, float) @ self.R.T + self.t


#: The reconstruction frame used by most tests: half size, rotated, shifted.
MODEL_FRAME = Transform(0.5, Rotation.from_rotvec([0.3, -0.5, 0.8]).as_matrix(),
                        np.array([10.0, -4.0, 7.0]))


@dataclass(frozen=True)
class FakeTruth:
    directory: Path
    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray  # per vertex
    frames: np.ndarray
    rotations: np.ndarray  # camera-to-world
    centres: np.ndarray
    seen_fraction: float
    lesions: pd.DataFrame

    @property
    def barycentre(self) -> np.ndarray:
        return CENTRE.copy()


def direction(az_deg: np.ndarray | float, el_deg: np.ndarray | float) -> np.ndarray:
    az, el = np.radians(az_deg), np.radians(el_deg)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def az_el(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (np.degrees(np.arctan2(d[..., 1], d[..., 0])),
            np.degrees(np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))))


def is_seen(d: np.ndarray) -> np.ndarray:
    az, el = az_el(d)
    return (el < 30.0) & ~((az >= 0.0) & (az < 60.0))


def albedo_of(d: np.ndarray) -> np.ndarray:
    az, el = np.radians(az_el(d)[0]), np.radians(az_el(d)[1])
    vessels = np.abs(np.sin(7 * az + 5 * el)) < 0.3  # thin dark bands: detail to score
    return 128 + 60 * np.sin(2 * az) * np.cos(el) + 50 * np.sin(el) - 40 * vessels


def grid_directions(h: int) -> np.ndarray:
    w = 2 * h
    az = -180 + (np.arange(w) + 0.5) * 360 / w
    el = 90 - (np.arange(h) + 0.5) * 180 / h
    az, el = np.meshgrid(az, el)
    return direction(az, el)


def ellipsoid(resolution: int = 30) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=resolution)
    v = np.asarray(mesh.vertices) * SEMI_AXES + CENTRE
    mesh.vertices = o3d.utility.Vector3dVector(v)
    mesh.compute_vertex_normals()
    return v, np.asarray(mesh.triangles), np.asarray(mesh.vertex_normals)


def sample_mesh(v: np.ndarray, f: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = rng.choice(len(f), n, p=area / area.sum())
    u, w = rng.random(n), rng.random(n)
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    return a[tri] + u[:, None] * (b[tri] - a[tri]) + w[:, None] * (c[tri] - a[tri])


def write_ply(path: Path, v: np.ndarray, f: np.ndarray) -> Path:
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f))
    path.parent.mkdir(parents=True, exist_ok=True)
    assert o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def look_rotation(forward: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Camera-to-world rotation whose z axis (OpenCV forward) is ``forward``."""
    z = forward / np.linalg.norm(forward)
    x = np.cross(rng.normal(size=3), z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def make_truth(directory: Path, n_frames: int = 24, bad_frames: Sequence[int] = (3, 7),
               with_lesions: bool = True, seed: int = 1) -> FakeTruth:
    rng = np.random.default_rng(seed)
    directory.mkdir(parents=True, exist_ok=True)
    v, f, normals = ellipsoid()
    write_ply(directory / "surface.ply", v, f)
    CAMERA.save(directory / "camera.json")

    centres = CENTRE + rng.uniform(-0.5, 0.5, size=(n_frames, 3)) * SEMI_AXES
    rots = np.stack([look_rotation(rng.normal(size=3), rng) for _ in range(n_frames)])
    q = Rotation.from_matrix(rots).as_quat(scalar_first=True)
    poses = pd.DataFrame({"frame": np.arange(n_frames)})
    for i, k in enumerate(("qw", "qx", "qy", "qz")):
        poses[k] = q[:, i]
    for i, k in enumerate(("tx", "ty", "tz")):
        poses[k] = centres[:, i]
    poses.to_csv(directory / "poses.csv", index=False)

    dirs = grid_directions(GRID_H)
    cv2.imwrite(str(directory / "seen.png"), np.where(is_seen(dirs), 255, 0).astype(np.uint8))
    alb = np.clip(albedo_of(dirs), 0, 255).astype(np.uint8)
    cv2.imwrite(str(directory / "albedo.png"), np.repeat(alb[..., None], 3, axis=2))

    pts = sample_mesh(v, f, 200_000, rng)
    seen_fraction = float(is_seen(pts - CENTRE).mean())

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(
        o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f))))
    rows = []
    for i, (az, el, diam) in enumerate(LESIONS if with_lesions else ()):
        d = direction(az, el)
        ray = np.concatenate([CENTRE, d]).astype(np.float32)[None]
        hit = scene.cast_rays(o3d.core.Tensor(ray))
        p = CENTRE + float(hit["t_hit"].numpy()[0]) * d
        n = hit["primitive_normals"].numpy()[0]
        rows.append({"id": f"L{i}", "x": p[0], "y": p[1], "z": p[2], "nx": n[0], "ny": n[1],
                     "nz": n[2], "diameter_mm": diam, "azimuth_deg": az, "elevation_deg": el})
    cols = ["id", "x", "y", "z", "nx", "ny", "nz", "diameter_mm", "azimuth_deg", "elevation_deg"]
    lesions = pd.DataFrame(rows, columns=cols)
    lesions.to_csv(directory / "lesions.csv", index=False)

    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())
    meta = {"n_frames": n_frames, "barycentre": CENTRE.tolist(),
            "extent_mm": float(2 * SEMI_AXES.max()), "area_mm2": area,
            "seen_fraction": seen_fraction, "bad_frames": list(bad_frames)}
    (directory / "truth.json").write_text(json.dumps(meta, indent=2))
    return FakeTruth(directory, v, f, normals, np.arange(n_frames), rots, centres,
                     seen_fraction, lesions)


def write_model(
    directory: Path,
    truth: FakeTruth,
    frame: Transform = MODEL_FRAME,
    frames: Iterable[int] | None = None,
    centre_sigma_mm: float = 0.0,
    outliers: dict[int, Sequence[float]] | None = None,
    rotation_noise_deg: float = 0.0,
    pixel_error_px: float = 0.0,
    focal_factor: float = 1.0,
    n_points: int = 300,
    seed: int = 2,
    quality: dict | None = None,
) -> Path:
    """A COLMAP binary model of ``truth`` seen in ``frame`` (truth → model), with known errors.

    Camera centres get Gaussian noise of ``centre_sigma_mm`` per axis (truth mm) before the
    transform; each orientation is turned by exactly ``rotation_noise_deg`` about a random
    axis; every keypoint is displaced by exactly ``pixel_error_px`` from the projection of its
    3-D point in the model, so the model's mean reprojection error is ``pixel_error_px``.
    ``outliers`` adds a further offset (truth mm) to the centres of some frames. Only the
    registered images are written (pycolmap 4 drops images without a pose on write).
    """
    import pycolmap

    rng = np.random.default_rng(seed)
    frames = list(truth.frames if frames is None else frames)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "PINHOLE", CAMERA.fx, CAMERA.width,
                                                 CAMERA.height)
    cam.params = [CAMERA.fx * focal_factor, CAMERA.fy * focal_factor, CAMERA.cx + 0.5,
                  CAMERA.cy + 0.5]
    rec.add_camera_with_trivial_rig(cam)
    world_pts = frame(sample_mesh(truth.vertices, truth.triangles, n_points, rng))
    tracks: list[list[tuple[int, int]]] = [[] for _ in range(n_points)]
    for image_id, k in enumerate(frames, start=1):
        centre = truth.centres[k] + rng.normal(scale=centre_sigma_mm, size=3)
        centre = centre + np.asarray((outliers or {}).get(k, (0.0, 0.0, 0.0)))
        axis = rng.normal(size=3)
        turn = Rotation.from_rotvec(math.radians(rotation_noise_deg) * axis / np.linalg.norm(axis))
        r_c2w = frame.R @ truth.rotations[k] @ turn.as_matrix()
        r_cw = r_c2w.T
        t_cw = -r_cw @ frame(centre)
        in_cam = world_pts @ r_cw.T + t_cw
        uv = cam.img_from_cam(in_cam, check_cheirality=False)
        ok = (in_cam[:, 2] > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < CAMERA.width) \
            & (uv[:, 1] >= 0) & (uv[:, 1] < CAMERA.height)
        idx = np.flatnonzero(ok)
        phi = rng.uniform(0, 2 * math.pi, len(idx))
        kp = uv[idx] + pixel_error_px * np.column_stack([np.cos(phi), np.sin(phi)])
        image = pycolmap.Image(name=f"frames/f{k:06d}.png", keypoints=kp.reshape(-1, 2),
                               camera_id=1, image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(r_cw), t_cw))
        for p2d, p3d in enumerate(idx):
            tracks[p3d].append((image_id, p2d))
    for p3d, track in enumerate(tracks):
        if track:
            rec.add_point3D(world_pts[p3d],
                            pycolmap.Track([pycolmap.TrackElement(i, j) for i, j in track]))
    directory.mkdir(parents=True, exist_ok=True)
    rec.write(str(directory))
    if quality is not None:
        (directory / "quality.json").write_text(json.dumps(quality))
    return directory


def offset_mesh(truth: FakeTruth, offset_mm: float, frame: Transform = MODEL_FRAME,
                keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The true wall moved ``offset_mm`` along its normals, optionally only triangles ``keep``,
    expressed in ``frame``."""
    v = frame(truth.vertices + offset_mm * truth.normals)
    f = truth.triangles if keep is None else truth.triangles[keep]
    return v, f


def write_atlas(directory: Path, truth: FakeTruth, frame: Transform = MODEL_FRAME,
                coverage_percent: float | None = None, height: int = 100,
                paint_all: bool = False, ignore_rotation: bool = False) -> Path:
    """atlas.json + atlas.png (RGBA) in ``frame``: the true seen albedo resampled to the model
    frame about the transformed barycentre."""
    directory.mkdir(parents=True, exist_ok=True)
    d_model = grid_directions(height)
    d_truth = d_model if ignore_rotation else d_model @ frame.R  # R^T · d per pixel
    painted = np.ones(d_truth.shape[:2], bool) if paint_all else is_seen(d_truth)
    grey = np.clip(albedo_of(d_truth), 1, 255)
    rgba = np.zeros((*painted.shape, 4), np.uint8)
    rgba[..., :3] = np.where(painted, grey, 0)[..., None]
    rgba[..., 3] = np.where(painted, 255, 0)
    cv2.imwrite(str(directory / "atlas.png"), rgba)
    meta = {"barycentre": frame(truth.barycentre).tolist(),
            "coverage_percent": 100 * truth.seen_fraction if coverage_percent is None
            else coverage_percent}
    (directory / "atlas.json").write_text(json.dumps(meta))
    return directory


def write_changes(path: Path, rows: Sequence[dict], frame: Transform = MODEL_FRAME) -> Path:
    """changes.csv from detections given in the truth frame (x, y, z, diameter_mm, …)."""
    df = pd.DataFrame(rows)
    xyz = frame(df[["x", "y", "z"]].to_numpy(float))
    df[["x", "y", "z"]] = xyz
    df["diameter_mm"] = df["diameter_mm"] * frame.s
    if "area_mm2" in df:
        df["area_mm2"] = df["area_mm2"] * frame.s**2
    path.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(path, index=False)
    return path
