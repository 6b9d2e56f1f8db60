"""The scorer on synthetic truth: known errors in, the same errors out."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import fake_truth as ft
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cystomap.errors import InputError
from cystomap.evaluate import (
    EvalConfig,
    align,
    comparisons_from_lists,
    evaluate_changes,
    evaluate_session,
    evaluate_subject,
    load_truth,
    sessions_from_lists,
    umeyama,
)
from cystomap.settings import from_mapping

N_FRAMES = 24
BAD = (3, 7)
DROPPED = (3, 10, 17)  # one bad frame, two good ones
KEPT = [k for k in range(N_FRAMES) if k not in DROPPED]
SIGMA = 0.5  # mm, per axis
ROT_NOISE = 2.0  # deg


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("evaluate")


@pytest.fixture(scope="module")
def truth(work: Path) -> ft.FakeTruth:
    return ft.make_truth(work / "truth", n_frames=N_FRAMES, bad_frames=BAD)


@pytest.fixture(scope="module")
def exact_sfm(work: Path, truth: ft.FakeTruth) -> Path:
    """Registered frames KEPT, poses exact up to MODEL_FRAME, keypoints 0.5 px off, f +5 %."""
    return ft.write_model(work / "sfm_exact", truth, frames=KEPT, pixel_error_px=0.5,
                          focal_factor=1.05, quality={"mean_reprojection_error_px": 0.49,
                                                      "units": "mm"})


@pytest.fixture(scope="module")
def noisy_sfm(work: Path, truth: ft.FakeTruth) -> Path:
    return ft.write_model(work / "sfm_noisy", truth, centre_sigma_mm=SIGMA,
                          rotation_noise_deg=ROT_NOISE, seed=5)


# ---------------------------------------------------------------- alignment


def test_umeyama_recovers_a_known_sim3() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(30, 3)) * 10
    frame = ft.MODEL_FRAME
    sim = umeyama(src, frame(src))
    assert sim.scale == pytest.approx(frame.s, abs=1e-12)
    np.testing.assert_allclose(sim.rotation, frame.R, atol=1e-12)
    np.testing.assert_allclose(sim.apply(src), frame(src), atol=1e-9)
    np.testing.assert_allclose(sim.inverse().apply(sim.apply(src)), src, atol=1e-9)


def test_trimmed_alignment_ignores_a_wild_point_and_plain_does_not() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3)) * 10
    dst = ft.MODEL_FRAME(src) + rng.normal(scale=0.01, size=src.shape)
    dst[4] += [40.0, 0.0, 0.0]
    plain, _ = align(src, dst)
    robust, inliers = align(src, dst, trim=3.0)
    assert abs(plain.scale - 0.5) > 0.01
    assert robust.scale == pytest.approx(0.5, abs=1e-3)
    assert not inliers[4] and inliers.sum() == 19


# ------------------------------------------------------ registration, trajectory


def test_registered_share_is_exactly_the_frames_kept(truth: ft.FakeTruth, exact_sfm: Path) -> None:
    reg = evaluate_session(truth.directory, exact_sfm)["registration"]
    good = set(range(N_FRAMES)) - set(BAD)
    assert reg["n_models"] == 1
    assert reg["n_registered"] == len(KEPT)
    assert reg["registered_share"] == len(KEPT) / N_FRAMES
    assert reg["registered_share_good"] == len(good & set(KEPT)) / len(good)
    assert reg["n_registered_bad"] == 1  # frame 7


def test_exact_model_scores_its_known_frame_and_pixel_error(
    truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    res = evaluate_session(truth.directory, exact_sfm)
    traj = res["trajectory"]
    assert traj["n_matched"] == len(KEPT)
    assert traj["rmse_mm"] < 1e-6
    assert traj["scale_ratio"] == pytest.approx(0.5, abs=1e-9)
    assert traj["scale_error"] == pytest.approx(0.5, abs=1e-9)
    assert traj["rotation_error_deg_median"] < 1e-4
    assert traj["claims_metric"] is True
    np.testing.assert_allclose(np.array(traj["sim3_model_to_truth"]["rotation"]),
                               ft.MODEL_FRAME.R.T, atol=1e-9)
    assert res["reprojection"]["mean_error_px"] == pytest.approx(0.5, abs=1e-6)
    assert res["reprojection"]["reported_mean_error_px"] == 0.49
    assert res["models"][0]["focal_error_percent"] == pytest.approx(5.0, abs=1e-9)


def test_noisy_model_reports_the_injected_noise(truth: ft.FakeTruth, noisy_sfm: Path) -> None:
    traj = evaluate_session(truth.directory, noisy_sfm)["trajectory"]
    n = N_FRAMES
    expected = SIGMA * math.sqrt(3 * (n - 7 / 3) / n)  # 7 of 3n dof absorbed by the Sim(3)
    assert 0.75 * expected < traj["rmse_mm"] < 1.25 * expected
    assert traj["rmse_percent_extent"] == pytest.approx(100 * traj["rmse_mm"] / 80.0)
    # scale from centres spread over ~±10 mm: its error is ~σ / (spread·√n) ≈ 1 %
    assert traj["scale_ratio"] == pytest.approx(0.5, rel=0.03)
    assert traj["rotation_error_deg_median"] == pytest.approx(ROT_NOISE, abs=0.4)


def test_trimmed_alignment_on_a_model_with_a_wild_camera(
    work: Path, truth: ft.FakeTruth
) -> None:
    sfm = ft.write_model(work / "sfm_wild", truth, outliers={5: (60.0, 0.0, 0.0)}, seed=7)
    plain = evaluate_session(truth.directory, sfm)["trajectory"]
    robust = evaluate_session(truth.directory, sfm, cfg=EvalConfig(alignment_trim=3.0))
    traj = robust["trajectory"]
    assert abs(plain["scale_ratio"] - 0.5) > 0.01
    assert traj["n_inliers"] == N_FRAMES - 1
    assert traj["scale_ratio"] == pytest.approx(0.5, abs=1e-6)
    assert traj["median_error_mm"] < 1e-6
    assert traj["max_error_mm"] == pytest.approx(60.0, rel=1e-6)


def test_several_models_are_counted_and_one_is_the_reference(
    work: Path, truth: ft.FakeTruth
) -> None:
    parent = work / "sfm_multi"
    ft.write_model(parent / "0", truth, frame=ft.Transform(2.0), frames=range(10))
    big = [k for k in range(8, N_FRAMES) if k != 20]
    ft.write_model(parent / "1", truth, frames=big)
    res = evaluate_session(truth.directory, parent)
    reg = res["registration"]
    assert reg["n_models"] == 2
    assert reg["n_registered"] == N_FRAMES - 1  # union: all but frame 20
    assert reg["largest_model_share"] == len(big) / N_FRAMES
    assert res["trajectory"]["n_matched"] == 10  # model 0, as the mesh stage picks it
    assert res["trajectory"]["scale_ratio"] == pytest.approx(2.0, abs=1e-9)
    largest = evaluate_session(truth.directory, parent, cfg=EvalConfig(reference_model="largest"))
    assert largest["trajectory"]["n_matched"] == len(big)
    assert largest["trajectory"]["scale_ratio"] == pytest.approx(0.5, abs=1e-9)
    # the same models given as a list: the first path given is the reference
    again = evaluate_session(truth.directory, [parent / "1", parent / "0"])
    assert again["registration"] == reg
    assert again["trajectory"]["n_matched"] == len(big)


# ---------------------------------------------------------------- surface


def test_mesh_offset_along_normals_gives_that_accuracy(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    mesh = ft.write_ply(work / "mesh_offset.ply", *ft.offset_mesh(truth, 0.3))
    surf = evaluate_session(truth.directory, exact_sfm, mesh)["surface"]
    assert surf["accuracy_mean_mm"] == pytest.approx(0.3, abs=0.05)
    assert surf["accuracy_median_mm"] == pytest.approx(0.3, abs=0.05)
    assert surf["completeness"] == 1.0
    strict = evaluate_session(truth.directory, exact_sfm, mesh,
                              cfg=EvalConfig(completeness_threshold_mm=0.2))["surface"]
    assert strict["completeness"] < 0.05


def test_half_mesh_gives_the_share_of_seen_wall_it_covers(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    centroids = truth.vertices[truth.triangles].mean(axis=1)
    keep = centroids[:, 0] > ft.CENTRE[0]
    mesh = ft.write_ply(work / "mesh_half.ply", *ft.offset_mesh(truth, 0.0, keep=keep))
    surf = evaluate_session(truth.directory, exact_sfm, mesh)["surface"]
    pts = ft.sample_mesh(truth.vertices, truth.triangles, 100_000, np.random.default_rng(3))
    seen = ft.is_seen(pts - ft.CENTRE)
    # the seen wall with x > centre (~0.39, not 0.5: the unseen wedge is at azimuth 0…60°),
    # plus the band within 2 mm of the cut, which counts as reconstructed (the wall is
    # roughly perpendicular to the cut plane there)
    covered = pts[seen, 0] > ft.CENTRE[0]
    within = pts[seen, 0] > ft.CENTRE[0] - EvalConfig().completeness_threshold_mm
    assert covered.mean() + 0.01 < surf["completeness"]
    assert surf["completeness"] == pytest.approx(within.mean(), abs=0.015)
    assert surf["completeness_whole_wall"] > surf["completeness"] + 0.05
    assert surf["accuracy_mean_mm"] < 1e-3
    assert surf["area_ratio"] == pytest.approx(keep.mean(), abs=0.1)


def test_closure_of_an_opening_is_scored_apart_from_the_wall(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    """A mesh 4 mm off only inside the truth's aperture cone: wall accuracy exact, closure 4 mm."""
    opened = work / "truth_open"
    shutil.copytree(truth.directory, opened, dirs_exist_ok=True)
    meta = json.loads((opened / "truth.json").read_text())
    meta["aperture"] = {"azimuth_deg": 30.0, "elevation_deg": -70.0, "angular_radius_deg": 25.0}
    (opened / "truth.json").write_text(json.dumps(meta))
    t = load_truth(opened)
    inside = t.in_opening(truth.vertices)
    assert 0.02 < inside.mean() < 0.2
    v = truth.vertices + np.where(inside, 4.0, 0.0)[:, None] * truth.normals
    mesh = ft.write_ply(work / "mesh_cap.ply", ft.MODEL_FRAME(v), truth.triangles)
    surf = evaluate_session(opened, exact_sfm, mesh)["surface"]
    assert surf["accuracy_mean_mm"] < 0.05
    assert surf["closure_mean_mm"] > 3.0
    assert surf["accuracy_mean_mm_with_closure"] > surf["accuracy_mean_mm"] + 0.1
    assert surf["closure_share"] == pytest.approx(inside.mean(), abs=0.05)
    plain = evaluate_session(truth.directory, exact_sfm, mesh)["surface"]  # no aperture known
    assert plain["closure_share"] == 0 and plain["accuracy_mean_mm"] > 0.1


# ----------------------------------------------------------------- atlas


def test_atlas_coverage_error_and_mask(work: Path, truth: ft.FakeTruth, exact_sfm: Path) -> None:
    true_pct = 100 * truth.seen_fraction
    atlas = ft.write_atlas(work / "atlas_good", truth, coverage_percent=true_pct + 3.0)
    res = evaluate_session(truth.directory, exact_sfm, atlas_dir=atlas)["atlas"]
    assert res["coverage_percent_true"] == pytest.approx(true_pct, abs=1e-9)
    assert res["coverage_error_pp"] == pytest.approx(3.0, abs=1e-9)
    assert res["mask_iou"] > 0.97
    assert res["albedo_correlation"] > 0.95
    assert res["painted_percent"] == pytest.approx(true_pct, abs=1.5)
    assert res["ssim"] > 0.85 and res["ssim_stretched"] > 0.85
    assert res["detail_correlation"] > 0.6  # sharp-edged bands resampled between grids
    assert 0.85 < res["sharpness_ratio"] < 1.1


def _spoil_atlas(directory: Path, spoil) -> Path:
    img = cv2.imread(str(directory / "atlas.png"), cv2.IMREAD_UNCHANGED)
    img[..., :3] = spoil(img[..., :3].astype(np.float32)).clip(0, 255).astype(np.uint8)
    cv2.imwrite(str(directory / "atlas.png"), img)
    return directory


def test_atlas_blur_and_ghosting_lower_ssim_detail_and_sharpness(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    good = evaluate_session(truth.directory, exact_sfm,
                            atlas_dir=ft.write_atlas(work / "atlas_ok", truth))["atlas"]
    blurred = _spoil_atlas(ft.write_atlas(work / "atlas_blur", truth),
                           lambda x: cv2.GaussianBlur(x, (0, 0), 2.0))
    blur = evaluate_session(truth.directory, exact_sfm, atlas_dir=blurred)["atlas"]
    ghosted = _spoil_atlas(ft.write_atlas(work / "atlas_ghost", truth),
                           lambda x: 0.5 * x + 0.5 * np.roll(x, 4, axis=1))
    ghost = evaluate_session(truth.directory, exact_sfm, atlas_dir=ghosted)["atlas"]
    for bad in (blur, ghost):
        assert bad["ssim_stretched"] < good["ssim_stretched"] - 0.1
        assert bad["detail_correlation"] < good["detail_correlation"] - 0.1
        assert bad["sharpness_ratio"] < good["sharpness_ratio"] - 0.15
        assert bad["mask_iou"] == pytest.approx(good["mask_iou"], abs=0.02)  # the mask is fine


def test_atlas_painted_everywhere_or_misoriented_is_caught(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    everywhere = ft.write_atlas(work / "atlas_all", truth, paint_all=True)
    res = evaluate_session(truth.directory, exact_sfm, atlas_dir=everywhere / "atlas.json")
    assert res["atlas"]["mask_recall"] > 0.99
    assert res["atlas"]["mask_precision"] == pytest.approx(truth.seen_fraction, abs=0.02)
    wrong = ft.write_atlas(work / "atlas_rot", truth, ignore_rotation=True)
    res = evaluate_session(truth.directory, exact_sfm, atlas_dir=wrong)["atlas"]
    assert res["mask_iou"] < 0.8
    assert res["albedo_correlation"] < 0.8
    assert res["ssim_stretched"] < 0.6 and res["detail_correlation"] < 0.5


# ---------------------------------------------------------------- lesions


def _detections(truth: ft.FakeTruth) -> list[dict]:
    """True lesions shifted by known offsets; L2 dropped; one spurious 8 mm from L2."""
    les = truth.lesions.set_index("id")
    shifts = {"L0": (1.0, 0, 0), "L1": (0, 1.2, 1.6), "L3": (0, 0.5, 0), "L4": (0, 0, -3.0)}
    sizes = {"L0": 1.1, "L1": 1.0, "L3": 0.8, "L4": 1.1}
    scores = {"L0": 0.9, "L1": 0.8, "L3": 0.6, "L4": 0.5}
    rows = []
    for lid, shift in shifts.items():
        p = les.loc[lid, ["x", "y", "z"]].to_numpy(float) + shift
        rows.append({"x": p[0], "y": p[1], "z": p[2],
                     "diameter_mm": les.loc[lid, "diameter_mm"] * sizes[lid],
                     "area_mm2": 1.0, "score": scores[lid]})
    p = les.loc["L2", ["x", "y", "z"]].to_numpy(float) + np.array([8.0, 0, 0])
    rows.insert(2, {"x": p[0], "y": p[1], "z": p[2], "diameter_mm": 5.0, "area_mm2": 1.0,
                    "score": 0.7})
    return rows


def test_changes_report_the_injected_lesion_errors(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    changes = ft.write_changes(work / "changes.csv", _detections(truth))
    res = evaluate_changes(truth.directory, exact_sfm, changes)
    les = res["lesions"]
    assert res["alignment"]["rmse_mm"] < 1e-6
    assert (les["n_true"], les["n_detected"], les["n_matched"]) == (5, 5, 4)
    assert les["recall"] == 0.8
    assert les["false_positives"] == 1
    assert les["false_positive_rows"] == [2]
    per = {e["id"]: e for e in les["lesions"]}
    expected_loc = {"L0": 1.0, "L1": 2.0, "L3": 0.5, "L4": 3.0}
    expected_size = {"L0": 10.0, "L1": 0.0, "L3": -20.0, "L4": 10.0}
    assert not per["L2"]["detected"]
    for lid, loc in expected_loc.items():
        assert per[lid]["localisation_error_mm"] == pytest.approx(loc, abs=1e-6)
        assert per[lid]["size_error_percent"] == pytest.approx(expected_size[lid], abs=1e-6)
    assert les["localisation_error_mm_mean"] == pytest.approx(6.5 / 4, abs=1e-6)
    assert {k: v["recall"] for k, v in les["recall_by_diameter"].items()} == {
        "3": 1.0, "6": 0.5, "4": 1.0}
    assert les["average_precision"] == pytest.approx((1 + 1 + 3 / 4 + 4 / 5) / 5)


def test_session_without_lesions_counts_every_detection_as_false(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    truth_a = work / "truth_a"
    shutil.copytree(truth.directory, truth_a)
    (truth_a / "lesions.csv").write_text(
        "id,x,y,z,nx,ny,nz,diameter_mm,azimuth_deg,elevation_deg\n")
    changes = ft.write_changes(work / "changes_a.csv", _detections(truth)[:2])
    les = evaluate_changes(truth_a, exact_sfm, changes)["lesions"]
    assert les["recall"] is None
    assert les["false_positives"] == 2
    assert les["precision"] == 0.0


def test_changes_without_required_columns_raise(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    bad = work / "changes_bad.csv"
    bad.write_text("x,y,z\n1,2,3\n")
    with pytest.raises(InputError, match=r"changes_bad\.csv.*diameter_mm"):
        evaluate_changes(truth.directory, exact_sfm, bad)


# ------------------------------------------------------- missing inputs, reports


def test_missing_outputs_leave_their_scores_out(work: Path, truth: ft.FakeTruth) -> None:
    res = evaluate_session(truth.directory, work / "no_sfm", work / "no_mesh.ply", work / "no_at")
    assert not {"registration", "trajectory", "surface", "atlas"} & set(res)
    assert len(res["left_out"]) == 3
    assert "lesions" not in evaluate_changes(truth.directory, None, work / "none.csv")


def test_missing_truth_files_raise_input_error_naming_them(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path
) -> None:
    partial = work / "truth_partial"
    shutil.copytree(truth.directory, partial)
    (partial / "surface.ply").unlink()
    mesh = ft.write_ply(work / "mesh_any.ply", *ft.offset_mesh(truth, 0.0))
    with pytest.raises(InputError, match=r"truth_partial/surface\.ply not found"):
        evaluate_session(partial, exact_sfm, mesh)
    (partial / "poses.csv").unlink()
    with pytest.raises(InputError, match=r"poses\.csv not found"):
        evaluate_session(partial)


def test_evaluate_subject_writes_json_tsv_and_markdown(
    work: Path, truth: ft.FakeTruth, exact_sfm: Path, noisy_sfm: Path
) -> None:
    mesh = ft.write_ply(work / "mesh_subject.ply", *ft.offset_mesh(truth, 0.3))
    changes = ft.write_changes(work / "changes_subject.csv", _detections(truth))
    sessions = sessions_from_lists(["s1", "s2"], [truth.directory] * 2, [noisy_sfm, exact_sfm],
                                   ["", mesh], [None, None])
    comparisons = comparisons_from_lists(["s1_s2"], [truth.directory], [exact_sfm], [changes])
    out = work / "report"
    report = evaluate_subject(out, sessions, comparisons)
    saved = json.loads((out / "evaluation.json").read_text())
    assert saved["sessions"]["s2"]["surface"]["accuracy_mean_mm"] == pytest.approx(0.3, abs=0.05)
    assert "surface" not in saved["sessions"]["s1"]
    assert saved["comparisons"]["s1_s2"]["lesions"]["recall"] == 0.8
    assert saved["config"]["completeness_threshold_mm"] == 2.0
    assert report["sessions"]["s1"]["trajectory"]["n_matched"] == N_FRAMES
    rows = [line.split("\t") for line in (out / "evaluation.tsv").read_text().splitlines()]
    assert rows[0] == ["kind", "name", "metric", "value"]
    tsv = {(r[1], r[2]): r[3] for r in rows[1:]}
    assert float(tsv["s2", "trajectory.scale_ratio"]) == pytest.approx(0.5)
    assert tsv["s1_s2", "lesions.lesions.2.detected"] == "false"
    md = (out / "evaluation.md").read_text()
    assert "| metric | s1 | s2 |" in md and "| lesions.recall | 0.8 |" in md


def test_config_from_mapping_checks_keys_and_values() -> None:
    cfg = from_mapping(EvalConfig, {"completeness_threshold_mm": 1, "alignment_trim": 3},
                       "evaluate")
    assert cfg.completeness_threshold_mm == 1.0 and cfg.alignment_trim == 3.0
    with pytest.raises(InputError, match="evaluate: unknown key"):
        from_mapping(EvalConfig, {"threshold": 1}, "evaluate")
    with pytest.raises(InputError, match="completeness_threshold_mm > 0"):
        from_mapping(EvalConfig, {"completeness_threshold_mm": 0}, "evaluate")
    with pytest.raises(InputError, match="capture group"):
        from_mapping(EvalConfig, {"frame_pattern": r"\d+"}, "evaluate")


def test_rotation_convention_of_truth_poses(truth: ft.FakeTruth) -> None:
    """poses.csv holds camera-to-world (w, x, y, z): the camera's z axis is its forward view."""
    from cystomap.evaluate import load_truth

    loaded = load_truth(truth.directory)
    np.testing.assert_allclose(loaded.rotations, truth.rotations, atol=1e-12)
    np.testing.assert_allclose(loaded.centres, truth.centres, atol=1e-12)
    assert Rotation.from_matrix(loaded.rotations).magnitude().max() > 0.5  # not all identity


def test_command_line(work: Path, truth: ft.FakeTruth, exact_sfm: Path) -> None:
    from cystomap.evaluate.__main__ import main

    changes = ft.write_changes(work / "changes_cli.csv", _detections(truth))
    cfg = work / "evaluate.yaml"
    cfg.write_text("evaluate:\n  lesion_tolerance_mm: 0.6\n"
                   "  lesion_tolerance_diameter_factor: 0.1\n")
    out = work / "cli"
    assert main(["--out", str(out), "--session", "s2", str(truth.directory), f"sfm={exact_sfm}",
                 "--compare", "s1_s2", str(truth.directory), f"sfm={exact_sfm}",
                 f"changes={changes}", "--config", str(cfg)]) == 0
    report = json.loads((out / "evaluation.json").read_text())
    assert report["sessions"]["s2"]["registration"]["n_registered"] == len(KEPT)
    assert report["comparisons"]["s1_s2"]["lesions"]["n_matched"] == 1  # only L3 is < 0.6 mm off
    assert main(["--out", str(out), "--session", "s2", str(work / "nowhere")]) == 2
    assert main(["--out", str(out), "--session", "s2", str(truth.directory), "msh=x"]) == 2


def test_seen_share_of_a_lesion_is_the_part_of_it_the_frames_saw(truth: ft.FakeTruth) -> None:
    """The fake truth saw elevations below 30° outside the azimuth wedge 0°…60°: a lesion
    there is seen whole, one inside the wedge not at all, one centred on the 30° line half."""
    from cystomap.evaluate.lesions import seen_share

    t = load_truth(truth.directory)
    dist = 30.0
    sites = ((-120.0, 0.0), (30.0, 0.0), (-90.0, 30.0), (-90.0, 60.0))
    xyz = np.array([ft.CENTRE + dist * ft.direction(az, el) for az, el in sites])
    share = seen_share(t, xyz, np.full(len(sites), 8.0))
    assert share[0] == pytest.approx(1.0) and share[1] == pytest.approx(0.0)
    assert share[2] == pytest.approx(0.5, abs=0.08) and share[3] == pytest.approx(0.0)
