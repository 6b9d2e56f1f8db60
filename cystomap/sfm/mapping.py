"""Incremental mapping with bundle adjustment (COLMAP), densification at full size, then a
final filter-and-adjust pass."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)


@dataclass
class MappingResult:
    """The largest model and the sizes (and frame names) of all models found."""

    reconstruction: Any  # pycolmap.Reconstruction
    models: list[list[str]]  # registered names per model, largest first
    final_ba: dict[str, Any]
    others: list[Any] = field(default_factory=list)  # the other models (pieces), models[1:]


@contextlib.contextmanager
def _clock(times: dict[str, float], name: str) -> Iterator[None]:
    """Adds the CPU seconds of the block to ``times[name]`` (this process, all threads)."""
    c = time.process_time()
    try:
        yield
    finally:
        times[name] = times.get(name, 0.0) + time.process_time() - c


def refine_intrinsics(cfg: SfmConfig, calibrated: bool) -> bool:
    if cfg.intrinsics == "auto":
        return not calibrated
    return cfg.intrinsics == "refine"


def camera_model(cfg: SfmConfig, calibrated: bool) -> str:
    """COLMAP model of the shared camera: PINHOLE when fixed, else the self-calibration's."""
    return cfg.self_calibration_model if refine_intrinsics(cfg, calibrated) else "PINHOLE"


def _refine_distortion(cfg: SfmConfig, refine: bool) -> bool:
    return refine and cfg.self_calibration_model != "SIMPLE_PINHOLE"


def _shared(o: Any, cfg: SfmConfig, image_path: Path) -> Any:
    """The settings COLMAP's incremental and global pipeline options have in common."""
    o.num_threads = cfg.mapping_threads
    o.random_seed = cfg.seed
    o.multiple_models = True
    o.min_model_size = cfg.min_model_frames
    o.min_num_matches = cfg.min_num_inliers
    o.image_path = str(image_path)
    return o


def pipeline_options(cfg: SfmConfig, refine: bool, image_path: Path) -> Any:
    import pycolmap

    o = _shared(pycolmap.IncrementalPipelineOptions(), cfg, image_path)
    o.extract_colors = False
    o.ba_refine_focal_length = refine
    o.ba_refine_principal_point = False
    o.ba_refine_extra_params = _refine_distortion(cfg, refine)
    o.ba_global_frames_ratio = cfg.ba_global_ratio
    o.ba_global_points_ratio = cfg.ba_global_ratio
    o.ba_local_max_num_iterations = cfg.ba_local_max_iterations
    o.ba_global_max_num_iterations = cfg.ba_global_max_iterations
    o.ba_global_max_refinements = cfg.ba_global_refinements
    m = o.mapper
    m.num_threads = cfg.mapping_threads
    m.random_seed = cfg.seed
    m.init_min_num_inliers = cfg.init_min_num_inliers
    m.init_min_tri_angle = cfg.init_min_tri_angle
    m.init_max_error = cfg.ransac_max_error_px
    m.abs_pose_max_error = cfg.abs_pose_max_error_px
    m.abs_pose_min_num_inliers = cfg.abs_pose_min_num_inliers
    m.abs_pose_refine_focal_length = refine
    m.abs_pose_refine_extra_params = _refine_distortion(cfg, refine)
    m.filter_max_reproj_error = cfg.max_reproj_error_px
    t = o.triangulation
    t.random_seed = cfg.seed
    t.merge_max_reproj_error = cfg.track_merge_error_px
    t.complete_max_reproj_error = cfg.track_merge_error_px
    return o


def global_options(cfg: SfmConfig, refine: bool, image_path: Path) -> Any:
    """COLMAP's global mapper (GLOMAP) with the stage's threads, seed, thresholds and
    intrinsics (refined as :func:`pipeline_options` would), on the CPU."""
    import pycolmap

    o = _shared(pycolmap.GlobalPipelineOptions(), cfg, image_path)
    m = o.mapper
    m.num_threads = cfg.mapping_threads
    m.random_seed = cfg.seed
    m.rotation_averaging.random_seed = cfg.seed
    m.global_positioning.random_seed = cfg.seed
    m.global_positioning.use_gpu = False
    m.retriangulation.random_seed = cfg.seed
    ba = m.bundle_adjustment
    ba.refine_focal_length = refine
    ba.refine_principal_point = False
    ba.refine_extra_params = _refine_distortion(cfg, refine)
    ba.ceres.use_gpu = False
    ba.ceres.solver_options.num_threads = cfg.mapping_threads
    return o


def _map_keyframes(database: Path, color_dir: Path, out: Path, cfg: SfmConfig, refine: bool,
                   opts: Any) -> dict[int, Any]:
    """Map ``opts.image_names`` (all frames when empty) with ``cfg.mapper``: the models by id;
    ``opts`` are the incremental pipeline's (:func:`pipeline_options`)."""
    import pycolmap

    if cfg.mapper == "global":
        o = global_options(cfg, refine, color_dir)
        o.image_names = opts.image_names
        return dict(pycolmap.global_mapping(database, color_dir, out, options=o))
    return dict(pycolmap.incremental_mapping(database, color_dir, out, options=opts))


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


def weak_frames(verified: dict[tuple[int, int], int], n: int, cfg: SfmConfig) -> set[int]:
    """Frames whose link to their video neighbours is weak (motion blur, defocus, glare): the
    median verified inliers of a frame's pairs within ``sequential_overlap`` frames is below
    ``weak_frame_rel`` times the median of that figure over the frames within
    ``sequential_max_gap`` of it, in runs that a strong pair (``extend_min_inliers``) of
    other frames spans. Mapped last, so a blurred stretch cannot split the model."""

    if cfg.weak_frame_rel <= 0 or n < 3:
        return set()
    links: list[list[int]] = [[] for _ in range(n)]
    for (i, j), inliers in verified.items():
        if abs(i - j) <= cfg.sequential_overlap:
            links[i].append(inliers)
            links[j].append(inliers)
    strength = np.array([float(np.median(v)) if v else 0.0 for v in links])
    w = cfg.sequential_max_gap
    typical = np.array([np.median(strength[max(0, i - w): i + w + 1]) for i in range(n)])
    weak = [int(i) for i in np.nonzero(strength < cfg.weak_frame_rel * typical)[0]]
    # a run of consecutive weak frames is left out of the mapping only when a strong pair of
    # other frames spans it: otherwise the weak frames are the chain's only link, and
    # mapping without them would split the model there
    runs: list[list[int]] = []
    for i in weak:
        if runs and i == runs[-1][-1] + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    weak_set = set(weak)
    strong = [(i, j) for (i, j), v in verified.items()
              if v >= cfg.extend_min_inliers and i not in weak_set and j not in weak_set]
    return {i for run in runs if any(i < run[0] and j > run[-1] for i, j in strong)
            for i in run}


def keyframes(n: int, stride: int) -> list[int]:
    frames = list(range(0, n, stride))
    if frames[-1] != n - 1:
        frames.append(n - 1)
    return frames


def reconstruct(
    database: Path, color_dir: Path, work_dir: Path, cfg: SfmConfig, calibrated: bool,
    names: list[str], key: list[int], enhanced_dir: Path | None = None,
    mask_path: Path | None = None, masks_dir: Path | None = None, weak: set[int] | None = None,
    close_loops: Callable[[Any, Any], dict[str, Any]] | None = None,
    undistort: Callable[[Any], tuple[Path, Path | None]] | None = None,
    guard: Callable[[Any], int] | None = None,
) -> MappingResult | None:
    """Map the keyframes ``key`` (indices into ``names``) that are not ``weak`` incrementally,
    register every other frame to the largest model (the weak ones, the other keyframes and
    the frames of other models, nearest in video order to the model first; pose +
    triangulation, then one global adjustment when that added many), add full-size corner
    tracks (``densify_corners``; on the frames of ``enhanced_dir`` inside ``mask_path`` and the
    per-frame masks of ``masks_dir``), then adjust globally. ``close_loops(rec,
    triangulation_options)``, when given, runs after the frames are registered and before
    densification (loop pairs held back from mapping).
    With ``undistort`` (self-calibrated distortion) the model is made pinhole before
    densification (it returns the undistorted enhanced frames and mask; the per-frame glint
    masks, drawn on the distorted frames, are then not used), and the final adjustment keeps
    the intrinsics it was undistorted with. With ``guard`` (places where a model contradicts
    its frame pairs), the other models that share frames with the largest are joined to it
    when that adds no such place (:func:`cystomap.sfm.pieces.join`).
    ``None`` when no model of at least ``min_model_frames`` was found."""

    from cystomap.sfm.densify import densify, drop_short_sift

    refine = refine_intrinsics(cfg, calibrated)
    weak = weak or set()
    mapped = [i for i in key if i not in weak]
    if len(mapped) < max(cfg.min_model_frames, len(key) // 2):
        mapped = key  # mostly weak: nothing better to start from
    if len(mapped) < len(key):
        log.info("mapping: %d weak frame(s) (blur) are registered after the others: %s",
                 len(key) - len(mapped), [names[i] for i in key if i not in mapped][:20])
    cpu: dict[str, float] = {}
    attempt = _map_and_extend(database, color_dir, work_dir / "models", cfg, refine, names,
                              mapped, key, guard, cpu)
    if len(mapped) < len(key) and (attempt is None or attempt[1]):
        # sharp frames first did not give one model: the weak frames may be the only links
        # (blur everywhere); map them together with the others too, keep the larger model
        log.info("mapping: again with the weak frames mapped together with the others")
        plain = _map_and_extend(database, color_dir, work_dir / "models_all", cfg, refine,
                                names, key, key, guard, cpu)
        if plain is not None and (attempt is None
                                  or plain[0].num_reg_images() > attempt[0].num_reg_images()):
            attempt = plain
            weak = set()
    if attempt is None:
        return None
    rec, others, added, joined = attempt
    with _clock(cpu, "loops"):
        loops = (close_loops(rec, pipeline_options(cfg, refine, color_dir).get_triangulation())
                 if close_loops is not None else {})
    if undistort is not None:
        with _clock(cpu, "undistort"):
            enhanced_dir, mask_path = undistort(rec)
        masks_dir = None
        refine = False
    dense: dict[str, int] = {}
    if enhanced_dir is not None and cfg.densify_corners > 0:
        mask = None
        if mask_path is not None and mask_path.is_file():
            mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        stride = key[1] - key[0] if len(key) > 1 else 1
        with _clock(cpu, "densify"):
            sift = set(rec.points3D)
            dense = densify(rec, enhanced_dir, mask, cfg, stride, masks_dir).to_dict()
            if cfg.densify_drop_short_sift and dense["points"]:
                dense["sift_points_dropped"] = drop_short_sift(rec, sift, cfg, stride)
    with _clock(cpu, "final_ba"):
        final = final_adjustment(rec, cfg, refine)
    final["lone_frames"] = drop_lone_frames(rec, names, cfg.sequential_overlap)
    final["registered_after_keyframes"] = added
    final["pieces_joined"] = joined
    final["weak_frames"] = sorted(names[i] for i in weak)
    final["densification"] = dense
    final["loops"] = loops
    final["cpu_s"] = {k: round(v, 2) for k, v in cpu.items()}
    log.info("mapping: CPU s per part %s", final["cpu_s"])
    main = sorted(rec.image(i).name for i in rec.reg_image_ids())
    # the other models without the frames the largest took over
    rest = [[n for n in sorted(r.image(i).name for i in r.reg_image_ids()) if n not in main]
            for r in others]
    keep = sorted((k for k, m in enumerate(rest) if len(m) >= 2),
                  key=lambda k: (-len(rest[k]), rest[k]))
    return MappingResult(rec, [main, *(rest[k] for k in keep)], final, [others[k] for k in keep])


def _map_and_extend(database: Path, color_dir: Path, out: Path, cfg: SfmConfig, refine: bool,
                    names: list[str], mapped: list[int], key: list[int],
                    guard: Callable[[Any], int] | None = None,
                    cpu: dict[str, float] | None = None,
                    ) -> tuple[Any, list[Any], int, dict[str, Any]] | None:
    """Incremental mapping of ``mapped`` (indices into ``names``), then every other frame
    registered to the largest model (keyframes ``key`` among them with a local bundle
    adjustment each, as the mapper would: they extend the model rather than fill it in):
    (largest model, the other models it did not absorb, frames added); None when no model
    was started. With ``guard``, the other models are then joined where they can be
    (:func:`cystomap.sfm.pieces.join`; its figures are the tuple's last item). CPU seconds
    per part are added to ``cpu``."""
    import pycolmap

    cpu = {} if cpu is None else cpu

    pycolmap.set_random_seed(cfg.seed)
    opts = pipeline_options(cfg, refine, color_dir)
    if len(mapped) < len(names):
        opts.image_names = [names[i] for i in mapped]
    out.mkdir(parents=True, exist_ok=True)
    with _clock(cpu, cfg.mapper):
        recs = _map_keyframes(database, color_dir, out, cfg, refine, opts)
    recs = {k: r for k, r in recs.items() if r.num_reg_images() >= 2}
    if not recs:
        return None
    ordered = sorted(recs.values(), key=lambda r: -r.num_reg_images())
    log.info("mapping: %d model(s) with %s of %d mapped frames", len(ordered),
             [r.num_reg_images() for r in ordered], len(mapped))
    rec = ordered[0]
    added = 0
    before = rec.num_reg_images()
    if before < len(names):
        with _clock(cpu, "register_rest"):
            added = register_rest(database, rec, names, opts, {names[i] for i in key})
        if (cfg.ba_global_after_registering
                and added > cfg.ba_global_ratio * before - before):  # as the mapper would have
            with _clock(cpu, "register_rest_ba"):
                adjust(rec, cfg, refine, cfg.ba_global_max_iterations)
    registered = {rec.image(i).name for i in rec.reg_image_ids()}
    others = [r for r in ordered[1:]
              if not {r.image(i).name for i in r.reg_image_ids()} <= registered]
    if len(others) < len(ordered) - 1:
        log.info("mapping: %d other model(s) joined the largest through their frames",
                 len(ordered) - 1 - len(others))
    joined: dict[str, Any] = {}
    if guard is not None and others:
        from cystomap.sfm.pieces import join

        with _clock(cpu, "join"):
            rec, others, joined = join(database, rec, others, names, {names[i] for i in key},
                                       opts, cfg, refine, guard)
        registered = {rec.image(i).name for i in rec.reg_image_ids()}
        others = [r for r in others
                  if not {r.image(i).name for i in r.reg_image_ids()} <= registered]
        added = rec.num_reg_images() - before
    return rec, others, added, joined


def register_rest(database: Path, rec: Any, names: list[str], opts: Any,
                  refine_names: set[str] | None = None) -> int:
    """Register the frames missing from ``rec`` by absolute pose, triangulate their matches,
    merge tracks; returns how many were added. Passes until one adds nothing; in each, the
    frames nearest in video order to a registered one come first (a chain grows both ways
    from the model, across a stretch it could not map). Frames of ``refine_names`` get a
    local bundle adjustment after registration."""
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
    local_ba = opts.get_local_bundle_adjustment()
    refine = refine_names or set()

    registered = set(rec.reg_image_ids())
    index = {ids[n]: k for k, n in enumerate(names) if n in ids}
    # frames without a verified pair are not in the cache (nothing to register them with)
    pending = [ids[n] for n in names
               if n in ids and ids[n] not in registered and cache.exists_image(ids[n])]
    added = 0
    while pending:
        done = np.array(sorted(index[i] for i in registered))
        if not len(done):
            break
        pos = np.array([index[i] for i in pending])
        near = np.abs(pos[:, None] - done[None, :]).min(axis=1)
        left = []
        for k in np.lexsort((pos, near)):
            image_id = pending[int(k)]
            if mapper.register_next_image(mopts, image_id):
                mapper.triangulate_image(tri, image_id)
                if names[index[image_id]] in refine:
                    mapper.iterative_local_refinement(
                        opts.ba_local_max_refinements, opts.ba_local_max_refinement_change,
                        mopts, local_ba, tri, image_id)
                registered.add(image_id)
                added += 1
            else:
                left.append(image_id)
        if len(left) == len(pending):
            break
        pending = sorted(left, key=index.__getitem__)
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
    thin = drop_thin_frames(rec, cfg.min_frame_points_rel)
    rec.update_point_3d_errors()
    after = float(rec.compute_mean_reprojection_error())
    log.info("final adjustment: reprojection error %.3f -> %.3f px, %d observations dropped",
             before, after, dropped)
    return {"iterations": rounds, "observations_dropped": dropped,
            "reprojection_error_before_px": before, "reprojection_error_after_px": after,
            "thin_frames": thin}


def drop_lone_frames(rec: Any, names: list[str], reach: int) -> dict[str, str]:
    """Take out of ``rec`` every registered frame with no other registered frame within
    ``reach`` places of it in the video (``names``, video order; ``sequential_overlap``): no
    chain pair tests its pose, which rests on loop matches alone. Returns why, per frame name
    (quality.json's ``dropped_frames``).

    On held-out glints:11 (1280x720, blurred) frame 106, between black, blurred and thin
    frames, was placed by 95 points shared with frames 63-67 (a blurred stretch, 0.5-1.6 mm
    off) 12.9 mm from its true pose, and no check could see it (docs/measurements.md,
    "Pieces joined on two shared frames")."""
    import pycolmap

    at = {n: k for k, n in enumerate(names)}
    reg = {i: at[rec.image(i).name] for i in rec.reg_image_ids() if rec.image(i).name in at}
    if len(reg) < 3:
        return {}
    placed = set(reg.values())
    lone = sorted((i for i, k in reg.items()
                   if not any(k + d in placed for d in range(-reach, reach + 1) if d)),
                  key=lambda i: reg[i])
    if not lone:
        return {}
    obs = pycolmap.ObservationManager(rec)
    out = {}
    for i in lone:
        name = rec.image(i).name
        out[name] = (f"registered alone (no other frame within {reach} of it in the model): "
                     "its pose rests on loop matches no neighbour checks")
        obs.deregister_frame(rec.image(i).frame_id)
    log.warning("mapping: %d frame(s) registered with no neighbour within %d frames taken out "
                "of the model (nothing along the video checks their poses): %s", len(out),
                reach, ", ".join(out))
    return out


def drop_thin_frames(rec: Any, share: float) -> dict[str, str]:
    """Take out of ``rec`` every registered frame posed from fewer 3-D points than ``share``
    times the median over its frames (``SfmConfig.min_frame_points_rel``); returns why, per
    frame name (quality.json's ``dropped_frames``)."""
    import pycolmap

    ids = list(rec.reg_image_ids())
    if share <= 0 or len(ids) < 3:
        return {}
    points = {i: int(rec.image(i).num_points3D) for i in ids}
    median = float(np.median(list(points.values())))
    thin = sorted((i for i in ids if points[i] < share * median), key=lambda i: rec.image(i).name)
    if not thin:  # below a share (< 1) of the median: never more than half the frames
        return {}
    obs = pycolmap.ObservationManager(rec)
    out = {}
    for i in thin:
        name = rec.image(i).name
        out[name] = f"posed from too few points ({points[i]}, median {median:.0f})"
        obs.deregister_frame(rec.image(i).frame_id)
    log.warning("mapping: %d frame(s) posed from fewer than %g x the median %d points taken out "
                "of the model (their poses are not reliable): %s", len(out), share, median,
                ", ".join(out))
    return out
