"""Image formation: ray casting the bladder mesh from the true pose, through the lens model.

Per pixel: the ray of the *distorted* pixel (the pixel grid undistorted once with
cv2.undistortPoints), first hit on the wall/tube mesh, albedo from the cube map at the hit's
material point, prefiltered by the pixel's footprint on the wall (ray differentials: two
trilinear mipmap taps along the footprint's longer edge, so the fine texture neither aliases
nor over-blurs at low resolution), light at the tip: ``E = cos(incidence) / distance^2``,
vignetting ``cos^3`` of the ray's angle to the optical axis, auto-exposure, gamma 1/2.2,
session gain, a slight optical blur (a fixed angle, so the same optics at every resolution),
optional motion blur, specular glints and bad frames, Gaussian sensor noise. Output is 8-bit
RGB.

The display value is ``albedo * (exposure * E * V) ** (1 / 2.2) * gain``, i.e. a per-pixel
scalar times the true albedo colour (up to glints, blur, noise and clipping).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cystomap.camera import Camera
from cystomap.errors import InputError
from cystomap.phantom.cubemap import CubeMap
from cystomap.phantom.geometry import Bladder, unit
from cystomap.phantom.wall_rays import cast

GAMMA = 2.2
EXPOSURE_TARGET = 0.55  # 60th percentile of exposure * E * V
TUBE_DARKENING = 0.6
# optical point spread (Gaussian sigma) as an angle: 0.55 px of the 1280x720 76-degree camera
# (the same optics at every resolution)
OPTICAL_BLUR_RAD = 0.55 / 939.864
MIN_COS_FOOTPRINT = 0.1  # grazing incidence: pixel footprints at most 10x stretched
SPECULAR_STRENGTH = 3.0
SPECULAR_EXPONENT = 150.0


def rotate(v: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """``v @ rot.T`` for many row vectors (cv2.transform: fast, no BLAS threading)."""
    v = np.ascontiguousarray(v)
    return cv2.transform(v.reshape(-1, 1, 3), np.asarray(rot, np.float64)).reshape(-1, 3)


def default_camera(width: int = 1280, height: int = 720) -> Camera:
    """The phantom's default camera: 76 deg diagonal (pinhole), mild barrel distortion.

    Modelled on the miniature camera of the reference phantom study (1280 x 720, 76 deg).
    """
    f = 0.5 * math.hypot(width, height) / math.tan(math.radians(76.0) / 2)
    return Camera(width, height, f, f, (width - 1) / 2, (height - 1) / 2,
                  (-0.18, 0.04, 0.0005, -0.0003, 0.0), calibrated=True, name="phantom")


@dataclass
class RayGrid:
    """Unit camera-frame rays of every pixel (row-major), with per-pixel helpers."""

    width: int
    height: int
    dirs: np.ndarray  # (H*W, 3) float32
    pixel_angle: np.ndarray  # (H*W,) float32, angular size of the pixel (rad)
    vignette: np.ndarray  # (H*W,) float32, cos^3 of the angle to the optical axis
    max_radius: float = np.inf  # largest undistorted normalised radius in the image
    du: np.ndarray | None = None  # (H*W, 3) float32, change of the ray per pixel step in u
    dv: np.ndarray | None = None  # (H*W, 3) float32, ... in v


def _distort(x: np.ndarray, y: np.ndarray, dist) -> tuple[np.ndarray, ...]:
    """OpenCV distortion of normalised coordinates and its Jacobian."""
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d rad / d r2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    dxx = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    dxy = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    dyx = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    dyy = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    return xd, yd, dxx, dxy, dyx, dyy


def project_points(camera: Camera, xc: np.ndarray) -> np.ndarray:
    """Same as ``camera.project`` (OpenCV pinhole + distortion), vectorised for many points."""
    x = xc[:, 0] / xc[:, 2]
    y = xc[:, 1] / xc[:, 2]
    xd, yd = _distort(x, y, camera.dist)[:2]
    return np.stack([camera.fx * xd + camera.cx, camera.fy * yd + camera.cy], -1)


def _refine_undistort(xy: np.ndarray, pix: np.ndarray, camera: Camera) -> np.ndarray:
    """Newton iterations on cv2.undistortPoints' approximate answer (to ~1e-12)."""
    xt = (pix[:, 0] - camera.cx) / camera.fx
    yt = (pix[:, 1] - camera.cy) / camera.fy
    x, y = xy[:, 0].copy(), xy[:, 1].copy()
    for _ in range(8):
        xd, yd, a, b, c, d = _distort(x, y, camera.dist)
        ex, ey = xd - xt, yd - yt
        det = a * d - b * c
        x -= (d * ex - b * ey) / det
        y -= (a * ey - c * ex) / det
        if max(np.abs(ex).max(), np.abs(ey).max()) < 1e-13:
            break
    return np.stack([x, y], -1)


def pixel_rays(camera: Camera) -> RayGrid:
    """Rays of the distorted pixel grid (pixel centres at integer coordinates)."""
    w, h = camera.width, camera.height
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u, v], -1).reshape(-1, 1, 2)
    if camera.has_distortion:
        und = cv2.undistortPoints(pts, camera.K, camera.dist_array)
        xy = _refine_undistort(und.reshape(-1, 2), pts.reshape(-1, 2), camera)
    else:
        xy = np.stack([(pts[:, 0, 0] - camera.cx) / camera.fx,
                       (pts[:, 0, 1] - camera.cy) / camera.fy], -1)
    xyz = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    # round trip through Camera.project (OpenCV) on a subsample including the image border
    border = np.flatnonzero((u == 0) | (v == 0) | (u == w - 1) | (v == h - 1))
    check = np.union1d(np.arange(0, len(xy), 97), border)
    back = camera.project(xyz[check])
    err = float(np.abs(back - pts.reshape(-1, 2)[check]).max())
    if not err < 1e-3:
        raise InputError(f"camera {camera.name!r}: distortion not invertible over the image "
                         f"(round-trip error {err:.3g} px)")
    d = unit(xyz)
    grid = d.reshape(h, w, 3)
    du = np.gradient(grid, axis=1) if w > 1 else np.zeros_like(grid)
    dv = np.gradient(grid, axis=0) if h > 1 else np.zeros_like(grid)
    gx = np.linalg.norm(du, axis=-1)
    gy = np.linalg.norm(dv, axis=-1)
    ang = np.sqrt(gx * gy).reshape(-1)
    return RayGrid(w, h, d.astype(np.float32), ang.astype(np.float32),
                   (d[:, 2] ** 3).astype(np.float32), float(np.hypot(xy[:, 0], xy[:, 1]).max()),
                   du.reshape(-1, 3).astype(np.float32), dv.reshape(-1, 3).astype(np.float32))


@dataclass
class Trace:
    t: np.ndarray  # (N,) distance along the ray, inf = miss
    hit: np.ndarray  # (N,) bool
    wall: np.ndarray  # (N,) bool, hit on the wall (not the tube)
    material: np.ndarray  # (M, 3) material points of hits (M = hit.sum())
    normal: np.ndarray  # (M, 3) normals of hits (interpolated vertex normals, session frame)
    cos_inc: np.ndarray  # (M,) cosine of incidence (light at the tip)
    t_hit: np.ndarray  # (M,) distances of the hits
    all_hit: bool  # every pixel hit something (then M = N and hit-indexing is a no-op)
    rot: np.ndarray | None = None  # camera-to-world rotation of the frame
    dirs: np.ndarray | None = None  # (M, 3) unit ray directions of the hits (session frame)
    pid: np.ndarray | None = None  # (M,) triangle ids of the hits
    dot: np.ndarray | None = None  # (M,) normal . ray direction (signed cos_inc)

    def of_hits(self, per_pixel: np.ndarray) -> np.ndarray:
        """Per-pixel array restricted to the hit pixels."""
        return per_pixel if self.all_hit else per_pixel[self.hit]


class Renderer:
    def __init__(self, camera: Camera, bladder: Bladder, scene, cube: CubeMap,
                 rays: RayGrid | None = None, falloff_exponent: float = 2.0) -> None:
        self.camera = camera
        self.falloff_exponent = falloff_exponent
        self.bladder = bladder
        self.scene = scene
        self.cube = cube
        self.rays = rays if rays is not None else pixel_rays(camera)
        tri = bladder.triangles
        # session 1: the material point is the hit point itself (no per-pixel gather)
        self.material_is_world = bladder.material is bladder.vertices or bool(
            np.array_equal(bladder.material, bladder.vertices))
        self.tri_mat = bladder.material[tri].reshape(-1, 9).astype(np.float32)
        self.tri_nrm = bladder.normals[tri].reshape(-1, 9).astype(np.float32)
        self.tri_jac = None if self.material_is_world else material_jacobians(bladder)

    def trace(self, rot: np.ndarray, centre: np.ndarray, nthreads: int = 0,
              rays: RayGrid | None = None) -> Trace:
        rg = rays if rays is not None else self.rays
        dirs = rotate(rg.dirs, rot)
        hit = cast(self.scene, centre.astype(np.float32), dirs, nthreads=nthreads)
        t = hit["t_hit"]
        ok = np.isfinite(t)
        everything = bool(ok.all())
        pid = hit["primitive_ids"] if everything else hit["primitive_ids"][ok]
        uv = hit["primitive_uvs"] if everything else hit["primitive_uvs"][ok]
        d_ok = dirs if everything else dirs[ok]
        u, v = uv[:, :1], uv[:, 1:]
        w0 = 1 - u - v
        tn = np.take(self.tri_nrm, pid, axis=0)
        nrm = tn[:, 0:3] * w0
        nrm += tn[:, 3:6] * u
        nrm += tn[:, 6:9] * v
        del tn
        # (interpolated unit vertex normals differ by ~1 deg: their length is 1 - 1e-4, so
        # they are not renormalised)
        dot = np.einsum("ij,ij->i", nrm, d_ok)
        cos_inc = np.abs(dot)
        th = t if everything else t[ok]
        if self.material_is_world:
            mat = d_ok * th[:, None]
            mat += centre.astype(np.float32)
        else:
            tm = np.take(self.tri_mat, pid, axis=0)
            mat = tm[:, 0:3] * w0
            mat += tm[:, 3:6] * u
            mat += tm[:, 6:9] * v
        wall = np.zeros(len(t), bool)
        wall[ok] = pid < self.bladder.n_wall_tris
        return Trace(t, ok, wall, mat, nrm, cos_inc, th, everything, rot, d_ok, pid, dot)

    def footprint_axes(self, tr: Trace) -> tuple[np.ndarray, np.ndarray]:
        """Edges of each hit pixel's footprint on the wall (ray differentials): two (3, M)
        arrays (x, y, z rows) in material mm.

        A one-pixel step of the ray (``du``/``dv``) moves the hit along the tangent plane by
        ``t * (dd - (dd . n) / (d . n) * d)``; the session-2 deformation maps it to material
        coordinates with the hit triangle's Jacobian. Grazing incidence is capped at
        MIN_COS_FOOTPRINT.
        """
        rg = self.rays
        t = tr.t_hit
        d = np.ascontiguousarray(tr.dirs.T)
        n = np.ascontiguousarray(tr.normal.T)
        dn = tr.dot
        inv = t / np.copysign(np.maximum(np.abs(dn), MIN_COS_FOOTPRINT), dn)
        jac = None if self.tri_jac is None else np.take(self.tri_jac, tr.pid, axis=1)
        out = []
        for dd in (rg.du, rg.dv):
            w = np.ascontiguousarray(rotate(tr.of_hits(dd), tr.rot).T)
            c = w[0] * n[0]
            c += w[1] * n[1]
            c += w[2] * n[2]
            c *= inv
            w *= t
            for i in range(3):
                w[i] -= d[i] * c
            if jac is not None:
                w = np.stack([jac[3 * i] * w[0] + jac[3 * i + 1] * w[1] + jac[3 * i + 2] * w[2]
                              for i in range(3)])
            out.append(w)
        return out[0], out[1]

    def irradiance(self, tr: Trace, rays: RayGrid | None = None) -> np.ndarray:
        """E * V per hit pixel (linear, before exposure)."""
        rg = rays if rays is not None else self.rays
        return tr.cos_inc / self.falloff(tr.t_hit) * tr.of_hits(rg.vignette)

    def falloff(self, th: np.ndarray) -> np.ndarray:
        """Illumination fall-off with distance: ``t ** falloff_exponent`` (2 = inverse square)."""
        if self.falloff_exponent == 2.0:
            return th * th
        return np.power(th, np.float32(self.falloff_exponent))

    def shade(self, tr: Trace, exposure: float, gain: float, specular: bool) -> np.ndarray:
        """Float RGB image (H, W, 3) in display units 0..255 (before noise and blur)."""
        rg = self.rays
        th = tr.t_hit
        if rg.du is not None and tr.rot is not None:
            albedo, gloss = self.cube.sample(tr.material, with_gloss=specular,
                                             axes=self.footprint_axes(tr))
        else:
            footprint = th * tr.of_hits(rg.pixel_angle) / np.maximum(tr.cos_inc, 0.2)
            albedo, gloss = self.cube.sample(tr.material, footprint, with_gloss=specular)
        tube = ~tr.of_hits(tr.wall)
        if tube.any():
            albedo[tube] *= TUBE_DARKENING
        lin = exposure * self.irradiance(tr)
        if specular and gloss is not None:
            a_lin = (albedo / 255.0) ** GAMMA * lin[:, None]
            spec = (SPECULAR_STRENGTH * exposure * gloss * tr.cos_inc**SPECULAR_EXPONENT
                    / self.falloff(th) * tr.of_hits(rg.vignette))
            shaded = 255.0 * np.power(a_lin + spec[:, None], 1 / GAMMA) * gain
        else:
            albedo *= (np.power(lin, 1 / GAMMA) * gain)[:, None]
            shaded = albedo
        if tr.all_hit:
            img = shaded
        else:
            img = np.zeros((rg.height * rg.width, 3), np.float32)
            img[tr.hit] = shaded
        return img.reshape(rg.height, rg.width, 3)


def material_jacobians(bladder: Bladder) -> np.ndarray:
    """Per triangle, the 3x3 map of in-plane world displacements to material ones: (9, N),
    row-major matrix entries in rows."""
    tri = bladder.triangles
    pw = bladder.vertices[tri]
    pm = bladder.material[tri]
    ew = np.stack([pw[:, 1] - pw[:, 0], pw[:, 2] - pw[:, 0]], -1)  # (N, 3, 2)
    em = np.stack([pm[:, 1] - pm[:, 0], pm[:, 2] - pm[:, 0]], -1)
    gram = np.einsum("nki,nkj->nij", ew, ew)
    det = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] ** 2
    det = np.where(np.abs(det) > 1e-12, det, 1e-12)
    ginv = np.stack([np.stack([gram[:, 1, 1], -gram[:, 0, 1]], -1),
                     np.stack([-gram[:, 0, 1], gram[:, 0, 0]], -1)], 1) / det[:, None, None]
    jac = np.einsum("nai,nij,nbj->nab", em, ginv, ew)  # em (ew^T ew)^-1 ew^T
    return np.ascontiguousarray(jac.reshape(-1, 9).T, dtype=np.float32)


def optical_blur_px(camera: Camera) -> float:
    """Gaussian sigma (px) of the optical point spread for ``camera``."""
    return OPTICAL_BLUR_RAD * math.sqrt(camera.fx * camera.fy)


def motion_kernel(length: float, angle_rad: float) -> np.ndarray:
    """Normalised linear motion-blur kernel of ``length`` px along ``angle_rad``."""
    half = length / 2
    size = 2 * math.ceil(half) + 3
    k = np.zeros((size, size), np.float32)
    c = size // 2
    n = max(8, math.ceil(length * 4))
    s = np.linspace(-half, half, n)
    x = c + s * math.cos(angle_rad)
    y = c + s * math.sin(angle_rad)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                        (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(k, (y0 + dy, x0 + dx), wgt)
    return k / k.sum()


def finish(img: np.ndarray, noise_rng: np.random.Generator, noise_sigma: float,
           blur_len: float = 0.0, blur_angle: float = 0.0, bad: str | None = None,
           optical_px: float = 0.55) -> np.ndarray:
    """Optical/motion blur, bad-frame effects, sensor noise → uint8 RGB.

    ``optical_px``: sigma of the optical blur in pixels (``optical_blur_px(camera)``).
    """
    if optical_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), optical_px)
    if blur_len >= 1.0:
        img = cv2.filter2D(img, -1, motion_kernel(blur_len, blur_angle),
                           borderType=cv2.BORDER_REFLECT)
    if bad == "defocus":
        img = cv2.GaussianBlur(img, (0, 0), 0.015 * img.shape[1])
    elif bad == "black":
        img = img * 0.03
    if noise_sigma > 0:
        img = img + noise_rng.standard_normal(img.shape, dtype=np.float32) * noise_sigma
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)
