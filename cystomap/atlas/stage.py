"""Stage ``atlas``: the 2-D atlas of the whole wall, its coverage, and the textured 3-D model.

Inputs: the SfM model (poses, shared PINHOLE camera), the preprocessed colour frames and
field-of-view mask, and the surface mesh of the ``mesh`` stage. Two passes over the frames
(:mod:`cystomap.atlas.texture`): first depth maps, sharpness and coarse samples for the
exposure model and the robust per-cell brightness; then every frame adds its exposure-corrected
colours to the atlas pixels it sees (two-band blending, glints down-weighted and inpainted;
pixels the preprocess stage found clipped, ``clipped/``, given no weight, and wall that every
frame showed clipped left unseen: it has no colour to give).

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
  wall patch), views statistics, ``clipped_only_percent`` (share of the wall's pixels left
  unseen because every frame showing them had them clipped), photometry, settings and timing;
* ``model.obj`` + ``model.mtl`` + ``texture.png`` and ``model.glb`` (glTF 2.0): the mesh with
  the atlas as texture (unseen wall flat grey), UVs from the atlas projection, cut at the seam
  and around the poles (:mod:`cystomap.atlas.model`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.anatomy import REGIONS, Anatomy, AnatomyHint, atlas_axes, estimate
from cystomap.atlas.config import AtlasConfig
from cystomap.atlas.model import uv_unwrap, write_glb, write_obj
from cystomap.atlas.paint import drop_overexposed, paint
from cystomap.atlas.projection import Projection, SurfaceRays
from cystomap.atlas.regions import ORIENTATION_NOTE, region_overlay
from cystomap.atlas.texture import (
    WallSamples,
)
from cystomap.errors import StageError
from cystomap.geometry.trimesh import volume_centroid
from cystomap.images import imwrite_rgb
from cystomap.io.colmap import camera_centres, load_reconstruction, registered_images
from cystomap.io.ply import read_mesh
from cystomap.io.views import load_views
from cystomap.outputs import atomic_dir, software_versions, write_json

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- stage


def session_anatomy(sfm_dir: Path, bary: np.ndarray, rays: SurfaceRays,
                    hint: AnatomyHint) -> Anatomy:
    """The session's anatomical frame from its registered frames (in name = video order)."""
    images = registered_images(load_reconstruction(sfm_dir))
    rots, cens = camera_centres(images)
    return estimate([im.name for im in images], rots, cens, bary, rays, hint)


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
    registered = len(views)
    views = drop_overexposed(views, mask, cfg.max_clipped)
    log.info("%d registered frames, mesh %d faces, atlas %s %dx%d", registered, len(faces),
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
        "frames": {"registered": registered, "overexposed": registered - len(views),
                   "contributing": int(result.contributing)},
        "glint_inpainted_percent": 100.0 * result.n_inpainted / max(int(seen.sum()), 1),
        "clipped_only_percent": 100.0 * result.n_clipped_only
        / max(int(seen.sum()) + result.n_clipped_only, 1),
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


