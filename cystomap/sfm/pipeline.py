"""The structure-from-motion stage: preprocessed frames -> camera poses and a sparse cloud.

Steps (each timed in quality.json): SIFT features at reduced size inside the mask; pairs =
video-order neighbours and VLAD retrieval neighbours (loop closure); COLMAP matching and
two-view verification; incremental mapping with bundle adjustment and fixed (calibrated) or
refined intrinsics, kept when the model agrees with the sequential pairs and with most loop
pairs; otherwise (a fold, or repeated texture) mapped again from the sequential pairs alone,
loop pairs used only where their geometry agrees with that model (cystomap/sfm/consistency.py);
densification with corner tracks aligned on the full-size frames; a final
filter-and-adjust pass; a self-check that fails a folded model; metric scale from the known
extent or volume of the bladder. A model that is short, flagged or failed is mapped once more
with features twice as fine (cystomap/sfm/retry.py).
"""

from __future__ import annotations

import contextlib
import logging
import math
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from cystomap.camera import Camera
from cystomap.errors import InputError, StageError
from cystomap.io.ply import write_ply
from cystomap.outputs import atomic_dir, software_versions, write_json
from cystomap.sfm import (
    consistency,
    drift,
    intrinsics,
    mapping,
    matching,
    pairs,
    quality,
    retry,
    rotation,
    scale,
)
from cystomap.sfm import features as feat
from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)

MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin")


@contextlib.contextmanager
def _quiet_colmap() -> Iterator[None]:
    """COLMAP's own INFO lines only when this module logs at DEBUG."""
    import pycolmap

    old = pycolmap.logging.minloglevel
    if not log.isEnabledFor(logging.DEBUG):
        pycolmap.logging.minloglevel = 1
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


class _Timer:
    """Wall-clock and CPU (all threads) seconds per step."""

    def __init__(self) -> None:
        self.times: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self._t0 = time.perf_counter()
        self._c0 = time.process_time()

    @contextlib.contextmanager
    def step(self, name: str) -> Iterator[None]:
        t, c = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.times[name] = self.times.get(name, 0.0) + time.perf_counter() - t
            self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - c

    def totals(self) -> tuple[dict[str, float], dict[str, float]]:
        wall, cpu = dict(self.times), dict(self.cpu)
        wall["total"] = time.perf_counter() - self._t0
        cpu["total"] = time.process_time() - self._c0
        return wall, cpu


def run_sfm(
    preprocessed_dir: str | Path,
    out_dir: str | Path,
    cfg: SfmConfig | None = None,
    extent_mm: float | None = None,
    volume_ml: float | None = None,
) -> Path:
    """Estimate camera poses and a sparse cloud of one session; write them to ``out_dir``.

    ``preprocessed_dir`` holds ``enhanced/`` (features), ``color/`` (point colours),
    ``mask.png`` and ``camera.json``. ``out_dir`` receives a COLMAP binary model
    (``cameras.bin``, ``images.bin``, ``points3D.bin``; in mm when ``extent_mm`` or
    ``volume_ml`` is known), ``points.ply`` and ``quality.json``, all or nothing. A short,
    flagged or failed model is mapped again with finer features when they were detected below
    the lit field's size, and the better model kept (cystomap/sfm/retry.py).

    Raises :class:`StageError` when too few frames register (the message says how many and
    why) or the model contradicts the matches that link its parts (a fold), and
    :class:`InputError` when the inputs are missing or inconsistent.
    """
    cfg = cfg or SfmConfig()
    pre = Path(preprocessed_dir)
    out_dir = Path(out_dir)
    for value, name in ((extent_mm, "extent_mm"), (volume_ml, "volume_ml")):
        if value is not None and not (value > 0 and math.isfinite(value)):
            raise InputError(f"{name} must be a positive number, got {value!r}")
    camera = Camera.load(pre / "camera.json")
    mask = pre / "mask.png" if (pre / "mask.png").is_file() else None
    working = feat.working_scale(camera, cfg, feat.lit_extent(mask, camera))
    return retry.map_with_retry(
        lambda out, c: _attempt(pre, out, c, extent_mm, volume_ml), out_dir, cfg, working,
        _failed_dir)


def _attempt(pre: Path, out_dir: Path, cfg: SfmConfig, extent_mm: float | None,
             volume_ml: float | None) -> dict[str, Any]:
    """One mapping of the session into ``out_dir`` (see :func:`run_sfm`); its quality.json."""
    camera = Camera.load(pre / "camera.json")
    if camera.has_distortion:
        log.warning("%s has distortion coefficients; the frames are assumed undistorted and "
                    "the distortion is ignored", pre / "camera.json")
    enhanced = pre / "enhanced"
    names = feat.list_frames(enhanced)
    color_dir = pre / "color" if (pre / "color").is_dir() else enhanced
    mask = pre / "mask.png" if (pre / "mask.png").is_file() else None
    if mask is None:
        log.warning("%s: no mask.png; features are taken from the whole frame", pre)
    masks_dir = pre / "masks" if (pre / "masks").is_dir() else None  # per frame: glints
    n = len(names)
    log.info("sfm: %d frames from %s (%s intrinsics)", n, pre,
             "calibrated" if camera.calibrated else "uncalibrated")
    timer = _Timer()
    with tempfile.TemporaryDirectory(prefix="cystomap-sfm-") as tmp, _quiet_colmap():
        work = Path(tmp)
        database = work / "database.db"
        refine = mapping.refine_intrinsics(cfg, camera.calibrated)
        model = mapping.camera_model(cfg, camera.calibrated)
        undistort = None
        if model in intrinsics.DISTORTION_MODELS:  # self-calibrated lens: undistorted after mapping
            undistort = intrinsics.Undistortion(pre, work / intrinsics.UNDISTORTED, camera, names,
                                                cfg.num_threads)
        with timer.step("features"):
            features = feat.extract(enhanced, mask, camera, names, database, work, cfg, model,
                                    masks_dir)
        cfg = feat.matching_config(features, cfg)  # plain frames: guided matching
        with timer.step("matching"):
            verified, n_tried = matching.match_sequence(database, names, work, cfg)
        stride = mapping.keyframe_stride(verified, n, cfg)
        key = mapping.keyframes(n, stride)
        if stride > 1:
            log.info("keyframes: every %d-th frame, %d of %d", stride, len(key), n)
        with timer.step("matching"):
            matches = matching.read_stats(database, n_tried, cfg.min_num_inliers)
        chain = set(verified)
        need = max(cfg.min_registered_frames, math.ceil(cfg.min_registered_fraction * n))
        if matches.num_verified == 0:
            raise StageError(
                f"sfm: 0 of {n} frames registered: none of the {n_tried} image pairs "
                f"had {cfg.min_num_inliers} geometrically verified matches (median "
                f"{_median(features.num_keypoints.values()):.0f} features per frame)"
            )
        with timer.step("pairs"):
            tried = pairs.loop_pairs(database, names, key, cfg) - chain
        with timer.step("matching"):
            matching.match(database, names, tried, work, cfg)
        geoms = consistency.read_geometries(database, names, chain | tried, cfg.min_num_inliers)
        weak = mapping.weak_frames(verified, n, cfg)
        loops: dict[str, Any] = {}

        def check_joint(rec: Any, tri_options: Any, used: set[tuple[int, int]] = tried,
                        ) -> dict[str, Any]:
            # mapped with (untested) loop pairs: kept only when the model agrees with the chain
            with timer.step("loops"):
                fig = consistency.joint_check(rec, names, geoms, chain, used, cfg)
            loops.update(fig)
            if not fig["consistent"]:
                raise _HoldBack(fig["reason"])
            return loops  # quality.json's final_adjustment.loops (completed by bridge())

        def close_loops(rec: Any, tri_options: Any) -> dict[str, Any]:
            # loop (retrieval) pairs held back from mapping and used only where they agree
            # with the model of the sequential chain (cystomap/sfm/consistency.py)
            with timer.step("loops"):
                loops.update(consistency.close_loops(
                    rec, database, names, chain, tried, cfg, tri_options,
                    lambda r: mapping.adjust(r, cfg, refine, cfg.ba_global_max_iterations),
                    geoms))
            return {k: v for k, v in loops.items()
                    if k not in ("accepted", "rejected", "geometries")}

        def bridge(held: mapping.MappingResult) -> mapping.MappingResult | None:
            # the sequential chain broke into pieces: map again with the loop pairs that agreed
            # with the largest piece and those that link it to the others (they could not be
            # tested), kept only when that model passes the same check as a joint one
            rec = held.reconstruction
            inside = {rec.image(i).name for i in rec.reg_image_ids()}
            accepted = set(loops.get("accepted", ()))
            links = {p for p in tried if p in geoms
                     and (names[p[0]] in inside) != (names[p[1]] in inside)}
            if not links:
                return None
            used = accepted | links
            saved = dict(loops)
            log.info("sfm: %d of %d frames in the largest piece; mapping again with the %d loop "
                     "pairs that agree with it and the %d that link it to the other pieces",
                     len(inside), n, len(accepted), len(links))
            consistency.write_pairs(database, names, [geoms[p] for p in sorted(links)])
            loops.clear()
            try:
                out = run(lambda r, t: check_joint(r, t, used), "bridged")
            except _HoldBack as why:
                log.warning("sfm: not bridged: the model mapped with the linking loop pairs %s; "
                            "keeping the largest piece", why)
                out = None
            if out is None or out.reconstruction.num_reg_images() <= len(inside):
                consistency.delete_pairs(database, names, links)
                loops.clear()
                loops.update(saved)
                return None
            # the loop pairs the largest piece rejected stay rejected (they were not used)
            earlier = [p for p in saved.get("rejected_pairs", []) if p not in loops["rejected_pairs"]]
            loops["rejected_pairs"] = sorted(loops["rejected_pairs"] + earlier)
            loops["loop_pairs_rejected"] += len(earlier)
            loops["loop_pairs_verified"] += len(earlier)
            loops["bridged_pieces"] = len(held.others)
            return out

        def contradictions(rec: Any) -> int:
            # places (seams) where the chain pairs contradict the model: a piece joined by
            # the frames it shares with the model must not add one (cystomap/sfm/pieces.py)
            fig, _, _ = consistency.figures(rec, names, geoms, chain, tried, cfg)
            return len(fig["seams_broken"]) + fig["seams_weak_count"]

        def run(hook: Any, sub: str) -> mapping.MappingResult | None:
            return mapping.reconstruct(database, color_dir, work / sub, cfg, camera.calibrated,
                                       names, key, enhanced, mask, masks_dir, weak,
                                       undistort=undistort, close_loops=hook,
                                       guard=contradictions)

        with timer.step("mapping"):
            try:
                result = run(check_joint, "joint")
                mode = "joint"
            except _HoldBack as why:
                log.warning("sfm: the model mapped with the loop pairs %s; mapping again from "
                            "the sequential pairs alone, loop pairs used only where they "
                            "agree with that model", why)
                consistency.delete_pairs(database, names, tried)
                loops.clear()
                result = run(close_loops, "held_back")
                mode = "held_back"
                if result is not None and result.others:
                    bridged = bridge(result)
                    if bridged is not None:
                        result, mode = bridged, "bridged"
        n_loops = len(tried)
        pair_stats = {"sequential": n_tried, "retrieval": n_loops, "total": n_tried + n_loops,
                      "keyframe_stride": stride}
        failed = _failed_dir(out_dir)
        if result is None:
            matched = sum(1 for v in matches.verified_per_image.values() if v)
            message = (
                f"sfm: 0 of {n} frames registered: no model of at least {cfg.min_model_frames} "
                f"frames could be started ({matches.num_verified} verified pairs, {matched} frames "
                f"with a verified match)"
            )
            _write_failed(failed, message, names, None, pair_stats)
            raise StageError(f"{message}; details in {failed}")
        rec = result.reconstruction
        n_reg = rec.num_reg_images()
        if n_reg < need:
            message = (
                f"sfm: only {n_reg} of {n} frames registered in the largest model (need {need}); "
                f"{len(result.models)} model(s) of {[len(m) for m in result.models]} frames, "
                f"{matches.num_verified} of {n_tried} pairs verified"
            )
            _write_failed(failed, message, names, result, pair_stats)
            raise StageError(f"{message}; what did reconstruct (every model and a quality.json "
                             f"listing their frames) is in {failed}, for inspection only")
        n_tried += n_loops
        matches = matching.read_stats(database, n_tried, cfg.min_num_inliers)
        with timer.step("loops"):
            check = consistency.self_check(rec, names, geoms, chain, tried, cfg)
            check["loop_mode"] = mode
        if cfg.halves_check != "off":
            with timer.step("halves"):
                check["halves"] = drift.halves_check(database, color_dir, work / "halves", rec,
                                                     names, key, cfg, refine)
            _judge_halves(check, cfg, failed, names, result, pair_stats)
        if cfg.rotation_check != "off":
            with timer.step("loops"):
                # self-calibrated: the stored essential matrices saw the prior camera's rays
                check["rotation"] = rotation.rotation_check(rec, names, geoms, tried, cfg,
                                                            from_rays=not camera.calibrated)
            _judge_rotation(check, cfg, failed, names, result, pair_stats)
        mapping.as_pinhole(rec)
        if undistort is not None:
            color_dir = undistort.color_dir
        with timer.step("scale"):
            xyz, _, length, _ = quality.points_arrays(rec)
            est = scale.estimate_scale(
                xyz[length >= cfg.scale_min_track_length], cfg, extent_mm, volume_ml
            )
            scale.apply_scale(rec, est.factor)
            if est.metric and n_reg < n:
                # the known extent/volume is the whole bladder's: a model of part of it is
                # scaled too large (seen: 17 % with 66 of 124 frames)
                log.warning("sfm: the metric scale comes from the whole bladder's %s, but only "
                            "%d of %d frames are in the model: if it covers part of the wall, "
                            "its scale is too large", est.source, n_reg, n)
        with timer.step("colours"):
            n_read = quality.colour_points(rec, color_dir, cfg.num_threads, cfg.colour_max_frames)
            log.info("colours: from %d of %d frames", n_read, n_reg)
        with timer.step("write"), atomic_dir(out_dir) as out:
            rec.write_binary(str(out))
            if undistort is not None:
                shutil.copytree(undistort.out, out / intrinsics.UNDISTORTED)
                undistort.write(out)
            else:
                camera.save(out / "camera.json")
            xyz, rgb, _, _ = quality.points_arrays(rec)
            write_ply(out / "points.ply", xyz, colors=rgb, comment="cystomap sparse cloud")
            timings, cpu_times = timer.totals()
            q = quality.summarise(
                rec, names, features, matches, result.models, pair_stats, est.to_dict(), timings,
                {"final_adjustment": result.final_ba,
                 "intrinsics": "refined" if refine else "fixed",
                 "calibration": undistort.summary if undistort is not None
                 else intrinsics.fixed_summary(camera),
                 "working_scale": features.scale,
                 "doubled_frames": feat.doubled_frames(features, len(names), cfg),
                 "consistency": check,
                 "cpu_s": {k: round(v, 3) for k, v in cpu_times.items()},
                 "software": software_versions()},
                cfg.min_num_inliers,
            )
            q["other_models"] = [_piece(m, names) for m in result.models[1:]]
            write_json(out / "quality.json", q)
    if failed.exists():  # a failure of an earlier run: no longer true
        shutil.rmtree(failed, ignore_errors=True)
    log.info("sfm: %d of %d frames registered, %d points, reprojection error %.3f px, %.1f s",
             q["registered"], n, q["points"], q["mean_reprojection_error_px"] or float("nan"),
             timings["total"])
    if q["models_found"] > 1:
        log.warning("sfm: %d models found; wrote the largest (%d frames); left out (listed in "
                    "quality.json, other_models): %s", q["models_found"], q["model_sizes"][0],
                    "; ".join(f"{p['frames']} frames {p['first']}..{p['last']}"
                              for p in q["other_models"]))
    return q


def _judge(check: dict[str, Any], reason: str, mode: str, key: str, failed: Path,
           names: list[str], result: mapping.MappingResult, pair_stats: dict[str, int]) -> None:
    """A self-check found the model wrong by ``reason``: flag it in ``check`` and warn
    (``mode`` warn) or fail the stage with what reconstructed left in ``failed`` (fail)."""
    check["consistent"] = False
    check["reason"] = f"{check['reason']}; {reason}" if check.get("reason") else reason
    message = f"sfm self-check: the model shows {reason}; its poses there are not reliable"
    if mode == "fail":
        _write_failed(failed, message, names, result, pair_stats)
        raise StageError(f"{message}; details in {failed}")
    log.warning("%s (flagged in quality.json consistency; sfm.%s: fail would fail the stage)",
                message, key)


def _judge_halves(check: dict[str, Any], cfg: SfmConfig, failed: Path, names: list[str],
                  result: mapping.MappingResult, pair_stats: dict[str, int]) -> None:
    """Flag (warn) or fail (``halves_check: fail``) a model the independent halves contradict
    (cystomap/sfm/drift.py)."""
    h = check["halves"]
    if h.get("consistent", True):
        return
    _judge(check, f"drift: {h['longest_off_run']} consecutive frames from {h['off_run_from']} "
                  f"are placed more than one frame step ({h['residual_max_steps']} steps at "
                  f"most) from where two maps of disjoint halves of the frames put them",
           cfg.halves_check, "halves_check", failed, names, result, pair_stats)


def _judge_rotation(check: dict[str, Any], cfg: SfmConfig, failed: Path, names: list[str],
                    result: mapping.MappingResult, pair_stats: dict[str, int]) -> None:
    """Flag (warn) or fail (``rotation_check: fail``) a model the loop pairs' rotations say has
    turned one place of the video against another (cystomap/sfm/rotation.py)."""
    r = check["rotation"]
    if not r.get("flagged"):
        return
    (a0, a1), (b0, b1) = r["worst_frames"]
    _judge(check, f"rotation drift: {r['worst_pairs']} loop pairs linking {a0}..{a1} to "
                  f"{b0}..{b1} measure the model {r['worst_deg']:.1f}° off between them (the "
                  f"loop pairs' rotations agree with their neighbours' beyond noise, p "
                  f"{r['p_value']:.3f})",
           cfg.rotation_check, "rotation_check", failed, names, result, pair_stats)


class _HoldBack(Exception):
    """The model mapped with the loop pairs contradicts the sequential chain."""


def _failed_dir(out_dir: Path) -> Path:
    """Where a failed run leaves what did reconstruct: beside, not inside, the outputs."""
    return out_dir.with_name(out_dir.name + ".failed")


def _piece(frames: list[str], names: list[str]) -> dict[str, object]:
    """One model's frames for quality.json: count, first/last, names and video indices."""
    order = {name: k for k, name in enumerate(names)}
    frames = sorted(frames, key=lambda f: order.get(f, -1))
    indices = []
    for f in frames:
        m = feat.FRAME_RE.search(f)
        indices.append(int(m.group(1)) if m else order.get(f, -1))
    return {"frames": len(frames), "first": frames[0] if frames else None,
            "last": frames[-1] if frames else None, "names": frames, "video_frames": indices}


def _write_failed(failed: Path, message: str, names: list[str],
                  result: mapping.MappingResult | None, pair_stats: dict[str, int]) -> None:
    """Write every model of a failed run (``model_0`` = the largest, COLMAP binary, model
    units) and a quality.json listing their frames and the frames left out, to ``failed``."""
    try:
        with atomic_dir(failed) as tmp:
            pieces: list[dict[str, object]] = []
            if result is not None:
                recs = [result.reconstruction, *result.others]
                for k, (rec, frames) in enumerate(zip(recs, result.models, strict=False)):
                    (tmp / f"model_{k}").mkdir()
                    rec.write_binary(str(tmp / f"model_{k}"))
                    pieces.append({"model": f"model_{k}", **_piece(frames, names)})
            seen = {f for p in pieces for f in p["names"]}  # type: ignore[attr-defined]
            write_json(tmp / "quality.json", {
                "failed": True, "error": message, "frames_in": len(names),
                "models_found": len(pieces), "model_sizes": [p["frames"] for p in pieces],
                "models": pieces, "pairs": pair_stats,
                "unregistered": [f for f in names if f not in seen],
                "units": "model (no metric scale applied)",
            })
    except OSError as exc:  # the StageError that follows matters more
        log.warning("sfm: could not write %s: %s", failed, exc)
        return
    log.error("sfm: failed; what did reconstruct is in %s (not an output of the stage)", failed)


def _median(values: object) -> float:
    import numpy as np

    arr = np.fromiter(values, dtype=float)  # type: ignore[arg-type]
    return float(np.median(arr)) if len(arr) else 0.0
