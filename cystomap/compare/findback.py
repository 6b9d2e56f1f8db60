"""Find back: the frames of each session that show a change, and crops of it.

For every change found by :func:`cystomap.compare.changes.detect` (a region on session B's
wall), the site is taken in both sessions: B's wall points of the region, and the same points
carried into session A's frame by the B → A warp (with the dense flow correction) and put on
A's wall (ray from A's barycentre to A's mesh). Each registered frame of a session is then
scored for how well it sees the site, with the atlas stage's own visibility and blending
weight (:class:`cystomap.atlas.texture.ViewGeometry`, :func:`~cystomap.atlas.texture.view_weights`,
the settings of that session's atlas.json): a frame sees a wall point when it lies inside the
image and the field-of-view mask, faces the camera and is not occluded by the mesh; its
weight favours frontal, close, central and sharp views (sharpness from the frames stage's
``frames.csv``) and fades out at the mask edge. A frame's score is the mean weight over the
region's points (0 for points it does not see), counted only when it sees the region's
centroid (unless no frame does): the whole change, large, central and frontal scores highest.

The frames that see the centroid form *visits* (runs of consecutive registered frames in video
order); the best frame of each visit is listed, the visits ranked by that score, at most
``findback_frames`` per change and session. Frames are named by their index in the video
(``f000123.png`` = frame 123); the time comes from the frames stage (``frames.csv``).

Outputs (written by :meth:`FindBack.write`):

* ``findback.csv``: one row per listed frame: ``id`` (the change, as in changes.csv),
  ``session`` (``a`` or ``b``), ``rank`` (1 = the best view), ``frame`` (index in the video),
  ``time_s``, ``image`` (file name), ``score`` (relative to the best view of the change in that
  session, 1 = best), ``visible_share`` (share of the region the frame sees),
  ``incidence_deg`` and ``distance_mm`` (at the centroid), ``centre_offset`` (distance of the
  centroid from the image centre / half the image diagonal), ``u, v`` (the centroid in the
  original video frame, pixels, centres at integers), ``centroid_seen`` (False when no frame
  of the session sees the centroid, which then lies on wall that session did not film, e.g. a
  strip the detection bridged: the frames are then scored on the part of the region they see,
  and ``u, v`` is the centre of that part), ``crop`` (file of the frame crop, rank 1 only);
  header only when there is no change;
* ``findback/change{id}_atlas_a.png`` / ``_atlas_b.png``: square crops (``findback_crop_px``)
  of A's and B's atlas about the site, the region outlined in magenta (A: where the region's
  points fall in A's atlas);
* ``findback/change{id}_frame_a.png`` / ``_frame_b.png``: crops of the best original frame
  of each session (the decoded video frame of the frames stage; the preprocessed frame when
  that is not available), the region outlined where that frame sees it.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.atlas.projection import SurfaceRays
from cystomap.atlas.texture import TextureSettings, View, ViewGeometry, view_weights
from cystomap.compare.crops import CROP_MARGIN, atlas_crop
from cystomap.compare.crops import crop_outlined as crop_outlined  # re-exported (tests)
from cystomap.compare.images import HIGHLIGHT as HIGHLIGHT  # re-exported (tests)
from cystomap.errors import InputError
from cystomap.images import imwrite_rgb

log = logging.getLogger(__name__)

FINDBACK_COLUMNS = ("id", "session", "rank", "frame", "time_s", "image", "score",
                    "visible_share", "incidence_deg", "distance_mm", "centre_offset", "u", "v",
                    "centroid_seen", "crop")
FRAME_INDEX = re.compile(r"(\d+)\.[A-Za-z0-9]+$")  # frames stage: f000123.png = frame 123
MAX_SAMPLES = 300  # region points scored per frame (a seeded subsample of larger regions)


@dataclass
class PointSamples:
    """Wall points and outward normals in the layout ViewGeometry.observe reads."""

    xyz32: np.ndarray  # (3, n) float32
    nrm32: np.ndarray  # (3, n) float32

    @classmethod
    def of(cls, points: np.ndarray, normals: np.ndarray) -> PointSamples:
        return cls(np.ascontiguousarray(np.asarray(points).T, dtype=np.float32),
                   np.ascontiguousarray(np.asarray(normals).T, dtype=np.float32))

    def __len__(self) -> int:
        return self.xyz32.shape[1]


@dataclass
class Site:
    """A change in one session: centroid, wall points and normals (that session's frame)."""

    centroid: np.ndarray  # (3,)
    normal: np.ndarray  # (3,)
    points: np.ndarray  # (n, 3)
    normals: np.ndarray  # (n, 3)


# --------------------------------------------------------------------------- one session


@dataclass
class SessionFrames:
    """A session's registered frames with the atlas stage's visibility test, their video
    index and time, and where their original image is."""

    views: list[View]
    geometry: ViewGeometry
    settings: TextureSettings
    rays: SurfaceRays
    sharp: np.ndarray  # (n_views,) sharpness relative to the session's median (1 if unknown)
    frame: list[int | None]  # index in the video
    time_s: list[float | None]
    original: list[Path]  # the original (decoded) frame, or the preprocessed one
    to_original: Callable[[np.ndarray, np.ndarray], np.ndarray]  # preprocessed (u, v) → original
    original_kind: str
    depths: dict[int, Any] = field(default_factory=dict)

    @classmethod
    def load(cls, sfm: Path, preprocessed: Path, atlas_dir: Path, frames: Path | None,
             rays: SurfaceRays) -> SessionFrames:
        from cystomap.atlas.config import AtlasConfig
        from cystomap.io.views import load_views

        views, mask = load_views(Path(sfm), Path(preprocessed))
        try:
            meta = json.loads((Path(atlas_dir) / "atlas.json").read_text())
            atlas_cfg = AtlasConfig(**meta.get("config", {}))
        except (OSError, ValueError, TypeError) as exc:
            log.warning("findback: %s/atlas.json has no usable atlas settings (%s); defaults "
                        "used", atlas_dir, exc)
            atlas_cfg = AtlasConfig()
        settings = atlas_cfg.texture_settings()
        frame = [_frame_index(v.name) for v in views]
        table = _frames_table(frames)
        times = [table.get(f, {}).get("time_s") if f is not None else None for f in frame]
        sharp_raw = np.array([table.get(f, {}).get("sharpness", np.nan) if f is not None
                              else np.nan for f in frame], dtype=np.float64)
        sharp = np.ones(len(views))
        good = np.isfinite(sharp_raw) & (sharp_raw > 0)
        if good.any():  # as the atlas stage: relative to the median, clipped
            sharp[good] = np.clip(sharp_raw[good] / np.median(sharp_raw[good]), 0.1, 4.0)
        mapping = _original_mapping(Path(preprocessed))
        originals = []
        use_frames = frames is not None and Path(frames).is_dir() and mapping is not None
        for v in views:
            p = Path(frames) / Path(v.name).name if use_frames and frames is not None else None
            originals.append(p if p is not None and p.is_file() else v.path)
        kind = "video frame" if use_frames and all(p != v.path for p, v in
                                                    zip(originals, views, strict=True)) else ""
        if not kind:  # mixed or no original frames: the preprocessed ones throughout
            originals = [v.path for v in views]
            kind = "preprocessed frame"
            mapping = None
        return cls(views, ViewGeometry(mask, settings), settings, rays, sharp, frame, times,
                   originals, mapping or _identity, kind)

    def observe(self, i: int, samples: PointSamples) -> dict[str, np.ndarray]:
        view = self.views[i]
        if i not in self.depths:
            self.depths[i] = self.geometry.depth_map(view, self.rays)
        return self.geometry.observe(view, samples, np.arange(len(samples)),  # type: ignore[arg-type]
                                     self.depths[i])

    def _may_see(self, points: np.ndarray) -> np.ndarray:
        """Views whose image contains any of ``points`` (cheap test before the depth maps)."""
        out = np.zeros(len(self.views), bool)
        for i, v in enumerate(self.views):
            p = v.to_camera(points)
            front = p[:, 2] > 1e-6
            if not front.any():
                continue
            p = p[front]
            u = v.K[0, 0] * p[:, 0] / p[:, 2] + v.K[0, 2]
            w = v.K[1, 1] * p[:, 1] / p[:, 2] + v.K[1, 2]
            out[i] = bool(((u >= 0) & (u <= v.width - 1) & (w >= 0) & (w <= v.height - 1)).any())
        return out

    def scores(self, site: Site, rng: np.random.Generator,
               ) -> tuple[np.ndarray, list[Any], bool]:
        """Per view: the score and its observation of [centroid, samples] (None when not
        scored), and whether the scores require the centroid seen. Views that do not see
        the centroid score 0, unless no view sees it (it lies on wall the session did not
        film, e.g. a strip bridged by the detection): then every view seeing part of the
        region is scored."""
        pts, nrm = site.points, site.normals
        if len(pts) > MAX_SAMPLES:
            keep = np.sort(rng.choice(len(pts), MAX_SAMPLES, replace=False))
            pts, nrm = pts[keep], nrm[keep]
        samples = PointSamples.of(np.vstack([site.centroid[None], pts]),
                                  np.vstack([site.normal[None], nrm]))
        score = np.zeros(len(self.views))
        sees_centroid = np.zeros(len(self.views), bool)
        obs: list[Any] = [None] * len(self.views)
        for i in np.flatnonzero(self._may_see(np.vstack([site.centroid[None], pts]))):
            o = self.observe(int(i), samples)
            if not o["ok"].any():
                continue
            w = view_weights(o, self.views[i], self.settings, float(self.sharp[i]), 1.0)
            w = np.where(o["ok"], w, 0.0)
            score[i] = float(w[1:].mean()) if len(w) > 1 else float(w[0])
            sees_centroid[i] = bool(o["ok"][0])
            obs[i] = o
        if sees_centroid.any():
            return np.where(sees_centroid, score, 0.0), obs, True
        return score, obs, False


def _identity(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.stack([np.asarray(u, float), np.asarray(v, float)], axis=-1)


def _frame_index(name: str) -> int | None:
    m = FRAME_INDEX.search(Path(name).name)
    return int(m.group(1)) if m else None


def _frames_table(frames: Path | None) -> dict[int, dict[str, float]]:
    """frames.csv of the frames stage by video index ({} when not available)."""
    from cystomap.frames import read_frames_csv

    if frames is None:
        return {}
    path = Path(frames) / "frames.csv"
    if not path.is_file():
        log.warning("findback: %s not found; frame times and sharpness unknown", path)
        return {}
    try:
        return {r["frame"]: r for r in read_frames_csv(path)}
    except (OSError, KeyError, ValueError) as exc:
        log.warning("findback: cannot read %s (%s); frame times unknown", path, exc)
        return {}


def _original_mapping(preprocessed: Path) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None:
    """Preprocessed (undistorted) pixel → pixel of the original frame, through the cameras
    the preprocess stage wrote (camera.json and preprocess.json's input_camera); None when
    they are not available."""
    from cystomap.camera import Camera

    try:
        out_cam = Camera.load(preprocessed / "camera.json")
        meta = json.loads((preprocessed / "preprocess.json").read_text())
        in_cam = Camera.from_config(meta["input_camera"])
    except (OSError, ValueError, KeyError, TypeError, InputError) as exc:
        log.warning("findback: no camera of the original frames in %s (%s); the preprocessed "
                    "frames are shown", preprocessed, exc)
        return None

    def mapping(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        u, v = np.asarray(u, float).ravel(), np.asarray(v, float).ravel()
        if len(u) == 0:
            return np.zeros((0, 2))
        pts = np.stack([(u - out_cam.cx) / out_cam.fx, (v - out_cam.cy) / out_cam.fy,
                        np.ones(len(u))], axis=1)
        return in_cam.project(pts)

    return mapping


def visits(score: np.ndarray) -> list[int]:
    """Best view of each run of consecutive views with a positive score, best runs first."""
    best: list[int] = []
    i, n = 0, len(score)
    while i < n:
        if score[i] <= 0:
            i += 1
            continue
        j = i
        while j < n and score[j] > 0:
            j += 1
        best.append(i + int(np.argmax(score[i:j])))
        i = j
    return sorted(best, key=lambda k: -score[k])


def frame_crop(session: SessionFrames, i: int, site: Site, out_px: int,
               centroid_seen: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Crop of frame ``i``'s original image about the site's centroid (or, when the frame
    does not see it, the centre of the part of the region it sees), that part outlined;
    and that centre in the original image."""
    import cv2

    samples = PointSamples.of(np.vstack([site.centroid[None], site.points]),
                              np.vstack([site.normal[None], site.normals]))
    o = session.observe(i, samples)
    uv = session.to_original(o["u"], o["v"])
    bgr = cv2.imread(str(session.original[i]), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(f"{session.original[i]}: cannot read image")
    img = bgr[..., ::-1]
    h, w = img.shape[:2]
    seen = uv[1:][o["ok"][1:]]
    centre = uv[0] if centroid_seen or not len(seen) else seen.mean(axis=0)
    extent = float(np.abs(seen - centre).max()) if len(seen) else 0.0
    half = min(max(CROP_MARGIN * extent, 0.08 * math.hypot(w, h)), min(w, h) / 2)
    cx = float(np.clip(centre[0], half, w - 1 - half)) if 2 * half < w else (w - 1) / 2
    cy = float(np.clip(centre[1], half, h - 1 - half)) if 2 * half < h else (h - 1) / 2
    return crop_outlined(img, (cx, cy), (half, half), seen, out_px), centre


# --------------------------------------------------------------------------- all changes


@dataclass
class FindBack:
    """The rows of findback.csv and the crops (file name → RGB)."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    crops: dict[str, np.ndarray] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    def write(self, out_dir: Path) -> None:
        out_dir = Path(out_dir)
        with open(out_dir / "findback.csv", "w", newline="") as fh:
            wr = csv.DictWriter(fh, fieldnames=list(FINDBACK_COLUMNS))
            wr.writeheader()
            for r in self.rows:
                wr.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
        if self.crops:
            (out_dir / "findback").mkdir(exist_ok=True)
            for name, img in self.crops.items():
                imwrite_rgb(out_dir / "findback" / name, img)


def _on_wall(rays: SurfaceRays, centre: np.ndarray, points: np.ndarray,
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points put on a mesh along their direction from ``centre``: points, normals, hit."""
    d = points - centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    t, tri = rays.cast(centre, d)
    hit = tri >= 0
    wall = np.where(hit[:, None], centre + np.where(hit, t, 0.0)[:, None] * d, points)
    nrm = np.zeros_like(wall)
    nrm[hit] = rays.face_normals[tri[hit]]
    return wall, nrm, hit


def find_back(regions: list[Any], grid: Any, a_points: np.ndarray, atlas_a: Any, atlas_b: Any,
              paths_a: Any, paths_b: Any, n_frames: int, crop_px: int, seed: int = 0) -> FindBack:
    """Frames and crops of every region (see the module docstring).

    ``grid`` is the comparison grid (B's wall points and normals per pixel), ``a_points`` the
    A-frame point of every grid pixel (the B → A warp with the flow correction), ``paths_*``
    the sessions' :class:`~cystomap.compare.stage.SessionPaths`.
    """
    out = FindBack()
    if not regions or n_frames <= 0:
        return out
    sessions = {}
    for key, paths, atlas in (("a", paths_a, atlas_a), ("b", paths_b, atlas_b)):
        sessions[key] = SessionFrames.load(paths.sfm, paths.preprocessed, paths.atlas,
                                           getattr(paths, "frames", None), atlas.rays)
    pts_b = grid.points.reshape(-1, 3)
    nrm_b = grid.normals.reshape(-1, 3)
    pa = np.asarray(a_points).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    listed = {"a": 0, "b": 0}
    for g in regions:
        px = np.asarray(g.pixels)
        px = px[np.isfinite(pts_b[px]).all(axis=1)]
        if not len(px):
            continue
        cb = np.array([g.x, g.y, g.z], float)
        _, nb_c, _ = _on_wall(atlas_b.rays, atlas_b.proj.barycentre, cb[None])
        site_b = Site(cb, nb_c[0], pts_b[px], nrm_b[px])
        wa, na, hit_a = _on_wall(atlas_a.rays, atlas_a.proj.barycentre, pa[px])
        ca, nca, _ = _on_wall(atlas_a.rays, atlas_a.proj.barycentre, pa[px].mean(axis=0)[None])
        site_a = Site(ca[0], nca[0], wa[hit_a], na[hit_a])
        for key, site, atlas in (("a", site_a, atlas_a), ("b", site_b, atlas_b)):
            out.crops[f"change{g.id}_atlas_{key}.png"] = atlas_crop(atlas, site.centroid,
                                                                    site.points, crop_px)
            s = sessions[key]
            if not len(site.points):
                continue
            score, obs, centroid_seen = s.scores(site, rng)
            best = visits(score)[:n_frames]
            if not best:
                continue
            top = score[best[0]]
            crop_name = f"change{g.id}_frame_{key}.png"
            crop, centre0 = frame_crop(s, best[0], site, crop_px, centroid_seen)
            out.crops[crop_name] = crop
            listed[key] += 1
            for rank, i in enumerate(best, start=1):
                o = obs[i]
                if rank == 1:
                    uv = centre0
                elif centroid_seen:
                    uv = s.to_original(o["u"][:1], o["v"][:1])[0]
                else:
                    ok = o["ok"][1:]
                    uv = s.to_original(o["u"][1:][ok], o["v"][1:][ok]).mean(axis=0)
                v = s.views[i]
                off = math.hypot(float(o["u"][0]) - v.K[0, 2], float(o["v"][0]) - v.K[1, 2])
                out.rows.append({
                    "id": g.id, "session": key, "rank": rank,
                    "frame": "" if s.frame[i] is None else s.frame[i],
                    "time_s": "" if s.time_s[i] is None else float(s.time_s[i]),
                    "image": Path(v.name).name, "score": float(score[i] / top),
                    "visible_share": float(o["ok"][1:].mean()) if len(o["ok"]) > 1 else 1.0,
                    "incidence_deg": math.degrees(math.acos(float(np.clip(o["cos"][0], -1, 1)))),
                    "distance_mm": float(o["dist"][0]),
                    "centre_offset": off / (math.hypot(v.width, v.height) / 2),
                    "u": float(uv[0]), "v": float(uv[1]),
                    "centroid_seen": centroid_seen,
                    "crop": f"findback/{crop_name}" if rank == 1 else ""})
    out.info = {"changes": len(regions), "seen_in_a": listed["a"], "seen_in_b": listed["b"],
                "frames_per_change": n_frames, "crop_px": crop_px,
                "original_frames": {k: s.original_kind for k, s in sessions.items()}}
    log.info("findback: %d change(s): seen in %d by frames of A, in %d by frames of B",
             len(regions), listed["a"], listed["b"])
    return out
