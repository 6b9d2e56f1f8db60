"""Descriptors of the 3-D points of an SfM model: the mean SIFT descriptor of each track.

The SfM stage keeps no descriptors, so they are computed again with OpenCV SIFT at the
track's 2-D keypoints on the ``enhanced/`` frames. Each observation is described at the same
*physical* scale (keypoint size = focal length × ``keypoint_size_mm`` / depth), so a point seen
from 30 mm in one session and from 80 mm in the other gets comparable descriptors. The
orientation is SIFT's (peak of the Gaussian-weighted gradient-orientation histogram at the
keypoint's scale), so the descriptor does not depend on the roll of the camera. The
RootSIFT-normalised descriptors of a track are averaged (as the reference study averages the
SURF descriptors of each homologous point) and normalised again.
"""

from __future__ import annotations

import logging
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cystomap.camera import colmap_to_opencv_xy, opencv_calibration
from cystomap.errors import InputError
from cystomap.io.colmap import load_reconstruction, world_to_camera
from cystomap.sfm.intrinsics import frames_dir

log = logging.getLogger(__name__)

N_LEVELS = 9  # orientation gradient scales 1.6 · 2^(l/2), l = 0 … 8 (σ 1.6 … 25.6 px)
ORI_GRID = 9  # orientation histogram: ORI_GRID × ORI_GRID samples over ±4.5 σ
ORI_BINS = 36


@dataclass(frozen=True)
class PointFeatures:
    """3-D points of one model with their mean descriptor."""

    ids: np.ndarray  # (N,) point3D ids
    xyz: np.ndarray  # (N, 3) model frame
    desc: np.ndarray  # (N, 128) float32, unit length (mean RootSIFT)
    n_obs: np.ndarray  # (N,) observations averaged
    n_points_model: int  # points in the model before filtering
    n_images: int  # registered images used
    # (M, 3) every point that passed the track and error filters, before spreading and
    # describing (the compare stage's raised-centroid test reads them: cystomap.compare.relief)
    kept_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass
class _Obs:
    image: str
    xy: np.ndarray  # (n, 2) OpenCV pixel coordinates (centres at integers)
    size: np.ndarray  # (n,) keypoint size in pixels
    row: np.ndarray  # (n,) index into the kept points


def _image_size(enhanced: Path, name: str) -> tuple[int, int] | None:
    import cv2

    path = enhanced / Path(name).name
    if not path.is_file():
        return None
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    return None if img is None else (img.shape[1], img.shape[0])


def spread_subset(xyz: np.ndarray, track: np.ndarray, n: int) -> np.ndarray:
    """Indices of at most ``n`` points spread evenly over the cloud: one per cell of a
    voxel grid (the point with the longest track), the cell size chosen so that about ``n``
    cells are occupied. Deterministic."""
    if len(xyz) <= n:
        return np.arange(len(xyz))
    span = float(np.ptp(xyz, axis=0).max()) or 1.0
    lo, hi = span / 4096, span
    best = None
    for _ in range(30):  # bisection on the cell size (occupied cells fall as it grows)
        mid = math.sqrt(lo * hi)
        if len(np.unique(_cell_keys(xyz, mid))) > n:
            lo = mid
        else:
            hi, best = mid, mid
        if hi / lo < 1.01:
            break
    keys = _cell_keys(xyz, best or hi)
    order = np.lexsort((np.arange(len(xyz)), -track))  # longest tracks first, stable
    _, first = np.unique(keys[order], return_index=True)  # first occurrence of each cell
    return np.sort(order[first])


def _cell_keys(xyz: np.ndarray, cell: float) -> np.ndarray:
    """One int64 per point naming its voxel of side ``cell`` (the three cell indices packed:
    a 1-D unique is several times faster than a unique of rows)."""
    cells = np.floor((xyz - xyz.min(axis=0)) / cell).astype(np.int64)
    m = cells.max(axis=0) + 1
    return (cells[:, 0] * m[1] + cells[:, 1]) * m[2] + cells[:, 2]


def collect_observations(
    sfm_dir: Path, preprocessed_dir: Path, keypoint_size_mm: float, min_track_length: int,
    max_reprojection_error_px: float, max_observations: int, max_points: int = 0,
) -> tuple[np.ndarray, np.ndarray, list[_Obs], int, np.ndarray]:
    """Kept points (ids, xyz) and, per image, the observations to describe; at most
    ``max_points`` (0 = all) spread evenly over the wall (:func:`spread_subset`); the points
    in the model and the xyz of every point that passed the filters (before spreading)."""
    rec = load_reconstruction(Path(sfm_dir))
    enhanced = frames_dir(sfm_dir, preprocessed_dir) / "enhanced"  # undistorted if self-calibrated
    if not enhanced.is_dir():
        raise InputError(f"{enhanced}: enhanced frames not found")
    n_model = len(rec.points3D)
    ids, xyz, keep, tracks = [], [], [], []
    for pid, p in rec.points3D.items():
        ids.append(pid)
        xyz.append(p.xyz)
        tracks.append(p.track.length())
        ok = p.track.length() >= min_track_length
        if max_reprojection_error_px > 0 and p.has_error() and p.error > max_reprojection_error_px:
            ok = False
        keep.append(ok)
    ids_a = np.asarray(ids, dtype=np.int64)
    xyz_a = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    keep_a = np.asarray(keep, dtype=bool)
    ids_a, xyz_a = ids_a[keep_a], xyz_a[keep_a]
    kept_xyz = xyz_a
    if max_points > 0 and len(ids_a) > max_points:
        sub = spread_subset(xyz_a, np.asarray(tracks)[keep_a], max_points)
        log.info("%s: %d of %d points kept, spread over the wall", sfm_dir, len(sub), len(ids_a))
        ids_a, xyz_a = ids_a[sub], xyz_a[sub]
    # the kept points' observations, per image: (keypoint index, row), from their tracks
    # (a few of each image's keypoints, not all of them)
    by_image: dict[int, list[tuple[int, int]]] = {}
    for r, pid in enumerate(ids_a):
        for el in rec.points3D[int(pid)].track.elements:
            by_image.setdefault(el.image_id, []).append((el.point2D_idx, r))
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    size_cache: dict[int, tuple[int, int] | None] = {}
    # every observation: (row, image index, x, y, depth, size)
    o_row, o_img, o_x, o_y, o_depth, o_size = [], [], [], [], [], []
    names = []
    for im in images:
        if im.camera_id not in size_cache:
            size_cache[im.camera_id] = _image_size(enhanced, im.name)
        wh = size_cache[im.camera_id]
        if wh is None or not (enhanced / Path(im.name).name).is_file():
            continue
        cam = rec.cameras[im.camera_id]
        k = opencv_calibration(cam, *wh)
        sx, sy = wh[0] / cam.width, wh[1] / cam.height
        rot, t = world_to_camera(im)
        seen = by_image.get(im.image_id)
        if not seen:
            continue
        seen.sort()  # in the order of the image's keypoints
        rows_a = np.asarray([r for _, r in seen], dtype=np.int64)
        xy_a = np.asarray([im.points2D[k].xy for k, _ in seen],
                          dtype=np.float64).reshape(-1, 2)
        depth = (xyz_a[rows_a] @ rot.T + t)[:, 2]
        ok = depth > 1e-9
        idx = len(names)
        names.append(im.name)
        o_row.append(rows_a[ok])
        o_img.append(np.full(int(ok.sum()), idx))
        cv_xy = colmap_to_opencv_xy(xy_a[ok], sx, sy)
        o_x.append(cv_xy[:, 0])
        o_y.append(cv_xy[:, 1])
        o_depth.append(depth[ok])
        o_size.append(k[0, 0] * keypoint_size_mm / depth[ok])
    if not names:
        raise InputError(f"{sfm_dir}: no registered frame with points and an enhanced image "
                         f"in {enhanced}")
    row = np.concatenate(o_row)
    img = np.concatenate(o_img)
    x, y = np.concatenate(o_x), np.concatenate(o_y)
    depth, size = np.concatenate(o_depth), np.concatenate(o_size)
    # at most max_observations per point: the closest views (sharpest texture per mm)
    order = np.lexsort((depth, row))
    row, img, x, y, size = row[order], img[order], x[order], y[order], size[order]
    first = np.r_[0, np.flatnonzero(np.diff(row)) + 1]
    rank = np.arange(len(row)) - np.repeat(first, np.diff(np.r_[first, len(row)]))
    sel = rank < max_observations
    row, img, x, y, size = row[sel], img[sel], x[sel], y[sel], size[sel]
    obs = []
    for i, name in enumerate(names):
        m = img == i
        if m.any():
            obs.append(_Obs(name, np.column_stack([x[m], y[m]]), size[m], row[m]))
    return ids_a, xyz_a, obs, n_model, kept_xyz


def _orientations(grey: np.ndarray, xy: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """SIFT dominant orientation (OpenCV keypoint angle, degrees) of each keypoint."""
    import cv2

    n = len(xy)
    lev = np.clip(np.rint(2 * np.log2(np.maximum(sigma, 1e-6) / 1.6)), 0, N_LEVELS - 1).astype(int)
    g = (np.arange(ORI_GRID) - (ORI_GRID - 1) / 2) / ((ORI_GRID - 1) / 2)  # -1 … 1
    ox, oy = np.meshgrid(g, g)
    ox, oy = ox.ravel(), oy.ravel()
    radius = 4.5 * sigma  # 3 × the 1.5 σ Gaussian window
    wgt = np.exp(-(ox**2 + oy**2) * (4.5**2) / (2 * 1.5**2))
    keep = (ox**2 + oy**2) <= 1.0
    angle = np.zeros(n)
    f = grey.astype(np.float32)
    for level in np.unique(lev):
        m = np.flatnonzero(lev == level)
        gx, gy = _gradients(f, 1.6 * 2 ** (level / 2))
        mx = (xy[m, 0, None] + radius[m, None] * ox[None]).astype(np.float32)
        my = (xy[m, 1, None] + radius[m, None] * oy[None]).astype(np.float32)
        sx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        sy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        mag = np.hypot(sx, sy) * (wgt * keep)[None]
        ori = np.degrees(np.arctan2(sy, sx)) % 360.0  # sy: upward-positive (OpenCV SIFT)
        b = (ori * ORI_BINS / 360.0).astype(int) % ORI_BINS
        hist = np.zeros((len(m), ORI_BINS))
        np.add.at(hist, (np.repeat(np.arange(len(m)), b.shape[1]), b.ravel()), mag.ravel())
        # OpenCV's smoothing of the histogram ([1 4 6 4 1] / 16, circular)
        hist = (np.roll(hist, 2, 1) + np.roll(hist, -2, 1)
                + 4 * (np.roll(hist, 1, 1) + np.roll(hist, -1, 1)) + 6 * hist) / 16.0
        k = hist.argmax(axis=1)
        rr = np.arange(len(m))
        left, c, right = hist[rr, (k - 1) % ORI_BINS], hist[rr, k], hist[rr, (k + 1) % ORI_BINS]
        den = left - 2 * c + right
        off = np.where(np.abs(den) > 1e-12, 0.5 * (left - right) / np.where(den == 0, 1, den), 0)
        theta = ((k + off) * 360.0 / ORI_BINS) % 360.0
        angle[m] = (360.0 - theta) % 360.0
    return angle


def _gradients(f: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradients of ``f`` smoothed at ``sigma`` (y upward positive)."""
    import cv2

    b = cv2.GaussianBlur(f, (0, 0), sigma)
    gx = np.zeros_like(b)
    gy = np.zeros_like(b)
    gx[:, 1:-1] = b[:, 2:] - b[:, :-2]
    gy[1:-1, :] = b[:-2, :] - b[2:, :]
    return gx, gy


def describe_image(path: Path, obs: _Obs) -> tuple[np.ndarray, np.ndarray]:
    """RootSIFT descriptors (n, 128) at ``obs`` in the image at ``path``, and validity.

    The image is reduced by a power of two so that the typical keypoint has σ ≈ 2–4 px
    (SIFT's own octaves would do the same, at the cost of a full-size pyramid).
    """
    import cv2

    grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if grey is None:
        raise InputError(f"{path}: cannot read image")
    h, w = grey.shape
    n = len(obs.row)
    desc = np.zeros((n, 128), np.float32)
    valid = np.zeros(n, bool)
    size = np.clip(obs.size, 2.0, 0.25 * min(h, w))
    inside = ((obs.xy[:, 0] >= 0) & (obs.xy[:, 0] <= w - 1)
              & (obs.xy[:, 1] >= 0) & (obs.xy[:, 1] <= h - 1))
    if not inside.any():
        return desc, valid
    down = 2 ** max(0, math.floor(math.log2(float(np.median(size[inside])) / 2 / 2.0)))
    xy = obs.xy
    if down > 1:
        grey = cv2.resize(grey, (max(8, round(w / down)), max(8, round(h / down))),
                          interpolation=cv2.INTER_AREA)
        sxy = np.array([grey.shape[1] / w, grey.shape[0] / h])
        xy = (obs.xy + 0.5) * sxy - 0.5
        size = size * float(sxy.mean())
    size = np.maximum(size, 2.0)
    sigma = size / 2.0
    angle = _orientations(grey, xy, sigma)
    kps = []
    for i in np.flatnonzero(inside):
        rel = math.log2(max(sigma[i] / 1.6, 1.0))
        octave = math.floor(rel)
        layer = round(float(3 * (rel - octave)))
        if layer == 3:
            octave, layer = octave + 1, 0
        kps.append(cv2.KeyPoint(float(xy[i, 0]), float(xy[i, 1]), float(size[i]),
                                float(angle[i]), 0.0, (octave & 255) | (layer << 8), int(i)))
    sift = cv2.SIFT_create()
    kps_out, d = sift.compute(grey, kps)
    if d is None or not len(kps_out):
        return desc, valid
    idx = np.array([k.class_id for k in kps_out], dtype=np.int64)
    d = d.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)  # RootSIFT
    desc[idx] = np.sqrt(d)
    valid[idx] = True
    return desc, valid


def point_features(
    sfm_dir: Path, preprocessed_dir: Path, keypoint_size_mm: float = 1.2,
    min_track_length: int = 2, max_reprojection_error_px: float = 4.0,
    max_observations: int = 6, threads: int = 2, max_points: int = 0,
) -> PointFeatures:
    """Mean RootSIFT descriptor of every kept 3-D point of the model in ``sfm_dir``."""
    import cv2

    enhanced = frames_dir(sfm_dir, preprocessed_dir) / "enhanced"  # undistorted if self-calibrated
    ids, xyz, obs, n_model, kept_xyz = collect_observations(
        sfm_dir, preprocessed_dir, keypoint_size_mm, min_track_length,
        max_reprojection_error_px, max_observations, max_points)
    acc = np.zeros((len(ids), 128), np.float64)
    count = np.zeros(len(ids), np.int64)
    old_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        def work(o: _Obs) -> tuple[_Obs, np.ndarray, np.ndarray]:
            d, v = describe_image(enhanced / Path(o.image).name, o)
            return o, d, v

        with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
            for o, d, v in pool.map(work, obs):
                rows = o.row[v]
                if len(np.unique(rows)) == len(rows):  # one view of a point per frame
                    acc[rows] += d[v]  # the same sums as add.at, several times faster
                    count[rows] += 1
                else:
                    np.add.at(acc, rows, d[v])
                    np.add.at(count, rows, 1)
    finally:
        cv2.setNumThreads(old_threads)
    ok = count > 0
    desc = acc[ok] / np.maximum(np.linalg.norm(acc[ok], axis=1, keepdims=True), 1e-12)
    log.info("%s: %d of %d points described from %d frames (%.1f observations each)", sfm_dir,
             int(ok.sum()), n_model, len(obs), float(count[ok].mean()) if ok.any() else 0.0)
    return PointFeatures(ids[ok], xyz[ok], desc.astype(np.float32), count[ok], n_model, len(obs),
                         kept_xyz)
