"""Photo-consistency of a changed region in session B's own frames: is it on the wall?

Where the mesh does not follow a real surface (the aperture to the urethra, which the mesh
closes with a cap, or wall the mesh misses by many millimetres), the atlas shows whatever the
frames saw through or in front of it, and that differs from frame to frame (parallax). A
texture really on the wall looks the same from every frame that sees it (after exposure).

For each region: points of the region and of a ring around it are projected into the
registered frames of session B that see them unoccluded and from the front; the colour of
every point is sampled in up to ``consistency_views`` frames (exposure-normalised per frame
on the ring); the spread across frames (robust, in log units) is compared between the region
and its ring. ``inconsistency = spread(region) / spread(ring)``: about 1 for wall texture, a
lesion included, several times larger where the frames disagree.

A raised lesion new in session B (papillary fronds several millimetres high) is real wall
that B's smooth mesh does not follow, so B's frames disagree on it too. The stage therefore
tests the same site in session A's frames when B's disagree: where A's agree, the relief is
new in B and the region is kept; the aperture disagrees in both sessions.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cystomap.atlas.projection import SurfaceRays

log = logging.getLogger(__name__)

MIN_VIEWS = 3
SPREAD_FLOOR = 0.02  # log units: the spread of a perfectly consistent texture (noise)


@dataclass
class ViewSet:
    """Session B's registered frames (poses, intrinsics, colour files) and the FOV mask."""

    views: list[Any]
    mask: np.ndarray
    cache: dict[str, np.ndarray]

    @classmethod
    def load(cls, sfm_dir: Path, preprocessed_dir: Path) -> ViewSet:
        from cystomap.io.views import load_views

        views, mask = load_views(Path(sfm_dir), Path(preprocessed_dir))
        return cls(views, mask, {})

    def image(self, i: int) -> np.ndarray:
        """Frame ``i`` (BGR, float32); kept in memory as read (8 bits: a quarter of the size)."""
        import cv2

        v = self.views[i]
        if v.name not in self.cache:
            img = cv2.imread(str(v.path), cv2.IMREAD_COLOR)
            if img is None:
                img = np.zeros((v.height, v.width, 3), np.uint8)
            self.cache[v.name] = img
        return self.cache[v.name].astype(np.float32)


def _visible(vs: ViewSet, rays: SurfaceRays, pts: np.ndarray, normals: np.ndarray,
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n_views, n_pts) visibility and image coordinates u, v."""
    nv, n = len(vs.views), len(pts)
    vis = np.zeros((nv, n), bool)
    uu = np.zeros((nv, n), np.float32)
    vv = np.zeros((nv, n), np.float32)
    mh, mw = vs.mask.shape
    for i, view in enumerate(vs.views):
        pc = view.to_camera(pts)
        z = pc[:, 2]
        front = z > 1e-6
        zz = np.where(front, z, 1.0)
        u = view.K[0, 0] * pc[:, 0] / zz + view.K[0, 2]
        v = view.K[1, 1] * pc[:, 1] / zz + view.K[1, 2]
        ok = front & (u >= 1) & (u <= mw - 2) & (v >= 1) & (v <= mh - 2)
        if not ok.any():
            continue
        ok[ok] &= vs.mask[np.rint(v[ok]).astype(int), np.rint(u[ok]).astype(int)]
        c = view.centre
        ray = pts - c
        dist = np.linalg.norm(ray, axis=1)
        # outward normals; the camera is inside, so it sees the wall from the inner side
        cos = np.einsum("ij,ij->i", normals, ray) / np.maximum(dist, 1e-12)
        ok &= cos > 0.2
        if ok.any():
            d = ray[ok] / dist[ok, None]
            t, _ = rays.cast(c, d)
            ok[ok] &= t >= dist[ok] * 0.97
        vis[i], uu[i], vv[i] = ok, u, v
    return vis, uu, vv


def _spread(col: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """Per point: median over channels of the MAD across views of log colour (NaN if < 3)."""
    import warnings

    x = np.where(vis[..., None], np.log(col + 4.0), np.nan)  # (views, pts, 3)
    with warnings.catch_warnings():  # points seen by no chosen view: NaN, dropped below
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(x, axis=0)
        mad = np.nanmedian(np.abs(x - med[None]), axis=0)
    out = np.median(mad, axis=1)
    out[vis.sum(axis=0) < MIN_VIEWS] = np.nan
    return out


@dataclass
class Samples:
    """A region's and its ring's points sampled in the frames of one session that see both
    (exposure-normalised per frame on the ring)."""

    colours: np.ndarray  # (views, n_region + n_ring, 3) RGB
    visible: np.ndarray  # (views, n_region + n_ring)
    n_region: int

    @property
    def views(self) -> int:
        return len(self.colours)


def sample(vs: ViewSet, rays: SurfaceRays, region_pts: np.ndarray, region_nrm: np.ndarray,
           ring_pts: np.ndarray, ring_nrm: np.ndarray, max_views: int, seed: int = 0,
           ) -> Samples | int:
    """The region's and ring's colours in up to ``max_views`` frames that see at least half
    of the region and a third of the ring (evenly spread over the video: different
    viewpoints); the number of such frames instead when there are fewer than ``MIN_VIEWS``."""
    import cv2

    rng = np.random.default_rng(seed)

    def sub(p: np.ndarray, n: np.ndarray, k: int = 300) -> tuple[np.ndarray, np.ndarray]:
        if len(p) > k:
            i = rng.choice(len(p), k, replace=False)
            return p[i], n[i]
        return p, n

    rp, rn = sub(region_pts, region_nrm)
    sp, sn = sub(ring_pts, ring_nrm)
    if len(rp) < 5 or len(sp) < 5:
        return 0
    pts = np.vstack([rp, sp])
    nrm = np.vstack([rn, sn])
    vis, uu, vv = _visible(vs, rays, pts, nrm)
    nr = len(rp)
    share_r = vis[:, :nr].mean(axis=1)
    share_s = vis[:, nr:].mean(axis=1)
    good = np.flatnonzero((share_r >= 0.5) & (share_s >= 0.3))
    if len(good) < MIN_VIEWS:
        return len(good)
    if len(good) > max_views:  # evenly spread over the video (different viewpoints)
        good = good[np.unique(np.linspace(0, len(good) - 1, max_views).round().astype(int))]
    col = np.zeros((len(good), len(pts), 3), np.float32)
    for k, i in enumerate(good):
        img = vs.image(i)
        s = cv2.remap(img, uu[i][None], vv[i][None], cv2.INTER_LINEAR)[0]
        ring = vis[i, nr:]
        grey = s[nr:][ring].mean(axis=1)
        norm = float(np.median(grey)) if ring.any() else 1.0
        col[k] = s[:, ::-1] * (128.0 / max(norm, 1.0))  # RGB, exposure-normalised on the ring
    return Samples(col, vis[good], nr)


def spread_ratio(samples: Samples | int) -> dict[str, Any]:
    """Spread of the region's colours across frames relative to its ring's."""
    if isinstance(samples, int):
        return {"views": samples, "inconsistency": None}
    nr = samples.n_region
    spread = _spread(samples.colours, samples.visible)
    r_sp = float(np.nanmedian(spread[:nr])) if np.isfinite(spread[:nr]).any() else np.nan
    s_sp = float(np.nanmedian(spread[nr:])) if np.isfinite(spread[nr:]).any() else np.nan
    if not (np.isfinite(r_sp) and np.isfinite(s_sp)):
        return {"views": samples.views, "inconsistency": None}
    return {"views": samples.views, "spread_region": r_sp, "spread_ring": s_sp,
            "inconsistency": r_sp / max(s_sp, SPREAD_FLOOR)}


def inconsistency(vs: ViewSet, rays: SurfaceRays, region_pts: np.ndarray,
                  region_nrm: np.ndarray, ring_pts: np.ndarray, ring_nrm: np.ndarray,
                  max_views: int, seed: int = 0) -> dict[str, Any]:
    """Spread of the region's colours across frames relative to its ring's."""
    return spread_ratio(sample(vs, rays, region_pts, region_nrm, ring_pts, ring_nrm,
                               max_views, seed))


def contrasts(samples: Samples) -> np.ndarray:
    """(views, 3) per frame: CIE L*a*b* of the region's mean colour minus its ring's."""
    from cystomap.compare.difference import lab

    nr = samples.n_region
    means = np.stack([[c[:nr][v[:nr]].mean(axis=0), c[nr:][v[nr:]].mean(axis=0)]
                      for c, v in zip(samples.colours, samples.visible, strict=True)])
    out = lab(means)  # (views, 2, 3)
    return (out[:, 0] - out[:, 1]).astype(np.float64)


def frame_local_delta_e(b: Samples | int, a: Samples | int) -> float | None:
    """CIE76 ΔE*ab between the region's contrast to its ring in session B's frames and in
    A's (each the median over the frames; None when either session has too few frames)."""
    if isinstance(b, int) or isinstance(a, int):
        return None
    return float(np.linalg.norm(np.median(contrasts(b), axis=0)
                                - np.median(contrasts(a), axis=0)))
