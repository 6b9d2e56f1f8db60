"""Densification of a mapped model with full-resolution corner tracks.

SIFT runs on frames reduced to ``max_image_size`` (fast), so its keypoints are few, short-lived
and only as precise as that working size allows, while the finest texture of the mucosa (and
of the phantom) is only visible at full size. On the fine-textured phantom the poses of the
SIFT-only model are then poorly constrained along some directions (the true poses reproject
the same observations as well as the estimated ones, 0.3 mm apart). With the poses of the
mapped model, many long, precise tracks are found cheaply by patch alignment on the full-size
enhanced frames: corners are detected in every registered frame, each is predicted in the
next ``densify_neighbors`` frames (depth from the nearest model points), aligned there, and
the corners seen in enough frames are triangulated and added as new tracks.

Alignment: a square patch around the corner is the template, warped into the other frame by
the local affine map the model predicts (plane through the 3D point facing the reference
camera); the point in the other frame is moved by Gauss-Newton to where the patches fit best
(zero-mean, unit-variance patches, so exposure changes do not matter). Poor fits (ZNCC) and
large shifts are rejected. The caller re-runs bundle adjustment afterwards.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections import Counter, OrderedDict, defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cystomap.camera import colmap_to_opencv_xy, opencv_to_colmap_xy
from cystomap.errors import InputError
from cystomap.images import sample_bilinear
from cystomap.parallel import ordered_map
from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DensifyStats:
    """What densification added."""

    corners: int  # corners detected (all frames)
    aligned: int  # corner-to-frame alignments accepted
    points: int  # new 3D points
    observations: int  # their observations
    frames: int = 0  # registered frames
    frames_read: int = 0  # full-size images read from disk (the cache holds a few at a time)
    min_zncc: float = 0.0  # the ZNCC an alignment needed (from the null, see zncc_threshold)
    null_alignments: int = 0  # wrong alignments that ZNCC was drawn from

    def to_dict(self) -> dict[str, float]:
        return {"corners": self.corners, "aligned": self.aligned, "points": self.points,
                "observations": self.observations, "frames": self.frames,
                "frames_read": self.frames_read, "min_zncc": round(self.min_zncc, 4),
                "null_alignments": self.null_alignments}


class _Frames:
    """Full-size frames (float32) with their x and y gradients as 3 channels (sampled at
    once); a small cache."""

    def __init__(self, image_dir: Path, capacity: int = 12) -> None:
        self.image_dir = image_dir
        self.capacity = capacity
        self._cache: OrderedDict[str, np.ndarray] = OrderedDict()
        self.reads = 0

    def get(self, name: str) -> np.ndarray:
        if name in self._cache:
            self._cache.move_to_end(name)
            return self._cache[name]
        img = cv2.imread(str(self.image_dir / name), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f"{self.image_dir / name}: cannot read image")
        self.reads += 1
        img = img.astype(np.float32)
        ix = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
        iy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
        self._cache[name] = cv2.merge([img, ix, iy])
        if len(self._cache) > self.capacity:
            self._cache.popitem(last=False)
        return self._cache[name]


def _grid(patch_px: int) -> tuple[np.ndarray, np.ndarray]:
    half = patch_px // 2
    g = np.arange(-half, half + 1, dtype=np.float32)
    gx, gy = np.meshgrid(g, g)
    return gx.ravel(), gy.ravel()


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of ``img`` (one or more channels) at (x, y) (OpenCV pixel centres;
    arrays of equal shape), shaped (*x.shape, channels), and whether each lies inside it."""
    h, w = img.shape[:2]
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    val = sample_bilinear(img, x.ravel(), y.ravel()).reshape(*x.shape, -1)
    return val, inside


def _normalise(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean, unit-variance patches (N, K) and their standard deviations."""
    centred = p - p.mean(axis=1, keepdims=True)
    std = np.sqrt((centred**2).mean(axis=1, keepdims=True)) + 1e-6
    return centred / std, std[:, 0]


def _project(k: np.ndarray, pose: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP pixels and depths of world points ``xyz`` (N, 3) in a camera (3x4 cam_from_world,
    or (N, 3, 4) one per point)."""
    if pose.ndim == 2:
        cam = xyz @ pose[:, :3].T + pose[:, 3]
    else:
        cam = np.einsum("nij,nj->ni", pose[:, :, :3], xyz) + pose[:, :, 3]
    proj = cam @ k.T
    return proj[:, :2] / proj[:, 2:3], cam[:, 2]


def _unproject(k_inv: np.ndarray, pose: np.ndarray, xy: np.ndarray, depth: np.ndarray
               ) -> np.ndarray:
    """World points at ``depth`` along the rays of COLMAP pixels ``xy`` of a camera (3x4)."""
    cam = (np.c_[xy, np.ones(len(xy))] @ k_inv.T) * depth[:, None]
    return (cam - pose[:, 3]) @ pose[:, :3]  # R^T (x - t)


def _inverse_affines(k: np.ndarray, ref_pose: np.ndarray, tgt_pose: np.ndarray,
                     xyz: np.ndarray, ref_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses of the (N, 2, 2) maps of pixel offsets around the reference points to offsets
    in the target frames (plane through the 3D point facing the reference camera, poses 3x4
    or (N, 3, 4)), and whether each map is well-conditioned."""
    k_inv = np.linalg.inv(k)
    ref = ref_pose if ref_pose.ndim == 3 else np.repeat(ref_pose[None], len(xyz), 0)
    depth = np.einsum("nij,nj->ni", ref[:, :, :3], xyz)[:, 2] + ref[:, 2, 3]
    cols = []
    base = None
    for axis in (-1, 0, 1):
        uv = ref_xy.astype(np.float64).copy()
        if axis >= 0:
            uv[:, axis] += 1.0
        cam = (np.c_[uv, np.ones(len(uv))] @ k_inv.T) * depth[:, None]
        world = np.einsum("nji,nj->ni", ref[:, :, :3], cam - ref[:, :, 3])
        px, _ = _project(k, tgt_pose, world)
        if base is None:
            base = px
        else:
            cols.append(px - base)
    a, b, c, d = cols[0][:, 0], cols[1][:, 0], cols[0][:, 1], cols[1][:, 1]
    det = a * d - b * c
    ok = np.abs(det) > 0.1
    safe = np.where(ok, det, 1.0)
    inv = np.stack([np.stack([d, -b], 1), np.stack([-c, a], 1)], 1) / safe[:, None, None]
    return inv, ok


def _templates(img: np.ndarray, ref_cv: np.ndarray, inv: np.ndarray, gx: np.ndarray,
               gy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised templates (N, K) of ``img`` around ``ref_cv`` (OpenCV pixels), sampled at
    ref + A^-1 g for the target grid g; their contrast and whether they lie inside."""
    cx = ref_cv[:, 0:1] + inv[:, 0, 0:1] * gx + inv[:, 0, 1:2] * gy
    cy = ref_cv[:, 1:2] + inv[:, 1, 0:1] * gx + inv[:, 1, 1:2] * gy
    patch, inside = _sample(img, cx, cy)
    patch = patch[..., 0]
    tpl, std = _normalise(patch)
    return tpl, std, inside.all(axis=1)


def _align(stack: np.ndarray, tpl: np.ndarray,
           start_cv: np.ndarray, gx: np.ndarray, gy: np.ndarray, iterations: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton on the translation of each patch in a frame (``_Frames.get``: grey, x and
    y gradients): positions (OpenCV pixels), ZNCC of the final fit, and whether the patch
    stayed inside the frame."""
    pos = start_cv.astype(np.float32).copy()
    live = np.ones(len(pos), dtype=bool)
    for _ in range(iterations):
        samples, inside = _sample(stack, pos[:, 0:1] + gx, pos[:, 1:2] + gy)
        val, dx, dy = samples[..., 0], samples[..., 1], samples[..., 2]
        live &= inside.all(axis=1)
        mean = val.mean(axis=1, keepdims=True)
        std = np.sqrt(((val - mean) ** 2).mean(axis=1, keepdims=True)) + 1e-6
        resid = (val - mean) / std - tpl
        gxn = (dx - dx.mean(axis=1, keepdims=True)) / std
        gyn = (dy - dy.mean(axis=1, keepdims=True)) / std
        a11 = (gxn * gxn).sum(1)
        a12 = (gxn * gyn).sum(1)
        a22 = (gyn * gyn).sum(1)
        b1 = -(gxn * resid).sum(1)
        b2 = -(gyn * resid).sum(1)
        det = a11 * a22 - a12 * a12
        safe = np.where(det > 1e-9, det, np.inf)
        step = np.stack([(a22 * b1 - a12 * b2) / safe, (a11 * b2 - a12 * b1) / safe], 1)
        step = np.clip(step, -1.0, 1.0) * live[:, None]
        pos += step
        if np.abs(step).max(initial=0.0) < 1e-3:
            break
    samples, inside = _sample(stack, pos[:, 0:1] + gx, pos[:, 1:2] + gy)
    val = samples[..., 0]
    zncc = (_normalise(val)[0] * tpl).mean(axis=1)
    return pos.astype(np.float64), zncc, live & inside.all(axis=1)


def _model_arrays(rec: Any) -> tuple[list[int], dict[int, str], dict[int, np.ndarray],
                                      dict[int, np.ndarray]]:
    """Registered image ids in name (video) order, their names, poses (3x4) and K."""
    ids = sorted(rec.reg_image_ids(), key=lambda i: rec.image(i).name)
    names = {i: rec.image(i).name for i in ids}
    poses = {i: np.asarray(rec.image(i).cam_from_world().matrix(), dtype=np.float64)
             for i in ids}
    ks = {i: np.asarray(rec.camera(rec.image(i).camera_id).calibration_matrix(),
                        dtype=np.float64) for i in ids}
    return ids, names, poses, ks


def _triangulate(ps: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of tracks of equal length: projection matrices (N, V, 3, 4)
    (K applied) and COLMAP pixels (N, V, 2) -> (N, 3)."""
    a = np.concatenate([xy[..., 0:1] * ps[:, :, 2] - ps[:, :, 0],
                        xy[..., 1:2] * ps[:, :, 2] - ps[:, :, 1]], axis=1)
    _, _, vt = np.linalg.svd(a)
    h = vt[:, -1]
    return h[:, :3] / h[:, 3:4]


@dataclass(frozen=True)
class _Reference:
    """A reference frame: its position in the model's frame order, image id, the frames its
    corners are aligned into, and its model points (COLMAP pixels, world coordinates)."""

    n: int
    image_id: int
    targets: list[int]
    points_xy: np.ndarray
    points_xyz: np.ndarray


@dataclass
class _Part:
    """What one run of reference frames found: new tracks by the reference's position."""

    tracks: dict[int, list[list[tuple[int, np.ndarray]]]]
    corners: int = 0
    aligned: int = 0
    reads: int = 0


class _Aligner:
    """Detects each reference frame's corners and aligns them into its target frames. Each
    :meth:`run` (one per thread) has its own frames cache; a reference frame's tracks depend
    on the model alone, so how the frames are shared out does not change them."""

    def __init__(self, image_dir: Path, mask: np.ndarray | None, masks_dir: Path | None,
                 cfg: SfmConfig, model: tuple[dict[int, str], dict[int, np.ndarray],
                                              dict[int, np.ndarray]],
                 stride: int) -> None:
        self.image_dir, self.masks_dir, self.cfg = image_dir, masks_dir, cfg
        self.names, self.poses, self.ks = model
        self.n_wanted = max(1, round(cfg.densify_corners / stride))
        self.capacity = cfg.densify_neighbors * stride + 3
        self.gx, self.gy = _grid(cfg.densify_patch_px)
        self.margin = cfg.densify_patch_px // 2 + 2
        self.box = np.ones((2 * self.margin + 1,) * 2, np.uint8)
        self.valid = (None if mask is None
                      else cv2.erode((mask > 127).astype(np.uint8) * 255, self.box))
        self.min_zncc = cfg.densify_max_zncc  # set from the null by densify()

    def run(self, jobs: list[_Reference]) -> _Part:
        part = _Part({})
        frames = _Frames(self.image_dir, capacity=self.capacity)
        glint_free: OrderedDict[str, np.ndarray | None] = OrderedDict()

        def free(name: str) -> np.ndarray | None:
            """255 where a patch centred there touches no glint of frame ``name``."""
            if self.masks_dir is None:
                return None
            if name not in glint_free:
                m = cv2.imread(str(self.masks_dir / name), cv2.IMREAD_GRAYSCALE)
                glint_free[name] = (None if m is None else
                                    cv2.erode((m > 127).astype(np.uint8) * 255, self.box))
                if len(glint_free) > frames.capacity:
                    glint_free.popitem(last=False)
            glint_free.move_to_end(name)
            return glint_free[name]

        for job in jobs:
            self._align_reference(job, frames, free, part)
        part.reads = frames.reads
        return part

    def _corners(self, job: _Reference, frames: _Frames,
                 free: Callable[[str], np.ndarray | None],
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The reference frame's corners: its grey image, their OpenCV and COLMAP pixels and
        world points (depth from the nearest model points); None when it has none."""
        cfg, names, poses, ks = self.cfg, self.names, self.poses, self.ks
        ref_id = job.image_id
        img = np.ascontiguousarray(frames.get(names[ref_id])[..., 0])
        h, w = img.shape
        valid = self.valid
        if valid is None:
            valid = np.zeros((h, w), np.uint8)
            valid[self.margin:h - self.margin, self.margin:w - self.margin] = 255
        ref_free = free(names[ref_id])
        corners = cv2.goodFeaturesToTrack(img, self.n_wanted, cfg.densify_quality,
                                          cfg.densify_min_distance_px, blockSize=5,
                                          mask=valid if ref_free is None
                                          else np.minimum(valid, ref_free))
        if corners is None:
            return None
        cv_xy = corners.reshape(-1, 2).astype(np.float64)
        xy = opencv_to_colmap_xy(cv_xy)
        # depth of each corner: median depth of the nearest model points seen in this frame
        _, pdepth = _project(ks[ref_id], poses[ref_id], job.points_xyz)
        d2 = ((xy[:, None, :] - job.points_xy[None]) ** 2).sum(-1)
        near = np.argsort(d2, axis=1)[:, : min(cfg.densify_depth_neighbors, len(pdepth))]
        depth = np.median(pdepth[near], axis=1)
        xyz = _unproject(np.linalg.inv(ks[ref_id]), poses[ref_id], xy, depth)
        return img, cv_xy, xy, xyz

    def _predicted(self, ref_id: int, tgt_id: int, img: np.ndarray, cv_xy: np.ndarray,
                   xy: np.ndarray, xyz: np.ndarray,
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The corners that can be aligned into frame ``tgt_id`` (indices), their templates
        and predicted places there (OpenCV pixels); None when there are none."""
        cfg, poses, ks, margin = self.cfg, self.poses, self.ks, self.margin
        h, w = img.shape
        pred, z = _project(ks[tgt_id], poses[tgt_id], xyz)
        inv, ok = _inverse_affines(ks[ref_id], poses[ref_id], poses[tgt_id], xyz, xy)
        ok &= (z > 0) & (pred[:, 0] > margin) & (pred[:, 1] > margin)
        ok &= (pred[:, 0] < w - margin) & (pred[:, 1] < h - margin)
        sel = np.nonzero(ok)[0]
        if not len(sel):
            return None
        tpl, std, inside = _templates(img, cv_xy[sel], inv[sel], self.gx, self.gy)
        keep = inside & (std > cfg.densify_min_contrast)
        sel, tpl = sel[keep], tpl[keep]
        if not len(sel):
            return None
        return sel, tpl, colmap_to_opencv_xy(pred[sel])

    def null_zncc(self, jobs: list[_Reference], rng: np.random.Generator) -> np.ndarray:
        """ZNCC of wrong alignments: each sampled reference frame's corners aligned into its
        first target from starts one to two patch sides away from the predicted places, kept
        as an alignment would be (inside, within densify_max_shift_px of the start): what a
        patch of this video reaches by chance on wall that is not its own."""
        frames = _Frames(self.image_dir, capacity=4)
        found: list[np.ndarray] = []
        for job in jobs:
            corners = self._corners(job, frames, lambda name: None)
            if corners is None:
                continue
            img, cv_xy, xy, xyz = corners
            cand = self._predicted(job.image_id, job.targets[0], img, cv_xy, xy, xyz)
            if cand is None:
                continue
            _, tpl, start = cand
            angle = rng.uniform(0.0, 2.0 * np.pi, len(start))
            radius = rng.uniform(1.0, 2.0, len(start)) * self.cfg.densify_patch_px
            start = start + np.c_[np.cos(angle), np.sin(angle)] * radius[:, None]
            pos, zncc, live = _align(frames.get(self.names[job.targets[0]]), tpl, start,
                                     self.gx, self.gy, self.cfg.densify_iterations)
            shift = np.linalg.norm(pos - start, axis=1)
            found.append(zncc[live & (shift <= self.cfg.densify_max_shift_px)])
        return np.concatenate(found) if found else np.zeros(0)

    def _align_reference(self, job: _Reference, frames: _Frames,
                         free: Callable[[str], np.ndarray | None], part: _Part) -> None:
        cfg, names = self.cfg, self.names
        ref_id = job.image_id
        corners = self._corners(job, frames, free)
        if corners is None:
            return
        img, cv_xy, xy, xyz = corners
        h, w = img.shape
        part.corners += len(xy)
        found: list[list[tuple[int, np.ndarray]]] = [[(ref_id, xy[c])] for c in range(len(xy))]
        for tgt_id in job.targets:
            cand = self._predicted(ref_id, tgt_id, img, cv_xy, xy, xyz)
            if cand is None:
                continue
            sel, tpl, start = cand
            pos, zncc, live = _align(frames.get(names[tgt_id]), tpl, start, self.gx, self.gy,
                                     cfg.densify_iterations)
            shift = np.linalg.norm(pos - start, axis=1)
            accept = live & (zncc >= self.min_zncc) & (shift <= cfg.densify_max_shift_px)
            tgt_free = free(names[tgt_id])
            if tgt_free is not None and accept.any():
                px = np.clip(np.rint(pos).astype(int), 0, [w - 1, h - 1])
                accept &= tgt_free[px[:, 1], px[:, 0]] > 0
            for c, p in zip(sel[accept], opencv_to_colmap_xy(pos[accept]), strict=True):
                found[c].append((tgt_id, p))
            part.aligned += int(accept.sum())
        part.tracks[job.n] = [t for t in found if len(t) >= cfg.densify_min_views]


def zncc_threshold(null: np.ndarray, cfg: SfmConfig) -> float:
    """The ZNCC an alignment needs: the (1 - densify_null_rate) quantile of the wrong
    alignments ``null`` (:meth:`_Aligner.null_zncc`), clipped to [densify_min_zncc,
    densify_max_zncc]; densify_max_zncc alone when the rate is 0 or the null has too few
    values to place the quantile (fewer than 5 above it)."""
    rate = cfg.densify_null_rate
    if rate <= 0 or len(null) * rate < 5:
        return cfg.densify_max_zncc
    return min(cfg.densify_max_zncc,
               max(cfg.densify_min_zncc, float(np.quantile(null, 1.0 - rate))))


def densify(rec: Any, image_dir: Path, mask: np.ndarray | None, cfg: SfmConfig,
            stride: int = 1, masks_dir: Path | None = None) -> DensifyStats:
    """Add full-size corner tracks to ``rec`` (see the module docstring); in place.

    ``masks_dir`` (optional) holds per-frame masks (0 = specular glint): no corner is taken,
    and no alignment accepted, where a patch would touch a glint of its frame.

    With keyframes every ``stride`` frames (dense video), each frame gets 1/stride of the
    corners and is aligned to every ``stride``-th following frame, so the cost and the
    baselines of the tracks stay those of the keyframes. Each keyframe's corners are also
    aligned into the ``densify_loop_neighbors`` later frames beyond that window that share the
    most model points with it (loop closures, against drift)."""
    import pycolmap

    ids, names, poses, ks = _model_arrays(rec)
    stride = max(1, stride)
    order = {i: n for n, i in enumerate(ids)}
    shared: dict[int, Counter[int]] = defaultdict(Counter)  # model points two frames share
    for point in rec.points3D.values():
        seen = {e.image_id for e in point.track.elements if e.image_id in order}
        for i in seen:
            shared[i].update(seen - {i})
    window = cfg.densify_neighbors * stride
    jobs: list[_Reference] = []
    # the frames of one residue class modulo the stride in turn: a frame's targets are the
    # following frames of its class, so the frames cache holds one class's window (in plain
    # video order two classes' windows alternate and overflow it: every frame was read ~8x);
    # the tracks are then put back in video order, so the result is that of video order
    for n in sorted(range(len(ids)), key=lambda k: (k % stride, k)):
        ref_id = ids[n]
        targets = ids[n + stride:: stride][: cfg.densify_neighbors]
        if n % stride == 0:  # keyframes only: far frames are not cached, reading them is slow
            loops = [j for j, c in shared[ref_id].most_common()
                     if order[j] > n + window and c >= cfg.densify_loop_min_shared]
            targets += loops[: cfg.densify_loop_neighbors]
        if not targets:
            continue
        image = rec.image(ref_id)
        pts = [(p.xy, rec.point3D(p.point3D_id).xyz) for p in image.points2D if p.has_point3D()]
        if len(pts) < 3:
            continue
        jobs.append(_Reference(n, ref_id, targets, np.array([p[0] for p in pts]),
                               np.array([p[1] for p in pts])))
    aligner = _Aligner(image_dir, mask, masks_dir, cfg, (names, poses, ks), stride)
    n_null = 0
    if cfg.densify_null_rate > 0 and jobs:
        sample = jobs[:: max(1, math.ceil(len(jobs) / cfg.densify_null_frames))]
        null = aligner.null_zncc(sample, np.random.default_rng(cfg.seed))
        aligner.min_zncc = zncc_threshold(null, cfg)
        n_null = len(null)
        log.info("densification: alignments need ZNCC >= %.3f (%.0f %% of %d wrong "
                 "alignments in %d frames reach it)", aligner.min_zncc,
                 100 * float(np.mean(null >= aligner.min_zncc)) if len(null) else 0.0,
                 len(null), len(sample))
    # each reference frame's tracks depend on the model alone, so the frames are shared out
    # in contiguous runs (one frames cache per run) and the result is that of one thread
    runs = max(1, min(cfg.num_threads, len(jobs)))
    bounds = np.linspace(0, len(jobs), runs + 1).round().astype(int)
    per_ref: dict[int, list[list[tuple[int, np.ndarray]]]] = {}  # new tracks by reference frame
    n_corners = n_aligned = reads = 0
    for part in ordered_map(aligner.run, [jobs[a:b] for a, b in itertools.pairwise(bounds)],
                            runs):
        per_ref.update(part.tracks)
        n_corners += part.corners
        n_aligned += part.aligned
        reads += part.reads
    tracks = [t for n in sorted(per_ref) for t in per_ref[n]]  # per new point: (image id, xy)

    # triangulate (grouped by track length), keep tracks that reproject well, add them
    n_points = n_obs = 0
    by_len: dict[int, list[list[tuple[int, np.ndarray]]]] = defaultdict(list)
    for t in tracks:
        by_len[len(t)].append(t)
    proj = {i: ks[i] @ poses[i] for i in ids}
    for length, group in by_len.items():
        ps = np.array([[proj[i] for i, _ in t] for t in group])
        xy = np.array([[p for _, p in t] for t in group])
        xyz = _triangulate(ps, xy)
        h4 = np.c_[xyz, np.ones(len(xyz))]
        rep = np.einsum("nvij,nj->nvi", ps, h4)
        err = np.linalg.norm(rep[..., :2] / rep[..., 2:3] - xy, axis=2)
        good = (rep[..., 2] > 0).all(1) & (err.max(1) <= cfg.densify_max_reproj_error_px)
        for t, point in zip((g for g, k in zip(group, good, strict=True) if k), xyz[good],
                            strict=True):
            track = pycolmap.Track()
            for image_id, p in t:
                image = rec.image(image_id)
                image.points2D.append(pycolmap.Point2D(p))
                track.add_element(image_id, image.num_points2D() - 1)
            rec.add_point3D(point, track)
            n_points += 1
            n_obs += length
    stats = DensifyStats(n_corners, n_aligned, n_points, n_obs, len(ids), reads,
                         aligner.min_zncc, n_null)
    log.info("densification: %d corners at full size, %d alignments, %d points with %d "
             "observations added; %d reads of %d frames", n_corners, n_aligned, n_points, n_obs,
             reads, len(ids))
    return stats


def drop_short_sift(rec: Any, sift: set[int], cfg: SfmConfig, stride: int = 1) -> int:
    """Delete the SIFT points (ids ``sift``, those of the model before densification) whose
    frames all lie within one densification window (``densify_neighbors`` x ``stride``
    consecutive registered frames): there the full-size corner tracks measure the same
    relative geometry several times more precisely (reprojection error per point 0.10-0.12
    against 0.40-0.48 px on family-A FROC sessions), and an unweighted adjustment lets the
    coarser SIFT observations pull the poses. SIFT points that span more (loop closures,
    long tracks) stay: densification does not replace them. A point is kept when any of its
    frames has fewer than ``abs_pose_min_num_inliers`` corner observations. In place; returns
    the number deleted."""
    ids = sorted(rec.reg_image_ids(), key=lambda i: rec.image(i).name)
    order = {i: n for n, i in enumerate(ids)}
    dense: Counter[int] = Counter()
    for pid, point in rec.points3D.items():
        if pid not in sift:
            dense.update(e.image_id for e in point.track.elements)
    window = cfg.densify_neighbors * max(1, stride)
    drop = []
    for pid in sift:
        if pid not in rec.points3D:
            continue
        frames = [e.image_id for e in rec.point3D(pid).track.elements if e.image_id in order]
        if not frames:
            continue
        pos = [order[i] for i in frames]
        if (max(pos) - min(pos) <= window
                and min(dense[i] for i in frames) >= cfg.abs_pose_min_num_inliers):
            drop.append(pid)
    for pid in drop:
        rec.delete_point3D(pid)
    log.info("densification: %d SIFT points within one window dropped before the final "
             "adjustment, %d kept", len(drop), len(sift) - len(drop))
    return len(drop)
