"""Registration, reprojection error and camera trajectory of COLMAP models against the truth.

The Sim(3) found here (model frame → truth frame) also brings the mesh, the atlas and the
detected changes of that model into the truth frame for their scores.
"""

from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.errors import InputError
from cystomap.evaluate.config import EvalConfig
from cystomap.evaluate.truth import Truth
from cystomap.geometry.sim3 import Similarity
from cystomap.geometry.sim3 import umeyama as _umeyama
from cystomap.io.colmap import camera_centres, model_dirs, read_model

log = logging.getLogger(__name__)


#: the evaluation's name for the pipeline's one similarity transform
Sim3 = Similarity


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Sim3:
    """Least-squares Sim(3) with dst ≈ s·R·src + t (Umeyama 1991); ≥ 3 non-collinear points."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama needs two Nx3 arrays, N >= 3; got {src.shape}, {dst.shape}")
    sim = _umeyama(src, dst, with_scale)
    if sim is None:
        raise ValueError("umeyama: the source points are (nearly) coincident")
    return sim


def align(
    src: np.ndarray, dst: np.ndarray, trim: float = 0.0, rounds: int = 3
) -> tuple[Sim3, np.ndarray]:
    """Umeyama Sim(3); with ``trim`` > 0 refit on points whose error ≤ trim × median error.

    Returns the transform and the boolean mask of the points used in the last fit.
    """
    inliers = np.ones(len(src), dtype=bool)
    sim = umeyama(src, dst)
    if trim <= 0:
        return sim, inliers
    for _ in range(rounds):
        err = np.linalg.norm(sim.apply(src) - dst, axis=1)
        new = err <= trim * max(float(np.median(err)), 1e-12)
        if new.sum() < 3 or np.array_equal(new, inliers):
            break
        inliers = new
        sim = umeyama(src[inliers], dst[inliers])
    return sim, inliers


@dataclass(frozen=True)
class Model:
    """The registered images of one COLMAP model, keyed by video frame index."""

    path: Path
    frames: np.ndarray  # (N,) int
    rotations: np.ndarray  # (N, 3, 3) camera-to-world
    centres: np.ndarray  # (N, 3)
    n_images: int
    n_points3d: int
    reprojection_error_px: float | None
    focal_per_width: float | None
    quality: dict[str, Any]

    @property
    def claims_metric(self) -> bool | None:
        q = self.quality
        if isinstance(q.get("metric"), bool):
            return q["metric"]
        units = q.get("units")
        return None if units is None else str(units).lower() in ("mm", "millimetre", "millimeter")


def find_models(path: Path) -> list[Path]:
    """Model directories under ``path``: itself, or its subdirectories holding a model (0/, 1/…).

    Sorted by name, so the first is the one ``cystomap.mesh.find_model_dir`` picks.
    """
    return model_dirs(path)


def load_model(path: Path, cfg: EvalConfig) -> Model:
    """Read a COLMAP model with pycolmap; frame index from image names (``cfg.frame_pattern``)."""
    rec = read_model(path, f"COLMAP model {path}")
    pattern = re.compile(cfg.frame_pattern)
    frames, images, skipped = [], [], []
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        m = pattern.search(Path(image.name).name)
        if m is None:
            skipped.append(image.name)
            continue
        frames.append(int(m.group(1)))
        images.append(image)
    rotations, centres = camera_centres(images)
    if skipped:
        log.warning("%s: %d image name(s) without a frame index (pattern %r), e.g. %s",
                    path, len(skipped), cfg.frame_pattern, skipped[0])
    frames_arr = np.asarray(frames, dtype=np.int64)
    if len(np.unique(frames_arr)) != len(frames_arr):
        raise InputError(f"COLMAP model {path}: several registered images share a frame index")
    reproj = None
    if rec.num_points3D() > 0:
        rec.update_point_3d_errors()
        reproj = float(rec.compute_mean_reprojection_error())
    focal = None
    if rec.cameras:
        cam = rec.cameras[min(rec.cameras)]
        focal = float(cam.focal_length_x) / float(cam.width)
    return Model(
        path=path,
        frames=frames_arr,
        rotations=rotations,
        centres=centres,
        n_images=int(rec.num_images()),
        n_points3d=int(rec.num_points3D()),
        reprojection_error_px=reproj,
        focal_per_width=focal,
        quality=_read_quality(path),
    )


def _read_quality(model_dir: Path) -> dict[str, Any]:
    for p in (model_dir / "quality.json", model_dir.parent / "quality.json"):
        if p.is_file():
            try:
                q = json.loads(p.read_text())
            except (OSError, json.JSONDecodeError) as exc:
                raise InputError(f"{p}: cannot read JSON ({exc})") from exc
            return q if isinstance(q, dict) else {}
    return {}


def score_registration(truth: Truth, models: list[Model]) -> dict[str, Any]:
    """Share of video frames registered (in any model), overall and without the bad frames."""
    all_frames = set(range(truth.n_frames))
    good = all_frames - truth.bad_frames
    registered: set[int] = set()
    for m in models:
        registered |= {int(f) for f in m.frames}
    unknown = registered - all_frames
    if unknown:
        log.warning("%d registered frame index(es) outside 0..%d, e.g. %d",
                    len(unknown), truth.n_frames - 1, min(unknown))
    reg = registered & all_frames
    return {
        "n_frames": truth.n_frames,
        "n_bad_frames": len(truth.bad_frames & all_frames),
        "n_models": len(models),
        "n_registered": len(reg),
        "registered_share": len(reg) / truth.n_frames if truth.n_frames else None,
        "registered_share_good": len(reg & good) / len(good) if good else None,
        "n_registered_bad": len(reg & truth.bad_frames),
        "n_registered_unknown": len(unknown),
        "largest_model_share": max((len(m.frames) for m in models), default=0) / truth.n_frames
        if truth.n_frames else None,
    }


def score_model(truth: Truth, model: Model) -> dict[str, Any]:
    """Per-model figures: size, reprojection error (computed and as reported), intrinsics."""
    out: dict[str, Any] = {
        "path": str(model.path),
        "n_registered": len(model.frames),
        "n_images": model.n_images,
        "n_points3d": model.n_points3d,
        "mean_reprojection_error_px": model.reprojection_error_px,
        "reported_reprojection_error_px": model.quality.get("mean_reprojection_error_px"),
        "claims_metric": model.claims_metric,
    }
    if model.focal_per_width is not None:  # focal length relative to image width
        true_fw = truth.camera.fx / truth.camera.width
        out["focal_error_percent"] = 100.0 * (model.focal_per_width - true_fw) / true_fw
    return out


def score_trajectory(
    truth: Truth, model: Model, cfg: EvalConfig
) -> tuple[dict[str, Any], Sim3] | None:
    """Sim(3)-align the model's camera centres to the true ones (same frames); errors in mm and deg.

    Returns None (and logs why) when fewer than ``cfg.min_alignment_frames`` frames match.
    """
    common, i_model, i_truth = np.intersect1d(model.frames, truth.frames, return_indices=True)
    if len(common) < cfg.min_alignment_frames:
        log.warning("%s: only %d registered frame(s) have a true pose; trajectory not scored",
                    model.path, len(common))
        return None
    src, dst = model.centres[i_model], truth.centres[i_truth]
    if np.linalg.matrix_rank(src - src.mean(0), tol=1e-9 * max(1.0, np.abs(src).max())) < 2:
        log.warning("%s: camera centres are collinear; trajectory not scored", model.path)
        return None
    sim, inliers = align(src, dst, cfg.alignment_trim)
    err = np.linalg.norm(sim.apply(src) - dst, axis=1)
    rmse = float(np.sqrt(np.mean(err**2)))
    aligned = sim.rotation @ model.rotations[i_model]  # (N,3,3) camera-to-world in truth frame
    rel = np.einsum("nji,njk->nik", truth.rotations[i_truth], aligned)
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    rot_err = np.degrees(np.arccos(cos))
    ratio = 1.0 / sim.scale  # model size / true size
    scores = {
        "n_matched": len(common),
        "n_inliers": int(inliers.sum()),
        "rmse_mm": rmse,
        "rmse_percent_extent": 100.0 * rmse / truth.extent_mm if truth.extent_mm > 0 else None,
        "median_error_mm": float(np.median(err)),
        "max_error_mm": float(err.max()),
        "scale_ratio": ratio,
        "scale_error": abs(ratio - 1.0),
        "claims_metric": model.claims_metric,
        "rotation_error_deg_median": float(np.median(rot_err)),
        "rotation_error_deg_mean": float(np.mean(rot_err)),
        "rotation_error_deg_max": float(np.max(rot_err)),
        "sim3_model_to_truth": sim.to_dict(),
    }
    log.info("%s: %d frames, RMSE %.3f mm, scale ratio %.4f, rotation error %.3f deg (median)",
             model.path, len(common), rmse, ratio, scores["rotation_error_deg_median"])
    if not math.isfinite(rmse):
        raise InputError(f"COLMAP model {model.path}: non-finite camera poses")
    return scores, sim
