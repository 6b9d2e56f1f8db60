"""Structure from motion: accuracy on a small phantom session, failure path, helpers."""

from __future__ import annotations

import json
import logging
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from cystomap.camera import Camera
from cystomap.errors import InputError, StageError
from cystomap.settings import from_mapping
from cystomap.sfm import SfmConfig, run_sfm
from cystomap.sfm.pairs import extension_pairs, gap_schedule, retrieval_pairs, sequential_pairs
from cystomap.sfm.scale import estimate_scale

# Small phantom session: the default path at 640x360 with the coarse ("low texture") wall,
# all 124 frames, reconstructed at that size. (With the default fine texture and mp4v video,
# SfM at 640x360 is poor - mp4v's fixed quantiser removes the fine texture at the video's own
# pixel scale: clean bench seeds 1-3 79-124/124 frames at 0.61-0.77 mm, with FFV1 124/124 at
# 0.06-0.09 mm - while the 1280x720 render downsampled to 640 is fine; see cystomap.bench.sfm.)
SMALL_SCALE = 0.5
FAST = {"max_image_size": 0}  # threads: the defaults
RMSE_GLINT = 0.6  # mm; measured 0.296 at one thread (seed 3)
RMSE_GLOBAL = 0.32  # mm; measured 0.160 on the small session (2026-12-06)


def _phantom_camera() -> Camera:
    return Camera(1280, 720, 939.864, 939.864, 639.5, 359.5, (-0.12, 0.02, 0.0, 0.0, 0.0))


def _decode(video: Path, frames: Path) -> Path:
    """Every frame of ``video`` as f000000.png … in ``frames``."""
    from cystomap.video import iter_frames

    frames.mkdir()
    for index, _, img in iter_frames(video):
        cv2.imwrite(str(frames / f"f{index:06d}.png"), img)
    return frames


@pytest.fixture(scope="module")
def small_session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(truth dir, preprocessed dir with every frame) of a 640x360 phantom session."""
    return _render_and_preprocess(tmp_path_factory.mktemp("sfm_phantom"),
                                  {"texture_detail_mm": 0.4})


def _render_and_preprocess(root: Path, phantom: dict) -> tuple[Path, Path]:
    """A 640x360 phantom session (``phantom`` overrides) decoded and preprocessed."""
    from cystomap.phantom import PhantomConfig, generate_session
    from cystomap.preprocess import PreprocessConfig, preprocess_frames

    camera = _phantom_camera().scaled(SMALL_SCALE)
    truth = generate_session(root / "session", 1, PhantomConfig(**phantom), camera)
    frames = _decode(truth / "video.mp4", root / "frames")
    pre = root / "preprocessed"
    preprocess_frames(frames, pre, camera, PreprocessConfig())
    return truth, pre


def test_small_session_registers_accurately(small_session, tmp_path):
    from cystomap.evaluate import evaluate_session, load_truth

    truth_dir, pre = small_session
    truth = load_truth(truth_dir)
    volume_ml = float(truth.meta["volume_ml"])
    out = tmp_path / "sfm"
    cfg = from_mapping(SfmConfig, FAST, "sfm")
    assert run_sfm(pre, out, cfg, extent_mm=truth.extent_mm, volume_ml=volume_ml) == out
    for name in ("cameras.bin", "images.bin", "points3D.bin", "points.ply", "quality.json"):
        assert (out / name).is_file(), name
    q = json.loads((out / "quality.json").read_text())
    n = truth.n_frames
    assert q["frames_in"] == n
    assert q["registered"] == n, q["dropped_frames"]
    assert q["models_found"] == 1
    assert q["mean_reprojection_error_px"] < 0.7
    assert q["mean_track_length"] > 3
    assert set(q["time_s"]) >= {"features", "pairs", "matching", "mapping", "total"}
    # metric: scaled by the known extent, volume as a cross-check
    assert q["metric"] is True and q["units"] == "mm"
    assert q["scale"]["source"] == "extent_mm"
    assert abs(q["scale"]["cross_check"]["relative_difference"]) < 0.1
    assert q["scale"]["factor"] * q["scale"]["model_extent"] == pytest.approx(truth.extent_mm)
    assert q["mean_reprojection_error_mm"] < 0.1
    # self-check recorded: loop pairs were used, agree with the model, no fold or break
    c = q["consistency"]
    assert c["consistent"] and c["seams_broken"] == [] and c["weakest_seam_share"] > 0.5, c
    assert c["loop_pairs"] > 20 and c["loop_agreeing_share"] > 0.8, c
    assert q["final_adjustment"]["loops"]["loop_pairs_accepted"] > 20
    # two maps of alternate frames agree with the model (cystomap/sfm/drift.py)
    h = c["halves"]
    # (median measured 0.52 steps on a 0.15 mm model, 2026-12-03: the halves are the noisier)
    assert h["checked"] and h["consistent"] and h["residual_median_steps"] < 1.0, h
    # loop rotations show no drift (cystomap/sfm/rotation.py)
    r = c["rotation"]
    assert not r["flagged"] and (not r["checked"] or r["p_value"] > 0.01), r

    report = evaluate_session(truth_dir, out)
    traj = report["trajectory"]
    assert traj["n_matched"] == n
    # camera centres and orientations close to the truth after Sim(3); scale within 3 %
    assert traj["rmse_mm"] < 0.5, traj
    assert traj["rotation_error_deg_median"] < 0.5, traj
    assert traj["scale_error"] < 0.03, traj
    # the points.ply is readable, coloured and as large as the model
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(out / "points.ply"))
    assert len(cloud.points) == q["points"] and cloud.has_colors()


def test_global_mapper_registers_accurately(small_session, tmp_path):
    """sfm.mapper: global (COLMAP's GLOMAP) maps the keyframes; the rest of the stage as usual."""
    from cystomap.evaluate import evaluate_session, load_truth

    truth_dir, pre = small_session
    truth = load_truth(truth_dir)
    out = tmp_path / "sfm"
    cfg = from_mapping(SfmConfig, {**FAST, "mapper": "global"}, "sfm")
    run_sfm(pre, out, cfg, extent_mm=truth.extent_mm)
    q = json.loads((out / "quality.json").read_text())
    assert q["registered"] == truth.n_frames and q["models_found"] == 1, q["dropped_frames"]
    assert "global" in q["final_adjustment"]["cpu_s"], q["final_adjustment"]["cpu_s"]
    traj = evaluate_session(truth_dir, out)["trajectory"]
    assert traj["rmse_mm"] < RMSE_GLOBAL and traj["scale_error"] < 0.03, traj


def test_densification_adds_long_tracks_without_losing_accuracy(small_session, tmp_path):
    """Full-size corner tracks: many more points and observations, longer tracks, and the
    trajectory at least as close to the truth as SIFT alone (on the full-size fine-textured
    session: 0.32 -> 0.075 mm, see cystomap.bench.sfm)."""
    from cystomap.evaluate import evaluate_session, load_truth

    truth_dir, pre = small_session
    extent = load_truth(truth_dir).extent_mm
    runs = {}
    for corners in (0, 400):
        out = tmp_path / f"sfm{corners}"
        cfg = from_mapping(SfmConfig, {**FAST, "densify_corners": corners}, "sfm")
        run_sfm(pre, out, cfg, extent_mm=extent)
        q = json.loads((out / "quality.json").read_text())
        runs[corners] = (q, evaluate_session(truth_dir, out)["trajectory"]["rmse_mm"])
    (plain, rmse0), (dense, rmse1) = runs[0], runs[400]
    added = dense["final_adjustment"]["densification"]
    assert "densification" not in plain["final_adjustment"] or \
        not plain["final_adjustment"]["densification"].get("points")
    assert added["points"] > 1000 and dense["points"] > 1.5 * plain["points"], added
    assert dense["observations"] > 2 * plain["observations"]
    assert dense["mean_track_length"] > plain["mean_track_length"]
    assert dense["registered"] == plain["registered"]
    assert rmse1 < 1.1 * rmse0 + 0.005, (rmse0, rmse1)
    assert added["frames"] == dense["registered"]
    # frames streamed from disk, each read about once: the sequential window from a small
    # cache, loop targets read apart (measured 192 reads of 124 frames; in plain video order
    # with keyframes the window overflowed the cache and every frame was read ~8x)
    assert added["frames_read"] <= 2 * added["frames"], added


@pytest.fixture(scope="module")
def undensified(small_session: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory,
                ) -> tuple[Path, Path, np.ndarray]:
    """The small session mapped without densification: its preprocessed frames, the model
    and the field-of-view mask (densification is run on copies of the model)."""
    _, pre = small_session
    model = tmp_path_factory.mktemp("undensified") / "model"
    run_sfm(pre, model, from_mapping(SfmConfig, {**FAST, "densify_corners": 0}, "sfm"))
    return pre, model, cv2.imread(str(pre / "mask.png"), cv2.IMREAD_GRAYSCALE)


def test_densification_is_the_same_on_any_number_of_threads(undensified):
    """The reference frames are shared out among ``num_threads`` threads, each with its own
    frames cache: the points added are those of one thread, in the same order (issue 16: on
    the 60 s 1080p recording 22.1 -> 16.8 s wall, the same 31447 points)."""
    import pycolmap

    from cystomap.sfm.densify import densify

    pre, model, mask = undensified
    added = {}
    for threads in (1, 2, 3):
        rec = pycolmap.Reconstruction(str(model))
        before = set(rec.points3D)
        cfg = from_mapping(SfmConfig, {"num_threads": threads, "densify_corners": 200}, "sfm")
        stats = densify(rec, pre / "enhanced", mask, cfg, 2)
        new = sorted(set(rec.points3D) - before)
        added[threads] = (stats.points, stats.aligned,
                          np.array([rec.point3D(i).xyz for i in new]),
                          [[(e.image_id, e.point2D_idx) for e in rec.point3D(i).track.elements]
                           for i in new])
    assert added[1][0] > 500, added[1][:2]
    for threads in (2, 3):
        assert added[threads][:2] == added[1][:2]
        assert np.array_equal(added[threads][2], added[1][2])
        assert added[threads][3] == added[1][3]


def test_densification_threshold_comes_from_the_videos_wrong_alignments(undensified):
    """The ZNCC an alignment needs is the (1 - densify_null_rate) quantile of alignments
    started a patch or two away from the right place: a stricter rate raises it, rate 0
    leaves the fixed densify_max_zncc; right alignments pass it (on seven family-A/B FROC
    sessions it came out 0.57-0.61; trajectory RMSE median 0.20 mm with a fixed 0.8, 0.13
    with it)."""
    import pycolmap

    from cystomap.sfm.densify import densify

    pre, model, mask = undensified
    runs = {}
    for rate in (0.0, 0.05, 0.01):
        rec = pycolmap.Reconstruction(str(model))
        cfg = from_mapping(SfmConfig, {"densify_corners": 200, "densify_null_rate": rate,
                                       "densify_min_zncc": -1.0, "densify_max_zncc": 1.0
                                       if rate else 0.8}, "sfm")
        runs[rate] = densify(rec, pre / "enhanced", mask, cfg, 2)
    fixed, loose, strict = runs[0.0], runs[0.05], runs[0.01]
    assert fixed.min_zncc == 0.8 and fixed.null_alignments == 0
    assert loose.null_alignments > 500, loose
    assert -1.0 < loose.min_zncc < strict.min_zncc < 1.0, (loose, strict)
    assert strict.aligned <= loose.aligned
    # right alignments pass it: at least half as many accepted as with the fixed 0.8
    assert loose.aligned > 0.5 * fixed.aligned, (loose, fixed)


def test_zncc_threshold_quantile_floor_and_fallback():
    from cystomap.sfm.densify import zncc_threshold

    null = np.linspace(0.0, 1.0, 1001)
    cfg = SfmConfig(densify_null_rate=0.05, densify_min_zncc=0.2, densify_max_zncc=1.0)
    assert zncc_threshold(null, cfg) == pytest.approx(0.95)
    assert zncc_threshold(null, SfmConfig(densify_null_rate=0.05, densify_min_zncc=0.97,
                                          densify_max_zncc=1.0)) == 0.97
    assert zncc_threshold(null, SfmConfig(densify_null_rate=0.05, densify_min_zncc=0.2,
                                          densify_max_zncc=0.8)) == 0.8  # ceiling
    assert zncc_threshold(null[:50], cfg) == 1.0  # 2.5 values above the quantile: ceiling
    assert zncc_threshold(null, SfmConfig(densify_null_rate=0.0, densify_max_zncc=0.8)) == 0.8


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason=(
    "known defect, issue 12: two fresh processes can write different models (2026-12-04: "
    "32863 vs 32866 points, camera centres up to 0.03 mm apart, in a full `make test` on an "
    "otherwise idle machine; the same test passed in the run before); the source is not found"))
def test_stage_is_deterministic_across_processes(small_session, tmp_path):
    """Deterministic at the default threads (several for features and matching): the same
    inputs and config give the same model, byte for byte, in two fresh processes (as each
    Snakemake job is). In one long-lived process the stage is not: after other runs in the
    same pytest process the third run wrote a different images.bin (2026-12-03, CI on a clean
    clone). Fresh processes mostly agree but not always (see the mark): reported as XPASS or
    XFAIL until the cause is found, so that it stays visible without blocking CI."""
    from cystomap.evaluate import load_truth

    truth_dir, pre = small_session
    extent = load_truth(truth_dir).extent_mm
    import hashlib
    import subprocess
    import sys

    assert SfmConfig().num_threads > 1
    code = ("import sys; from pathlib import Path; from cystomap.sfm import SfmConfig, run_sfm; "
            "from cystomap.settings import from_mapping; "
            f"run_sfm(Path(sys.argv[1]), Path(sys.argv[2]), from_mapping(SfmConfig, "
            f"{{**{FAST!r}, 'densify_corners': 400}}, 'sfm'), extent_mm={extent!r})")
    outs = [tmp_path / f"again{k}" for k in range(2)]
    for out in outs:
        subprocess.run([sys.executable, "-c", code, str(pre), str(out)], check=True)
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        digests = [hashlib.sha256((d / name).read_bytes()).hexdigest() for d in outs]
        assert digests[0] == digests[1], name


@pytest.mark.slow
def test_unmatchable_frames_raise_stage_error(tmp_path):
    pre = tmp_path / "pre"
    (pre / "enhanced").mkdir(parents=True)
    rng = np.random.default_rng(0)
    n = 8
    for k in range(n):
        img = rng.integers(0, 256, size=(180, 320), dtype=np.uint8)
        cv2.imwrite(str(pre / "enhanced" / f"f{k:06d}.png"), img)
    cv2.imwrite(str(pre / "mask.png"), np.full((180, 320), 255, np.uint8))
    _phantom_camera().scaled(0.25).without_distortion().save(pre / "camera.json")
    out = tmp_path / "sfm"
    with pytest.raises(StageError, match=rf"0 of {n} frames registered"):
        run_sfm(pre, out, SfmConfig(max_image_size=0, retrieval_neighbors=2))
    assert not out.exists()
    assert not any(p.name.startswith(".sfm") for p in tmp_path.iterdir())


def test_missing_inputs_raise_input_error(tmp_path):
    with pytest.raises(InputError):
        run_sfm(tmp_path / "nothing", tmp_path / "out")
    pre = tmp_path / "pre"
    (pre / "enhanced").mkdir(parents=True)
    _phantom_camera().scaled(0.25).without_distortion().save(pre / "camera.json")
    with pytest.raises(InputError, match="no frame PNGs"):
        run_sfm(pre, tmp_path / "out")
    with pytest.raises(InputError, match="extent_mm"):
        run_sfm(pre, tmp_path / "out", extent_mm=-1.0)


def test_config_defaults_and_validation():
    cfg = from_mapping(SfmConfig, {"max_image_size": 800, "guided_matching": True}, "sfm")
    assert cfg.max_image_size == 800 and cfg.guided_matching
    assert SfmConfig().intrinsics == "auto"
    with pytest.raises(InputError, match="sfm"):
        from_mapping(SfmConfig, {"intrinsics": "sometimes"}, "sfm")
    with pytest.raises(InputError, match="unknown"):
        from_mapping(SfmConfig, {"no_such_key": 1}, "sfm")
    with pytest.raises(ValueError):
        SfmConfig(sequential_overlap=5, sequential_max_gap=3)


def test_sequential_and_extension_pairs():
    assert sequential_pairs(5, 2) == {(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4)}
    # gaps double; a gap g > 4 is only tried from multiples of g / 2 (candidate keyframes)
    assert gap_schedule(3, 32) == [(4, 1), (8, 4), (16, 8), (32, 16)]
    assert gap_schedule(1, 4) == [(2, 1), (4, 1)]
    verified = {(0, 2): 100, (1, 3): 10, (2, 4): 60, (4, 6): 50}
    assert extension_pairs(verified, 10, 2, 4, 40) == {(0, 4), (2, 6), (4, 8)}
    assert extension_pairs(verified, 10, 2, 4, 40, every=4) == {(0, 4), (4, 8)}


def test_retrieval_finds_revisits():
    """Frames 0-9 and 30-39 show the same 'place' (shared descriptors): retrieval pairs them."""
    rng = np.random.default_rng(1)
    places = [rng.integers(0, 256, size=(150, 128)).astype(np.uint8) for _ in range(5)]
    descs = []
    for k in range(40):
        place = places[0] if (k < 10 or k >= 30) else places[1 + (k - 10) // 5]
        noise = rng.integers(-8, 9, size=place.shape)
        descs.append(np.clip(place.astype(int) + noise, 0, 255).astype(np.uint8))
    cfg = SfmConfig(retrieval_neighbors=2, retrieval_words=8, sequential_overlap=3)
    pairs = retrieval_pairs(descs, cfg)
    loops = {(i, j) for i, j in pairs if i < 10 and j >= 30}
    assert len(loops) >= 10
    assert all(j - i > 3 for i, j in pairs)


def test_scale_estimate_is_rotation_invariant_and_robust():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = d * np.array([85.0, 65.0, 55.0])  # ellipsoid: extent 170, volume 4/3 pi abc
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    model = 0.01 * pts @ rot.T + 3.0
    noisy = np.vstack([model, 0.01 * rng.normal(size=(8, 3)) * 400])  # far outliers
    cfg = SfmConfig()
    est = estimate_scale(noisy, cfg, extent_mm=170.0, volume_ml=None)
    assert est.source == "extent_mm" and est.metric
    assert est.factor == pytest.approx(100.0, rel=0.01)
    vol_ml = 4 / 3 * math.pi * 85 * 65 * 55 / 1000
    est = estimate_scale(noisy, cfg, extent_mm=None, volume_ml=vol_ml)
    assert est.source == "volume_ml"
    assert est.factor == pytest.approx(100.0, rel=0.02)
    star = estimate_scale(noisy, SfmConfig(volume_method="star"), None, vol_ml)
    assert star.factor == pytest.approx(100.0, rel=0.05)
    none = estimate_scale(model, cfg, None, None)
    assert none.factor == 1.0 and not none.metric and none.to_dict()["units"] == "arbitrary"


@pytest.mark.slow
def test_failed_run_keeps_earlier_output(tmp_path):
    """A StageError leaves a previous result at out_dir untouched (atomic output)."""
    pre = tmp_path / "pre"
    (pre / "enhanced").mkdir(parents=True)
    rng = np.random.default_rng(3)
    for k in range(6):
        cv2.imwrite(str(pre / "enhanced" / f"f{k:06d}.png"),
                    rng.integers(0, 256, size=(90, 160), dtype=np.uint8))
    Camera(160, 90, 120.0, 120.0, 79.5, 44.5).save(pre / "camera.json")
    out = tmp_path / "sfm"
    out.mkdir()
    (out / "marker").write_text("old")
    with pytest.raises(StageError):
        run_sfm(pre, out, SfmConfig(max_image_size=0, retrieval_neighbors=0))
    assert (out / "marker").read_text() == "old"
    shutil.rmtree(out)


def test_short_model_is_mapped_again_with_finer_features(small_session, tmp_path):
    """Features at 120 px (of 640) are too coarse to map the session; the stage maps again at
    240 px, keeps that model and says so (cystomap/sfm/retry.py). (At 160 px the first mapping
    held all 124 frames and its rotation flag came and went between runs: not a premise a test
    can rest on.)"""
    from cystomap.evaluate import evaluate_session, load_truth

    truth_dir, pre = small_session
    truth = load_truth(truth_dir)
    n = truth.n_frames
    out = tmp_path / "sfm"
    cfg = from_mapping(SfmConfig, {"max_image_size": 120, "densify_corners": 0,
                                   "retry_registered_share": 0.95}, "sfm")
    run_sfm(pre, out, cfg, extent_mm=truth.extent_mm)
    q = json.loads((out / "quality.json").read_text())
    a = q["attempts"]
    first, second = a["runs"]
    # the premise: the coarse mapping failed (measured: 22 of 124 frames in the largest of 9
    # models, 38 needed)
    assert first["max_image_size"] == 120 and first["failed"], a
    # measured: 124/124 at 240 px, 0.28 mm
    assert second["max_image_size"] == 240 and not second["failed"], a
    assert a["kept"] == 1 and q["registered"] >= 0.95 * n, a
    assert q["cpu_s"]["attempts_total"] == pytest.approx(first["cpu_s"] + second["cpu_s"], abs=0.01)
    traj = evaluate_session(truth_dir, out)["trajectory"]
    assert traj["rmse_mm"] < 0.6 and traj["scale_error"] < 0.03, traj
    # the second mapping was written beside the outputs and moved in; the first's pieces
    # (sfm.failed) are removed with it: nothing is left beside
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sfm"]


def test_retry_keeps_the_better_run_and_reports_both(tmp_path, caplog):
    """The retry's bookkeeping, with stand-in mappings: a failed or short first run is
    replaced by a better second; a worse second is dropped; both failing raise one error that
    names both, with the second's pieces beside the first's."""
    from cystomap.sfm import retry

    def fake(results: dict[int, object]):
        def attempt(out: Path, cfg: SfmConfig) -> dict:
            got = results.get((cfg.max_image_size, cfg.first_octave), results.get(cfg.max_image_size))
            if isinstance(got, tuple):  # (frames, flagged)
                got, flagged = got
            else:
                flagged = False
            if isinstance(got, int):
                out.mkdir(parents=True)
                q = {"frames_in": 100, "registered": got,
                     "consistency": {"consistent": not flagged, "reason": "drift"},
                     "time_s": {"total": 1.0}, "cpu_s": {"total": 1.0}}
                (out / "quality.json").write_text(json.dumps(q))
                return q
            failed = out.with_name(out.name + ".failed")
            failed.mkdir(parents=True)
            (failed / "quality.json").write_text(json.dumps({"model_sizes": [7]}))
            raise StageError(f"sfm: only 7 frames; details in {failed}")
        return attempt

    def failed_dir(p: Path) -> Path:
        return p.with_name(p.name + ".failed")

    cfg = SfmConfig(max_image_size=640, retry_registered_share=0.95)
    # frames first: a flagged model is kept over an unflagged one that holds less than the
    # share of its frames (held-out glints:4: flagged 113 frames at 0.46 mm, unflagged 78 at
    # 1.42 mm); of about the same size, the one the self-checks pass
    for results, kept, registered in (({640: 60, 1280: 98}, 1, 98), ({640: 90, 1280: 80}, 0, 90),
                                      ({640: "fail", 1280: 97}, 1, 97), ({640: 96}, None, 96),
                                      ({640: (91, True), 1280: 62}, 0, 91),
                                      ({640: (92, True), 1280: 89}, 1, 89),
                                      ({640: 94, 1280: (98, True)}, 0, 94),
                                      ({640: (92, True), 1280: (98, True)}, 1, 98)):
        root = tmp_path / f"case{len(list(tmp_path.iterdir()))}"
        root.mkdir()
        out = retry.map_with_retry(fake(results), root / "sfm", cfg, 0.5, failed_dir)
        q = json.loads((out / "quality.json").read_text())
        assert q["registered"] == registered
        assert q.get("attempts", {}).get("kept") == kept, q
        assert sorted(p.name for p in root.iterdir()) == ["sfm"], results
    # a short model handed on is named in the log and in quality.json (short_model, which
    # compare and the report read), after two mappings or one; one that holds the share is not
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="cystomap.sfm.retry"):
        for name, results, at_full in (("short", {640: 60, 1280: 70}, 0.5),
                                       ("short1", {640: 70}, 1.0)):
            out = retry.map_with_retry(fake(results), tmp_path / name / "sfm", cfg, at_full,
                                       failed_dir)
            assert "holds only 70 of the 100 frames" in caplog.text
            short = json.loads((out / "quality.json").read_text())["short_model"]
            assert short["registered"] == 70 and short["frames_with_features"] == 100
            caplog.clear()
        out = retry.map_with_retry(fake({640: 96}), tmp_path / "long" / "sfm", cfg, 0.5,
                                   failed_dir)
        assert "holds only" not in caplog.text
        assert "short_model" not in json.loads((out / "quality.json").read_text())
    # at the lit field's full size, a short model is mapped again on the image doubled (one
    # octave finer, guided matching) unless its features were detected so already; a model
    # that is only flagged is not
    out = retry.map_with_retry(fake({640: 60, (640, -1): 98}), tmp_path / "dbl" / "sfm", cfg,
                               1.0, failed_dir)
    q = json.loads((out / "quality.json").read_text())
    assert q["registered"] == 98 and q["attempts"]["kept"] == 1
    assert [r["image_doubled"] for r in q["attempts"]["runs"]] == [False, True]
    doubled = {"frames_in": 100, "registered": 60, "doubled_frames": 100}
    assert retry.finer(cfg, 1.0, retry.Run(640, doubled, None, tmp_path, 1.0, 1.0), 0.95) is None
    flagged = {"frames_in": 100, "registered": 99, "consistency": {"consistent": False}}
    assert retry.finer(cfg, 1.0, retry.Run(640, flagged, None, tmp_path, 1.0, 1.0), 0.95) is None
    short = retry.finer(cfg, 1.0, retry.Run(640, {**doubled, "doubled_frames": 0}, None,
                                            tmp_path, 1.0, 1.0), 0.95)
    assert short is not None and short.first_octave == -1 and short.guided_matching
    assert retry.finer(cfg, 0.5).max_image_size == 1280  # below full size: the size doubles
    # black frames (too few features at any size) do not count against the share
    black = {"frames_in": 100, "registered": 93, "dropped_reasons": {"too few features": 5}}
    # a flag of the rotation check alone maps again only when asked (retry_on_rotation_flag)
    rot = {"frames_in": 100, "registered": 100,
           "consistency": {"consistent": False, "reason": "rotation drift",
                           "halves": {"consistent": True}, "rotation": {"flagged": True}}}
    assert retry.flagged_by(rot) == ["rotation"]
    assert retry.reason(retry.Run(640, rot, None, tmp_path, 1.0, 1.0), 0.95) is None
    assert "rotation drift" in (retry.reason(retry.Run(640, rot, None, tmp_path, 1.0, 1.0),
                                             0.95, on_rotation_flag=True) or "")
    both = {**rot, "consistency": {**rot["consistency"], "halves": {"consistent": False}}}
    assert retry.flagged_by(both) == ["halves", "rotation"]
    assert retry.reason(retry.Run(640, both, None, tmp_path, 1.0, 1.0), 0.95)
    short = {**rot, "registered": 90}  # short as well: mapped again for that
    assert "90 of the 100" in (retry.reason(retry.Run(640, short, None, tmp_path, 1.0, 1.0),
                                            0.95) or "")
    run = retry.Run(640, black, None, tmp_path, 1.0, 1.0)
    assert retry.mappable(black) == 95 and retry.reason(run, 0.95) is None
    black["dropped_reasons"] = {"no geometrically verified match with any paired frame": 5}
    assert "93 of the 100 frames" in (retry.reason(run, 0.95) or "")
    # at the lit field's full size already, or retry off: one mapping, its error as it was
    with pytest.raises(StageError, match="only 7 frames"):
        retry.map_with_retry(fake({640: "fail"}), tmp_path / "full" / "sfm", cfg, 1.0, failed_dir)
    off = SfmConfig(max_image_size=640, retry_registered_share=0.0)  # never
    out = retry.map_with_retry(fake({640: 10}), tmp_path / "off" / "sfm", off, 0.5, failed_dir)
    assert "attempts" not in json.loads((out / "quality.json").read_text())
    both = tmp_path / "both"
    with pytest.raises(StageError, match=r"Mapped again with features at 1280 px") as err:
        retry.map_with_retry(fake({640: "fail", 1280: "fail"}), both / "sfm", cfg, 0.5, failed_dir)
    assert str(both / "sfm.failed" / "retry") in str(err.value)
    assert sorted(p.name for p in both.iterdir()) == ["sfm.failed"]
    assert (both / "sfm.failed" / "retry" / "quality.json").is_file()


def _turn_from(rec: object, names: list[str], first: int, degrees: float,
               shift: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
    """Turn the frames of ``rec`` from the ``first``-th on by ``degrees`` about y (and shift)."""
    import pycolmap
    from scipy.spatial.transform import Rotation

    turn = pycolmap.Rigid3d(pycolmap.Rotation3d(Rotation.from_euler("y", degrees, degrees=True)
                                                .as_quat()), np.array(shift))
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        if names.index(image.name) >= first:
            frame = rec.frame(image.frame_id)
            frame.rig_from_world = frame.rig_from_world * turn


def test_self_check_fails_a_folded_model(tmp_path):
    """A synthetic model whose second half is turned by 30 degrees (a fold) contradicts the
    matches linking the halves: the self-check names the place; the unfolded model passes."""
    from cystomap.sfm import consistency

    rec, db, names = _synthetic_model(tmp_path, 12, 300)
    geoms = consistency.read_geometries(db, names)
    chain = {p for p in geoms if p[1] - p[0] <= 3}
    loops = set(geoms) - chain
    fig = consistency.self_check(rec, names, geoms, chain, loops, SfmConfig())
    assert fig["consistent"] and fig["weakest_seam_share"] == 1.0
    assert fig["loop_agreeing_share"] == 1.0 and fig["loop_pairs"] == len(loops)
    _turn_from(rec, names, 6, 30, (0.5, 0.0, 0.0))
    with pytest.raises(StageError, match=rf"between {names[5]} and {names[6]} .* contradict"):
        consistency.self_check(rec, names, geoms, chain, loops, SfmConfig())


def _inject_false_loops(database: Path, names: list[str], far: list[tuple[int, int]],
                        rng: np.random.Generator) -> dict[tuple[int, int], int]:
    """Write matches consistent with one homography (a repeated patch) between frames that
    see different walls; returns their number of matches."""
    import pycolmap
    from scipy.spatial import cKDTree

    db = pycolmap.Database.open(str(database))
    out = {}
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for i, j in far:
            a, b = ids[names[i]], ids[names[j]]
            k1 = np.asarray(db.read_keypoints(a))[:, :2]
            k2 = np.asarray(db.read_keypoints(b))[:, :2]
            angle = rng.uniform(-0.3, 0.3)
            h = np.array([[np.cos(angle), -np.sin(angle), rng.uniform(-40, 40)],
                          [np.sin(angle), np.cos(angle), rng.uniform(-40, 40)], [0, 0, 1]])
            moved = k1 @ h[:2, :2].T + h[:2, 2]
            dist, nearest = cKDTree(k2).query(moved)
            keep = dist < 3.0  # within the RANSAC threshold (4 px) of one homography
            m = np.c_[np.flatnonzero(keep), nearest[keep]].astype(np.uint32)
            m = m[np.unique(m[:, 1], return_index=True)[1]]
            geom = pycolmap.TwoViewGeometry()
            geom.config = pycolmap.TwoViewGeometryConfiguration.PLANAR
            geom.H = h
            geom.inlier_matches = m
            db.write_matches(a, b, m)
            db.write_two_view_geometry(a, b, geom)
            out[(i, j)] = len(m)
    finally:
        db.close()
    return out


def test_false_loop_matches_are_rejected(small_session, tmp_path, monkeypatch):
    """Forced fold: strong, geometrically consistent matches between frames that look at
    different walls (as repeated texture gives) are offered as loop pairs; the stage tests
    them against the sequential model, uses none of them, and the model stays true."""
    from cystomap.evaluate import evaluate_session, load_truth
    from cystomap.sfm import pairs as pairs_mod

    truth_dir, pre_all = small_session
    truth = load_truth(truth_dir)
    n = 64  # the first half of the session: one run of about half the time
    pre = tmp_path / "pre"
    for sub in ("enhanced", "color"):
        (pre / sub).mkdir(parents=True)
        for k in range(n):
            (pre / sub / f"f{k:06d}.png").symlink_to(pre_all / sub / f"f{k:06d}.png")
    for name in ("mask.png", "camera.json"):
        shutil.copy(pre_all / name, pre / name)
    axes = truth.rotations[:n, :, 2]
    rng = np.random.default_rng(5)
    opposite = np.argwhere(np.triu(axes @ axes.T < -0.5))
    far = [tuple(int(v) for v in p) for p in opposite[rng.choice(len(opposite), 12, False)]]
    real = pairs_mod.loop_pairs
    injected: dict[tuple[int, int], int] = {}

    def loops_with_false(database, names, frames, cfg):
        injected.update(_inject_false_loops(database, names, far, rng))
        return real(database, names, frames, cfg) | set(far)

    monkeypatch.setattr(pairs_mod, "loop_pairs", loops_with_false)
    out = tmp_path / "sfm"
    run_sfm(pre, out, from_mapping(SfmConfig, FAST, "sfm"), extent_mm=truth.extent_mm)
    q = json.loads((out / "quality.json").read_text())
    assert min(injected.values()) >= 2 * SfmConfig().min_num_inliers, injected
    loops = q["final_adjustment"]["loops"]
    rejected = {tuple(p) for p in loops["rejected_pairs"]}
    assert {(f"f{i:06d}.png", f"f{j:06d}.png") for i, j in far} <= rejected
    c = q["consistency"]
    assert c["consistent"] and c["loop_pairs"] >= len(far)
    assert c["loop_pairs_agreeing"] <= c["loop_pairs"] - len(far)
    assert q["registered"] == n
    traj = evaluate_session(truth_dir, out)["trajectory"]
    assert traj["n_matched"] == n and traj["rmse_mm"] < 0.5, traj


# Small session with the nuisances of clinical video: specular glints, motion blur on every
# moving frame (up to 8 px at 640x360), 7 black or defocused frames among the 124.
GLINT = {"seed": 3, "texture_detail_mm": 0.4, "specular": True, "motion_blur_px": 8.0,
         "bad_frame_fraction": 0.06}


@pytest.fixture(scope="module")
def glint_session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(truth dir, preprocessed dir with every frame, glint masks) of that session."""
    return _render_and_preprocess(tmp_path_factory.mktemp("sfm_glint"), GLINT)


def test_glints_blur_and_bad_frames_register_in_one_model(glint_session, tmp_path):
    from cystomap.evaluate import evaluate_session, load_truth

    truth_dir, pre = glint_session
    glints = json.loads((pre / "preprocess.json").read_text())["glint_share"]
    assert glints["frames_with_glints"] > 30 and glints["max"] > 0.02, glints
    assert len(list((pre / "masks").glob("f*.png"))) == load_truth(truth_dir).n_frames
    out = tmp_path / "sfm"
    # one thread: at two, feature extraction and matching vary a little from run to run, and
    # on this blurred session that changes which frames register (seen: 1 model of 117
    # frames, or 113 + a piece of 4)
    run_sfm(pre, out, from_mapping(SfmConfig, {**FAST, "num_threads": 1}, "sfm"),
            extent_mm=load_truth(truth_dir).extent_mm)
    q = json.loads((out / "quality.json").read_text())
    report = evaluate_session(truth_dir, out)
    print("glint session:", report["registration"], report["trajectory"])
    assert q["models_found"] == 1 and q["other_models"] == [], q["other_models"]
    reg, traj = report["registration"], report["trajectory"]
    usable = reg["n_frames"] - reg["n_bad_frames"]
    assert reg["n_bad_frames"] == 7
    assert reg["n_registered"] - reg["n_registered_bad"] >= 0.95 * usable, reg
    assert reg["n_registered_bad"] <= 1, reg  # a black frame has nothing to register with
    assert traj["rmse_mm"] < RMSE_GLINT, traj
    assert traj["scale_error"] < 0.02, traj
    assert q["consistency"]["halves"]["consistent"], q["consistency"]["halves"]


def _two_pieces(pre: Path, root: Path) -> Path:
    """A preprocessed session of two stretches that see different walls (dome, then neck):
    the video 'lost the wall' in between."""
    sub = root / "pre"
    for d in ("enhanced", "color", "masks"):
        (sub / d).mkdir(parents=True)
    shutil.copy(pre / "mask.png", sub / "mask.png")
    shutil.copy(pre / "camera.json", sub / "camera.json")
    for k, src in enumerate([*range(6, 27), *range(88, 107)]):
        for d in ("enhanced", "color", "masks"):
            shutil.copy(pre / d / f"f{src:06d}.png", sub / d / f"f{k:06d}.png")
    return sub


def test_broken_chain_lists_pieces_and_failure_writes_them(glint_session, tmp_path):
    """Two unconnected stretches: the largest model is written and the other listed with its
    frames in quality.json; when the stage fails, both pieces and a quality.json are written
    to <out>.failed (not to the outputs) and the error says so."""
    import pycolmap

    _, pre = glint_session
    sub = _two_pieces(pre, tmp_path)
    out = tmp_path / "sfm"
    cfg = from_mapping(SfmConfig, {**FAST, "densify_corners": 0}, "sfm")
    run_sfm(sub, out, cfg)
    q = json.loads((out / "quality.json").read_text())
    assert q["models_found"] == 2, q["model_sizes"]
    (other,) = q["other_models"]
    main = {pycolmap.Reconstruction(str(out)).image(i).name
            for i in pycolmap.Reconstruction(str(out)).reg_image_ids()}
    assert other["frames"] == len(other["names"]) >= 15
    assert not main & set(other["names"])
    first = [f"f{k:06d}.png" for k in range(21)]
    assert set(other["names"]) <= set(first) or not set(other["names"]) & set(first)
    assert other["video_frames"] == [int(n[1:7]) for n in other["names"]]

    strict = from_mapping(SfmConfig, {**FAST, "densify_corners": 0,
                                      "min_registered_fraction": 0.8}, "sfm")
    out2 = tmp_path / "strict"
    with pytest.raises(StageError, match=r"strict\.failed"):
        run_sfm(sub, out2, strict)
    assert not out2.exists()
    failed = tmp_path / "strict.failed"
    fq = json.loads((failed / "quality.json").read_text())
    assert fq["failed"] and fq["models_found"] == 2 and "frames registered" in fq["error"]
    pieces = [set(m["names"]) for m in fq["models"]]
    assert not pieces[0] & pieces[1] and len(pieces[0]) >= len(pieces[1]) >= 15
    assert set(fq["unregistered"]) == {f"f{k:06d}.png" for k in range(40)} - pieces[0] - pieces[1]
    for k, piece in enumerate(pieces):
        rec = pycolmap.Reconstruction(str(failed / f"model_{k}"))
        assert {rec.image(i).name for i in rec.reg_image_ids()} >= piece
    # a later successful run removes the stale failure
    run_sfm(sub, out2, cfg)
    assert out2.is_dir() and not failed.exists()


def test_weak_frames_are_deferred_only_where_the_chain_holds_without_them():
    from cystomap.sfm.mapping import weak_frames

    n = 40
    verified = {(i, i + d): 120 for i in range(n) for d in (1, 2, 3) if i + d < n}
    for k in verified:
        if {10, 11, 12} & set(k) or 30 in k:  # a blurred stretch and a single blurred frame
            verified[k] = 12
    cfg = SfmConfig(weak_frame_rel=0.5)
    # the lone blurred frame: its neighbours match each other directly; the stretch: no pair
    # spans it, its frames are the chain's only link
    assert weak_frames(verified, n, cfg) == {30}
    verified[(8, 14)] = 60  # an extension pair across the stretch
    assert weak_frames(verified, n, cfg) == {10, 11, 12, 30}
    for a, b in verified:
        if a < 30 < b:
            verified[(a, b)] = 12  # too weak to count as a link
    assert weak_frames(verified, n, cfg) == {10, 11, 12}
    assert weak_frames(verified, n, SfmConfig(weak_frame_rel=0)) == set()


@pytest.mark.slow
def test_uncalibrated_distorted_scope_is_self_calibrated(tmp_path_factory, tmp_path):
    """A scope known only by its diagonal FOV (given 70 deg, truly 76) with barrel distortion
    k1 = -0.2: the stage estimates focal length and distortion, undistorts the model and the
    frames, and the trajectory and scale are close to the truth (before self-calibration:
    RMSE 14 mm, scale +160 % on this session)."""
    from cystomap.evaluate import evaluate_session, load_truth
    from cystomap.phantom import PhantomConfig, generate_session
    from cystomap.preprocess import PreprocessConfig, preprocess_frames
    from cystomap.sfm.intrinsics import frames_dir

    root = tmp_path_factory.mktemp("sfm_uncalibrated")
    true_cam = Camera(1280, 720, 939.864, 939.864, 639.5, 359.5,
                      (-0.2, 0.02, 0.0, 0.0, 0.0)).scaled(SMALL_SCALE)
    truth_dir = generate_session(root / "session", 1, PhantomConfig(texture_detail_mm=0.4),
                                 true_cam)
    frames = _decode(truth_dir / "video.mp4", root / "frames")
    prior = Camera.from_fov(true_cam.width, true_cam.height, 70.0, name="scope")
    pre = root / "preprocessed"
    preprocess_frames(frames, pre, prior, PreprocessConfig())
    truth = load_truth(truth_dir)
    out = tmp_path / "sfm"
    run_sfm(pre, out, from_mapping(SfmConfig, FAST, "sfm"), extent_mm=truth.extent_mm)
    q = json.loads((out / "quality.json").read_text())
    cal = q["calibration"]
    assert cal["estimated"] and cal["model"] == "RADIAL"
    assert cal["focal_px"] == pytest.approx(true_cam.fx, rel=0.03), cal
    assert cal["focal_vs_prior"] < 0.95  # the wrong prior was corrected
    assert cal["k1"] == pytest.approx(-0.2, abs=0.04), cal
    assert cal["reprojection_error_px"] < 1.0
    est = Camera.load(out / "camera.json")
    assert est.dist[0] == pytest.approx(cal["k1"], abs=1e-4) and not est.calibrated
    # the model is pinhole and its frames are undistorted beside it
    und = frames_dir(out, pre)
    assert und == out / "undistorted"
    assert len(list((und / "color").glob("*.png"))) == truth.n_frames
    # with the preprocess stage's clipped-pixel masks, which the atlas reads from there
    assert len(list((und / "clipped").glob("*.png"))) == truth.n_frames
    assert not Camera.load(und / "camera.json").has_distortion
    assert q["registered"] >= 0.95 * truth.n_frames
    traj = evaluate_session(truth_dir, out)["trajectory"]
    assert traj["rmse_mm"] < 0.5, traj
    assert traj["scale_error"] < 0.03, traj


def test_working_size_follows_the_lit_field_of_view(tmp_path):
    """SIFT's working size is relative to the lit disc, not to the frame: a round image 760 px
    across in a black 1920x1080 frame is worked at 640/760 of full size (not 640/1920), and
    a frame lit edge to edge as before."""
    from cystomap.sfm.features import lit_extent, working_scale

    cam = Camera.from_fov(1920, 1080, 75.0)
    mask = np.zeros((1080, 1920), np.uint8)
    cv2.circle(mask, (900, 560), 379, 255, -1)
    path = tmp_path / "mask.png"
    cv2.imwrite(str(path), mask)
    assert lit_extent(path, cam) == 759
    cfg = SfmConfig()
    assert working_scale(cam, cfg, lit_extent(path, cam)) == pytest.approx(640 / 759)
    assert lit_extent(None, cam) == 1920
    assert working_scale(cam, cfg, lit_extent(None, cam)) == pytest.approx(1 / 3)
    assert working_scale(cam, from_mapping(SfmConfig, {"max_image_size": 0}, "sfm"), 759) == 1.0


def _synthetic_model(tmp: Path, n_frames: int = 12, n_points: int = 400) -> tuple:
    """A synthetic COLMAP model with its database (matches of every pair) and frame names in
    order."""
    import pycolmap

    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_frames_per_rig, opts.num_points3D = 1, n_frames, n_points
    pycolmap.set_random_seed(0)
    db = pycolmap.Database.open(str(tmp / "db.db"))
    rec = pycolmap.synthesize_dataset(opts, db)
    db.close()
    names = sorted(rec.image(i).name for i in rec.reg_image_ids())
    return rec, tmp / "db.db", names


def test_piece_sharing_frames_is_joined_and_a_contradicting_join_undone(tmp_path):
    """Two pieces of one mapping that share three frames (the second moved by a similarity, as
    its own mapping would place it): joined into one model at the right poses; a guard that
    sees a new contradiction undoes the join."""
    import pycolmap

    from cystomap.sfm import mapping, pieces

    rec, db, names = _synthetic_model(tmp_path)
    by_name = {rec.image(i).name: i for i in rec.reg_image_ids()}
    truth = {n: np.asarray(rec.image(by_name[n]).projection_center()) for n in names}
    main, piece = pycolmap.Reconstruction(rec), pycolmap.Reconstruction(rec)
    for k, n in enumerate(names):
        if k >= 9:
            main.deregister_frame(main.image(by_name[n]).frame_id)
        if k < 6:
            piece.deregister_frame(piece.image(by_name[n]).frame_id)
    piece.transform(pycolmap.Sim3d(2.5, pycolmap.Rotation3d(np.array([0.3, -0.2, 0.5])),
                                   np.array([4.0, -1.0, 2.0])))
    cfg = SfmConfig()
    opts = mapping.pipeline_options(cfg, False, tmp_path)
    joined, left, fig = pieces.join(db, pycolmap.Reconstruction(main), [piece], names,
                                    set(names), opts, cfg, False, lambda r: 0)
    assert joined.num_reg_images() == len(names) and not left and fig["joined"] == 1, fig
    err = [np.linalg.norm(np.asarray(joined.image(by_name[n]).projection_center()) - truth[n])
           for n in names]
    assert max(err) < 1e-3 * np.ptp(np.array(list(truth.values())), axis=0).max(), err
    count = iter(range(100))
    undone, left, fig = pieces.join(db, main, [piece], names, set(names), opts, cfg, False,
                                    lambda r: next(count))
    assert undone.num_reg_images() == 9 and len(left) == 1 and fig["undone"] == 1, fig


def test_frames_posed_from_too_few_points_are_taken_out(tmp_path):
    """A frame left with a twentieth of the points the others see (a plain stretch of wall)
    leaves the model with its reason; a model of evenly observed frames is untouched."""
    from cystomap.sfm.mapping import drop_thin_frames

    rec, _, names = _synthetic_model(tmp_path)
    assert drop_thin_frames(rec, 0.1) == {}
    by_name = {rec.image(i).name: i for i in rec.reg_image_ids()}
    thin = rec.image(by_name[names[5]])
    seen = [k for k, p in enumerate(thin.points2D) if p.has_point3D()]
    median = float(np.median([rec.image(i).num_points3D for i in rec.reg_image_ids()]))
    for k in seen[int(0.05 * median):]:
        rec.delete_observation(thin.image_id, k)
    out = drop_thin_frames(rec, 0.1)
    assert list(out) == [names[5]] and out[names[5]].startswith("posed from too few points")
    assert not rec.image(by_name[names[5]]).has_pose
    assert rec.num_reg_images() == len(names) - 1
    assert drop_thin_frames(rec, 0.0) == {}


def test_pose_similarity_of_shared_frames():
    """The similarity from the shared frames' poses alone (little parallax: too few shared
    3-D points agree) maps the piece's cameras onto the model's."""
    import tempfile

    import pycolmap

    from cystomap.sfm.pieces import _pose_similarity

    with tempfile.TemporaryDirectory() as tmp:
        rec, _, _ = _synthetic_model(Path(tmp))
    piece = pycolmap.Reconstruction(rec)
    piece.transform(pycolmap.Sim3d(0.4, pycolmap.Rotation3d(np.array([-0.7, 0.1, 0.2])),
                                   np.array([1.0, 2.0, -3.0])))
    shared = set(sorted(rec.reg_image_ids())[5:8])
    sim = _pose_similarity(piece, rec, shared)
    assert sim is not None and sim.scale == pytest.approx(2.5, rel=1e-6)
    piece.transform(sim)
    for i in rec.reg_image_ids():
        assert np.allclose(piece.image(i).projection_center(), rec.image(i).projection_center(),
                           atol=1e-6)
    assert _pose_similarity(piece, rec, set(sorted(rec.reg_image_ids())[:1])) is None
    # two shared frames: the scale would rest on the one step between them, untested
    assert _pose_similarity(piece, rec, set(sorted(rec.reg_image_ids())[5:7])) is None


def test_frames_registered_alone_are_taken_out(tmp_path):
    """A frame registered with no other frame within sequential_overlap places of it in the
    video (posed by loop matches alone) leaves the model with its reason; frames with a
    neighbour in reach, even across a gap, stay."""
    from cystomap.sfm.mapping import drop_lone_frames

    rec, _, names = _synthetic_model(tmp_path, n_frames=14)
    assert drop_lone_frames(rec, names, 3) == {}
    by_name = {rec.image(i).name: i for i in rec.reg_image_ids()}
    for k in (5, 6, 7, 9, 10, 11):  # frame 8 alone; frames 4 and 12 still 3 places from 1 more
        rec.deregister_frame(rec.image(by_name[names[k]]).frame_id)
    assert drop_lone_frames(rec, names, 4) == {}  # 4 and 8 are 4 places apart
    out = drop_lone_frames(rec, names, 3)
    assert list(out) == [names[8]] and out[names[8]].startswith("registered alone")
    assert not rec.image(by_name[names[8]]).has_pose
    assert rec.num_reg_images() == len(names) - 7


def test_independent_halves_flag_a_drifted_stretch():
    """A model whose stretch of 8 frames is bent away by 3 frame steps: two maps of
    alternate halves (here the true trajectory, each in its own similarity frame and noise
    of 5 % of a step) flag it; the true model with the same noise passes, and so does a model
    with one half's frame placed badly (one frame, not a stretch)."""
    from cystomap.sfm.drift import MIN_OFF_RUN, compare

    rng = np.random.default_rng(3)
    n = 60
    t = np.linspace(0, 3 * np.pi, n)
    truth = np.c_[20 * np.cos(t), 20 * np.sin(t), 5 * t]  # a helix, step about 1.9
    step = np.median(np.linalg.norm(np.diff(truth, axis=0), axis=1))
    order = [f"f{k:06d}.png" for k in range(n)]

    def half(k0: int, pieces: int = 2) -> list[dict[str, np.ndarray]]:
        ks = list(range(k0, n, 2))
        out = []
        for part in np.array_split(ks, pieces):  # each piece in its own frame
            a = rng.normal(size=3)
            from scipy.spatial.transform import Rotation

            r = Rotation.from_rotvec(a).as_matrix()
            out.append({order[k]: 0.7 * r @ (truth[k] + rng.normal(0, 0.05 * step, 3)) + a
                        for k in part})
        return out

    halves = [half(0), half(1)]
    good = {order[k]: truth[k] + rng.normal(0, 0.05 * step, 3) for k in range(n)}
    ok = compare(good, order, halves)
    assert ok["consistent"] and ok["residual_max_steps"] < 0.5, ok
    bent = dict(good)
    for k in range(40, 48):
        bent[order[k]] = truth[k] + np.array([0.0, 0.0, 3 * step * (k - 39) / 8])
    bad = compare(bent, order, halves)
    assert not bad["consistent"] and bad["longest_off_run"] >= MIN_OFF_RUN, bad
    assert bad["off_run_from"] in order[40:48], bad
    one = [dict(h) for h in halves[0]], halves[1]
    key = order[20]
    piece = next(p for p in one[0] if key in p)
    piece[key] = piece[key] + 3 * step
    single = compare(good, order, [one[0], one[1]])
    assert single["consistent"] and single["frames_off"][0] >= 1, single
    # a wrong piece of one half beside one that agrees over the same frames: that half's
    # fault, not the model's (seen on a good full-size model: 12 frames 4.6 steps off)
    wrong = {k: v * 1.0 for k, v in halves[0][0].items()}
    for k in list(wrong)[5:15]:
        wrong[k] = wrong[k] + 5 * step
    both = compare(good, order, [[wrong, *halves[0]], halves[1]])
    assert both["consistent"] and both["frames_off"] == [0, 0], both
    # one half off on both sides of the other half's gap: that half's fault, not a run (seen on
    # a clean 640x360 session at 0.15 mm: frames 92-96 of the even half off, 93 and 95 lost by
    # the odd half)
    gap = [dict(p) for p in halves[0]], [{k: v for k, v in p.items() if k not in order[41:44:2]}
                                         for p in halves[1]]
    for p in gap[0]:
        for k in order[40:45:2]:
            if k in p:
                p[k] = p[k] + 3 * step * 0.7
    lone = compare(good, order, [gap[0], gap[1]])
    assert lone["consistent"] and lone["frames_off"][0] >= 3, lone


def test_drift_flag_warns_or_fails_the_stage(tmp_path):
    """A model the halves contradict: flagged in the figures (warn, the default), or the
    stage fails with the place named and what reconstructed left beside the outputs (fail)."""
    from cystomap.sfm.pipeline import _judge_halves

    halves = {"checked": True, "consistent": False, "longest_off_run": 4,
              "off_run_from": "f000027.png", "residual_max_steps": 2.5}
    check = {"consistent": True, "halves": halves}
    failed = tmp_path / "sfm.failed"
    _judge_halves(check, SfmConfig(), failed, ["f000027.png"], None, {})
    assert check["consistent"] is False and "f000027.png" in check["reason"]
    assert not failed.exists()
    with pytest.raises(StageError, match=r"4 consecutive frames from f000027\.png"):
        _judge_halves({"consistent": True, "halves": halves},
                      from_mapping(SfmConfig, {"halves_check": "fail"}, "sfm"), failed,
                      ["f000027.png"], None, {})
    assert json.loads((failed / "quality.json").read_text())["failed"] is True
    ok = {"consistent": True, "halves": {**halves, "consistent": True}}
    _judge_halves(ok, SfmConfig(), failed, [], None, {})
    assert ok["consistent"] is True and "reason" not in ok
    # the loop rotations' flag goes the same way (cystomap/sfm/rotation.py)
    from cystomap.sfm.pipeline import _judge_rotation

    rot = {"flagged": True, "worst_pairs": 10, "worst_deg": 3.44, "p_value": 0.001,
           "worst_frames": [["f000002.png", "f000007.png"], ["f000065.png", "f000068.png"]]}
    check = {"consistent": True, "rotation": rot}
    _judge_rotation(check, SfmConfig(), tmp_path / "rot.failed", [], None, {})
    assert check["consistent"] is False and "f000002.png..f000007.png" in check["reason"]
    assert "3.4°" in check["reason"] and not (tmp_path / "rot.failed").exists()
    with pytest.raises(StageError, match=r"rotation drift: 10 loop pairs linking f000002"):
        _judge_rotation({"consistent": True, "rotation": rot},
                        from_mapping(SfmConfig, {"rotation_check": "fail"}, "sfm"),
                        tmp_path / "rot.failed", ["f000002.png"], None, {})
    assert json.loads((tmp_path / "rot.failed" / "quality.json").read_text())["failed"] is True


def test_plain_frames_are_detected_on_doubled_images(tmp_path_factory, tmp_path):
    """A pale, coarse-textured wall (phantom texture family B) is too plain for SIFT at
    640x360: every frame is detected again on the doubled image (sfm.plain_keypoints_share),
    for several times the keypoints; the default wall is not (same features, no extra cost)."""
    from cystomap.sfm.features import extract, list_frames, plain_session

    cfg = SfmConfig()
    assert plain_session([100, 200, 250, 900], cfg)  # median 225 < 2048 / 8
    assert not plain_session([100, 300, 400], cfg)
    assert not plain_session([100, 200], from_mapping(SfmConfig, {"plain_keypoints_share": 0},
                                                      "sfm"))
    off = from_mapping(SfmConfig, {"plain_keypoints_share": 0}, "sfm")
    medians = {}
    for wall, phantom in (("B", {"seed": 302, "texture_family": "B"}), ("default", {})):
        _, pre = _render_and_preprocess(tmp_path_factory.mktemp(f"plain_{wall}"),
                                        {"n_frames": 8, "lossless_video": True, **phantom})
        camera = Camera.load(pre / "camera.json")
        names = list_frames(pre / "enhanced")
        for tag, c in (("on", cfg), ("off", off)):
            work = tmp_path / f"{wall}_{tag}"
            work.mkdir()
            f = extract(pre / "enhanced", pre / "mask.png", camera, names, work / "db.db", work, c)
            medians[wall, tag] = float(np.median(list(f.num_keypoints.values())))
            assert f.plain == (tuple(names) if (wall, tag) == ("B", "on") else ())
    # measured (8 frames): B 233 -> 2173 keypoints per frame (median), default wall 440 both ways
    assert medians["B", "off"] < 256
    assert medians["B", "on"] > 4 * medians["B", "off"]
    assert medians["default", "on"] == medians["default", "off"] > 256


def test_doubled_frames_counts_every_frame_of_a_doubled_mapping():
    """quality.json ``doubled_frames``: the plain-frame rule's frames, or every frame when the
    whole mapping ran on the image doubled (first_octave -1: the retry's second mapping),
    which recorded 0 before."""
    from types import SimpleNamespace

    from cystomap.sfm.features import doubled_frames

    plain = SimpleNamespace(plain=("f1.png", "f2.png"))
    assert doubled_frames(plain, 10, SfmConfig()) == 2
    doubled = from_mapping(SfmConfig, {"first_octave": -1}, "sfm")
    assert doubled_frames(SimpleNamespace(plain=()), 10, doubled) == 10


def test_loop_rotations_flag_rotation_drift(tmp_path):
    """Rotation drift the epipolar tests cannot see: a synthetic model whose frames from 8 on
    are turned by 3° (loop pairs measured with 0.5 px noise) is flagged, with the size and the
    place of the turn; the unturned model is not (cystomap/sfm/rotation.py)."""
    from types import SimpleNamespace

    import pycolmap

    from cystomap.sfm import consistency, rotation

    rec, db, names = _synthetic_model(tmp_path, 16)
    geoms = consistency.read_geometries(db, names)
    noise = pycolmap.SyntheticNoiseOptions()
    noise.point2D_stddev = 0.5
    pycolmap.synthesize_noise(noise, rec)
    for g in geoms.values():  # essential matrices estimated again from the noisy points
        g.geometry = SimpleNamespace(config=rotation.CALIBRATED, E=np.zeros((3, 3)))
    loops = {p for p in geoms if p[1] - p[0] > 3}
    ok = rotation.rotation_check(rec, names, geoms, loops, SfmConfig())
    assert ok["checked"] and not ok["flagged"] and ok["p_value"] > 0.05, ok
    assert ok["pairs_tested"] == len(loops) and ok["median_deg"] < 1.5, ok
    _turn_from(rec, names, 8, 3)
    bad = rotation.rotation_check(rec, names, geoms, loops, SfmConfig())
    assert bad["flagged"] and bad["p_value"] <= rotation.ALPHA, bad
    assert 2.0 < bad["worst_deg"] < 4.0, bad  # measured 2.89
    (_, a1), (b0, _) = bad["worst_frames"]
    assert names.index(a1) < 8 <= names.index(b0), bad


def test_loop_rotations_of_a_self_calibrated_lens_use_its_estimate(tmp_path):
    """A scope known only by its FOV is matched through the prior camera (no distortion), so
    the stored essential matrices of its loop pairs are biased (held-out uncal:8, k1 -0.2: the
    model 0.14 mm from the truth, yet every loop pair 8.4° from it and the model flagged); with
    ``from_rays`` each pair's rotation comes from its rays through the model's (estimated)
    camera, and the same model passes."""
    from types import SimpleNamespace

    import pycolmap

    from cystomap.sfm import consistency, rotation

    rec, db, names = _synthetic_model(tmp_path, 16)
    geoms = consistency.read_geometries(db, names)
    noise = pycolmap.SyntheticNoiseOptions()
    noise.point2D_stddev = 0.5
    pycolmap.synthesize_noise(noise, rec)
    loops = {p for p in geoms if p[1] - p[0] > 3}
    by_name = {rec.image(i).name: i for i in rec.reg_image_ids()}

    def rays(name: str, idx: np.ndarray) -> np.ndarray:
        im = rec.image(by_name[name])
        xy = np.array([im.points2D[k].xy for k in idx]).reshape(-1, 2)
        cam = rec.camera(im.camera_id)
        x = np.asarray(cam.cam_from_img(xy))
        # what a pinhole prior makes of a barrel lens that shrinks the image's corners by 12 %
        # (the phantom's k1 -0.2 at a 76° diagonal: 0.2 tan(38°)^2), its focal length 20 % off
        corner2 = (cam.width**2 + cam.height**2) / 4 / cam.focal_length_x**2
        return 1.2 * x * (1 - 0.12 * np.sum(x * x, axis=1, keepdims=True) / corner2)

    for p, g in geoms.items():
        x1, x2 = rays(names[p[0]], g.matches[:, 0]), rays(names[p[1]], g.matches[:, 1])
        g.geometry = SimpleNamespace(config=rotation.CALIBRATED,
                                     E=rotation._essential_from_rays(x1, x2))
    stored = rotation.rotation_check(rec, names, geoms, loops, SfmConfig())
    assert stored["median_deg"] > 1.0, stored  # the premise: the prior's matrices are off
    ok = rotation.rotation_check(rec, names, geoms, loops, SfmConfig(), from_rays=True)
    assert ok["checked"] and not ok["flagged"] and ok["median_deg"] < 0.5, ok


def test_loop_rotation_null_is_calibrated():
    """Independent, heavy-tailed discrepancies (no drift) are flagged at about the rate ALPHA
    asks for; a drift of 1° (its own direction at each return) under the same noise (0.7°, t
    with 3 degrees of freedom, as loop pairs with parallax measured on dev sessions) is flagged
    (nearly) every time."""
    from cystomap.sfm.rotation import drift_test

    flagged = found = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        # four returns to earlier places, 30 loop pairs each between two runs of 10 frames
        starts = rng.integers(0, 50, (4, 2)) + np.array([0, 60])
        pairs = np.concatenate([s + rng.integers(0, 10, (30, 2)) for s in starts])
        noise = np.radians(0.7) * rng.standard_t(3, size=(len(pairs), 3))
        flagged += drift_test(pairs, noise, 3, seed, replicates=200)["flagged"]
        axes = rng.normal(size=(4, 3))
        drift = np.radians(1.0) * np.repeat(axes / np.linalg.norm(axes, axis=1)[:, None], 30, 0)
        found += drift_test(pairs, noise + drift, 3, seed, replicates=200)["flagged"]
    assert flagged <= 3, flagged  # ALPHA 0.01 of 40: 0.4 expected
    assert found >= 38, found  # measured 39
