"""Stage ``atlas``: the 2-D atlas of the whole wall, its coverage, and the textured 3-D model.

Inputs: the SfM model (poses, shared PINHOLE camera), the preprocessed colour frames and
field-of-view mask, and the surface mesh of the ``mesh`` stage. Two passes over the frames
(:mod:`cystomap.atlas.texture`): first depth maps, sharpness and coarse samples for the
exposure model and the robust per-cell brightness; then every frame adds its exposure-corrected
colours to the atlas pixels it sees (two-band blending, glints down-weighted and inpainted).

Outputs in ``out_dir`` (written atomically):

* ``atlas.png``: the wall about the mesh barycentre (equirectangular by default, see
  :mod:`cystomap.atlas.projection`), RGBA: alpha 255 where seen by at least one frame, else 0
  (colour 0);
* ``regions.png``: the atlas with the standard regions' grid, their names, clock positions and
  the orientation legend;
* ``coverage.png``: number of frames seeing each pixel (black = unseen, then viridis up to
  ``coverage_max_views``);
* ``atlas.json``: the projection contract (size, barycentre, axes, pixel ↔ point formulas),
  ``anatomy`` (the session's anatomical frame, :mod:`cystomap.anatomy`; the atlas axes are
  drawn from it), ``regions`` (area and seen share of each standard region),
  ``coverage_percent`` (share of the wall *area* seen, each pixel weighted by the area of its
  wall patch), views statistics, photometry, settings and timing;
* ``model.obj`` + ``model.mtl`` + ``texture.png`` and ``model.glb`` (glTF 2.0): the mesh with
  the atlas as texture (unseen wall flat grey), UVs from the atlas projection, cut at the seam
  and around the poles (:mod:`cystomap.atlas.model`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.anatomy import REGIONS, Anatomy, AnatomyHint, atlas_axes, estimate
from cystomap.atlas.model import uv_unwrap, write_glb, write_obj
from cystomap.atlas.projection import PROJECTIONS, Projection, SurfaceRays
from cystomap.atlas.regions import ORIENTATION_NOTE, region_overlay
from cystomap.atlas.texture import (
    Photometry,
    TextureSettings,
    View,
    ViewGeometry,
    WallSamples,
    _covariates,
    brightness_outlier_weight,
    cell_reference,
    fit_photometry,
    glint_weight,
    load_image,
    pyramid,
    sample_mip,
    sharpness,
    view_weights,
)
from cystomap.camera import opencv_calibration
from cystomap.errors import InputError, StageError
from cystomap.images import imwrite_rgb
from cystomap.mesh import load_reconstruction, read_mesh, volume_centroid
from cystomap.outputs import atomic_dir, software_versions, write_json
from cystomap.sfm.intrinsics import frames_dir

log = logging.getLogger(__name__)

EXPOSURE_MODES = ("model", "gain", "none")


@dataclass(frozen=True)
class AtlasConfig:
    """Settings of the ``atlas`` stage."""

    # Atlas projection: equirectangular (column → azimuth, row → elevation) or equal_area
    # (Lambert cylindrical equal-area: row → sin elevation, every pixel the same solid angle).
    projection: str = "equirectangular"
    # Atlas size in pixels (also the texture of the 3-D model).
    width: int = 2048
    height: int = 1024
    # A frame sees a wall point only when cos(angle between the wall normal and the view ray)
    # is at least this (defines coverage too; grazing views get little blending weight).
    min_cos_incidence: float = 0.02
    # Blending weight = cos(incidence)^a · (d_ref / distance)^b · sharpness^c · centrality
    # · mask-edge ramp; these are a, b, c.
    weight_cos_power: float = 2.0
    weight_distance_power: float = 2.0
    weight_sharpness_power: float = 1.0
    # The weight ramps from 0 at the field-of-view mask edge to full over this many pixels.
    edge_feather_px: float = 40.0
    # Occlusion test: depth map of the mesh per frame at this fraction of the frame size, and
    # the relative depth tolerance.
    occlusion_scale: float = 0.125
    occlusion_tolerance: float = 0.03
    # Exposure compensation from the overlaps: "model" (per-frame gain and illumination
    # falloff with distance, incidence and image radius), "gain" (per-frame gain only), "none".
    exposure: str = "model"
    # Two-band blending: detail from weights raised to this power (1 = plain weighted mean),
    # low frequencies (Gaussian sigma in atlas pixels) from the plain weighted mean.
    detail_power: float = 6.0
    base_sigma_px: float = 4.0
    # Specular glints: a sample whose darkest colour channel exceeds the frame's median by
    # more than this fraction loses weight (none left at twice the fraction); 0 = off.
    glint_rel: float = 0.2
    # View-dependent brightening (glints, flare): a sample brighter than the robust (median
    # over views) brightness of its coarse cell by more than this fraction loses weight
    # (almost none left at 2.5 times the fraction); 0 = off.
    outlier_rel: float = 0.12
    # Pixels that no frame shows free of glints (best view's glint/outlier weight below this)
    # are inpainted from their surroundings; 0 = off.
    inpaint_below: float = 0.3
    # Coarse cells (block × block atlas pixels) used to find which pixels a frame may see and
    # to estimate the exposure model.
    block: int = 8
    # Use at most this many frames (evenly spaced in name order); 0 = all.
    max_views: int = 0
    # Write the textured model (model.obj/.mtl, texture.png, model.glb).
    model: bool = True
    # The model's mesh is cut along meridians every this many degrees for the UVs.
    meridian_step_deg: float = 15.0
    # Grey level of the unseen wall in texture.png.
    unseen_grey: int = 96
    # coverage.png's colour scale saturates at this many views.
    coverage_max_views: int = 20
    # Frames processed concurrently (threads; numpy/OpenCV/open3d release the GIL).
    threads: int = 2
    # Decoded frames are kept in memory between the two passes when they fit in this many MB
    # (else they are read twice).
    frame_cache_mb: int = 1024
    # Atlas frame: "anatomical" = about the session's anatomical frame (cystomap.anatomy: neck
    # at the bottom, dome at the top, patient's right on the left), "model" = the SfM frame's
    # own axes.
    orientation: str = "anatomical"
    # The image's up direction while the scope enters, clockwise from anterior seen from the
    # neck (degrees; 0 = entered upright); the sessions sheet's entry_roll_deg overrides it.
    entry_roll_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.projection not in PROJECTIONS:
            known = ", ".join(PROJECTIONS)
            raise ValueError(f"projection {self.projection!r} is not one of {known}")
        if self.exposure not in EXPOSURE_MODES:
            known = ", ".join(EXPOSURE_MODES)
            raise ValueError(f"exposure {self.exposure!r} is not one of {known}")
        checks = {
            "width >= 16": self.width >= 16,
            "height >= 8": self.height >= 8,
            "0 <= min_cos_incidence < 1": 0 <= self.min_cos_incidence < 1,
            "weight powers >= 0": min(self.weight_cos_power, self.weight_distance_power,
                                      self.weight_sharpness_power) >= 0,
            "edge_feather_px >= 0": self.edge_feather_px >= 0,
            "0 < occlusion_scale <= 1": 0 < self.occlusion_scale <= 1,
            "occlusion_tolerance >= 0": self.occlusion_tolerance >= 0,
            "detail_power >= 1": self.detail_power >= 1,
            "base_sigma_px >= 0": self.base_sigma_px >= 0,
            "glint_rel >= 0": self.glint_rel >= 0,
            "outlier_rel >= 0": self.outlier_rel >= 0,
            "0 <= inpaint_below < 1": 0 <= self.inpaint_below < 1,
            "2 <= block <= 64": 2 <= self.block <= 64,
            "max_views >= 0": self.max_views >= 0,
            "1 <= meridian_step_deg <= 90": 1 <= self.meridian_step_deg <= 90,
            "0 <= unseen_grey <= 255": 0 <= self.unseen_grey <= 255,
            "coverage_max_views >= 1": self.coverage_max_views >= 1,
            "1 <= threads <= 64": 1 <= self.threads <= 64,
            "frame_cache_mb >= 0": self.frame_cache_mb >= 0,
            "orientation in (anatomical, model)": self.orientation in ("anatomical", "model"),
            "-360 <= entry_roll_deg <= 360": -360 <= self.entry_roll_deg <= 360,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"invalid atlas settings: need {', '.join(bad)}")

    def texture_settings(self) -> TextureSettings:
        return TextureSettings(
            min_cos_incidence=self.min_cos_incidence,
            weight_cos_power=self.weight_cos_power,
            weight_distance_power=self.weight_distance_power,
            weight_sharpness_power=self.weight_sharpness_power,
            edge_feather_px=self.edge_feather_px,
            occlusion_scale=self.occlusion_scale,
            occlusion_tolerance=self.occlusion_tolerance,
        )


# --------------------------------------------------------------------------- inputs


def load_views(
    sfm_dir: Path, preprocessed_dir: Path, max_views: int = 0
) -> tuple[list[View], np.ndarray]:
    """Registered frames with their colour files, and the field-of-view mask (bool)."""
    import cv2

    preprocessed_dir = frames_dir(sfm_dir, preprocessed_dir)  # undistorted if self-calibrated
    color_dir = preprocessed_dir / "color"
    if not color_dir.is_dir():
        raise InputError(f"{color_dir}: preprocessed colour frames not found")
    rec = load_reconstruction(sfm_dir)
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not images:
        raise InputError(f"{sfm_dir}: the COLMAP model has no registered image")
    mask_path = preprocessed_dir / "mask.png"
    mask = None
    if mask_path.is_file():
        mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise InputError(f"{mask_path}: cannot read image")
    views: list[View] = []
    missing: list[str] = []
    for im in images:
        path = color_dir / Path(im.name).name
        if not path.is_file():
            alt = sorted(color_dir.glob(Path(im.name).stem + ".*"))
            if not alt:
                missing.append(im.name)
                continue
            path = alt[0]
        if mask is None:
            first = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if first is None:
                raise InputError(f"{path}: cannot read image")
            mask = np.full(first.shape, 255, np.uint8)
        cam = rec.cameras[im.camera_id]
        model = str(cam.model.name if hasattr(cam.model, "name") else cam.model)
        if model not in ("PINHOLE", "SIMPLE_PINHOLE"):
            log.warning("%s: camera model %s; its distortion is ignored (frames should be "
                        "undistorted)", im.name, model)
        h, w = mask.shape
        k = opencv_calibration(cam, w, h)
        cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        views.append(View(im.name, np.asarray(cfw.rotation.matrix(), dtype=np.float64),
                          np.asarray(cfw.translation, dtype=np.float64).reshape(3), k, w, h, path))
    if missing:
        log.warning("%s: %d registered frame(s) without a colour file, e.g. %s", color_dir,
                    len(missing), missing[0])
    if not views:
        raise InputError(f"{color_dir}: none of the {len(images)} registered frames is there")
    if max_views and len(views) > max_views:
        keep = np.unique(np.linspace(0, len(views) - 1, max_views).round().astype(int))
        views = [views[i] for i in keep]
    assert mask is not None
    return views, mask > 127


# --------------------------------------------------------------------------- stage


def session_anatomy(sfm_dir: Path, bary: np.ndarray, rays: SurfaceRays,
                    hint: AnatomyHint) -> Anatomy:
    """The session's anatomical frame from its registered frames (in name = video order)."""
    rec = load_reconstruction(sfm_dir)
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    rots, cens = [], []
    for im in images:
        cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        r = np.asarray(cfw.rotation.matrix(), dtype=np.float64)
        rots.append(r.T)
        cens.append(-r.T @ np.asarray(cfw.translation, dtype=np.float64).reshape(3))
    return estimate([im.name for im in images], np.array(rots).reshape(-1, 3, 3),
                    np.array(cens).reshape(-1, 3), bary, rays, hint)


def build_atlas(
    sfm_dir: Path, preprocessed_dir: Path, mesh_ply: Path, out_dir: Path,
    cfg: AtlasConfig | None = None, anatomy: AnatomyHint | dict[str, Any] | None = None,
) -> Path:
    """Paint the atlas, measure coverage and write the textured model into ``out_dir``.

    ``anatomy``: the session's overrides of its anatomical frame (sessions sheet columns
    entry_roll_deg, neck_xyz, anterior_xyz; cfg.entry_roll_deg when it has none).
    """
    import cv2

    cfg = cfg or AtlasConfig()
    sfm_dir, preprocessed_dir = Path(sfm_dir), Path(preprocessed_dir)
    mesh_ply, out_dir = Path(mesh_ply), Path(out_dir)
    t0 = time.perf_counter()
    verts, faces = read_mesh(mesh_ply)
    bary = volume_centroid(verts, faces)
    rays = SurfaceRays(verts, faces, origin=bary)
    if not isinstance(anatomy, AnatomyHint):
        m = dict(anatomy or {})
        if m.get("entry_roll_deg") is None or m.get("entry_roll_deg") != m.get("entry_roll_deg"):
            m["entry_roll_deg"] = cfg.entry_roll_deg
        anatomy = AnatomyHint.from_mapping(m)
    frame = session_anatomy(sfm_dir, bary, rays, anatomy)
    axes = atlas_axes(frame) if cfg.orientation == "anatomical" else np.eye(3)
    proj = Projection(cfg.projection, cfg.width, cfg.height, bary, axes)
    views, mask = load_views(sfm_dir, preprocessed_dir, cfg.max_views)
    log.info("%d registered frames, mesh %d faces, atlas %s %dx%d", len(views), len(faces),
             cfg.projection, cfg.width, cfg.height)
    wall = WallSamples(proj, rays, cfg.block)
    if wall.hit.mean() < 0.99:
        log.warning("%s: %.1f%% of the atlas rays miss the mesh (not closed about its "
                    "barycentre?)", mesh_ply, 100 * (1 - wall.hit.mean()))
    if not wall.hit.any():
        raise StageError(f"{mesh_ply}: no ray from the barycentre meets the mesh")
    result = paint(views, mask, wall, rays, cfg)
    t_paint = time.perf_counter() - t0

    seen = result.n_views > 0
    area = wall.area
    total_area = float(area.sum())
    coverage = 100.0 * float(area[seen].sum()) / total_area
    h, w = cfg.height, cfg.width
    colour = np.clip(np.rint(result.colour), 0, 255).astype(np.uint8)
    atlas = np.zeros((h * w, 4), np.uint8)
    atlas[seen, :3] = colour[seen]
    atlas[seen, 3] = 255
    atlas = atlas.reshape(h, w, 4)
    views_seen = result.n_views[seen].astype(np.float64)
    region_names = frame.regions(proj.grid_directions().reshape(-1, 3) + bary)
    regions = {}
    for name in REGIONS:
        sel = region_names == name
        a = float(area[sel].sum())
        regions[name] = {"area_mm2": a, "seen_area_mm2": float(area[sel & seen].sum()),
                         "seen_percent": 100.0 * float(area[sel & seen].sum()) / max(a, 1e-12)}
    meta: dict[str, Any] = {
        **proj.to_json(),
        "orientation": (ORIENTATION_NOTE if cfg.orientation == "anatomical"
                        else "the SfM model frame's own axes (atlas.orientation: model)"),
        "anatomy": frame.to_json(),
        "regions": regions,
        "mesh": str(mesh_ply),
        "coverage_percent": coverage,
        "coverage": {
            "definition": "share of the wall area (each pixel weighted by the area of its wall "
                          "patch) seen by at least one registered frame",
            "wall_area_mm2": total_area,
            "seen_area_mm2": float(area[seen].sum()),
            "views_mean": float(np.average(views_seen, weights=area[seen])) if seen.any() else 0.0,
            "views_median": float(np.median(views_seen)) if seen.any() else 0.0,
            "views_max": int(views_seen.max()) if seen.any() else 0,
            "coverage_png": {"unseen": "black", "colormap": "viridis",
                             "max_views": cfg.coverage_max_views},
        },
        "atlas_png": "RGBA; alpha 255 = seen, 0 = unseen (colour 0)",
        "frames": {"registered": len(views), "contributing": int(result.contributing)},
        "glint_inpainted_percent": 100.0 * result.n_inpainted / max(int(seen.sum()), 1),
        "photometry": {
            "mode": cfg.exposure,
            "log_gain_min": float(result.photometry.gains.min()),
            "log_gain_max": float(result.photometry.gains.max()),
            "beta_log_distance": float(result.photometry.beta[0]),
            "beta_log_cos": float(result.photometry.beta[1]),
            "beta_radius2": float(result.photometry.beta[2]),
            "observations": int(result.n_photometric_obs),
        },
        "config": asdict(cfg),
    }
    with atomic_dir(out_dir) as tmp:
        imwrite_rgb(tmp / "atlas.png", atlas)
        imwrite_rgb(tmp / "regions.png", region_overlay(atlas, proj, frame,
                                                        cfg.orientation == "anatomical"))
        imwrite_rgb(tmp / "coverage.png", coverage_image(result.n_views.reshape(h, w),
                                                      cfg.coverage_max_views))
        if cfg.model:
            texture = np.full((h * w, 3), cfg.unseen_grey, np.uint8)
            texture[seen] = colour[seen]
            texture = texture.reshape(h, w, 3)
            ok, png = cv2.imencode(".png", np.ascontiguousarray(texture[..., ::-1]))
            if not ok:
                raise StageError("cannot encode texture.png")
            (tmp / "texture.png").write_bytes(png.tobytes())
            tm = uv_unwrap(verts, faces, proj, cfg.meridian_step_deg)
            write_obj(tmp, tm, "texture.png")
            write_glb(tmp / "model.glb", tm, png.tobytes())
            meta["model"] = {"obj": "model.obj", "mtl": "model.mtl", "texture": "texture.png",
                             "glb": "model.glb", "vertices": len(tm.vertices),
                             "faces": len(tm.faces), "max_u_span": tm.max_u_span(),
                             "uv": "u = (col + 0.5) / width, v = (row + 0.5) / height "
                                   "(glTF; OBJ vt = 1 - v)"}
        meta["seconds"] = {"paint": round(t_paint, 2),
                           "total": round(time.perf_counter() - t0, 2)}
        meta["software"] = software_versions()
        write_json(tmp / "atlas.json", meta)
    log.info("%s: coverage %.1f%% of the wall, %d frames contributed (%.1f s)", out_dir,
             coverage, result.contributing, time.perf_counter() - t0)
    return out_dir


def coverage_image(n_views: np.ndarray, max_views: int) -> np.ndarray:
    """RGB: black where unseen, viridis from 1 to ``max_views`` views."""
    import cv2

    level = np.clip(n_views.astype(np.float64) / max_views, 0, 1)
    grey = np.rint(40 + 215 * level).astype(np.uint8)
    rgb = cv2.applyColorMap(grey, cv2.COLORMAP_VIRIDIS)[..., ::-1]
    rgb[n_views == 0] = 0
    return np.ascontiguousarray(rgb)


# --------------------------------------------------------------------------- painting


@dataclass
class PaintResult:
    colour: np.ndarray  # (H·W, 3) float RGB 0..255
    n_views: np.ndarray  # (H·W,) frames seeing each pixel
    photometry: Photometry
    contributing: int
    n_photometric_obs: int
    n_inpainted: int = 0


def ordered_map(fn: Callable[[int], Any], n: int, workers: int) -> Iterator[Any]:
    """``fn(0) … fn(n-1)`` computed by ``workers`` threads (a few ahead), yielded in order.

    numpy, OpenCV and open3d release the GIL in the heavy work, so frames overlap.
    """
    if workers <= 1:
        for i in range(n):
            yield fn(i)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending = [pool.submit(fn, i) for i in range(min(n, 2 * workers))]
        for i in range(n):
            result = pending[i].result()
            pending[i] = None  # type: ignore[call-overload]
            if i + 2 * workers < n:
                pending.append(pool.submit(fn, i + 2 * workers))
            yield result


def paint(views: list[View], mask: np.ndarray, wall: WallSamples, rays: SurfaceRays,
          cfg: AtlasConfig) -> PaintResult:
    """Two passes over the frames: exposure model from the overlaps, then blending."""
    settings = cfg.texture_settings()
    geo = ViewGeometry(mask, settings)
    n_px = len(wall.hit)
    cells = np.flatnonzero(wall.hit[wall.cell_pixel])
    cell_px = wall.cell_pixel[cells]
    cell_size = np.where(np.isfinite(wall.cell_radius[cells]), wall.cell_radius[cells], 0) * 1.4

    def read(view: View) -> np.ndarray:
        img = load_image(view.path)
        if img.shape[:2] != mask.shape:
            raise InputError(f"{view.path}: size {img.shape[1]}x{img.shape[0]} differs from the "
                             f"mask {mask.shape[1]}x{mask.shape[0]}")
        return img

    def with_glint_weight(img: np.ndarray) -> np.ndarray:
        """BGR + a 4th channel: the glint weight (255 everywhere when glint_rel is 0)."""
        import cv2

        bgra = cv2.cvtColor(img, cv2.COLOR_BGR2BGRA)
        if cfg.glint_rel > 0:
            bgra[..., 3] = glint_weight(img, mask, cfg.glint_rel)
        return bgra

    # decoded frames (with their glint weight) are kept for pass 2 when they fit the budget
    cache = mask.size * 4 * len(views) <= cfg.frame_cache_mb * 2**20

    # ---- pass 1: depth maps, sharpness, coarse observations for the exposure model
    def survey(i: int) -> dict[str, Any]:
        view = views[i]
        img = read(view)
        depth = geo.depth_map(view, rays)
        out: dict[str, Any] = {"depth": depth, "sharp": sharpness(img, mask)}
        img4 = with_glint_weight(img)
        if cache:
            out["image"] = img4
        o = geo.observe(view, wall, cell_px, depth)
        ok = o["ok"]
        if ok.any():
            oo = {k: a[ok] for k, a in o.items()}
            level = np.log2(np.maximum(view.K[0, 0] * cell_size[ok] / oo["dist"], 1.0))
            bgrw = sample_mip(pyramid(img4, 6), oo["u"], oo["v"], level)
            grey = (bgrw[:, 0] + bgrw[:, 1] + bgrw[:, 2]) / 3
            out.update(cell=cells[ok], obs=oo, logi=np.log(grey + 1.0),
                       w=view_weights(oo, view, settings, 1.0, 1.0) * bgrw[:, 3] / 255.0)
        return out

    t0 = time.perf_counter()
    surveys = list(ordered_map(survey, len(views), cfg.threads))
    depths = [sv["depth"] for sv in surveys]
    images = [sv.pop("image", None) for sv in surveys]
    sharp = np.array([sv["sharp"] for sv in surveys])
    observed = [i for i, sv in enumerate(surveys) if "cell" in sv]
    log.info("pass 1 (depth maps, exposure samples) over %d frames: %.1f s", len(views),
             time.perf_counter() - t0)
    dist_ref = (float(np.median(np.concatenate([surveys[i]["obs"]["dist"] for i in observed])))
                if observed else 1.0)
    med_sharp = float(np.median(sharp[sharp > 0])) if (sharp > 0).any() else 1.0
    sharp_rel = np.clip(sharp / max(med_sharp, 1e-12), 0.1, 4.0)
    n_obs = int(sum(len(surveys[i]["cell"]) for i in observed))
    n_cells = len(wall.cell_pixel)
    photometry = Photometry.identity(len(views), dist_ref)
    ref_px: np.ndarray | None = None  # robust log brightness of each coarse cell
    if n_obs:
        o_cell = np.concatenate([surveys[i]["cell"] for i in observed])
        o_frame = np.concatenate([np.full(len(surveys[i]["cell"]), i) for i in observed])
        o_logi = np.concatenate([surveys[i]["logi"] for i in observed]).astype(np.float64)
        o_cov = np.concatenate([_covariates(surveys[i]["obs"], views[i], dist_ref)
                                for i in observed]).astype(np.float64)
        o_w = np.concatenate([surveys[i]["w"] for i in observed]).astype(np.float64) + 1e-6
        if cfg.exposure != "none":
            photometry = fit_photometry(o_cell, o_frame, o_logi, o_cov, o_w, len(views),
                                        dist_ref, illumination=cfg.exposure == "model")
            log.info("photometry: log gains %.2f…%.2f, beta %s (%d observations)",
                     photometry.gains.min(), photometry.gains.max(),
                     np.round(photometry.beta, 3).tolist(), n_obs)
        if cfg.outlier_rel > 0:
            ref_px = cell_reference(o_cell, o_frame, o_logi, o_cov, o_w, photometry,
                                    n_cells).astype(np.float32)
    del surveys
    # per pixel: its coarse cell (for the reference brightness and the cell footprint)
    w_atlas = cfg.width
    nbx = -(-w_atlas // cfg.block)
    pix = np.arange(n_px)
    cell_of = ((pix // w_atlas) // cfg.block) * nbx + (pix % w_atlas) // cfg.block
    cell_size_px = (np.where(np.isfinite(wall.cell_radius), wall.cell_radius, 0) * 1.4)[cell_of]
    cell_size_px = cell_size_px.astype(np.float32)
    del pix

    # ---- pass 2: blend
    pix_area = wall.area.astype(np.float32)

    def colours(i: int) -> tuple[np.ndarray, ...] | None:
        view = views[i]
        img4 = images[i]
        images[i] = None  # free as we go
        px = np.sort(wall.candidates(view))  # raster order: cache-friendly gathers/scatters
        if len(px) == 0:
            return None
        o = geo.observe(view, wall, px, depths[i])
        ok = o["ok"]
        if not ok.any():
            return None
        if img4 is None:
            img4 = with_glint_weight(read(view))
        px = px[ok]
        oo = {k: a[ok] for k, a in o.items()}
        wt = view_weights(oo, view, settings, float(sharp_rel[i]), dist_ref)
        # footprint of an atlas pixel in image pixels → pyramid level (anti-aliasing)
        foot = np.float32(view.K[0, 0]) * np.sqrt(pix_area[px] * np.clip(oo["cos"], 0.05, 1)) \
            / oo["dist"]
        level = np.log2(np.maximum(foot, 1.0))
        coarse = np.log2(np.maximum(np.float32(view.K[0, 0]) * cell_size_px[px] / oo["dist"],
                                    1.0))
        pyr = pyramid(img4, int(np.ceil(max(level.max(), coarse.max()))) + 1)
        bgrw = sample_mip(pyr, oo["u"], oo["v"], level)
        corr = photometry.correction(i, oo, view)
        bgr = bgrw[:, :3] * corr[:, None]
        clean = np.maximum(bgrw[:, 3] / np.float32(255.0), np.float32(1e-3))
        if ref_px is not None:
            ref = ref_px[cell_of[px]]
            known = np.isfinite(ref)
            lum = sample_mip(pyr, oo["u"][known], oo["v"][known], coarse[known])[:, :3]
            grey = (lum[:, 0] + lum[:, 1] + lum[:, 2]) / 3
            ratio = (grey + 1.0) * corr[known] / np.exp(ref[known])
            clean[known] *= brightness_outlier_weight(ratio, cfg.outlier_rel)
        wt = wt * clean
        return px, wt, wt ** np.float32(cfg.detail_power), bgr, clean

    t0 = time.perf_counter()
    # rows: weight, weight·R, weight·G, weight·B (soft weights, then detail weights)
    soft_acc = np.zeros((4, n_px), np.float32)
    det_acc = np.zeros((4, n_px), np.float32)
    n_views = np.zeros(n_px, np.uint16)
    best_clean = np.zeros(n_px, np.float32)
    contributing = 0
    for res in ordered_map(colours, len(views), cfg.threads):
        if res is None:
            continue
        px, wt, wd, bgr, clean = res
        contributing += 1
        n_views[px] += 1
        best_clean[px] = np.maximum(best_clean[px], clean)
        for acc, ww in ((soft_acc, wt), (det_acc, wd)):
            acc[0, px] += ww
            for ch in range(3):
                acc[1 + ch, px] += ww * bgr[:, 2 - ch]  # BGR → RGB
    log.info("pass 2 (blending) over %d frames: %.1f s", len(views), time.perf_counter() - t0)
    seen = n_views > 0
    soft = (soft_acc[1:] / np.maximum(soft_acc[0], 1e-30)).T
    det = (det_acc[1:] / np.maximum(det_acc[0], 1e-30)).T
    ok_det = seen & (det_acc[0] > 0)
    det[~ok_det] = soft[~ok_det]
    if cfg.base_sigma_px > 0 and cfg.detail_power > 1:
        h, w = cfg.height, cfg.width
        m = seen.reshape(h, w)
        low_soft = masked_blur(soft.reshape(h, w, 3), m, cfg.base_sigma_px)
        low_det = masked_blur(det.reshape(h, w, 3), m, cfg.base_sigma_px)
        colour = (low_soft + det.reshape(h, w, 3) - low_det).reshape(-1, 3)
    else:
        colour = det if cfg.detail_power > 1 else soft
    colour[~seen] = 0
    n_inpainted = 0
    if cfg.inpaint_below > 0:
        glinted = seen & (best_clean < cfg.inpaint_below)
        n_inpainted = int(glinted.sum())
        if n_inpainted:
            colour = inpaint(colour, glinted, seen, cfg.height, cfg.width)
    return PaintResult(colour, n_views, photometry, contributing, n_obs, n_inpainted)


def inpaint(colour: np.ndarray, holes: np.ndarray, seen: np.ndarray, h: int, w: int) -> np.ndarray:
    """Fill ``holes`` (flat pixel mask) from the seen pixels around them (Telea, wrapping)."""
    import cv2

    pad = 16
    base = colour.copy()
    if (~seen).any():  # unseen pixels are no source: give them the mean colour, not black
        base[~seen] = colour[seen & ~holes].mean(axis=0) if (seen & ~holes).any() else 128
    img = np.clip(np.rint(base), 0, 255).astype(np.uint8).reshape(h, w, 3)
    holes2 = holes.reshape(h, w).astype(np.uint8)
    img = cv2.copyMakeBorder(img, 0, 0, pad, pad, cv2.BORDER_WRAP)
    holes2 = cv2.copyMakeBorder(holes2, 0, 0, pad, pad, cv2.BORDER_WRAP)
    filled = cv2.inpaint(img, holes2, 5, cv2.INPAINT_TELEA)[:, pad:-pad].reshape(-1, 3)
    out = colour.copy()
    out[holes] = filled[holes]
    return out


def masked_blur(img: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised Gaussian blur over ``mask`` (wrapping around in azimuth)."""
    import cv2

    pad = max(1, math.ceil(3 * sigma))
    m = mask.astype(np.float32)
    x = img.astype(np.float32) * m[..., None]

    def blur(a: np.ndarray) -> np.ndarray:
        a = cv2.copyMakeBorder(a, 0, 0, pad, pad, cv2.BORDER_WRAP)
        a = cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        return a[:, pad:-pad]

    num = blur(x)
    den = blur(m)
    return num / np.maximum(den, 1e-6)[..., None]
