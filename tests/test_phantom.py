"""Tests of the synthetic bladder phantom (small seeded sessions; checks against the files)."""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import ConvexHull
from scipy.spatial.distance import pdist

from cystomap.camera import Camera
from cystomap.errors import InputError
from cystomap.phantom import PhantomConfig, bladder_extent_mm, default_camera, generate_session
from cystomap.phantom.geometry import base_bladder, session_bladder
from cystomap.phantom.render import EXPOSURE_TARGET, Renderer, finish, optical_blur_px
from cystomap.phantom.texture import build_mucosa
from cystomap.phantom.trajectory import make_trajectory
from cystomap.settings import from_mapping
from cystomap.video import iter_frames

SMALL = {"n_frames": 12, "cube_face_px": 512, "atlas_height": 1024}


# ---------------------------------------------------------------------------------------
# helpers that read the written files only


def read_frames(path: Path) -> list[np.ndarray]:
    return [cv2.cvtColor(f, cv2.COLOR_BGR2RGB) for _, _, f in iter_frames(path)]


def good_frame_hits(scene, cam: Camera, pix: np.ndarray, rot: np.ndarray, cen: np.ndarray,
                    truth: dict) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """For every frame that is not a bad frame: its index, the ray directions through the
    pixels ``pix`` and the distance to the wall along them (inf where a ray misses)."""
    rays = undistorted_rays(cam, pix)
    bad = {b["frame"] for b in truth["bad_frames"]}
    for k in range(len(cen)):
        if k not in bad:
            dirs = rays @ rot[k].T
            yield k, dirs, cast(scene, cen[k], dirs)["t_hit"]


def read_poses(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    with open(path) as fh:
        rows = list(csv.reader(fh))
    arr = np.array(rows[1:], dtype=np.float64)
    q, t = arr[:, 1:5], arr[:, 5:8]
    w, x, y, z = q.T
    rot = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    return rows[0], rot, t


def read_csv_dicts(path: Path) -> tuple[list[str], list[dict]]:
    with open(path) as fh:
        r = csv.DictReader(fh)
        rows = list(r)
        return list(r.fieldnames or []), rows


def load_scene(path: Path):
    mesh = o3d.io.read_triangle_mesh(str(path))
    v = np.asarray(mesh.vertices)
    t = np.asarray(mesh.triangles)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene, v, t


def cast(scene, origins: np.ndarray, dirs: np.ndarray) -> dict:
    rays = np.concatenate([np.broadcast_to(origins, dirs.shape), dirs], 1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    return {k: v.numpy() for k, v in ans.items()}


def undistorted_rays(camera: Camera, pix: np.ndarray) -> np.ndarray:
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    und = cv2.undistortPoints(pix.reshape(-1, 1, 2).astype(np.float64), camera.K,
                              camera.dist_array, None, None, None, crit).reshape(-1, 2)
    d = np.concatenate([und, np.ones((len(und), 1))], 1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def atlas_dirs(h: int) -> tuple[np.ndarray, np.ndarray]:
    w = 2 * h
    az = np.radians(-180 + (np.arange(w) + 0.5) * 360 / w)
    el = np.radians(90 - (np.arange(h) + 0.5) * 180 / h)
    d = np.stack(np.broadcast_arrays(np.cos(el)[:, None] * np.cos(az)[None, :],
                                     np.cos(el)[:, None] * np.sin(az)[None, :],
                                     np.sin(el)[:, None]), -1)
    return d.reshape(-1, 3), el


def sample_atlas(img: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Bilinear albedo.png lookup for unit directions (float RGB)."""
    h, w = img.shape[:2]
    az = np.degrees(np.arctan2(dirs[:, 1], dirs[:, 0]))
    el = np.degrees(np.arcsin(np.clip(dirs[:, 2], -1, 1)))
    x = ((az + 180) / 360 * w - 0.5).astype(np.float32)
    y = ((90 - el) / 180 * h - 0.5).astype(np.float32)
    n = len(x)
    pad = -n % 256
    x, y = np.pad(x, (0, pad)).reshape(-1, 256), np.pad(y, (0, pad)).reshape(-1, 256)
    out = cv2.remap(img.astype(np.float32), x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1, 3)[:n]


def diameter(v: np.ndarray) -> float:
    """Largest pairwise distance (exact): only points far from the box centre can be in the
    farthest pair, given a lower bound from the convex hull's extreme points."""
    hull = v[ConvexHull(v).vertices]
    c = 0.5 * (hull.max(0) + hull.min(0))
    r = np.linalg.norm(hull - c, axis=1)
    lower = pdist(hull[np.argsort(r)[-200:]]).max()
    return float(pdist(hull[r >= lower - r.max()]).max())


def highpass(img: np.ndarray) -> np.ndarray:
    img = img.astype(np.float32)
    return img - cv2.GaussianBlur(img, (0, 0), 4.0)


# ---------------------------------------------------------------------------------------
# fixtures


@pytest.fixture(scope="module")
def camera() -> Camera:
    return default_camera(320, 180)


@pytest.fixture(scope="module")
def sessions(tmp_path_factory, camera) -> dict[int, Path]:
    root = tmp_path_factory.mktemp("phantom")
    cfg = PhantomConfig(**SMALL)
    return {s: generate_session(root / f"s{s}", s, cfg, camera) for s in (1, 2)}


# ---------------------------------------------------------------------------------------
# tests


def test_files_and_formats(sessions, camera):
    for s, d in sessions.items():
        for name in ("video.mp4", "poses.csv", "camera.json", "surface.ply", "albedo.png",
                     "seen.png", "lesions.csv", "truth.json"):
            assert (d / name).is_file(), name
        header, rot, t = read_poses(d / "poses.csv")
        assert header == ["frame", "qw", "qx", "qy", "qz", "tx", "ty", "tz"]
        assert len(t) == SMALL["n_frames"]
        assert np.allclose(np.einsum("nij,nik->njk", rot, rot), np.eye(3), atol=1e-8)
        frames = read_frames(d / "video.mp4")
        assert len(frames) == SMALL["n_frames"]
        assert frames[0].shape == (camera.height, camera.width, 3)
        assert Camera.load(d / "camera.json") == camera
        fields, rows = read_csv_dicts(d / "lesions.csv")
        assert fields == ["id", "x", "y", "z", "nx", "ny", "nz", "diameter_mm", "azimuth_deg",
                          "elevation_deg", "kind", "site", "height_mm", "region", "clock",
                          "distance_from_neck_mm"]
        assert len(rows) == (0 if s == 1 else 6)
        truth = json.loads((d / "truth.json").read_text())
        assert truth["session"] == s and truth["n_frames"] == SMALL["n_frames"]
        # anatomy: neck towards the aperture (-z), anterior +y; the scope enters upright
        an = truth["anatomy"]
        assert an["neck"][2] < -0.99 and an["anterior"][1] > 0.99
        up, view = -rot[0][:, 1], rot[0][:, 2]
        neck = np.array(an["neck"])
        a = (view @ neck) * up - (up @ neck) * view
        a *= np.sign(a @ up)  # the plane of view and image up, orthogonal to the neck
        assert a @ np.array(an["anterior"]) > 0.99 * np.linalg.norm(a)
        albedo = cv2.imread(str(d / "albedo.png"))
        assert albedo.shape == (1024, 2048, 3)
        assert cv2.imread(str(d / "seen.png"), cv2.IMREAD_UNCHANGED).shape == (1024, 2048)


def test_rays_reproject_to_their_pixels(sessions, camera):
    """Surface points hit by the renderer's pixel rays project back onto those pixels."""
    from cystomap.phantom import pixel_rays

    d = sessions[1]
    scene, _, _ = load_scene(d / "surface.ply")
    _, rot, cen = read_poses(d / "poses.csv")
    cam = Camera.load(d / "camera.json")
    rays = pixel_rays(cam)
    pix = np.array([[cam.cx, cam.cy], [10, 10], [cam.width - 11, 15], [40, cam.height - 5],
                    [cam.width - 1, cam.height - 1], [200, 90]]).round().astype(int)
    idx = pix[:, 1] * cam.width + pix[:, 0]
    for k in range(0, len(cen), 3):
        dirs = rays.dirs[idx].astype(np.float64) @ rot[k].T
        hit = cast(scene, cen[k], dirs)
        ok = np.isfinite(hit["t_hit"])
        p = cen[k] + hit["t_hit"][ok, None] * dirs[ok]
        uv = cam.project((p - cen[k]) @ rot[k])
        assert np.abs(uv - pix[ok]).max() < 0.5


@pytest.mark.parametrize("session", [1, 2])
def test_images_show_the_true_surface(sessions, camera, session):
    """Predict each frame from surface.ply + poses + calibration + albedo.png; the video must
    match it without shift (< 0.5 px), without flip, with the albedo's colour balance."""
    d = sessions[session]
    truth = json.loads((d / "truth.json").read_text())
    scene, _, _ = load_scene(d / "surface.ply")
    _, rot, cen = read_poses(d / "poses.csv")
    cam = Camera.load(d / "camera.json")
    albedo = cv2.cvtColor(cv2.imread(str(d / "albedo.png")), cv2.COLOR_BGR2RGB)
    bary = np.array(truth["barycentre"])
    frames = read_frames(d / "video.mp4")
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    pix = np.stack([u, v], -1).reshape(-1, 2)
    shifts, corr, corr_flip, ratios = [], [], [], []
    for k, dirs, t_hit in good_frame_hits(scene, cam, pix, rot, cen, truth):
        if np.isfinite(t_hit).mean() < 0.95:
            continue  # looking through the aperture
        p = cen[k] + np.nan_to_num(t_hit)[:, None] * dirs
        rel = p - bary
        pred = sample_atlas(albedo, rel / np.linalg.norm(rel, axis=1, keepdims=True))
        pred = pred.reshape(cam.height, cam.width, 3)
        img = frames[k].astype(np.float32)
        lum_p = highpass(pred.mean(2))[20:-20, 20:-20]
        lum_i = highpass(img.mean(2))[20:-20, 20:-20]
        (dx, dy), _ = cv2.phaseCorrelate(lum_p, lum_i, cv2.createHanningWindow(lum_p.shape[::-1],
                                                                               cv2.CV_32F))
        shifts.append(np.hypot(dx, dy))
        corr.append(np.corrcoef(lum_p.ravel(), lum_i.ravel())[0, 1])
        corr_flip.append(np.corrcoef(lum_p.ravel(), lum_i[:, ::-1].ravel())[0, 1])
        ratios.append(img.reshape(-1, 3).mean(0) / pred.reshape(-1, 3).mean(0))
    assert len(shifts) >= SMALL["n_frames"] - 4
    assert np.median(shifts) < 0.25 and max(shifts) < 0.5
    assert min(corr) > 0.5
    assert max(np.abs(corr_flip)) < 0.3
    ratios = np.array(ratios)
    spread = ratios.max(1) / ratios.min(1)
    assert np.median(spread) < 1.08  # image = albedo x scalar shading (no channel swap)


@pytest.mark.slow
def test_determinism(tmp_path):
    cam = default_camera(320, 180)
    small = {"n_frames": 5, "cube_face_px": 256, "atlas_height": 64, "bad_frame_fraction": 0.2,
             "specular": True, "motion_blur_px": 5.0, "noise_sigma": 0.5}
    a = generate_session(tmp_path / "a", 1, PhantomConfig(seed=3, **small), cam)
    b = generate_session(tmp_path / "b", 1, PhantomConfig(seed=3, **small), cam)
    c = generate_session(tmp_path / "c", 1, PhantomConfig(seed=4, **small), cam)
    fa, fb, fc = (read_frames(x / "video.mp4") for x in (a, b, c))
    assert all(np.array_equal(x, y) for x, y in zip(fa, fb, strict=True))
    assert (a / "poses.csv").read_text() == (b / "poses.csv").read_text()
    assert (a / "poses.csv").read_text() != (c / "poses.csv").read_text()
    assert not np.array_equal(fa[2], fc[2])
    ta = json.loads((a / "truth.json").read_text())
    assert len(ta["bad_frames"]) == 1
    # the same session without bad frames: identical except the bad frame
    clean = dict(small, bad_frame_fraction=0.0)
    e = generate_session(tmp_path / "e", 1, PhantomConfig(seed=3, **clean), cam)
    fe = read_frames(e / "video.mp4")
    k, kind = ta["bad_frames"][0]["frame"], ta["bad_frames"][0]["kind"]
    for i in range(len(fa)):  # (lossy inter-frame coding: other frames nearly equal)
        diff = np.abs(fa[i].astype(np.float32) - fe[i]).mean()
        assert (diff < 2.0) == (i != k)
    bad, good = fa[k].astype(np.float32), fe[k].astype(np.float32)
    if kind == "black":
        assert bad.mean() < 12 < good.mean()
    else:
        def fine_detail(img: np.ndarray) -> float:
            return float(np.abs(img - cv2.GaussianBlur(img, (0, 0), 1.5)).mean())

        blurred = cv2.GaussianBlur(good, (0, 0), 0.015 * cam.width)
        assert fine_detail(bad) < 0.6 * fine_detail(good)
        assert np.abs(bad - blurred).mean() < 0.6 * np.abs(bad - good).mean()


@pytest.mark.slow
def test_lossless_video(tmp_path):
    """lossless_video codes the video with FFV1: the sensor noise and the fine texture survive
    (mp4v, the default, removes most of both); same content otherwise."""
    cam = default_camera(160, 90)
    cfg = PhantomConfig(n_frames=3, cube_face_px=256, atlas_height=64, noise_sigma=2.0)
    lossy = generate_session(tmp_path / "lossy", 1, cfg, cam)
    exact = generate_session(tmp_path / "exact", 1, replace(cfg, lossless_video=True), cam)
    assert json.loads((exact / "truth.json").read_text())["video_codec"] == "ffv1"
    assert json.loads((lossy / "truth.json").read_text())["video_codec"] == "mp4v"

    def fine(img: np.ndarray) -> float:  # typical fine-scale amplitude (edges excluded)
        g = img.astype(np.float32).mean(2)
        return float(np.median(np.abs(g - cv2.GaussianBlur(g, (0, 0), 1.0))))

    for a, b in zip(read_frames(lossy / "video.mp4"), read_frames(exact / "video.mp4"), strict=True):
        # the same picture (mp4v's YUV round trip also shifts the levels by a few DN)
        smooth_a, smooth_b = (cv2.GaussianBlur(x.astype(np.float32).mean(2), (0, 0), 2.0) for x in (a, b))
        assert np.corrcoef(smooth_a.ravel(), smooth_b.ravel())[0, 1] > 0.99
        assert fine(b) > 1.2 * fine(a)


def test_image_circle(tmp_path):
    """image_circle: the scope's round image in a black frame; inside it the same picture as
    the full frame's, outside black; seen.png counts only what the circle shows."""
    cam = default_camera(192, 108)
    cfg = PhantomConfig(n_frames=3, cube_face_px=256, atlas_height=64, lossless_video=True)
    full = generate_session(tmp_path / "full", 1, cfg, cam)
    round_ = generate_session(tmp_path / "round", 1, replace(cfg, image_circle=0.9), cam)
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    r = np.hypot(u - (cam.width - 1) / 2, v - (cam.height - 1) / 2)
    edge = 0.9 * cam.height / 2
    for a, b in zip(read_frames(full / "video.mp4"), read_frames(round_ / "video.mp4"), strict=True):
        assert b[r > edge + 3].max() <= 12  # sensor noise on black, clipped
        inside = r < edge - 3
        assert np.abs(a[inside].astype(int) - b[inside]).max() <= 1
    seen_full, seen_round = (json.loads((x / "truth.json").read_text())["seen_fraction"]
                             for x in (full, round_))
    assert 0.3 * seen_full < seen_round < 0.9 * seen_full


def test_render_scale(tmp_path):
    """render_scale 0.5: a quarter of the rays, enlarged to the camera's size: the same picture
    at coarse scale, the same truth."""
    cam = default_camera(192, 108)
    cfg = PhantomConfig(n_frames=3, cube_face_px=256, atlas_height=64, lossless_video=True,
                        noise_sigma=0.0)
    full = generate_session(tmp_path / "full", 1, cfg, cam)
    half = generate_session(tmp_path / "half", 1, replace(cfg, render_scale=0.5), cam)
    for a, b in zip(read_frames(full / "video.mp4"), read_frames(half / "video.mp4"), strict=True):
        assert a.shape == b.shape
        smooth_a, smooth_b = (cv2.GaussianBlur(x.astype(np.float32).mean(2), (0, 0), 3.0)
                              for x in (a, b))
        # measured: correlation 0.9998-1.0, mean difference 0.10-0.40 DN
        assert np.corrcoef(smooth_a.ravel(), smooth_b.ravel())[0, 1] > 0.999
        assert np.abs(smooth_a - smooth_b).mean() < 0.8
    ta, tb = (json.loads((x / "truth.json").read_text()) for x in (full, half))
    assert (tb["width"], tb["height"]) == (cam.width, cam.height)
    assert (full / "poses.csv").read_text() == (half / "poses.csv").read_text()
    assert abs(ta["seen_fraction"] - tb["seen_fraction"]) < 0.03 * ta["seen_fraction"]  # 1.4 %


def test_lesions(sessions):
    d1, d2 = sessions[1], sessions[2]
    cfg = PhantomConfig(**SMALL)
    a1 = cv2.imread(str(d1 / "albedo.png")).astype(np.int16)
    a2 = cv2.imread(str(d2 / "albedo.png")).astype(np.int16)
    _, rows = read_csv_dicts(d2 / "lesions.csv")
    assert sorted(float(r["diameter_mm"]) for r in rows) == sorted(cfg.lesion_diameters_mm)
    truth = json.loads((d2 / "truth.json").read_text())
    bary = np.array(truth["barycentre"])
    scene, _, _ = load_scene(d2 / "surface.ply")
    h = a1.shape[0]
    dirs, _ = atlas_dirs(h)
    hit = cast(scene, bary, dirs)
    pts = bary + np.nan_to_num(hit["t_hit"], posinf=0)[:, None] * dirs
    wall = np.isfinite(hit["t_hit"])
    diff = np.abs(a2 - a1).max(2).reshape(-1)
    near_any = np.zeros(len(pts), bool)
    for r in rows:
        c = np.array([float(r[k]) for k in "xyz"])
        n = np.array([float(r[k]) for k in ("nx", "ny", "nz")])
        diam = float(r["diameter_mm"])
        assert abs(np.linalg.norm(n) - 1) < 1e-6 and n @ (c - bary) > 0
        q = scene.compute_closest_points(o3d.core.Tensor(c[None].astype(np.float32)))
        assert np.linalg.norm(q["points"].numpy()[0] - c) < 0.01
        # the az/el of lesions.csv is the atlas pixel of the lesion centre
        az, el = float(r["azimuth_deg"]), float(r["elevation_deg"])
        col = int((az + 180) / 360 * 2 * h)
        row = int((90 - el) / 180 * h)
        dist = np.linalg.norm(pts - c, axis=1)
        assert dist[row * 2 * h + col] < 0.5
        inside = wall & (dist < 0.3 * diam)
        assert np.median(diff[inside]) > 25
        # painted extent ~ the configured diameter
        changed = wall & (dist < diam) & (diff > 40)
        radius = np.percentile(dist[changed], 98)
        assert 0.4 * diam < radius < 0.5 * diam * 1.2 + 0.6
        near_any |= dist < 0.5 * diam * 1.3 + 6.0
    assert (diff[wall & ~near_any] == 0).all()


def test_extent_and_size(sessions):
    cfg = PhantomConfig(**SMALL)
    for s, d in sessions.items():
        truth = json.loads((d / "truth.json").read_text())
        assert bladder_extent_mm(cfg, s) == pytest.approx(truth["extent_mm"], abs=1e-9)
        _, v, _ = load_scene(d / "surface.ply")
        assert diameter(v) == pytest.approx(truth["extent_mm"], abs=1e-3)
        bbox = np.ptp(v, axis=0)
        assert np.allclose(bbox, cfg.size_mm, rtol=0.06)
        assert truth["extent_mm"] == pytest.approx(170, rel=0.06)
        assert 0.8e3 < truth["volume_ml"] < 1.6e3
    other = PhantomConfig(seed=99, size_mm=(150.0, 120.0, 100.0))
    e = bladder_extent_mm(other, 1)
    assert e == pytest.approx(150, rel=0.06)


def test_deformation(tmp_path, sessions):
    cam = default_camera(160, 90)
    cfg = PhantomConfig(n_frames=4, cube_face_px=256, atlas_height=128, deformation=0.07)
    d2 = generate_session(tmp_path / "s2", 2, cfg, cam)
    _, v1, t1 = load_scene(sessions[1] / "surface.ply")
    _, v2, t2 = load_scene(d2 / "surface.ply")
    assert np.array_equal(t1, t2)
    b1 = np.array(json.loads((sessions[1] / "truth.json").read_text())["barycentre"])
    rel = np.linalg.norm(v2 - v1, axis=1) / np.linalg.norm(v1 - b1, axis=1)
    assert 0.015 < rel.mean() < 0.1 and rel.max() < 0.2
    truth = json.loads((d2 / "truth.json").read_text())
    assert truth["deformation"]["magnitude"] == 0.07
    assert truth["extent_mm"] == pytest.approx(bladder_extent_mm(cfg, 2), abs=1e-9)
    assert bladder_extent_mm(cfg, 2) != pytest.approx(bladder_extent_mm(cfg, 1), rel=0.005)
    # lesions are reported in the deformed frame: on the deformed surface
    scene, _, _ = load_scene(d2 / "surface.ply")
    _, rows = read_csv_dicts(d2 / "lesions.csv")
    c = np.array([[float(r[k]) for k in "xyz"] for r in rows], np.float32)
    q = scene.compute_closest_points(o3d.core.Tensor(c))["points"].numpy()
    assert np.linalg.norm(q - c, axis=1).max() < 0.01


def test_seen_fraction(sessions):
    for d in sessions.values():
        truth = json.loads((d / "truth.json").read_text())
        seen = cv2.imread(str(d / "seen.png"), cv2.IMREAD_UNCHANGED) > 0
        albedo = cv2.imread(str(d / "albedo.png"))
        h = seen.shape[0]
        dirs, el = atlas_dirs(h)
        scene, _, _ = load_scene(d / "surface.ply")
        bary = np.array(truth["barycentre"])
        hit = cast(scene, bary, dirs)
        wall = np.isfinite(hit["t_hit"])
        assert not (seen.ravel() & ~wall).any()
        assert (albedo.reshape(-1, 3)[~wall] == 0).all()
        cos_inc = np.abs(np.einsum("ij,ij->i", hit["primitive_normals"], dirs))
        area = np.where(wall, np.nan_to_num(hit["t_hit"], posinf=0) ** 2, 0)
        area = area * np.repeat(np.cos(el), 2 * h) * (np.pi / h) ** 2 / np.maximum(cos_inc, 1e-3)
        frac = area[seen.ravel()].sum() / area.sum()
        assert 0 < truth["seen_fraction"] <= 1
        assert truth["seen_fraction"] == pytest.approx(frac, abs=0.01)
        assert area.sum() == pytest.approx(truth["area_mm2"], rel=0.01)
        # what the good frames show is marked seen
        cam = Camera.load(d / "camera.json")
        _, rot, cen = read_poses(d / "poses.csv")
        g = np.random.default_rng(0)
        pix = np.stack([g.uniform(0, cam.width - 1, 300), g.uniform(0, cam.height - 1, 300)], 1)
        missed = total = 0
        for k, dirs, t_hit in good_frame_hits(scene, cam, pix, rot, cen, truth):
            ok = np.isfinite(t_hit)
            rel = cen[k] + t_hit[ok, None] * dirs[ok] - bary
            az = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]))
            el = np.degrees(np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1])))
            col = np.clip(((az + 180) / 360 * 2 * h).astype(int), 0, 2 * h - 1)
            row = np.clip(((90 - el) / 180 * h).astype(int), 0, h - 1)
            missed += int((~seen[row, col]).sum())
            total += len(row)
        assert missed <= 0.005 * total


@pytest.mark.slow
def test_native_low_resolution_matches_downsized_render():
    """The texture is prefiltered by each pixel's footprint: a 320x180 render of a pose looks
    like the 640x360 render of it downsized (no aliasing of the fine vessels and grain, which
    SIFT would match as moiré, and no extra blur), noise-free and before video coding."""
    cfg = PhantomConfig(n_frames=12)  # default texture (2048-texel faces, 0.1 mm detail)
    bladder = base_bladder(cfg)
    scene = bladder.scene()
    cube = build_mucosa(cfg, bladder, scene)
    tj = make_trajectory(cfg, 1, bladder, scene)
    low, high = (Renderer(default_camera(w, h), bladder, scene, cube) for w, h in ((320, 180), (640, 360)))

    def fine(img: np.ndarray) -> np.ndarray:
        return img - cv2.GaussianBlur(img, (0, 0), 1.0)

    corr, energy, psnr = [], [], []
    for k in range(3, 8):
        images = []
        trh = high.trace(tj.rotations[k], tj.centres[k])
        assert trh.wall.all()  # wall only: no silhouettes (aperture rim, tube)
        exposure = EXPOSURE_TARGET / float(np.percentile(high.irradiance(trh), 60))
        for r, tr in ((low, low.trace(tj.rotations[k], tj.centres[k])), (high, trh)):
            img = finish(r.shade(tr, exposure, 1.0, False), np.random.default_rng(0), 0.0,
                         optical_px=optical_blur_px(r.camera))
            images.append(img.astype(np.float32).mean(2))
        native = images[0]
        down = cv2.resize(images[1], (320, 180), interpolation=cv2.INTER_AREA)
        fn, fd = fine(native), fine(down)
        corr.append(np.corrcoef(fn.ravel(), fd.ravel())[0, 1])
        energy.append(fn.std() / fd.std())
        psnr.append(10 * np.log10(255**2 / np.mean((native - down) ** 2)))
    # (medians now: correlation 0.968 (min 0.948), energy 0.85, PSNR 52.3 dB. Point-sampled
    # level 0, i.e. aliasing: 0.91, 1.24, 44 dB; the former 3-level isotropic mipmaps and
    # 0.55 px optical blur: 0.92, 0.67, 50.5 dB; one level blurrier: 0.79, 0.58, 46.7 dB)
    assert np.median(corr) > 0.94 and min(corr) > 0.92, corr
    assert 0.78 < np.median(energy) < 1.15, energy
    assert np.median(psnr) > 51, psnr


def test_trajectory_full_length():
    cfg = PhantomConfig()
    paths = []
    for s in (1, 2):
        b = session_bladder(cfg, s)
        scene = b.scene()
        tj = make_trajectory(cfg, s, b, scene)
        assert len(tj.centres) == 124
        # (the upright entry's roll turning to the sweep's adds up to half a turn: 9.4 deg max)
        assert tj.rotation_steps_deg().max() < 10.0
        assert tj.rotation_steps_deg().mean() < 8.5
        ap = b.vertices[b.rim].mean(0)
        assert np.linalg.norm(tj.centres[0] - ap) < 15
        assert np.linalg.norm(tj.centres[-1] - ap) < 15
        # the view ray hits the wall 20-80 mm away once inside (entry/exit excepted)
        hit = scene.cast_rays(o3d.core.Tensor(np.concatenate(
            [tj.centres, tj.rotations[:, :, 2]], 1).astype(np.float32)))["t_hit"].numpy()
        scan = np.array([p not in ("entry", "exit") for p in tj.phase])
        assert 20 <= hit[scan].min() and hit[scan].max() <= 85
        paths.append(tj.centres)
    assert not np.allclose(paths[0], paths[1])


def test_config_validation():
    cfg = from_mapping(PhantomConfig, {"size_mm": [160, 120, 100], "lesion_diameters_mm": [5, 10]},
                       "phantom")
    assert cfg.size_mm == (160.0, 120.0, 100.0) and cfg.lesion_diameters_mm == (5.0, 10.0)
    with pytest.raises(InputError):
        from_mapping(PhantomConfig, {"deformation": 0.9}, "phantom")
    with pytest.raises(InputError):
        from_mapping(PhantomConfig, {"n_frames": 1}, "phantom")
    with pytest.raises(InputError):
        generate_session(Path("/nonexistent/x"), 3, PhantomConfig(), default_camera(64, 36))
