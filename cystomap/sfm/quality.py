"""The stage's outputs besides the model: coloured point cloud and quality figures."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cystomap.sfm.features import Features
from cystomap.sfm.matching import MatchStats


def points_arrays(rec: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """xyz (N,3), rgb (N,3 uint8), track length (N,), error (N,) of all 3-D points."""
    pts = list(rec.points3D.values())
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, int), np.zeros(0)
    xyz = np.array([p.xyz for p in pts], dtype=np.float64)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    length = np.array([p.track.length() for p in pts], dtype=np.int64)
    err = np.array([p.error for p in pts], dtype=np.float64)
    return xyz, rgb, length, err


def colour_points(rec: Any, color_dir: Path, num_threads: int, max_frames: int = 48) -> int:
    """Colour every 3-D point from the colour frames; returns how many frames were read.

    Frames are chosen greedily (most uncoloured points first) until every point is seen in
    one or ``max_frames`` are chosen, so only part of the frames is decoded; a point's colour
    is the mean over the chosen frames that observe it, and points none of them sees take
    the colour of the nearest coloured point.
    """
    import cv2

    obs: list[tuple[str, np.ndarray, np.ndarray]] = []
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        pts = image.get_observation_points2D()
        if len(pts):
            xy = np.array([p.xy for p in pts], dtype=np.float64)
            ids = np.array([p.point3D_id for p in pts], dtype=np.int64)
            obs.append((image.name, xy, ids))
    obs.sort(key=lambda o: -len(o[2]))
    todo = set(rec.point3D_ids())
    chosen = []
    for name, xy, ids in obs:
        if not todo or len(chosen) >= max_frames:
            break
        if todo.isdisjoint(ids.tolist()):
            continue
        todo.difference_update(ids.tolist())
        chosen.append((name, xy, ids))

    def sample(item: tuple[str, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        name, xy, ids = item
        img = cv2.imread(str(color_dir / name), cv2.IMREAD_COLOR)
        if img is None:
            return ids[:0], np.zeros((0, 3))
        h, w = img.shape[:2]
        # COLMAP image coordinates: the centre of pixel (i, j) is at (j + 0.5, i + 0.5)
        col = np.clip(np.floor(xy[:, 0]).astype(int), 0, w - 1)
        row = np.clip(np.floor(xy[:, 1]).astype(int), 0, h - 1)
        return ids, img[row, col, ::-1].astype(np.float64)

    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max(1, num_threads)) as pool:
        samples = list(pool.map(sample, chosen))
    if not samples:
        return 0
    ids = np.concatenate([s[0] for s in samples])
    rgb = np.concatenate([s[1] for s in samples])
    uniq, inv = np.unique(ids, return_inverse=True)
    counts = np.bincount(inv, minlength=len(uniq)).astype(np.float64)
    mean = np.stack([np.bincount(inv, weights=rgb[:, c], minlength=len(uniq)) for c in range(3)], 1)
    mean = np.clip(np.rint(mean / counts[:, None]), 0, 255).astype(np.uint8)
    for pid, c in zip(uniq.tolist(), mean, strict=True):
        rec.point3D(pid).color = c
    rest = np.array(sorted(set(rec.point3D_ids()) - set(uniq.tolist())), dtype=np.int64)
    if len(rest):
        from scipy.spatial import cKDTree

        done_xyz = np.array([rec.point3D(int(p)).xyz for p in uniq])
        rest_xyz = np.array([rec.point3D(int(p)).xyz for p in rest])
        _, nearest = cKDTree(done_xyz).query(rest_xyz)
        for pid, k in zip(rest.tolist(), nearest.tolist(), strict=True):
            rec.point3D(pid).color = mean[k]
    return len(chosen)


def observation_depths(rec: Any) -> np.ndarray:
    """Depth (camera z) of every observation of every registered image."""
    depths = []
    pts = rec.points3D
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
        if not ids:
            continue
        xyz = np.array([pts[i].xyz for i in ids])
        pose = image.cam_from_world()
        cam = xyz @ np.asarray(pose.rotation.matrix()).T + np.asarray(pose.translation)
        depths.append(cam[:, 2])
    return np.concatenate(depths) if depths else np.zeros(0)


def dropped_frames(
    names: list[str], features: Features, matches: MatchStats, models: list[list[str]],
    min_keypoints: int, known: dict[str, str] | None = None,
) -> dict[str, str]:
    """Why each frame that is not in the written model is missing (``known``: reasons given
    by the mapping itself, e.g. frames it took out)."""
    registered = set(models[0]) if models else set()
    where = {n: k for k, model in enumerate(models) for n in model}
    known = known or {}
    out = {}
    for name in names:
        if name in registered:
            continue
        kp = features.num_keypoints.get(name, 0)
        if name in known:
            reason = known[name]
        elif name not in features.num_keypoints:
            reason = "could not be read"
        elif kp < min_keypoints:
            reason = f"too few features ({kp})"
        elif matches.verified_per_image.get(name, 0) == 0:
            reason = "no geometrically verified match with any paired frame"
        elif name in where:
            k = where[name]
            reason = f"in a separate smaller model (#{k}, {len(models[k])} frames)"
        else:
            reason = "pose could not be estimated (too few matches to the model)"
        out[name] = reason
    return out


def summarise(
    rec: Any, names: list[str], features: Features, matches: MatchStats, models: list[list[str]],
    pairs: dict[str, int], scale: dict[str, Any], timings: dict[str, float], extra: dict[str, Any],
    min_keypoints: int,
) -> dict[str, Any]:
    rec.update_point_3d_errors()
    reproj = float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else None
    depths = observation_depths(rec)
    cams = list(rec.cameras.values())
    fx = float(cams[0].focal_length_x) if cams else float("nan")
    reproj_world = None
    if reproj is not None and len(depths):
        reproj_world = reproj * float(np.median(depths)) / fx
    final = extra.get("final_adjustment") or {}
    thin = {**(final.get("thin_frames") or {}), **(final.get("lone_frames") or {})}
    dropped = dropped_frames(names, features, matches, models, min_keypoints, thin)
    reasons: dict[str, int] = {}
    for r in dropped.values():
        key = r.split(" (")[0]
        reasons[key] = reasons.get(key, 0) + 1
    kp = np.array(list(features.num_keypoints.values()) or [0])
    cam = cams[0] if cams else None
    return {
        "frames_in": len(names),
        "registered": int(rec.num_reg_images()),
        "registered_fraction": rec.num_reg_images() / len(names) if names else 0.0,
        "dropped": len(dropped),
        "dropped_reasons": reasons,
        "dropped_frames": dropped,
        "mean_reprojection_error_px": reproj,
        "mean_reprojection_error_mm" if scale["metric"] else "mean_reprojection_error_model_units":
            reproj_world,
        "median_depth": float(np.median(depths)) if len(depths) else None,
        "points": int(rec.num_points3D()),
        "observations": int(rec.compute_num_observations()),
        "mean_track_length": float(rec.compute_mean_track_length()) if rec.num_points3D() else 0.0,
        "mean_observations_per_frame": float(rec.compute_mean_observations_per_reg_image())
        if rec.num_reg_images() else 0.0,
        "metric": scale["metric"],
        "units": scale["units"],
        "scale": scale,
        "models_found": len(models),
        "model_sizes": [len(m) for m in models],
        "other_models": [{"frames": len(m), "first": m[0], "last": m[-1]} for m in models[1:]],
        "keypoints_per_frame": {"min": int(kp.min()), "median": float(np.median(kp)),
                                "max": int(kp.max())},
        "pairs": pairs,
        "verified_pairs": matches.num_verified,
        "mean_inlier_matches": matches.mean_inliers,
        "camera": None if cam is None else {
            "model": cam.model_name, "width": int(cam.width), "height": int(cam.height),
            "params": [float(p) for p in cam.params],
        },
        **extra,
        "time_s": {k: round(v, 3) for k, v in timings.items()},
    }
