"""Colour of every atlas pixel from all the frames that see its wall point.

Per atlas pixel, the ray from the barycentre gives a wall point X (with its normal). Each
registered frame that sees X (in front, inside the image and the field-of-view mask, facing
the camera, not occluded: its depth agrees with the frame's depth map of the mesh) adds the
colour it shows there, sampled from the image-pyramid level matched to the footprint of the
atlas pixel (no aliasing), with a weight favouring frontal, close, central and sharp views and
fading out towards the mask edge (no seams at frame borders).

Exposure and illumination differences are removed first: from the overlaps (coarse atlas
cells seen by several frames) a log-linear model ``log I = albedo(cell) + gain(frame) +
β · (log distance, log cos incidence, squared image radius)`` is fitted by robust weighted
least squares, and every sample is divided by its modelled gain and shading.

Specular glints are view-dependent: samples that are white and much brighter than the mucosa
around them in the frame, or much brighter than the median over all views of their coarse
cell, lose weight; pixels no frame shows free of glints are inpainted.

Blending is two-band: the low frequencies are the weighted mean over all views (seamless),
the detail comes from a mean with much sharper weights (the best one or two views), so slight
misregistration does not ghost or blur vessel edges.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cystomap.atlas.config import AtlasConfig
from cystomap.atlas.projection import Projection, SurfaceRays
from cystomap.errors import InputError
from cystomap.images import sample_bilinear
from cystomap.io.views import View

log = logging.getLogger(__name__)


#: the knobs of texturing (min_cos_incidence, weight_*_power, edge_feather_px, occlusion_*)
#: are the atlas settings themselves
TextureSettings = AtlasConfig


class WallSamples:
    """The wall point, normal and true area of every atlas pixel hit by its ray."""

    def __init__(self, proj: Projection, rays: SurfaceRays, block: int) -> None:
        self.proj = proj
        h, w = proj.height, proj.width
        dirs = proj.grid_directions().reshape(-1, 3)
        t, tri = rays.cast(proj.barycentre, dirs)
        self.hit = tri >= 0
        self.points = proj.barycentre + np.where(self.hit, t, 0.0)[:, None] * dirs
        normals = np.zeros_like(self.points)
        normals[self.hit] = rays.face_normals[tri[self.hit]]  # outward
        cos_b = np.abs(np.einsum("ij,ij->i", normals, dirs))
        del dirs
        solid = np.repeat(proj.pixel_solid_angle(), w)
        self.area = np.where(self.hit, np.where(self.hit, t, 0.0) ** 2 * solid
                             / np.maximum(cos_b, 0.1), 0.0)
        # Coarse cells of block × block pixels: centre pixel and radius on the wall.
        self.block = block
        nby, nbx = -(-h // block), -(-w // block)
        by, bx = np.meshgrid(np.arange(nby), np.arange(nbx), indexing="ij")
        r0, c0 = by.ravel() * block, bx.ravel() * block
        rc = np.minimum(r0 + block // 2, h - 1)
        cc = np.minimum(c0 + block // 2, w - 1)
        self.cell_pixel = rc * w + cc
        radius = np.zeros(len(r0))
        for dr, dc in ((0, 0), (0, block - 1), (block - 1, 0), (block - 1, block - 1)):
            corner = np.minimum(r0 + dr, h - 1) * w + np.minimum(c0 + dc, w - 1)
            d = np.linalg.norm(self.points[corner] - self.points[self.cell_pixel], axis=1)
            d[~(self.hit[corner] & self.hit[self.cell_pixel])] = np.inf
            radius = np.maximum(radius, d)
        self.cell_radius = radius
        rr = r0[:, None] + np.repeat(np.arange(block), block)[None, :]
        cc2 = c0[:, None] + np.tile(np.arange(block), block)[None, :]
        inside = (rr < h) & (cc2 < w)
        self.cell_pixels = np.where(inside, rr * w + cc2, -1)
        # float32 component arrays for the per-frame work (gathers and arithmetic are faster)
        self.xyz32 = np.ascontiguousarray(self.points.T, dtype=np.float32)
        self.nrm32 = np.ascontiguousarray(normals.T, dtype=np.float32)

    def candidates(self, view: View) -> np.ndarray:
        """Flat indices of the hit pixels of all cells that may project into ``view``."""
        pc = view.to_camera(self.points[self.cell_pixel])
        z = pc[:, 2]
        fx = view.K[0, 0]
        front = z > 1e-6
        zz = np.where(front, z, 1.0)
        u = view.K[0, 0] * pc[:, 0] / zz + view.K[0, 2]
        v = view.K[1, 1] * pc[:, 1] / zz + view.K[1, 2]
        radius = np.where(np.isfinite(self.cell_radius), self.cell_radius, 1e9)
        margin = fx * radius / zz + 2.0
        near = np.linalg.norm(pc, axis=1) <= 2 * radius  # camera (almost) inside the cell
        ok = (front & (u >= -margin) & (u <= view.width - 1 + margin) & (v >= -margin)
              & (v <= view.height - 1 + margin)) | near
        px = self.cell_pixels[ok].ravel()
        px = px[px >= 0]
        return px[self.hit[px]]


# --------------------------------------------------------------------------- views and images


def load_image(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"{path}: cannot read image")
    return img


def pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    import cv2

    pyr = [img]
    for _ in range(levels):
        if min(pyr[-1].shape[:2]) < 8:
            break
        pyr.append(cv2.pyrDown(pyr[-1]))
    return pyr


def sample_mip(pyr: Sequence[np.ndarray | None], u: np.ndarray, v: np.ndarray,
               level: np.ndarray) -> np.ndarray:
    """Bilinear samples from the pyramid level nearest to each sample's footprint ``level``
    (levels never sampled may be None)."""
    lv = np.clip(np.rint(level), 0, len(pyr) - 1).astype(np.int8)
    top = pyr[-1]
    if top is None:
        raise ValueError("the pyramid's coarsest level is missing")
    out = np.empty((len(u), top.shape[2] if top.ndim == 3 else 1), np.float32)
    for lvl in np.unique(lv):
        idx = np.flatnonzero(lv == lvl)
        s = np.float32(0.5**lvl)  # pyrDown halves; pixel centres: x_l = (x + 0.5) / 2^l - 0.5
        img = pyr[int(lvl)]
        if img is None:
            raise ValueError(f"pyramid level {lvl} was dropped but is sampled")
        out[idx] = sample_bilinear(img, (u[idx] + 0.5) * s - 0.5,
                                   (v[idx] + 0.5) * s - 0.5)
    return out


def glint_weight(img: np.ndarray, mask: np.ndarray, rel: float, grow_px: int = 8) -> np.ndarray:
    """uint8 weight (255 = usable) that fades out specular glints: bright, white spots.

    A glint is view-dependent: its darkest colour channel rises far above that of the mucosa
    around it (a wide median, so blobs up to ~1/10 of the frame are caught). The weight falls
    from 1 where the darkest channel exceeds that background by ``rel`` to 0 at ``2·rel``
    (saturated white is 0 anyway) and is spread ``grow_px`` pixels around (the soft halo).
    A bright but genuine patch loses weight in every view alike, so blending (relative
    weights) keeps it.
    """
    import cv2

    h, w = img.shape[:2]
    size = (max(8, w // 4), max(8, h // 4))
    small = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    ch = cv2.split(small)
    darkest = ch[0]
    for c in ch[1:]:
        darkest = cv2.min(darkest, c)
    m = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    if m.any() and not m.all():  # fill outside the mask so the median sees mucosa only
        fill = np.uint8(np.median(darkest[m]))
        darkest = np.where(m, darkest, fill).astype(np.uint8)
    k = max(3, (min(size) // 4) | 1)
    background = cv2.medianBlur(darkest, min(k, 255)).astype(np.float32)
    ratio = darkest.astype(np.float32) / np.maximum(background, 8.0)
    x = np.clip((ratio - 1.0 - rel) / rel, 0.0, 1.0)
    wgt = 1.0 - x * x * (3 - 2 * x)
    wgt[darkest >= 250] = 0.0
    r = max(1, round(grow_px / 4))
    wgt = cv2.erode(wgt, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
    wgt = cv2.resize(wgt, (w, h), interpolation=cv2.INTER_LINEAR)
    return np.clip(wgt * 255 + 0.5, 0, 255).astype(np.uint8)


def sharpness(img: np.ndarray, mask: np.ndarray) -> float:
    """Variance of the Laplacian of the (half-size) grey image inside the mask."""
    import cv2

    grey = cv2.cvtColor(cv2.pyrDown(img), cv2.COLOR_BGR2GRAY).astype(np.float32)
    lap = cv2.Laplacian(grey, cv2.CV_32F)
    m = cv2.resize(mask.astype(np.uint8), (grey.shape[1], grey.shape[0]),
                   interpolation=cv2.INTER_NEAREST) > 0
    m = cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return float(lap[m].var()) if m.any() else 0.0


class ViewGeometry:
    """Per-view visibility of wall samples: mask-edge distance and occlusion depth map."""

    def __init__(self, mask: np.ndarray, settings: TextureSettings) -> None:
        import cv2

        self.settings = settings
        m = (mask > 0).astype(np.uint8)
        m[[0, -1], :] = 0
        m[:, [0, -1]] = 0
        self.edge_dist = cv2.distanceTransform(m, cv2.DIST_L2, 5).astype(np.float32)
        self.height, self.width = mask.shape

    def depth_map(self, view: View, rays: SurfaceRays) -> tuple[np.ndarray, float, float]:
        """Inverse z-depth of the mesh on a coarse pixel grid (0 where no hit) and its scale.

        Inverse depth is linear in image coordinates over a plane, so bilinear interpolation of
        the coarse map is accurate on the smooth wall.
        """
        s = self.settings.occlusion_scale
        gw = min(view.width, max(64, round(view.width * s)))
        gh = min(view.height, max(2, round(view.height * gw / view.width)))
        sx, sy = gw / view.width, gh / view.height
        gx, gy = np.meshgrid((np.arange(gw) + 0.5) / sx - 0.5, (np.arange(gh) + 0.5) / sy - 0.5)
        kinv = np.linalg.inv(view.K)
        d_cam = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1) @ kinv.T
        d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
        d_world = d_cam @ view.rotation
        t, _ = rays.cast(view.centre, d_world)
        z = t * d_cam[:, 2]
        inv = np.where(np.isfinite(z) & (z > 0), 1.0 / np.where(z > 0, z, 1.0), 0.0)
        return inv.reshape(gh, gw).astype(np.float32), sx, sy

    def observe(self, view: View, wall: WallSamples, idx: np.ndarray,
                depth: tuple[np.ndarray, float, float] | None) -> dict[str, np.ndarray]:
        """Image coordinates, visibility and geometry of the wall samples ``idx`` in ``view``.

        Returns float32 arrays u, v (pixels), z (depth), dist (to the camera centre), cos
        (incidence), edge (distance to the mask edge, pixels) and the boolean ``ok``.
        """
        x, y, z0 = (wall.xyz32[k][idx] for k in range(3))
        rot = view.rotation.astype(np.float32)
        tr = view.translation.astype(np.float32)
        xc = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z0 + tr[0]
        yc = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z0 + tr[1]
        z = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z0 + tr[2]
        front = z > 1e-6
        inv_z = np.float32(1.0) / np.where(front, z, np.float32(1.0))
        u = np.float32(view.K[0, 0]) * xc * inv_z + np.float32(view.K[0, 2])
        v = np.float32(view.K[1, 1]) * yc * inv_z + np.float32(view.K[1, 2])
        inside = front & (u >= 0) & (u <= view.width - 1) & (v >= 0) & (v <= view.height - 1)
        ui = np.clip(u + 0.5, 0, self.width - 1).astype(np.int32)
        vi = np.clip(v + 0.5, 0, self.height - 1).astype(np.int32)
        edge = self.edge_dist[vi, ui]
        edge[~inside] = 0
        dist = np.sqrt(xc * xc + yc * yc + z * z)
        # cos of incidence: inward normal (−n) against the direction to the camera (−p_cam)
        n_x, n_y, n_z = (wall.nrm32[k][idx] for k in range(3))
        ncx = rot[0, 0] * n_x + rot[0, 1] * n_y + rot[0, 2] * n_z
        ncy = rot[1, 0] * n_x + rot[1, 1] * n_y + rot[1, 2] * n_z
        ncz = rot[2, 0] * n_x + rot[2, 1] * n_y + rot[2, 2] * n_z
        cos = (ncx * xc + ncy * yc + ncz * z) / np.maximum(dist, np.float32(1e-12))
        ok = inside & (edge >= 1.0) & (cos >= self.settings.min_cos_incidence)
        if depth is not None and ok.any():
            inv, sx, sy = depth
            sel = np.flatnonzero(ok)
            gu, gv = (u[sel] + 0.5) * sx - 0.5, (v[sel] + 0.5) * sy - 0.5
            inv_ref = sample_bilinear(inv, gu, gv)[:, 0]
            # visible unless the mesh along this pixel is clearly nearer than the point
            ok[sel] = inv_ref * (1.0 - self.settings.occlusion_tolerance) <= inv_z[sel]
        return {"ok": ok, "u": u, "v": v, "z": z, "dist": dist, "cos": cos, "edge": edge}


def view_weights(obs: dict[str, np.ndarray], view: View, settings: TextureSettings,
                 sharp: float, dist_ref: float) -> np.ndarray:
    """Blending weight: frontal, close, central, sharp; fading to 0 at the mask edge."""
    cos = np.clip(obs["cos"], 0.0, 1.0)
    w = cos ** settings.weight_cos_power
    w *= (dist_ref / np.maximum(obs["dist"], 1e-9)) ** settings.weight_distance_power
    half_diag = math.hypot(view.width, view.height) / 2
    rn2 = ((obs["u"] - view.K[0, 2]) ** 2 + (obs["v"] - view.K[1, 2]) ** 2) / half_diag**2
    w *= np.clip(1.0 - rn2, 0.05, 1.0)
    e = np.clip(obs["edge"] / max(settings.edge_feather_px, 1e-6), 0.0, 1.0)
    w *= e * e * (3 - 2 * e)  # smoothstep
    w *= sharp ** settings.weight_sharpness_power
    return w.astype(np.float32)


# --------------------------------------------------------------------------- exposure model


@dataclass(frozen=True)
class Photometry:
    """log I = albedo + gain[frame] + beta · (log dist, log cos, r²): per-sample correction."""

    gains: np.ndarray  # (n_views,) log gain
    beta: np.ndarray  # (3,)
    dist_ref: float

    def correction(self, i: int, obs: dict[str, np.ndarray], view: View) -> np.ndarray:
        """Factor that maps an observed colour to the common exposure (multiply)."""
        b0, b1, b2 = (np.float32(x) for x in self.beta)
        half_diag2 = np.float32((view.width**2 + view.height**2) / 4)
        du = obs["u"] - np.float32(view.K[0, 2])
        dv = obs["v"] - np.float32(view.K[1, 2])
        f = np.exp(np.float32(-self.gains[i]) - b2 * (du * du + dv * dv) / half_diag2)
        if b0:
            f *= (np.maximum(obs["dist"], 1e-9) / np.float32(self.dist_ref)) ** -b0
        if b1:
            f *= np.clip(obs["cos"], 0.05, 1.0) ** -b1
        return f.astype(np.float32)

    @classmethod
    def identity(cls, n: int, dist_ref: float) -> Photometry:
        return cls(np.zeros(n), np.zeros(3), dist_ref)


def _covariates(obs: dict[str, np.ndarray], view: View, dist_ref: float) -> np.ndarray:
    half_diag = math.hypot(view.width, view.height) / 2
    rn2 = ((obs["u"] - view.K[0, 2]) ** 2 + (obs["v"] - view.K[1, 2]) ** 2) / half_diag**2
    return np.stack([np.log(np.maximum(obs["dist"], 1e-9) / dist_ref),
                     np.log(np.clip(obs["cos"], 0.05, 1.0)), rn2], axis=1)


def fit_photometry(
    cell: np.ndarray, frame: np.ndarray, logi: np.ndarray, cov: np.ndarray, weight: np.ndarray,
    n_views: int, dist_ref: float, illumination: bool, robust_rounds: int = 3,
) -> Photometry:
    """Weighted least squares of the log-linear exposure model over the overlaps.

    The per-cell albedos are eliminated exactly (within-cell centring), so the normal equations
    are only (frames + 3)²; a weak ridge pulls gains to 1 (fixes the gauge, steadies frames with
    little overlap). Huber reweighting resists specular glints and misregistration.
    """
    import scipy.sparse as sp

    if len(cell) == 0:
        return Photometry.identity(n_views, dist_ref)
    _, cell = np.unique(cell, return_inverse=True)
    seen_by = np.bincount(cell)
    keep = seen_by[cell] >= 2  # only cells seen by at least two frames constrain gains
    if not keep.any():
        return Photometry.identity(n_views, dist_ref)
    _, cell = np.unique(cell[keep], return_inverse=True)
    frame, logi, cov, weight = frame[keep], logi[keep], cov[keep], weight[keep]
    n_cells = int(cell.max()) + 1
    n_cov = 3 if illumination else 0
    cov = cov[:, :n_cov]
    n_par = n_views + n_cov
    w = weight.astype(np.float64).copy()
    g = np.zeros(n_views)
    beta = np.zeros(n_cov)
    for _ in range(robust_rounds):
        wc = np.bincount(cell, w, n_cells)
        # X = [one-hot(frame), cov]; M = XᵀWX − Sᵀ diag(1/wc) S with S = per-cell sums of w·x
        m = np.zeros((n_par, n_par))
        m[np.arange(n_views), np.arange(n_views)] = np.bincount(frame, w, n_views)
        s_f = sp.csr_matrix((w, (cell, frame)), shape=(n_cells, n_views))
        s_c = np.stack([np.bincount(cell, w * cov[:, k], n_cells) for k in range(n_cov)], 1) \
            if n_cov else np.zeros((n_cells, 0))
        for k in range(n_cov):
            col = np.bincount(frame, w * cov[:, k], n_views)
            m[:n_views, n_views + k] = col
            m[n_views + k, :n_views] = col
        m[n_views:, n_views:] = (cov * w[:, None]).T @ cov
        inv_wc = sp.diags(1.0 / np.maximum(wc, 1e-300))
        s_all = sp.hstack([s_f, sp.csr_matrix(s_c)]).tocsr()
        m -= (s_all.T @ inv_wc @ s_all).toarray()
        sy = np.bincount(cell, w * logi, n_cells)
        rhs = np.concatenate([np.bincount(frame, w * logi, n_views),
                              (cov * (w * logi)[:, None]).sum(0)])
        rhs -= s_all.T @ (sy / np.maximum(wc, 1e-300))
        ridge = 1e-3 * max(float(np.diag(m)[:n_views].mean()), 1e-12)
        m[np.arange(n_views), np.arange(n_views)] += ridge
        m[np.arange(n_views, n_par), np.arange(n_views, n_par)] += 1e-9 * ridge + 1e-12
        sol = np.linalg.solve(m, rhs)
        g, beta = sol[:n_views], sol[n_views:]
        pred = g[frame] + cov @ beta
        a = np.bincount(cell, w * (logi - pred), n_cells) / np.maximum(wc, 1e-300)
        res = logi - a[cell] - pred
        sigma = 1.4826 * float(np.median(np.abs(res))) + 1e-6
        w = weight * np.minimum(1.0, 1.5 * sigma / np.maximum(np.abs(res), 1e-12))
    g = g - np.average(g, weights=np.maximum(np.bincount(frame, minlength=n_views), 1e-9))
    g = np.clip(g, -math.log(4.0), math.log(4.0))
    return Photometry(g, np.concatenate([beta, np.zeros(3 - n_cov)]), dist_ref)


def weighted_median(group: np.ndarray, values: np.ndarray, weights: np.ndarray,
                    n_groups: int) -> np.ndarray:
    """Weighted median of ``values`` per ``group`` (NaN for empty groups)."""
    out = np.full(n_groups, np.nan)
    if len(group) == 0:
        return out
    order = np.lexsort((values, group))
    g, v, w = group[order], values[order], weights[order]
    cw = np.cumsum(w)
    start = np.searchsorted(g, np.arange(n_groups), side="left")
    end = np.searchsorted(g, np.arange(n_groups), side="right")
    has = end > start
    before = np.where(start > 0, cw[np.maximum(start - 1, 0)], 0.0)
    half = before + 0.5 * (cw[np.maximum(end - 1, 0)] - before)
    idx = np.searchsorted(cw, half[has], side="left")
    out[has] = v[np.minimum(idx, end[has] - 1)]
    return out


def cell_reference(cell: np.ndarray, frame: np.ndarray, logi: np.ndarray, cov: np.ndarray,
                   weight: np.ndarray, photometry: Photometry, n_cells: int) -> np.ndarray:
    """Robust exposure-corrected log luminance of each coarse cell (weighted median over views).

    View-dependent brightening (specular glints, flare) sits in a minority of the views of a
    cell, so the median is the wall's own brightness; NaN where no view saw the cell.
    """
    corrected = logi - photometry.gains[frame] - cov @ photometry.beta
    return weighted_median(cell, corrected, weight, n_cells)


def brightness_outlier_weight(ratio: np.ndarray, rel: float) -> np.ndarray:
    """1 up to ``1 + rel`` times the reference brightness, fading to 1e-3 at ``1 + 2.5·rel``."""
    x = np.clip((ratio - 1.0 - rel) / (1.5 * rel), 0.0, 1.0)
    w = 1.0 - x * x * (3 - 2 * x)
    return np.maximum(w, 1e-3).astype(np.float32)
