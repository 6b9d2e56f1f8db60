"""Stage ``compare``: co-register two sessions, difference their textures, find the changes.

Outputs in ``out_dir`` (written atomically, all or nothing):

* ``registration.json``: ``registered`` (and ``reason`` when not), point and match counts,
  inliers, the similarity A → B (``p_B = scale · R p_A + t``), the spline (smoothing chosen
  by cross-validation, its scores), residuals (mm) of the inliers before and after the
  spline (and held out), the dense flow correction;
* ``changes.csv``: one row per changed region (header only when none or not registered):
  ``id, x, y, z`` (centroid on session B's wall, B's model frame, mm), ``azimuth_deg,
  elevation_deg`` (about B's atlas barycentre, B's atlas axes), ``area_mm2`` (wall area),
  ``diameter_mm`` (sqrt(4 area / π)), ``mean_difference`` (mean colour difference, 0-255 RGB
  units), ``score`` (largest ratio of its peak significance or excess mass to the level at
  which ``false_alarm_rate`` null regions are expected, > 1), ``expected_false`` (expected
  number of regions at least this strong in the pair had nothing changed), ``mass`` (excess
  significance mass above the candidate level, noise units × mm²),
  ``peak_significance`` (99th percentile), ``mean_significance`` (noise units), ``atlas_col, atlas_row``
  (centroid in B's atlas.png), ``pixels`` (comparison-grid pixels), and the checks it
  passed: ``inconsistency`` (photo-consistency in B's frames, empty if not tested),
  ``enclosed`` (share of a ring around it compared), ``luminance_a``/``luminance_b``
  (relative to the compared wall), ``point_distance_mm`` (to the nearest SfM points),
  ``elongation`` (length / width), ``observed_share`` (share of the area both sessions
  saw; below 1 when a strip of unseen wall through the region was bridged), ``delta_e``
  (CIE76 ΔE*ab between A's and B's mean colours over the region), ``local_delta_e`` (the
  same of the region's mean colour relative to its ring's, on the atlases) and
  ``frame_local_delta_e`` (the same measured in the frames that saw the site, empty if not
  measured; the one ``min_local_delta_e`` applies to when present); then where it is in B's
  anatomical frame (:mod:`cystomap.anatomy`, from B's atlas.json): ``region`` (standard
  bladder region), ``clock`` (o'clock seen from the neck, 12 = anterior) and
  ``distance_from_neck_mm`` (on the wall), ``straddles`` (the other regions its extent covers
  when it lies on a border, "; "-joined; :data:`cystomap.anatomy.STRADDLE_RULE`); sorted by
  score;
* ``difference.png``: on the comparison grid (B's atlas projection, pixels of about
  ``grid_mm``), RGB 128 + (B − A) per channel after illumination matching: 50 % grey = no
  change, black = not compared (not seen by both, or far from every inlier match);
* ``significance.png``: the per-pixel significance (grey = candidate level × 2 saturates;
  red = above the candidate level, the clusters tested against the pair's null), black = not
  compared;
* ``changes.png``: B's atlas with the regions outlined (numbered by ``id``);
* ``changes.glb``: B's textured model (glTF 2.0) with the regions tinted and outlined;
* ``side_by_side.png``: A's atlas (left) and B's atlas (right), for manual comparison;
* ``landmarks.csv`` and ``landmarks.png`` when landmarks are given (A → B, see
  :mod:`cystomap.compare.landmarks`);
* ``findback.csv`` and ``findback/``: per change, the frames of B that see it best and the
  frames of A that saw the same site (video frame index and time), and crops of both atlases
  and of the best original frame of each session (see :mod:`cystomap.compare.findback`);
* ``compare.json``: summary (registered, counts, threshold and noise level, regions
  dropped by each check, compared area, dense-flow correction, directions of the bladder
  neck (``opening_directions``), timings, settings).

When the sessions cannot be co-registered the stage still succeeds: ``registration.json``
says ``registered: false`` with the reason, ``changes.csv`` is empty (header only) and
``side_by_side.png`` shows both atlases.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.anatomy import ANATOMY_COLUMNS, Anatomy, locate
from cystomap.compare.changes import CHANGE_COLUMNS, Region, detect
from cystomap.compare.config import CompareConfig
from cystomap.compare.difference import (
    AtlasSampler,
    SessionAtlas,
    compose,
    compute_difference,
    difference_image,
    painted_b,
    refine_flow,
    wall_grid,
    warp_points,
)
from cystomap.compare.features import point_features
from cystomap.compare.findback import FindBack, find_back
from cystomap.compare.images import (
    _write_csv,
    _write_model,
    draw_landmarks,
    outline_atlas,
    region_masks,
    side_by_side,
    significance_image,
)
from cystomap.compare.landmarks import LANDMARK_COLUMNS, map_landmarks
from cystomap.compare.neck import neck_angles
from cystomap.compare.null import changed_mask
from cystomap.compare.registration import Registration, register
from cystomap.compare.relief import raise_centroids
from cystomap.errors import InputError
from cystomap.images import imwrite_rgb
from cystomap.outputs import atomic_dir, read_json_object, software_versions, write_json

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class SessionPaths:
    """The outputs of one session the comparison reads."""

    sfm: Path  # COLMAP model (sfm stage)
    preprocessed: Path  # enhanced/ frames (preprocess stage)
    mesh: Path  # surface.ply (mesh stage)
    atlas: Path  # atlas.png + atlas.json (atlas stage)
    frames: Path | None = None  # frames/ (frames stage: original frames, frames.csv); optional

    @classmethod
    def from_root(cls, root: Path) -> SessionPaths:
        """The standard layout: ``root/{sfm,preprocessed,mesh/surface.ply,atlas}``."""
        root = Path(root)
        return cls(root / "sfm", root / "preprocessed", root / "mesh" / "surface.ply",
                   root / "atlas", root / "frames")

    def check(self, what: str) -> None:
        for p, kind in ((self.sfm, "SfM model directory"), (self.preprocessed,
                        "preprocessed directory"), (self.atlas, "atlas directory")):
            if not Path(p).is_dir():
                raise InputError(f"session {what}: {kind} {p} not found")
        if not Path(self.mesh).is_file():
            raise InputError(f"session {what}: mesh {self.mesh} not found")


def compare_sessions(a: SessionPaths, b: SessionPaths, out_dir: Path,
                     cfg: CompareConfig | None = None, landmarks: Iterable[Any] = ()) -> Path:
    """Compare session A (earlier) with session B; write the outputs into ``out_dir``.

    Changes are what B shows and A did not, measured on B's wall in B's model frame.
    """
    cfg = cfg or CompareConfig()
    a, b = _paths(a), _paths(b)
    a.check("A")
    b.check("B")
    out_dir = Path(out_dir)
    landmarks = list(landmarks)
    t0 = time.perf_counter()
    times: dict[str, float] = {}

    def lap(name: str, since: float) -> float:
        now = time.perf_counter()
        times[name] = round(now - since, 3)
        return now

    t = t0
    # the atlases load (PNG decoding, ray-casting scenes) while the descriptors are computed
    loader = ThreadPoolExecutor(max_workers=1)
    atlases = loader.submit(lambda: (SessionAtlas.load(a.atlas, a.mesh),
                                     SessionAtlas.load(b.atlas, b.mesh)))
    loader.shutdown(wait=False)
    fa = point_features(a.sfm, a.preprocessed, cfg.keypoint_size_mm, cfg.min_track_length,
                        cfg.max_reprojection_error_px, cfg.max_observations, cfg.threads,
                        cfg.max_points)
    fb = point_features(b.sfm, b.preprocessed, cfg.keypoint_size_mm, cfg.min_track_length,
                        cfg.max_reprojection_error_px, cfg.max_observations, cfg.threads,
                        cfg.max_points)
    t = lap("descriptors", t)
    reg = register(fa.xyz, fa.desc, fb.xyz, fb.desc, cfg)
    t = lap("registration", t)
    atlas_a, atlas_b = atlases.result()
    t = lap("load_atlases", t)
    reg_json = reg.to_json()
    reg_json["descriptors"] = {
        "a": {"points_in_model": fa.n_points_model, "described": len(fa.ids),
              "frames": fa.n_images},
        "b": {"points_in_model": fb.n_points_model, "described": len(fb.ids),
              "frames": fb.n_images},
        "keypoint_size_mm": cfg.keypoint_size_mm}
    summary: dict[str, Any] = {"session_a": _describe(a), "session_b": _describe(b),
                               "registered": reg.registered}
    flags = sfm_flags(a, b)
    if flags:
        summary["sfm_flags"] = flags
    short = sfm_short(a, b)
    if short:
        summary["sfm_short"] = short
    regions: list[Region] = []
    diff = None
    det_info: dict[str, Any] = {}
    found = FindBack()
    if reg.registered:
        try:
            neck_rules = (cfg.opening_deg > 0, cfg.neck_levelling, cfg.neck_ratio,
                          cfg.neck_chroma)
            openings = (opening_directions(a, b, atlas_a, atlas_b, reg) if any(neck_rules)
                        else np.zeros((0, 3)))
            diff, grid_info = _difference(atlas_a, atlas_b, reg, cfg, openings)
        except InputError as exc:  # nothing seen by both: say so, do not crash
            reg.registered = False
            reg.reason = f"co-registered, but {exc}"
            reg_json.update(registered=False, reason=reg.reason)
            summary["registered"] = False
        else:
            reg_json["dense_flow"] = grid_info.pop("flow", {"flow": False})
            a_points = grid_info.pop("a_points")
            t = lap("difference", t)
            verify = None
            if cfg.max_inconsistency > 0 or cfg.local_colour_in_frames:
                verify = _consistency_check(a, b, diff, atlas_a, atlas_b, a_points, reg, cfg)
            summary["opening_directions"] = openings.tolist()
            regions, det_info = detect(diff, cfg, atlas_b.proj, atlas_b.rays, verify, openings)
            regions = raise_centroids(regions, fb.kept_xyz, atlas_b.proj.barycentre,
                                      atlas_b.rays, cfg)
            t = lap("changes", t)
            summary.update(grid_info)
            found = find_back(regions, diff.grid, a_points, atlas_a, atlas_b, a, b,
                              cfg.findback_frames, cfg.findback_crop_px, cfg.seed)
            t = lap("findback", t)
    if not reg.registered:
        log.warning("compare: the sessions could not be co-registered: %s. No changes are "
                    "reported; side_by_side.png shows both atlases for manual comparison.",
                    reg.reason)
        summary["reason"] = reg.reason
    lm_rows = map_landmarks(landmarks, atlas_a, atlas_b, reg) if landmarks else []

    with atomic_dir(out_dir) as tmp:
        write_json(tmp / "registration.json", reg_json)
        _write_csv(tmp / "changes.csv", CHANGE_COLUMNS + ANATOMY_COLUMNS + ("straddles",),
                   with_anatomy([g.row() for g in regions], atlas_b, sized=True))
        found.write(tmp)
        imwrite_rgb(tmp / "side_by_side.png", side_by_side(atlas_a.rgba, atlas_b.rgba))
        if diff is not None:
            imwrite_rgb(tmp / "difference.png", difference_image(diff))
            imwrite_rgb(tmp / "significance.png",
                     significance_image(diff.significance, diff.joint, det_info["threshold"]))
            masks = region_masks(regions, diff.grid.shape, atlas_b.proj)
            imwrite_rgb(tmp / "changes.png", outline_atlas(atlas_b.rgba, masks, regions, cfg))
            if cfg.model:
                _write_model(tmp / "changes.glb", atlas_b, masks, cfg)
        if landmarks:
            _write_csv(tmp / "landmarks.csv", LANDMARK_COLUMNS + ANATOMY_COLUMNS,
                       with_anatomy(lm_rows, atlas_b))
            imwrite_rgb(tmp / "landmarks.png", draw_landmarks(atlas_b.rgba, lm_rows))
        times["total"] = round(time.perf_counter() - t0, 3)
        summary.update(
            changes=len(regions),
            detection={k: v for k, v in det_info.items()},
            landmarks=len(lm_rows),
            findback=found.info,
            seconds=times,
            config=asdict(cfg),
        )
        write_json(tmp / "compare.json", {**summary, "software": software_versions()})
    log.info("compare: %s, %d change(s) in %.1f s -> %s",
             "registered" if reg.registered else "NOT registered", len(regions),
             times["total"], out_dir)
    return out_dir


# --------------------------------------------------------------------------- steps


def _paths(p: Any) -> SessionPaths:
    if isinstance(p, SessionPaths):
        return SessionPaths(Path(p.sfm), Path(p.preprocessed), Path(p.mesh), Path(p.atlas),
                            None if p.frames is None else Path(p.frames))
    if isinstance(p, str | Path):
        return SessionPaths.from_root(Path(p))
    raise InputError(f"expected SessionPaths or a session directory, got {p!r}")


def _quality(p: SessionPaths) -> dict[str, Any]:
    """A session's sfm/quality.json ({} when it has none: an older or foreign model)."""
    path = Path(p.sfm) / "quality.json"
    return read_json_object(path) if path.is_file() else {}


def sfm_flags(a: SessionPaths, b: SessionPaths) -> dict[str, str]:
    """Sessions whose SfM self-check flagged their model (sfm/quality.json ``consistency``:
    drift, rotation drift, contradicted frame pairs), by "a"/"b", with the check's reason.
    Such a model still reaches the comparison (the checks warn by default), and changes
    measured against it may be false or misplaced: compare says so in its log and
    compare.json, and the report beside the comparison."""
    out = {}
    for key, p in (("a", a), ("b", b)):
        c = _quality(p).get("consistency")
        if isinstance(c, dict) and c.get("consistent") is False:
            out[key] = str(c.get("reason") or "flagged by the self-check")
            log.warning("compare: session %s's SfM model was flagged by its self-check (%s): "
                        "changes measured against it may be false or misplaced", key.upper(),
                        out[key])
    return out


def sfm_short(a: SessionPaths, b: SessionPaths) -> dict[str, str]:
    """Sessions whose SfM model holds fewer than the stage's ``retry_registered_share`` of
    their frames (sfm/quality.json ``short_model``), by "a"/"b", in words. The wall only the
    missing frames filmed is absent from that session's mesh and atlas: a change there cannot
    be found, and compare says so in its log and compare.json, and the report beside the
    comparison."""
    out = {}
    for key, p in (("a", a), ("b", b)):
        s = _quality(p).get("short_model")
        if isinstance(s, dict) and s.get("frames_with_features"):
            n, r = int(s["frames_with_features"]), int(s.get("registered") or 0)
            out[key] = f"its model holds only {r} of the {n} frames with features ({100 * r / n:.0f} %)"
            log.warning("compare: session %s: %s: changes on wall that only the missing frames "
                        "filmed cannot be found", key.upper(), out[key])
    return out


def _describe(p: SessionPaths) -> dict[str, str]:
    return {k: str(v) for k, v in asdict(p).items()}


def grid_scale(atlas: SessionAtlas, grid_mm: float) -> float:
    """Scale of B's atlas giving equator pixels of about ``grid_mm`` on the wall."""
    if grid_mm <= 0:
        return 1.0
    p = atlas.proj
    az = np.linspace(-math.pi, math.pi, 72, endpoint=False)
    d = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], axis=1) @ p.axes
    t, _ = atlas.rays.cast(p.barycentre, d)
    t = t[np.isfinite(t)]
    radius = float(np.median(t)) if len(t) else float(
        np.median(np.linalg.norm(atlas.vertices - p.barycentre, axis=1)))
    width = 2 * math.pi * radius / grid_mm
    width = min(max(width, 64.0), 4096.0)
    return width / p.width


def _outside_cameras(sfm_dir: Path, atlas: SessionAtlas, rel: float = 0.95) -> np.ndarray:
    """Centres (k, 3) of registered frames at or beyond the session's wall (radially from
    its barycentre): the scope entering through the bladder neck."""
    from cystomap.io.colmap import load_reconstruction

    rec = load_reconstruction(sfm_dir)
    c = np.array([im.projection_center() for im in rec.images.values() if im.has_pose],
                 dtype=np.float64).reshape(-1, 3)
    if not len(c):
        return c
    v = c - atlas.proj.barycentre
    r = np.linalg.norm(v, axis=1)
    t, _ = atlas.rays.cast(atlas.proj.barycentre, v / np.maximum(r, 1e-12)[:, None])
    return c[np.isfinite(t) & (r >= rel * t)]


def opening_directions(a: SessionPaths, b: SessionPaths, atlas_a: SessionAtlas,
                       atlas_b: SessionAtlas, reg: Registration) -> np.ndarray:
    """Unit directions (k, 3), from B's barycentre in B's frame, of the cameras of either
    session at or beyond the wall (A's through the A → B warp)."""
    pts = [_outside_cameras(b.sfm, atlas_b)]
    outside_a = _outside_cameras(a.sfm, atlas_a)
    if len(outside_a):
        pts.append(reg.warp_ab(outside_a))
    p = np.vstack(pts) - atlas_b.proj.barycentre
    return p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)


def _difference(atlas_a: SessionAtlas, atlas_b: SessionAtlas, reg: Registration,
                cfg: CompareConfig, openings: np.ndarray | None = None,
                ) -> tuple[Any, dict[str, Any]]:
    scale = grid_scale(atlas_b, cfg.grid_mm)
    proj_g, rgba_b = atlas_b.scaled(scale, cfg.min_views)
    grid = wall_grid(proj_g, atlas_b.rays)
    shape = grid.shape
    sampler = AtlasSampler.of(atlas_a, scale, cfg.min_views)
    pa = warp_points(grid, reg.warp_ba).reshape(shape[0], shape[1], 3)
    maps = sampler.pixel_maps(pa.reshape(-1, 3), shape)
    a_rgb, a_seen = sampler.sample(maps)
    b_rgb, b_seen = rgba_b[..., :3], rgba_b[..., 3] > 0.999
    supported, point_dist = _supported(grid, pa, reg, cfg)
    b_seen = b_seen & supported
    support_share = float(grid.area[supported].sum() / max(grid.area[grid.hit].sum(), 1e-9))
    flow_info: dict[str, Any] = {"flow": False}
    if cfg.flow_refine:
        joint0 = grid.hit & b_seen & (a_seen > 0.999)
        if joint0.sum() >= 100:
            flow, flow_info = refine_flow(grid, b_rgb, a_rgb, joint0, cfg.flow_smooth_mm,
                                          cfg.flow_max_mm, cfg.min_luminance_a)
            if flow_info.get("flow"):
                pa = compose(pa, flow)
                maps = sampler.pixel_maps(pa.reshape(-1, 3), shape)
                a_rgb, a_seen = sampler.sample(maps)
    def hint(sig: np.ndarray, joint: np.ndarray) -> np.ndarray:
        return changed_mask(sig, joint, grid.area, cfg.false_alarm_rate)

    neck = (neck_angles(grid, openings)
            if cfg.neck_ratio and openings is not None and len(openings) else None)
    diff = compute_difference(grid, b_rgb, b_seen, a_rgb, a_seen > 0.999, cfg, hint, neck)
    if cfg.extend_into_unseen:
        painted_b(diff, atlas_b.scaled(scale, 0)[1] if cfg.min_views > 1 else rgba_b, cfg.smooth_mm)
    diff.point_distance = point_dist
    info = {"grid": {"width": shape[1], "height": shape[0],
                     "mm_per_px": grid.mm_per_px_y},
            "supported_share_of_b_wall": support_share,
            "difference": diff.info, "flow": flow_info, "a_points": pa}
    return diff, info


def _consistency_check(a: SessionPaths, b: SessionPaths, diff: Any, atlas_a: SessionAtlas,
                       atlas_b: SessionAtlas, a_points: np.ndarray, reg: Registration,
                       cfg: CompareConfig) -> Any:
    """``verify`` callback of :func:`detect`: photo-consistency in session B's frames and,
    where B's frames disagree, in A's frames at the same site (``a_points``: the grid's
    points warped into A)."""
    from cystomap.compare.consistency import ViewSet, frame_local_delta_e, sample, spread_ratio

    state: dict[str, Any] = {}
    pts = diff.grid.points.reshape(-1, 3)
    nrm = diff.grid.normals.reshape(-1, 3)
    pts_a = np.asarray(a_points).reshape(-1, 3)
    # B's normals in A's frame: the similarity A → B rotates n_a into n_b = R n_a
    nrm_a = nrm @ reg.transform.rotation if reg.transform is not None else None

    def views(key: str, paths: SessionPaths) -> Any:
        if key not in state:
            try:
                state[key] = ViewSet.load(paths.sfm, paths.preprocessed)
            except InputError as exc:
                log.warning("compare: photo-consistency check in session %s skipped (%s)",
                            key, exc)
                state[key] = None
        return state[key]

    def verify(region: np.ndarray, ring: np.ndarray) -> dict[str, Any]:
        vs_b = views("B", b)
        if vs_b is None:
            return {}
        in_b = sample(vs_b, atlas_b.rays, pts[region], nrm[region], pts[ring], nrm[ring],
                      cfg.consistency_views, cfg.seed)
        out = spread_ratio(in_b)
        value = out.get("inconsistency")
        disagree = cfg.max_inconsistency > 0 and value is not None and value > cfg.max_inconsistency
        if nrm_a is None or not (disagree or cfg.local_colour_in_frames):
            return out
        vs_a = views("A", a)
        if vs_a is not None:
            in_a = sample(vs_a, atlas_a.rays, pts_a[region], nrm_a[region], pts_a[ring],
                          nrm_a[ring], cfg.consistency_views, cfg.seed)
            if disagree:
                out["inconsistency_a"] = spread_ratio(in_a).get("inconsistency")
            if cfg.local_colour_in_frames:
                out["frame_local_delta_e"] = frame_local_delta_e(in_b, in_a)
        return out

    return verify


def _supported(grid: Any, pa: np.ndarray, reg: Registration,
               cfg: CompareConfig) -> tuple[np.ndarray, np.ndarray]:
    """Grid pixels near an inlier match (``support_mm``) and near an SfM point of each
    session (``point_support_mm``; A's through the warp), and per pixel the larger of the
    two sessions' distances to their nearest SfM point (inf beyond 50 model units)."""
    from scipy.spatial import cKDTree

    ok = grid.hit.copy()
    pts_b = np.where(grid.hit[..., None], grid.points, 0).reshape(-1, 3)

    def dist(tree_pts: np.ndarray, query: np.ndarray, bound: float) -> np.ndarray:
        if len(tree_pts) == 0:
            return np.full(len(query), np.inf)
        d, _ = cKDTree(tree_pts).query(query, distance_upper_bound=bound,
                                       workers=max(1, cfg.threads))
        return d

    if cfg.support_mm > 0:
        inl = reg.matches[reg.inliers]
        ok &= np.isfinite(dist(reg.b_points[inl[:, 1]], pts_b, cfg.support_mm)).reshape(
            grid.shape)
    point_dist = np.maximum(dist(reg.b_points, pts_b, 50.0),
                            dist(reg.a_points, pa.reshape(-1, 3), 50.0)).reshape(grid.shape)
    if cfg.point_support_mm > 0:
        ok &= point_dist <= cfg.point_support_mm
    return ok, point_dist


def with_anatomy(rows: list[dict[str, Any]], atlas: SessionAtlas,
                 sized: bool = False) -> list[dict[str, Any]]:
    """``rows`` (with x, y, z in the session's model frame) with region, clock and
    distance_from_neck_mm from the session's atlas.json anatomy (empty without one); ``sized``
    (rows with diameter_mm): also ``straddles``, the other regions the change covers
    (:data:`cystomap.anatomy.STRADDLE_RULE`)."""
    import json

    meta = json.loads((Path(atlas.atlas_dir) / "atlas.json").read_text())
    columns = ANATOMY_COLUMNS + (("straddles",) if sized else ())
    out = [{**r, **{k: "" for k in columns}} for r in rows]
    if "anatomy" not in meta:
        return out
    anatomy = Anatomy.from_json(meta["anatomy"])
    idx = [i for i, r in enumerate(rows) if all(isinstance(r.get(k), int | float)
                                                for k in ("x", "y", "z"))]
    if idx:
        pts = np.array([[rows[i]["x"], rows[i]["y"], rows[i]["z"]] for i in idx], float)
        diam = ([float(rows[i].get("diameter_mm") or 0.0) for i in idx] if sized else None)
        for i, loc in zip(idx, locate(anatomy, pts, atlas.rays, diameters=diam), strict=True):
            out[i].update(loc)
    return out
