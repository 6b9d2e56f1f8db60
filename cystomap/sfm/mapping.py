"""Incremental mapping with bundle adjustment (COLMAP), densification at full size, then a
final filter-and-adjust pass."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)


@dataclass
class MappingResult:
    """The largest model and the sizes (and frame names) of all models found."""

    reconstruction: Any  # pycolmap.Reconstruction
    models: list[list[str]]  # registered names per model, largest first
    final_ba: dict[str, Any]


def refine_intrinsics(cfg: SfmConfig, calibrated: bool) -> bool:
    if cfg.intrinsics == "auto":
        return not calibrated
    return cfg.intrinsics == "refine"


def pipeline_options(cfg: SfmConfig, refine: bool, image_path: Path) -> Any:
    import pycolmap

    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = cfg.mapping_threads
    o.random_seed = cfg.seed
    o.multiple_models = True
    o.min_model_size = cfg.min_model_frames
    o.min_num_matches = cfg.min_num_inliers
    o.extract_colors = False
    o.image_path = str(image_path)
    o.ba_refine_focal_length = refine
    o.ba_refine_principal_point = False
    o.ba_refine_extra_params = False
    o.ba_global_frames_ratio = cfg.ba_global_ratio
    o.ba_global_points_ratio = cfg.ba_global_ratio
    o.ba_local_max_num_iterations = cfg.ba_local_max_iterations
    o.ba_global_max_num_iterations = cfg.ba_global_max_iterations
    m = o.mapper
    m.num_threads = cfg.mapping_threads
    m.random_seed = cfg.seed
    m.init_min_num_inliers = cfg.init_min_num_inliers
    m.init_min_tri_angle = cfg.init_min_tri_angle
    m.init_max_error = cfg.ransac_max_error_px
    m.abs_pose_max_error = cfg.abs_pose_max_error_px
    m.abs_pose_min_num_inliers = cfg.abs_pose_min_num_inliers
    m.abs_pose_refine_focal_length = refine
    m.abs_pose_refine_extra_params = False
    m.filter_max_reproj_error = cfg.max_reproj_error_px
    t = o.triangulation
    t.random_seed = cfg.seed
    t.merge_max_reproj_error = cfg.max_reproj_error_px
    t.complete_max_reproj_error = cfg.max_reproj_error_px
    return o


def as_pinhole(rec: Any) -> None:
    """Turn SIMPLE_PINHOLE cameras of ``rec`` into the equivalent PINHOLE (fx = fy = f)."""
    import pycolmap

    for camera_id in list(rec.cameras):
        cam = rec.camera(camera_id)
        if cam.model_name == "SIMPLE_PINHOLE":
            f, cx, cy = (float(v) for v in cam.params)
            cam.model = pycolmap.CameraModelId.PINHOLE
            cam.params = [f, f, cx, cy]


def keyframe_stride(verified: dict[tuple[int, int], int], n: int, cfg: SfmConfig) -> int:
    """Largest power-of-two stride s (<= ``keyframe_max_stride``) such that nearly all
    candidate keyframes i (multiples of s) have strong pairs (i, i + s) and (i, i + 2s)."""
    stride, s = 1, 2
    while 2 * s <= cfg.sequential_max_gap and s <= cfg.keyframe_max_stride:
        cand = range(0, n - 2 * s, s)
        if len(cand) < 3:
            break
        strong = sum(
            verified.get((i, i + s), 0) >= cfg.extend_min_inliers
            and verified.get((i, i + 2 * s), 0) >= cfg.extend_min_inliers
            for i in cand
        )
        if strong < cfg.keyframe_min_share * len(cand):
            break
        stride, s = s, 2 * s
    return stride


def keyframes(n: int, stride: int) -> list[int]:
    frames = list(range(0, n, stride))
    if frames[-1] != n - 1:
        frames.append(n - 1)
    return frames


def reconstruct(
    database: Path, color_dir: Path, work_dir: Path, cfg: SfmConfig, calibrated: bool,
    names: list[str], key: list[int], enhanced_dir: Path | None = None,
    mask_path: Path | None = None, close_loops: Callable[[Any, Any], dict[str, Any]] | None = None,
) -> MappingResult | None:
    """Map the keyframes ``key`` (indices into ``names``) incrementally, register the other
    frames to that model (pose + triangulation, no local adjustment), add full-size corner
    tracks (``densify_corners``; on the frames of ``enhanced_dir`` inside ``mask_path``), then
    adjust globally. ``close_loops(rec, triangulation_options)``, when given, runs after the
    frames are registered and before densification (loop pairs held back from mapping).
    ``None`` when no model of at least ``min_model_frames`` was found."""
    import pycolmap

    from cystomap.sfm.densify import densify

    pycolmap.set_random_seed(cfg.seed)
    refine = refine_intrinsics(cfg, calibrated)
    opts = pipeline_options(cfg, refine, color_dir)
    if len(key) < len(names):
        opts.image_names = [names[i] for i in key]
    out = work_dir / "models"
    out.mkdir(parents=True, exist_ok=True)
    recs = pycolmap.incremental_mapping(database, color_dir, out, options=opts)
    recs = {k: r for k, r in recs.items() if r.num_reg_images() >= 2}
    if not recs:
        return None
    ordered = sorted(recs.values(), key=lambda r: -r.num_reg_images())
    models = [sorted(r.image(i).name for i in r.reg_image_ids()) for r in ordered]
    log.info("mapping: %d model(s) with %s of %d keyframes", len(models),
             [len(m) for m in models], len(key))
    rec = ordered[0]
    added = 0
    if len(key) < len(names):
        added = register_rest(database, rec, names, opts)
    loops = close_loops(rec, opts.get_triangulation()) if close_loops is not None else {}
    dense: dict[str, int] = {}
    if enhanced_dir is not None and cfg.densify_corners > 0:
        mask = None
        if mask_path is not None and mask_path.is_file():
            mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        stride = key[1] - key[0] if len(key) > 1 else 1
        dense = densify(rec, enhanced_dir, mask, cfg, stride).to_dict()
    final = final_adjustment(rec, cfg, refine)
    final["registered_after_keyframes"] = added
    final["densification"] = dense
    final["loops"] = loops
    models[0] = sorted(rec.image(i).name for i in rec.reg_image_ids())
    return MappingResult(rec, models, final)


def register_rest(database: Path, rec: Any, names: list[str], opts: Any) -> int:
    """Register the frames missing from ``rec`` by absolute pose (in video order, two
    passes), triangulate their matches, merge tracks; returns how many were added."""
    import pycolmap

    cache_opts = pycolmap.DatabaseCacheOptions()
    cache_opts.min_num_matches = opts.min_num_matches
    db = pycolmap.Database.open(str(database))
    try:
        cache = pycolmap.DatabaseCache.create(db, cache_opts)
        ids = {im.name: im.image_id for im in db.read_all_images()}
    finally:
        db.close()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    mopts = opts.get_mapper()
    tri = opts.get_triangulation()
    registered = set(rec.reg_image_ids())
    pending = [ids[n] for n in names if n in ids and ids[n] not in registered]
    added = 0
    for _ in range(3):
        left = []
        for image_id in pending:
            if mapper.register_next_image(mopts, image_id):
                mapper.triangulate_image(tri, image_id)
                added += 1
            else:
                left.append(image_id)
        if not left or len(left) == len(pending):
            break
        pending = left
    mapper.complete_and_merge_tracks(tri)
    mapper.end_reconstruction(False)
    log.info("mapping: %d more frames registered to the keyframe model", added)
    return added


def bundle_options(cfg: SfmConfig, refine: bool, iterations: int) -> Any:
    import pycolmap

    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = refine
    ba.refine_principal_point = False
    ba.refine_extra_params = False
    ba.print_summary = False
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.SOFT_L1
    ba.ceres.loss_function_scale = 1.0
    so = ba.ceres.solver_options
    so.num_threads = cfg.mapping_threads
    so.max_num_iterations = iterations
    so.function_tolerance = 1e-7
    return ba


def adjust(rec: Any, cfg: SfmConfig, refine: bool, iterations: int) -> bool:
    """Global bundle adjustment of all registered frames and points; True if converged."""
    import pycolmap

    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    if not refine:
        for camera_id in rec.cameras:
            config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    summary = pycolmap.create_default_bundle_adjuster(
        bundle_options(cfg, refine, iterations), config, rec
    ).solve()
    return summary.termination_type == pycolmap.BundleAdjustmentTerminationType.CONVERGENCE


def final_adjustment(rec: Any, cfg: SfmConfig, refine: bool) -> dict[str, Any]:
    """Drop observations above ``final_filter_error_px``, re-adjust, and repeat once."""
    import pycolmap

    before = float(rec.compute_mean_reprojection_error())
    dropped = 0
    rounds = 0
    if cfg.final_filter_error_px > 0:
        for _ in range(2):
            obs = pycolmap.ObservationManager(rec)
            n = obs.filter_all_points3D(cfg.final_filter_error_px, 1.0)
            dropped += int(n)
            adjust(rec, cfg, refine, cfg.final_ba_max_iterations)
            rounds += 1
            if n == 0:
                break
        obs = pycolmap.ObservationManager(rec)
        dropped += int(obs.filter_all_points3D(cfg.final_filter_error_px, 1.0))
        for frame_id in obs.filter_frames(0.1, 10.0, 1.0, 10):
            log.warning("frame %d has too few observations left; de-registered", frame_id)
            obs.deregister_frame(frame_id)
    rec.update_point_3d_errors()
    after = float(rec.compute_mean_reprojection_error())
    log.info("final adjustment: reprojection error %.3f -> %.3f px, %d observations dropped",
             before, after, dropped)
    return {"iterations": rounds, "observations_dropped": dropped,
            "reprojection_error_before_px": before, "reprojection_error_after_px": after}
