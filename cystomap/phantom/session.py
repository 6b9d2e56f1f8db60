"""Render one phantom session and write its video and ground truth (atomically)."""

from __future__ import annotations

import csv
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from cystomap.anatomy import ANATOMY_COLUMNS, Anatomy, locate
from cystomap.camera import Camera
from cystomap.errors import InputError, StageError
from cystomap.io.ply import write_ply
from cystomap.outputs import atomic_dir, write_json
from cystomap.phantom.atlas import Atlas
from cystomap.phantom.config import PhantomConfig
from cystomap.phantom.geometry import (
    Bladder,
    az_el,
    base_bladder,
    make_deformation,
    rng,
    session_bladder,
    wall_bbox,
    wall_extent,
)
from cystomap.phantom.lens import lens_truth, render_camera
from cystomap.phantom.lesions import (
    aperture_cone,
    lesion_rows,
    paint_lesions,
    paint_site_vessels,
    place_lesions,
)
from cystomap.phantom.render import (
    EXPOSURE_TARGET,
    GAMMA,
    RayGrid,
    Renderer,
    finish,
    optical_blur_px,
    pixel_rays,
    rotate,
)
from cystomap.phantom.texture import build_mucosa
from cystomap.phantom.trajectory import Trajectory, make_trajectory
from cystomap.phantom.wall_rays import cast

log = logging.getLogger(__name__)

STREAM_BAD = 30
STREAM_NOISE = 40
POSE_COLUMNS = ("frame", "qw", "qx", "qy", "qz", "tx", "ty", "tz")
LESION_COLUMNS = ("id", "x", "y", "z", "nx", "ny", "nz", "diameter_mm", "azimuth_deg",
                  "elevation_deg", "kind", "site", "height_mm", *ANATOMY_COLUMNS)
SURFACE_NOTE = ("bladder wall only (urethra tube excluded; open at the aperture), triangle mesh"
                " in mm in this session's world frame (the frame of poses.csv), binary PLY with"
                " vertex normals and vertex colours = albedo")


def bladder_extent_mm(cfg: PhantomConfig, session: int) -> float:
    """True wall extent of ``session``: largest distance between two wall points (mm).

    Cheap (geometry only, no rendering); equals truth.json's ``extent_mm``.
    """
    return wall_extent(session_bladder(cfg, session).wall_vertices)


def _quaternions(rot: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(rot).as_quat(scalar_first=True)
    q[q[:, 0] < 0] *= -1
    return q


def _bad_frames(cfg: PhantomConfig, session: int) -> dict[int, str]:
    n_bad = round(cfg.bad_frame_fraction * cfg.frame_count)
    if n_bad == 0:
        return {}
    pool = np.arange(2, cfg.frame_count - 2) if cfg.frame_count > 6 else np.arange(cfg.frame_count)
    n_bad = min(n_bad, len(pool))
    g = rng(cfg, STREAM_BAD + session)
    frames = np.sort(g.choice(pool, size=n_bad, replace=False))
    kinds = g.choice(["defocus", "black"], size=n_bad)
    return {int(f): str(k) for f, k in zip(frames, kinds, strict=True)}


STREAM_PHOTO = 50


def photometry(cfg: PhantomConfig, session: int) -> dict:
    """Per-session photometric draws (seeded); the nominal camera when photometric_variation
    is 0. white_balance: linear gain per RGB channel; exposure_bias: multiplies the
    auto-exposure target; autogain_alpha: weight of the new frame in the auto-exposure's
    geometric smoothing; flicker: std of a per-frame log-gain; vignetting_exponent: V =
    cos^p of the off-axis angle; falloff_exponent: E ~ cos(incidence) / distance^q."""
    v = cfg.photometric_variation
    if v == 0:
        return {"white_balance": [1.0, 1.0, 1.0], "exposure_bias": 1.0, "autogain_alpha": 0.5,
                "flicker": 0.0, "vignetting_exponent": 3.0, "falloff_exponent": 2.0,
                "variation": 0.0}
    g = rng(cfg, STREAM_PHOTO + session)
    wb = np.exp(g.normal(0, 0.06 * v, size=3))
    return {"white_balance": [float(x) for x in wb / np.exp(np.log(wb).mean())],
            "exposure_bias": float(np.exp(g.normal(0, 0.15 * v))),
            "autogain_alpha": float(np.clip(0.5 + g.uniform(-0.35, 0.35) * v, 0.1, 0.95)),
            "flicker": float(0.02 * v),
            "vignetting_exponent": float(np.clip(3.0 + g.uniform(-1.5, 2.0) * v, 0.5, 8.0)),
            "falloff_exponent": float(np.clip(2.0 + g.uniform(-0.4, 0.4) * v, 1.2, 2.8)),
            "variation": v}


def _exposures(renderer: Renderer, traj: Trajectory, target: float = EXPOSURE_TARGET,
               alpha: float = 0.5) -> np.ndarray:
    """Auto-exposure: a low-resolution pre-pass per frame, smoothed over time (geometric,
    weight ``alpha`` for the new frame) towards ``target``."""
    rg = renderer.rays
    step = max(1, rg.width // 80)
    sel = (np.arange(rg.height)[::step, None] * rg.width + np.arange(rg.width)[None, ::step]).ravel()
    low = RayGrid(len(range(0, rg.width, step)), len(range(0, rg.height, step)),
                  rg.dirs[sel], rg.pixel_angle[sel], rg.vignette[sel])
    out = np.empty(len(traj.centres))
    prev = None
    for k, (rot, c) in enumerate(zip(traj.rotations, traj.centres, strict=True)):
        tr = renderer.trace(rot, c, rays=low)
        e = renderer.irradiance(tr, rays=low)
        ideal = target / max(float(np.percentile(e, 60)) if len(e) else 1.0, 1e-12)
        cur = ideal if prev is None else float(np.exp(alpha * np.log(ideal) + (1 - alpha) * np.log(prev)))
        out[k] = prev = cur
    return out


def _motion_blur(cfg: PhantomConfig, camera: Camera, traj: Trajectory, centre_t: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame blur length (px) and angle (rad): image velocity of the aimed wall point."""
    n = len(traj.centres)
    if cfg.motion_blur_px <= 0 or n < 2:
        return np.zeros(n), np.zeros(n)
    p = traj.centres + np.nan_to_num(centre_t, nan=50.0)[:, None] * traj.rotations[:, :, 2]
    vel = np.zeros((n, 2))
    for k in range(n):
        a, b = max(0, k - 1), min(n - 1, k + 1)
        uv = [camera.project(((p[k] - traj.centres[j]) @ traj.rotations[j])[None])[0]
              for j in (a, b)]
        vel[k] = (uv[1] - uv[0]) / max(1, b - a)
    speed = np.linalg.norm(vel, axis=1)
    length = cfg.motion_blur_px * speed / max(float(speed.max()), 1e-9)
    return length, np.arctan2(vel[:, 1], vel[:, 0])


def _outside_circle(camera: Camera, share: float) -> np.ndarray | None:
    """(H, W) True outside the scope's round image of diameter ``share`` x the frame height,
    centred in the frame; None when the image fills the frame (``share`` 0)."""
    if share <= 0:
        return None
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    r = np.hypot(u - (camera.width - 1) / 2, v - (camera.height - 1) / 2)
    return r > share * camera.height / 2


def _write_poses(path: Path, traj: Trajectory) -> None:
    q = _quaternions(traj.rotations)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(POSE_COLUMNS)
        for k in range(len(q)):
            w.writerow([k, *(f"{x:.10f}" for x in q[k]), *(f"{x:.6f}" for x in traj.centres[k])])


def _write_lesions(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=LESION_COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6f}" if isinstance(v, float) else v) for k, v in r.items()})


def generate_session(out_dir: Path, session: int, cfg: PhantomConfig, camera: Camera) -> Path:
    """Render phantom ``session`` (1 or 2) into ``out_dir`` (written atomically).

    Files: video.mp4, poses.csv, camera.json, surface.ply, albedo.png, seen.png,
    lesions.csv, truth.json (see the package docstring for their conventions).

    ``cfg.lossless_video``: code the video with FFV1, lossless (~39 MB for 124 frames at 640x360,
    ~150 MB at 1280x720, in an .mp4 container that OpenCV/FFmpeg read) instead of MPEG-4
    part 2 (mp4v, ~40x smaller), whose fixed quantiser removes most of the mucosa's fine,
    low-contrast texture at the video's own pixel scale: at 640x360 that halves the SIFT
    matches between neighbouring frames and makes SfM unreliable (registration 40-90 %,
    trajectory errors 0.5-14 mm on seeds 7-10, varying from run to run; lossless: <= 0.3 mm,
    every frame).
    """
    if session not in (1, 2):
        raise InputError(f"phantom: session must be 1 or 2, got {session!r}")
    if camera.width < 16 or camera.height < 16:
        raise InputError(f"camera {camera.name!r}: image too small for the phantom")
    out_dir = Path(out_dir)
    t_start = time.perf_counter()
    given = camera
    shown = render_camera(cfg, camera)  # the video's camera
    camera = shown.scaled(cfg.render_scale) if cfg.render_scale < 1 else shown
    base = base_bladder(cfg)
    scene1 = base.scene()
    bladder = session_bladder(cfg, session)
    scene = scene1 if bladder is base else bladder.scene()
    cube = build_mucosa(cfg, base, scene1)
    lesions = place_lesions(cfg, base, scene1) if cfg.lesion_diameters_mm else []
    if lesions:
        paint_site_vessels(cube, lesions, base, scene1)
    if session == 2 and lesions:
        paint_lesions(cube, lesions, base, scene1)
    traj = make_trajectory(cfg, session, bladder, scene)
    n = cfg.frame_count
    photo = photometry(cfg, session)
    rays = pixel_rays(camera)
    if photo["vignetting_exponent"] != 3.0:
        rays.vignette = np.power(np.clip(rays.dirs[:, 2], 0, 1),
                                 np.float32(photo["vignetting_exponent"])).astype(np.float32)
    outside = _outside_circle(camera, cfg.image_circle)
    renderer = Renderer(camera, bladder, scene, cube, rays=rays,
                        falloff_exponent=photo["falloff_exponent"])
    axis_hit = cast(scene, traj.centres.astype(np.float32),
                    traj.rotations[:, :, 2].astype(np.float32))["t_hit"]
    exposure = _exposures(renderer, traj, EXPOSURE_TARGET * photo["exposure_bias"],
                          photo["autogain_alpha"])
    if photo["flicker"] > 0:
        exposure = exposure * np.exp(rng(cfg, STREAM_PHOTO + 2 + session).normal(
            0, photo["flicker"], size=len(exposure)))
    wb_display = np.power(np.array(photo["white_balance"], np.float32), np.float32(1 / GAMMA))
    blur_len, blur_ang = _motion_blur(cfg, camera, traj, axis_hit)
    blur_len = blur_len * cfg.render_scale  # motion_blur_px is in the video's pixels
    bad = _bad_frames(cfg, session)
    gain = cfg.session2_gain if session == 2 else 1.0
    atlas = Atlas(bladder, scene, cfg.atlas_height)
    optical = optical_blur_px(camera)
    threads = cfg.threads or min(2, os.cpu_count() or 1)
    cast_threads = 1 if threads > 1 else 0
    log.info("phantom session %d: %d frames %dx%d (rendered at %dx%d), %d threads (setup %.1f s)",
             session, n, shown.width, shown.height, camera.width, camera.height, threads,
             time.perf_counter() - t_start)

    def render(k: int) -> tuple[np.ndarray, dict, np.ndarray | None]:
        tr = renderer.trace(traj.rotations[k], traj.centres[k], nthreads=cast_threads)
        img = renderer.shade(tr, float(exposure[k]), gain, cfg.specular)
        if outside is not None:
            img[outside] = 0.0
        if photo["variation"] > 0:
            img = img * wb_display  # white balance on the linear signal, shown after gamma
        noise = np.random.default_rng(np.random.SeedSequence([cfg.seed, STREAM_NOISE + session, k]))
        out = finish(img, noise, cfg.noise_sigma, float(blur_len[k]), float(blur_ang[k]),
                     bad.get(k), optical)
        th = tr.t[tr.hit]
        stats = {"min": float(th.min()) if len(th) else float("nan"),
                 "median": float(np.median(th)) if len(th) else float("nan")}
        seen_idx = None
        if k not in bad:
            t_map = tr.t.reshape(camera.height, camera.width)
            if outside is not None:
                t_map = np.where(outside, np.nan, t_map)
            wall_t = tr.t[tr.wall]
            if len(wall_t):
                sub = np.flatnonzero(tr.wall)[::7]
                p = traj.centres[k] + tr.t[sub, None] * rotate(renderer.rays.dirs[sub], traj.rotations[k])
                rel = p - atlas.centre
                dirs = rel / np.linalg.norm(rel, axis=1, keepdims=True)
                seen_idx = atlas.visible(camera, traj.rotations[k], traj.centres[k], t_map, dirs,
                                          renderer.rays.max_radius)
        if camera is not shown:
            out = cv2.resize(out, (shown.width, shown.height), interpolation=cv2.INTER_LINEAR)
        return cv2.cvtColor(out, cv2.COLOR_RGB2BGR), stats, seen_idx

    seen = np.zeros(atlas.h * atlas.w, bool)
    dmin, dmed = np.zeros(n), np.zeros(n)
    codec = "FFV1" if cfg.lossless_video else "mp4v"
    t_render = time.perf_counter()
    with atomic_dir(out_dir) as tmp:
        writer = cv2.VideoWriter(str(tmp / "video.mp4"), cv2.VideoWriter_fourcc(*codec),
                                 float(cfg.fps), (shown.width, shown.height))
        if not writer.isOpened():
            raise StageError(f"phantom: cannot open an {codec} VideoWriter (OpenCV without FFMPEG?)")
        try:
            with ThreadPoolExecutor(max_workers=threads) as pool:
                for k, (frame, stats, seen_idx) in enumerate(pool.map(render, range(n))):
                    writer.write(frame)
                    dmin[k], dmed[k] = stats["min"], stats["median"]
                    if seen_idx is not None:
                        seen[seen_idx] = True
                    if (k + 1) % max(1, n // 10) == 0 or k + 1 == n:
                        log.info("rendered %d/%d frames (%.1f s)", k + 1, n,
                                 time.perf_counter() - t_render)
        finally:
            writer.release()
        render_s = {"render_seconds": round(time.perf_counter() - t_start, 2),
                    "frames_seconds": round(time.perf_counter() - t_render, 2),
                    "threads": threads}
        _write_poses(tmp / "poses.csv", traj)
        shown.save(tmp / "camera.json")
        nw = bladder.n_wall_verts
        vcol, _ = cube.sample(bladder.material[:nw])
        write_ply(tmp / "surface.ply", bladder.vertices[:nw], bladder.wall_triangles,
                  normals=bladder.normals[:nw], colors=np.clip(vcol + 0.5, 0, 255).astype(np.uint8),
                  comment="cystomap phantom wall, mm")
        albedo = atlas.albedo(cube)
        cv2.imwrite(str(tmp / "albedo.png"), cv2.cvtColor(albedo, cv2.COLOR_RGB2BGR))
        seen_img = (seen.reshape(atlas.h, atlas.w) * 255).astype(np.uint8)
        cv2.imwrite(str(tmp / "seen.png"), seen_img)
        rows = with_regions(lesion_rows(lesions, bladder), bladder) if session == 2 else []
        _write_lesions(tmp / "lesions.csv", rows)
        truth = _truth(cfg, session, shown, bladder, atlas, seen, traj, exposure,
                       blur_len / cfg.render_scale,
                       blur_ang, bad, gain, dmin, dmed, axis_hit, render_s, rows, optical)
        truth["video_codec"] = codec.lower()
        truth["lens"] = lens_truth(cfg, given, shown)
        truth["photometry"] = photo
        truth["texture"] = {"mode": cfg.texture_mode, "family": cfg.texture_family,
                            "params": cube.params.to_dict() if cube.params is not None else None,
                            "mosaic": cube.mosaic.to_dict() if cube.mosaic is not None else None}
        write_json(tmp / "truth.json", truth)
    log.info("phantom session %d written to %s in %.1f s (seen %.1f %%)", session, out_dir,
             time.perf_counter() - t_start, 100 * truth["seen_fraction"])
    return out_dir


def true_anatomy(bladder: Bladder) -> Anatomy:
    """The session's anatomical frame (world frame; see ``Bladder.anatomy``)."""
    a = bladder.anatomy
    return Anatomy(np.asarray(a["origin"]), np.asarray(a["neck"]), np.asarray(a["anterior"]),
                   "phantom truth: neck = aperture centre, anterior = world +y")


def with_regions(rows: list[dict], bladder: Bladder) -> list[dict]:
    """Lesion rows with their region, clock and distance from the neck (on the true wall,
    from the aperture centre)."""
    if not rows:
        return rows
    from cystomap.atlas.projection import SurfaceRays

    rays = SurfaceRays(bladder.wall_vertices, bladder.wall_triangles, bladder.barycentre)
    pts = np.array([[r["x"], r["y"], r["z"]] for r in rows], float)
    locs = locate(true_anatomy(bladder), pts, rays, neck_point=bladder.aperture_centre)
    return [{**r, **loc} for r, loc in zip(rows, locs, strict=True)]


def _truth(cfg: PhantomConfig, session: int, camera: Camera, bladder: Bladder, atlas: Atlas,
           seen: np.ndarray, traj: Trajectory, exposure: np.ndarray, blur_len: np.ndarray,
           blur_ang: np.ndarray, bad: dict[int, str], gain: float, dmin: np.ndarray,
           dmed: np.ndarray, axis_hit: np.ndarray, render_s: dict, rows: list[dict],
           optical_px: float) -> dict:
    ap_dir, ap_ang = aperture_cone(bladder)
    ap_az, ap_el = az_el(ap_dir)
    rim = bladder.vertices[bladder.rim]
    rot_steps = traj.rotation_steps_deg()
    deform = make_deformation(cfg).to_dict() if session == 2 and cfg.deformation > 0 else None
    r2 = lambda a: [round(float(x), 3) for x in a]  # noqa: E731
    return {
        "generator": "cystomap.phantom",
        "seed": cfg.seed,
        "session": session,
        "n_frames": cfg.frame_count,
        "fps": cfg.fps,
        "width": camera.width,
        "height": camera.height,
        "world_frame": (
            "mm; origin = session-1 barycentre; x = long axis of the bladder, z up (dome),"
            " aperture/urethra at the bottom along -z; session 2 shares the frame (deformed"
            " in place); camera poses camera-to-world, OpenCV camera axes"),
        "barycentre": [float(x) for x in bladder.barycentre],
        "barycentre_definition": "volume centroid of the wall with the aperture capped flat",
        "anatomy": {**true_anatomy(bladder).to_json(),
                    "neck_point": [float(x) for x in bladder.aperture_centre]},
        "extent_mm": wall_extent(bladder.wall_vertices),
        "bbox_mm": wall_bbox(bladder.wall_vertices),
        "size_mm": list(cfg.size_mm),
        "area_mm2": bladder.wall_area_mm2,
        "volume_ml": bladder.volume_mm3 / 1000.0,
        "seen_fraction": atlas.seen_fraction(seen),
        "seen_definition": (
            "area-weighted share of the wall (atlas pixels weighted by the wall area they"
            " show) inside the image and unoccluded in at least one good (not bad) frame"),
        "atlas": {
            "width": atlas.w, "height": atlas.h, "about": "barycentre",
            "column": "azimuth -180 + (j + 0.5) * 360 / width degrees",
            "row": "elevation 90 - (i + 0.5) * 180 / height degrees",
            "direction": "(cos el cos az, cos el sin az, sin el), world axes",
            "outside_wall": "aperture directions: albedo black, seen 0",
            "wall_area_mm2_from_atlas": float(atlas.area.sum()),
        },
        "aperture": {
            "diameter_mm": cfg.aperture_mm,
            "centre": [float(x) for x in rim.mean(0)],
            "axis_into_bladder": [float(x) for x in (bladder.barycentre - rim.mean(0))
                                  / np.linalg.norm(bladder.barycentre - rim.mean(0))],
            "azimuth_deg": float(ap_az), "elevation_deg": float(ap_el),
            "angular_radius_deg": ap_ang,
            "urethra_length_mm": cfg.urethra_length_mm,
        },
        "surface_ply": SURFACE_NOTE,
        "deformation": deform,
        "gain": gain,
        "bad_frames": [{"frame": k, "kind": v, "why": (
            "defocused (Gaussian blur, sigma 1.5 % of the width)" if v == "defocus"
            else "black (image x 0.03, e.g. scope against the wall)")} for k, v in bad.items()],
        "lesions": len(rows),
        "lesion_diameter_note": "diameter_mm is the painted (material) diameter; session-2"
                                " deformation stretches it by up to the deformation magnitude",
        "frames": {
            "distance_min_mm": r2(dmin),
            "distance_median_mm": r2(dmed),
            "distance_axis_mm": r2(np.nan_to_num(axis_hit, nan=-1.0)),
            "phase": traj.phase,
            "exposure": [float(f"{x:.6g}") for x in exposure],
            "motion_blur_px": r2(blur_len),
            "motion_blur_angle_deg": r2(np.degrees(blur_ang)),
            **({"motion": traj.motion} if traj.motion is not None else {}),
        },
        "trajectory": cfg.trajectory,
        "rotation_per_frame_deg": {"max": float(rot_steps.max()), "mean": float(rot_steps.mean())},
        "translation_per_frame_mm": {"max": float(traj.translation_steps_mm().max()),
                                     "mean": float(traj.translation_steps_mm().mean())},
        "image_model": (
            "pixel = albedo * (exposure * cos(incidence) / distance^2 * cos^3(off-axis))"
            f"^(1/2.2) * gain, optical blur sigma {optical_px:.3g} px (0.55 px at the 1280x720"
            " 76-degree camera: a fixed angle), + N(0, noise_sigma); light at the tip; albedo"
            " prefiltered by each pixel's footprint on the wall (mipmaps); albedo.png = the"
            " albedo of this model; with photometric_variation > 0 the exponents 2 and 3, the"
            " exposure target and smoothing and a per-channel white balance (linear) come from"
            " truth.json photometry"),
        **render_s,
        "render_seconds_note": "render_seconds = scene, texture, trajectory and all frames"
                               " (before writing the truth files); frames_seconds = frames only",
        "config": asdict(cfg),
    }
