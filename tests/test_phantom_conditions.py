"""Tests of the phantom's optional conditions: mosaic wall, strong lens distortion,
texture families, per-session photometry and lesion kinds (small seeded renders)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from test_phantom import (
    cast,
    highpass,
    load_scene,
    read_frames,
    read_poses,
    sample_atlas,
    undistorted_rays,
)

from cystomap.camera import Camera
from cystomap.phantom import PhantomConfig, default_camera, generate_session
from cystomap.phantom.geometry import base_bladder
from cystomap.phantom.texture import build_mucosa

TINY = {"n_frames": 3, "cube_face_px": 256, "atlas_height": 64, "lossless_video": True}


def _tile_pair(cube, mosaic, k: int, j: int, half_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Grey texture values at the same patch coordinates (a grid, mm) in tiles k and j, where
    both tiles show them (inside their own cells); prefiltered over 0.5 mm."""
    a = np.linspace(-half_mm, half_mm, 30)
    xy = np.stack(np.meshgrid(a, a), -1).reshape(-1, 2)
    pk, pj = mosaic.wall_offsets(k, xy), mosaic.wall_offsets(j, xy)
    own = (mosaic.cell(pk) == k) & (mosaic.cell(pj) == j)
    assert own.sum() > 100
    ck, _ = cube.sample(pk[own], np.full(own.sum(), 0.5))
    cj, _ = cube.sample(pj[own], np.full(own.sum(), 0.5))
    return ck.mean(1), cj.mean(1)


def _corr(pair: tuple[np.ndarray, np.ndarray]) -> float:
    return float(np.corrcoef(*pair)[0, 1])


@pytest.mark.slow  # renders a phantom session
def test_mosaic_repeats_patches():
    """texture_mode mosaic: tiles showing the same patch carry the same texture (up to tint),
    wherever they lie on the wall; the procedural wall at the same points does not repeat."""
    cfg = PhantomConfig(cube_face_px=512, texture_mode="mosaic", mosaic_patches=3,
                        mosaic_patch_mm=20.0)
    bladder = base_bladder(cfg)
    scene = bladder.scene()
    cube = build_mucosa(cfg, bladder, scene)
    plain = build_mucosa(replace(cfg, texture_mode="procedural"), bladder, scene)
    m = cube.mosaic
    assert m is not None and plain.mosaic is None
    counts = np.bincount(m.patch, minlength=3)
    assert len(m) >= 100 and counts.min() >= 20  # every patch appears in many places
    half = 0.3 * cfg.mosaic_patch_mm
    same, other, proc = [], [], []
    for p in range(3):
        tiles = [int(k) for k in np.flatnonzero(m.patch == p)[:6]]
        for k in tiles[1:]:
            same.append(_corr(_tile_pair(cube, m, tiles[0], k, half)))
            proc.append(_corr(_tile_pair(plain, m, tiles[0], k, half)))
        q = int(np.flatnonzero(m.patch == (p + 1) % 3)[0])
        other.append(_corr(_tile_pair(cube, m, tiles[0], q, half)))
    # measured (seed 7, 512 texels per face): same patch 0.81-0.95, median 0.86; the
    # procedural wall at those points |r| median 0.16; different patches 0.14-0.32
    assert np.median(same) > 0.75 and min(same) > 0.6
    assert np.median(np.abs(proc)) < 0.4
    assert np.median(np.abs(other)) < 0.5
    # seeded: the same config gives the same mosaic
    again = build_mucosa(cfg, bladder, scene)
    assert np.array_equal(again.levels[0], cube.levels[0])


@pytest.mark.slow  # renders a phantom session
def test_mosaic_session_renders_and_records(tmp_path):
    cam = default_camera(160, 90)
    a = generate_session(tmp_path / "a", 1, PhantomConfig(**TINY), cam)
    b = generate_session(tmp_path / "b", 1, PhantomConfig(texture_mode="mosaic", **TINY), cam)
    tb = json.loads((b / "truth.json").read_text())
    assert tb["texture"]["mode"] == "mosaic" and tb["texture"]["mosaic"]["tiles"] >= 100
    assert json.loads((a / "truth.json").read_text())["texture"]["mosaic"] is None
    fa, fb = read_frames(a / "video.mp4"), read_frames(b / "video.mp4")
    assert all(np.abs(x.astype(float) - y).mean() > 3 for x, y in zip(fa, fb, strict=True))


def _predict(d, cam: Camera, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame k predicted from surface.ply, poses, albedo.png and ``cam`` (NaN off the wall);
    also each pixel's normalised radius in the image."""
    import cv2

    truth = json.loads((d / "truth.json").read_text())
    scene, _, _ = load_scene(d / "surface.ply")
    _, rot, cen = read_poses(d / "poses.csv")
    albedo = cv2.cvtColor(cv2.imread(str(d / "albedo.png")), cv2.COLOR_BGR2RGB)
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    rays = undistorted_rays(cam, np.stack([u, v], -1).reshape(-1, 2))
    dirs = rays @ rot[k].T
    hit = cast(scene, cen[k], dirs)
    p = cen[k] + np.nan_to_num(hit["t_hit"], posinf=0.0)[:, None] * dirs
    rel = p - np.array(truth["barycentre"])
    pred = sample_atlas(albedo, rel / np.linalg.norm(rel, axis=1, keepdims=True)).mean(1)
    pred[~np.isfinite(hit["t_hit"])] = np.nan
    rad = np.hypot((u - cam.cx) / (cam.width / 2), (v - cam.cy) / (cam.height / 2))
    return pred.reshape(cam.height, cam.width), rad


@pytest.mark.slow  # renders a phantom session
def test_lens_k1_distortion(tmp_path):
    """lens_k1 -0.2 with a diagonal_fov_deg-only camera: the frames are rendered through
    that lens (wall points land where the OpenCV model of camera.json puts them, far from where
    the given pinhole camera would), camera.json and truth.json record it."""
    given = Camera.from_config({"width": 320, "height": 180, "diagonal_fov_deg": 76.0}, "fov76")
    cfg = PhantomConfig(lens_k1=-0.2, n_frames=5, cube_face_px=512, atlas_height=512,
                        lossless_video=True, lesion_diameters_mm=())
    d = generate_session(tmp_path / "s", 1, cfg, given)
    cam = Camera.load(d / "camera.json")
    assert cam.dist[0] == -0.2 and cam.calibrated and cam.fx == pytest.approx(given.fx)
    lens = json.loads((d / "truth.json").read_text())["lens"]
    assert lens["k1_override"] == -0.2 and not lens["given_is_rendered"]
    assert lens["diagonal_fov_deg_true"] > 80  # barrel: wider than the 76 deg pinhole guess
    # a wall point seen at a pixel projects there by the model (Camera.project, OpenCV)
    scene, _, _ = load_scene(d / "surface.ply")
    _, rot, cen = read_poses(d / "poses.csv")
    pix = np.array([[5.0, 5.0], [314.0, 170.0], [160.0, 90.0], [20.0, 150.0]])
    k = 2  # inside the bladder
    dirs = undistorted_rays(cam, pix) @ rot[k].T
    t = cast(scene, cen[k], dirs)["t_hit"]
    assert np.isfinite(t).all()
    pts = cen[k] + t[:, None] * dirs
    uv_model = cam.project((pts - cen[k]) @ rot[k])
    uv_pinhole = given.project((pts - cen[k]) @ rot[k])
    assert np.abs(uv_model - pix).max() < 1e-3
    assert np.linalg.norm(uv_pinhole - pix, axis=1)[:2].min() > 15  # corners: far off
    # the rendered image agrees with the distorted prediction, not the pinhole one, off-centre
    frame = read_frames(d / "video.mp4")[k].astype(np.float32).mean(2)
    corr = {}
    for name, c in (("model", cam), ("pinhole", given)):
        pred, rad = _predict(d, c, k)
        ok = np.isfinite(pred) & (rad > 0.6)
        hp_p, hp_i = highpass(np.nan_to_num(pred)), highpass(frame)
        inner = ok[4:-4, 4:-4]
        corr[name] = np.corrcoef(hp_p[4:-4, 4:-4][inner], hp_i[4:-4, 4:-4][inner])[0, 1]
    # measured (seed 7, 320x180, frame 2): model 0.74, pinhole 0.21
    assert corr["model"] > 0.5 and abs(corr["pinhole"]) < 0.5 * corr["model"], corr


def test_texture_families():
    """texture_family draws the subject's mucosa from a named family (seeded, recorded); the
    default (empty) keeps the built-in wall; the families differ as named."""
    from cystomap.phantom.texture import TEXTURE_FAMILIES, TextureParams, texture_params

    base = PhantomConfig(cube_face_px=256)
    assert texture_params(base) == TextureParams()
    bladder = base_bladder(base)
    scene = bladder.scene()
    stats = {}
    for fam in ("A", "B", "C"):
        cfg = replace(base, texture_family=fam)
        tp = texture_params(cfg)
        assert tp == texture_params(cfg)  # seeded
        assert tp != texture_params(replace(cfg, seed=8))  # per subject
        for key in ("mottle_scale", "mottle_contrast", "vessel_density", "grain"):
            lo, hi = TEXTURE_FAMILIES[fam][key]
            assert lo <= getattr(tp, key) <= hi
        cube = build_mucosa(cfg, bladder, scene)
        assert cube.params == tp
        img = cube.levels[0].reshape(-1, 3).astype(np.float64)
        stats[fam] = img.mean(0)
    ratio = {f: m[1] / m[0] for f, m in stats.items()}  # green / red
    assert ratio["B"] > ratio["A"] > ratio["C"]  # pale > pink > red
    a = build_mucosa(replace(base, texture_family="B"), bladder, scene)
    assert np.array_equal(a.levels[0], build_mucosa(replace(base, texture_family="B"), bladder,
                                                    scene).levels[0])


@pytest.mark.slow  # renders a phantom session
def test_photometry_and_lesion_kinds_in_a_session(tmp_path):
    """photometric_variation: each session's white balance shifts its channel means as
    recorded; lesion kinds and sites are recorded in lesions.csv; seeded renders repeat."""
    cam = default_camera(160, 90)
    kinds = ("papillary", "cis", "scar", "perivascular")
    cfg = PhantomConfig(**TINY, lesion_diameters_mm=(5.0, 12.0, 20.0, 25.0), lesion_kinds=kinds,
                        lesion_sites=("seam", "any", "any", "neck"), texture_family="C",
                        photometric_variation=1.5)
    plain = replace(cfg, photometric_variation=0.0)
    out = {}
    for name, c in (("var", cfg), ("plain", plain), ("again", cfg)):
        out[name] = generate_session(tmp_path / name, 2, c, cam)
    photo = json.loads((out["var"] / "truth.json").read_text())["photometry"]
    assert json.loads((out["plain"] / "truth.json").read_text())["photometry"]["white_balance"] == [1.0] * 3
    fv, fp = read_frames(out["var"] / "video.mp4"), read_frames(out["plain"] / "video.mp4")
    mv = np.mean([f.reshape(-1, 3).mean(0) for f in fv], 0)
    mp = np.mean([f.reshape(-1, 3).mean(0) for f in fp], 0)
    measured = (mv / mp) / (mv / mp).mean()
    wb = np.array(photo["white_balance"]) ** (1 / 2.2)
    predicted = wb / wb.mean()
    # measured (seed 7, session 2, upright entry): channel shifts 1.014 1.017 0.969, predicted
    # 0.994 1.027 0.978 (the rest: albedo colour correlated with the shading, which the
    # variation changes). Before the entry became upright the shifts were 1.005 1.022 0.973;
    # a correlation over three channels (0.78 now, > 0.8 then) is too noisy to assert, so the
    # test checks the size of the error and that the channel predicted lowest is measured lowest.
    assert np.ptp(predicted) > 0.02  # a visible shift
    assert np.abs(measured - predicted).max() < 0.5 * np.ptp(predicted)
    assert int(np.argmin(measured)) == int(np.argmin(predicted))
    assert photo != json.loads((generate_session(tmp_path / "s1", 1, replace(cfg, n_frames=2), cam)
                                / "truth.json").read_text())["photometry"]  # per session
    # kinds and sites recorded per lesion (config order = id)
    rows = (out["var"] / "lesions.csv").read_text().splitlines()
    assert rows[0].endswith(",kind,site,height_mm,region,clock,distance_from_neck_mm")
    rec = [r.split(",") for r in rows[1:]]
    assert [r[10] for r in rec] == list(kinds) and [r[11] for r in rec] == ["seam", "any", "any", "neck"]
    assert float(rec[0][12]) > 0 and all(float(r[12]) == 0 for r in rec[1:])
    # determinism
    assert all(np.array_equal(a, b) for a, b in zip(fv, read_frames(out["again"] / "video.mp4"),
                                                     strict=True))
    assert (out["var"] / "lesions.csv").read_text() == (out["again"] / "lesions.csv").read_text()


def test_lesion_sites_and_papillary_relief():
    """Sites put lesions across the atlas seam, over the pole and beside the neck; papillary
    lesions are raised into the cavity in session 2's geometry (only there)."""
    from cystomap.phantom.geometry import az_el, session_bladder
    from cystomap.phantom.lesions import (
        NECK_CLEARANCE_DEG,
        aperture_cone,
        lesion_kinds_and_sites,
        place_lesions,
    )

    cfg = PhantomConfig(lesion_diameters_mm=(8.0, 12.0, 20.0, 30.0),
                        lesion_kinds=("papillary", "cis", "papillary", "painted"),
                        lesion_sites=("seam", "pole", "neck", "any"))
    assert lesion_kinds_and_sites(replace(cfg, lesion_kinds=(), lesion_sites=()))[0] == ["painted"] * 4
    drawn = lesion_kinds_and_sites(replace(cfg, lesion_kinds=("cis", "scar")))[0]
    assert set(drawn) <= {"cis", "scar"} and len(drawn) == 4
    base = base_bladder(cfg)
    lesions = place_lesions(cfg, base, base.scene())
    ap_dir, ap_ang = aperture_cone(base)
    for les in lesions:
        r = float(np.linalg.norm(les.material))
        ang_r = np.degrees(les.diameter_mm / 2 / r)  # angular radius seen from the centre
        az, el = az_el(les.material)
        if les.site == "seam":
            assert 180 - abs(az) < 0.35 * ang_r  # spans the +-180 deg seam
        elif les.site == "pole":
            assert el > 90 - 0.35 * ang_r
        elif les.site == "neck":
            off = np.degrees(np.arccos(les.material @ ap_dir / r))
            assert ap_ang + NECK_CLEARANCE_DEG < off - ang_r < ap_ang + 25.0
    # relief: session 2 only, inward, about the configured height at the papillary centres
    s1, s2 = session_bladder(cfg, 1), session_bladder(cfg, 2)
    assert s1 is base
    nw = base.n_wall_verts
    disp = s2.vertices[:nw] - base.vertices[:nw]
    moved = np.linalg.norm(disp, axis=1) > 1e-9
    for les in lesions:
        dist = np.linalg.norm(base.vertices[:nw] - les.material, axis=1)
        near = dist < 0.15 * les.diameter_mm + 1.0
        if les.kind == "papillary":
            h = np.linalg.norm(disp[near], axis=1).max()
            assert 0.7 * les.height_mm < h <= les.height_mm + 1e-9
            assert np.all(disp[near] @ les.normal <= 0)  # into the cavity
            assert les.height_mm == pytest.approx(min(0.35 * les.diameter_mm, 6.0))
        else:
            assert les.height_mm == 0 and not moved[near].any()
    papillary = [les for les in lesions if les.kind == "papillary"]
    far = np.min([np.linalg.norm(base.vertices[:nw] - les.material, axis=1) - les.diameter_mm
                  for les in papillary], axis=0) > 0
    assert not moved[far].any() and moved.any()
    assert s2.volume_mm3 < base.volume_mm3  # raised lesions take volume from the cavity
    assert replace(cfg, lesion_kinds=()).lesion_kinds == () and session_bladder(
        replace(cfg, lesion_kinds=()), 2) is base  # no papillary lesion: no relief


def test_lesion_kinds_paint():
    """Each kind changes the wall as named: painted/papillary strongly, cis as a low-contrast
    reddening, scar paler, perivascular red with a vessel beside it that both sessions show."""
    from cystomap.phantom.cubemap import CubeMap
    from cystomap.phantom.lesions import paint_lesions, paint_site_vessels, place_lesions
    from cystomap.phantom.mosaic import tangent_frame

    kinds = ("painted", "cis", "scar", "perivascular")
    cfg = PhantomConfig(cube_face_px=512, lesion_diameters_mm=(12.0, 14.0, 16.0, 18.0),
                        lesion_kinds=kinds)
    bladder = base_bladder(cfg)
    scene = bladder.scene()
    wall = build_mucosa(cfg, bladder, scene)
    lesions = place_lesions(cfg, bladder, scene)
    s1 = CubeMap([wall.levels[0].copy()], wall.n, wall.gloss, params=wall.params)
    assert paint_site_vessels(s1, lesions, bladder, scene) == 1
    s2 = CubeMap([s1.levels[0].copy()], s1.n, s1.gloss, params=s1.params)
    paint_lesions(s2, lesions, bladder, scene)
    for les in lesions:
        e1, e2 = tangent_frame(les.normal[None])
        a = np.linspace(-0.3, 0.3, 15) * les.diameter_mm
        xy = np.stack(np.meshgrid(a, a), -1).reshape(-1, 2)
        pts = les.material + xy[:, :1] * e1 + xy[:, 1:] * e2
        c0, _ = wall.sample(pts)
        c1, _ = s1.sample(pts)
        c2, _ = s2.sample(pts)
        d = np.abs(c2 - c1).max(1)
        gain = c2.mean(0) / c1.mean(0)
        # measured (seed 7): max-channel change median painted 51, cis 14 (gain 1.02 0.92
        # 0.93, Delta E 8), scar 28 (brighter by 20), perivascular 39 (gain 1.02 0.76 0.79)
        if les.kind == "painted":
            assert np.median(d) > 25
        elif les.kind == "cis":  # low contrast, red kept, green and blue lowered
            assert 7 < np.median(d) < 25 and 0.85 < gain[1] < 0.95 and gain[0] > 0.99
        elif les.kind == "scar":  # paler and less saturated
            assert c2.mean() > c1.mean() + 5
            assert (c2[:, 0] - c2[:, 2]).mean() < (c1[:, 0] - c1[:, 2]).mean()
        else:
            assert gain[1] < 0.85 and np.median(d) > 8
            assert np.array_equal(c0, c1)  # the vessel is outside the lesion
            # ... and beside it, in both sessions: a ring around the lesion darkened in s1
            ang = np.linspace(0, 2 * np.pi, 720, endpoint=False)
            ring = []
            for rr in np.linspace(0.55, 1.6, 12) * les.diameter_mm:
                p = les.material + rr * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
                ring.append(np.abs(s1.sample(p)[0] - wall.sample(p)[0]).max(1))
            ring = np.concatenate(ring)
            assert (ring > 20).sum() > 90  # measured 191


def test_lesions_bound_to_a_site_are_placed_before_the_rest():
    """FROC pair 103: its 29 mm lesion (anywhere) was placed first and took the pole's small
    window, so the 4.4 mm pole lesion could not be placed and the benchmark stopped."""
    from cystomap.bench.froc import random_pair
    from cystomap.phantom.geometry import base_bladder
    from cystomap.phantom.lesions import place_lesions

    cfg = random_pair(103).cfg
    bladder = base_bladder(cfg)
    lesions = place_lesions(cfg, bladder, bladder.scene())
    assert [les.site for les in lesions] == list(cfg.lesion_sites)
    assert [les.diameter_mm for les in lesions] == list(cfg.lesion_diameters_mm)


def test_froc_counts_the_lesions_of_a_failed_session_as_missed():
    """A pair whose session the sfm stage refused (StageError) is scored, not a crash."""
    from cystomap.bench.froc import failed_rows, random_pair, summarise

    rows = failed_rows(random_pair(105), (0.1, 1.0), "sfm: only 24 of 120 frames registered")
    rows += failed_rows(random_pair(1100, no_change=True), (0.1, 1.0), "sfm: failed")
    summary = {(r["rate"], r["subset"]): r for r in summarise(rows)}
    whole = summary[(0.1, "all")]
    assert whole["lesions"] == 6 and whole["recall"] == 0.0 and whole["fp_per_pair"] == 0.0
    assert whole["no_change_pairs"] == 1


def test_froc_summary_gives_the_issue_targets_from_5_mm():
    """Recall from 5 and 10 mm, centroid errors over 2 mm and sizes within 20 %, of the
    lesions found from 5 mm (a 4 mm lesion counts in neither)."""
    from cystomap.bench.froc import summarise

    base = {"pair": "p1", "rate": 0.1, "family": "A", "no_change": False, "false_positives": 0,
            "kind": "cis"}
    lesions = [(4.0, True, 9.0, 50.0), (6.0, True, 0.5, 10.0), (12.0, True, 3.0, -30.0),
               (25.0, False, None, None)]
    rows = [{**base, "lesion": k, "diameter_mm": d, "detected": found, "centroid_error_mm": c,
             "size_error_pct": s} for k, (d, found, c, s) in enumerate(lesions)]
    whole = {r["subset"]: r for r in summarise(rows)}["all"]
    assert whole["recall_from_5mm"] == "2/3" and whole["recall_from_10mm"] == "1/2"
    assert whole["centroid_over_2mm"] == "1/2" and whole["size_within_20pct"] == "1/2"
    assert whole["centroid_error_mm_median"] == 1.75


def test_froc_leaves_out_a_pair_the_phantom_cannot_draw():
    """Held-out seeds 118 and 119: papillary relief on a deformed wall is not star-shaped, and
    the phantom's InputError ended the whole benchmark run; such a pair is named and left out,
    a drawable one is not."""
    from cystomap.bench.froc import random_pair, undrawable

    assert "not star-shaped" in (undrawable(random_pair(118)) or "")
    assert undrawable(random_pair(120)) is None


def test_froc_summary_counts_apart_the_lesions_both_sessions_saw():
    """A lesion on wall session A never filmed stays in "all" but not in "seen by both"."""
    from cystomap.bench.froc import summarise

    base = {"pair": "p1", "rate": 0.1, "family": "C", "no_change": False, "false_positives": 0,
            "kind": "cis"}
    rows = [{**base, "lesion": 1, "diameter_mm": 17.0, "detected": False, "centroid_error_mm": None,
             "size_error_pct": None, "seen_a": 0.0, "seen_b": 1.0},
            {**base, "lesion": 2, "diameter_mm": 8.0, "detected": True, "centroid_error_mm": 0.5,
             "size_error_pct": 5.0, "seen_a": 0.9, "seen_b": 1.0}]
    by = {r["subset"]: r for r in summarise(rows)}
    assert by["all"]["recall_from_5mm"] == "1/2"
    assert by["seen by both (>= 0.5 of the lesion)"]["recall_from_5mm"] == "1/1"
    assert by["seen by both, held-out family C"]["recall_from_5mm"] == "1/1"
