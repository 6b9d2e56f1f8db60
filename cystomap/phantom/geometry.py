"""Bladder geometry of the phantom: a closed, slightly irregular star-shaped wall with a neck.

World frame of session 1 (and of session 2, which is session 1 deformed in place):

* origin = barycentre (volume centroid) of session 1's bladder, the aperture capped flat;
* x = longest axis (``size_mm[0]``), y = ``size_mm[1]``, z = ``size_mm[2]``, z up;
* the aperture (bladder neck) is at the bottom, its axis along -z; the urethra tube is a
  straight cylinder of the aperture's diameter running from the neck downwards (-z);
* anatomy: the patient's anterior is +y (``ANTERIOR``), so the patient's left is -x and the
  right +x (:attr:`Bladder.anatomy`); the scope enters upright (image up = anterior).

The wall is star-shaped about the barycentre: ``r(u) = ellipsoid(u) * (1 + smooth noise(u))
* (1 + neck funnel(u))``, with the semi-axes rescaled so the bounding box is ``size_mm``.
The triangle mesh is built on a (neck-angle, azimuth) grid so the aperture rim is exact.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass, field

import numpy as np

from cystomap.errors import InputError
from cystomap.phantom.config import PhantomConfig

log = logging.getLogger(__name__)

# seed-stream ids (see rng())
STREAM_SHAPE = 1
STREAM_TEXTURE = 2
STREAM_LESIONS = 3
STREAM_DEFORM = 4

#: The patient's anterior direction in the world frame (the dome is +z, the neck -z).
ANTERIOR = np.array([0.0, 1.0, 0.0])


def rng(cfg: PhantomConfig, *stream: int) -> np.random.Generator:
    """The numpy Generator of one purpose (``stream``) of this phantom's seed."""
    return np.random.default_rng(np.random.SeedSequence([int(cfg.seed), *stream]))


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def direction(az_deg: np.ndarray | float, el_deg: np.ndarray | float) -> np.ndarray:
    """Unit vector(s) for azimuth/elevation in degrees: (cos el cos az, cos el sin az, sin el)."""
    az, el = np.radians(az_deg), np.radians(el_deg)
    return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                        np.sin(el)), axis=-1)


def az_el(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation in degrees of vectors ``v`` (..., 3)."""
    v = np.asarray(v, dtype=np.float64)
    az = np.degrees(np.arctan2(v[..., 1], v[..., 0]))
    el = np.degrees(np.arctan2(v[..., 2], np.hypot(v[..., 0], v[..., 1])))
    return az, el


@dataclass(frozen=True)
class StarShape:
    """Radius of the closed wall as a function of direction (about the construction centre)."""

    semi_axes: np.ndarray
    wave_vectors: np.ndarray  # (K, 3)
    wave_amps: np.ndarray  # (K,)
    wave_phases: np.ndarray  # (K,)
    funnel_amp: float = 0.12
    funnel_width_rad: float = math.radians(32.0)

    def radius(self, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=np.float64)
        ell = 1.0 / np.sqrt(((u / self.semi_axes) ** 2).sum(-1))
        noise = 1.0 + (self.wave_amps * np.cos(u @ self.wave_vectors.T + self.wave_phases)).sum(-1)
        psi = np.arccos(np.clip(-u[..., 2], -1.0, 1.0))  # angle from the neck axis (-z)
        funnel = 1.0 + self.funnel_amp * np.exp(-((psi / self.funnel_width_rad) ** 2))
        return ell * noise * funnel


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (3 - math.sqrt(5)) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def make_star_shape(cfg: PhantomConfig) -> StarShape:
    """Random smooth shape from the seed, rescaled so its bounding box is ``cfg.size_mm``."""
    g = rng(cfg, STREAM_SHAPE)
    k = 10
    wv = unit(g.normal(size=(k, 3))) * g.uniform(1.0, 3.2, size=(k, 1))
    amps = g.normal(size=k) / np.sqrt(k) * cfg.irregularity
    phases = g.uniform(0, 2 * np.pi, size=k)
    target = np.asarray(cfg.size_mm, dtype=np.float64)
    semi = target / 2
    dirs = fibonacci_sphere(40000)
    shape = StarShape(semi, wv, amps, phases)
    for _ in range(6):
        pts = shape.radius(dirs)[:, None] * dirs
        extent = pts.max(0) - pts.min(0)
        semi = semi * target / extent
        shape = StarShape(semi, wv, amps, phases)
    return shape


@dataclass(frozen=True)
class Deformation:
    """Session-2 deformation x' = A x (1 + w(x/|x|)), about the session-1 barycentre."""

    magnitude: float
    scale: np.ndarray  # (3,) diagonal of A
    wave_vectors: np.ndarray
    wave_amps: np.ndarray
    wave_phases: np.ndarray

    def warp(self, u: np.ndarray) -> np.ndarray:
        return (self.wave_amps * np.cos(u @ self.wave_vectors.T + self.wave_phases)).sum(-1)

    def apply(self, x: np.ndarray) -> np.ndarray:
        if self.magnitude == 0:
            return np.array(x, dtype=np.float64, copy=True)
        r = np.linalg.norm(x, axis=-1, keepdims=True)
        u = x / np.maximum(r, 1e-9)
        return x * (1.0 + self.warp(u))[..., None] * self.scale

    def to_dict(self) -> dict:
        return {
            "magnitude": self.magnitude,
            "model": "x2 = diag(scale) @ x1 * (1 + sum_k amp_k cos(k_k . x1/|x1| + phase_k)),"
                     " x1 relative to the session-1 barycentre (world origin)",
            "scale": self.scale.tolist(),
            "warp_wave_vectors": self.wave_vectors.tolist(),
            "warp_amps": self.wave_amps.tolist(),
            "warp_phases": self.wave_phases.tolist(),
        }


def make_deformation(cfg: PhantomConfig) -> Deformation:
    g = rng(cfg, STREAM_DEFORM)
    a = g.uniform(-1, 1, size=3)
    a /= np.abs(a).max()
    k = 4
    wv = unit(g.normal(size=(k, 3))) * g.uniform(1.0, 2.2, size=(k, 1))
    amps = g.normal(size=k)
    phases = g.uniform(0, 2 * np.pi, size=k)
    d = cfg.deformation
    probe = fibonacci_sphere(4000)
    peak = np.abs((amps * np.cos(probe @ wv.T + phases)).sum(-1)).max()
    amps = amps / peak * d
    return Deformation(d, 1.0 + d * a, wv, amps, phases)


@dataclass
class Bladder:
    """Triangle mesh of one session: wall (first ``n_wall_tris`` triangles) + urethra tube."""

    vertices: np.ndarray  # (V, 3) float64, world mm
    triangles: np.ndarray  # (T, 3) int32, outward-facing (normals point out of the cavity)
    n_wall_tris: int
    n_wall_verts: int  # wall vertices come first; tube vertices after
    material: np.ndarray  # (V, 3) session-1 position of each vertex (texture coordinates)
    rim: np.ndarray  # (N,) wall vertex indices of the aperture rim, in azimuth order
    barycentre: np.ndarray  # (3,) volume centroid, aperture capped
    volume_mm3: float
    wall_area_mm2: float
    normals: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 3)))
    info: dict = field(default_factory=dict)

    @property
    def wall_vertices(self) -> np.ndarray:
        return self.vertices[: self.n_wall_verts]

    @property
    def wall_triangles(self) -> np.ndarray:
        return self.triangles[: self.n_wall_tris]

    @property
    def aperture_centre(self) -> np.ndarray:
        return self.vertices[self.rim].mean(0)

    @property
    def anatomy(self) -> dict[str, list[float]]:
        """The anatomical frame (see :mod:`cystomap.anatomy`): origin = barycentre, neck =
        unit direction to the aperture centre, anterior = ``ANTERIOR`` made orthogonal to it."""
        neck = unit(self.aperture_centre - self.barycentre)
        ant = unit(ANTERIOR - (ANTERIOR @ neck) * neck)
        return {"origin": [float(x) for x in self.barycentre], "neck": [float(x) for x in neck],
                "anterior": [float(x) for x in ant]}

    def scene(self):  # -> o3d.t.geometry.RaycastingScene
        """A raycasting scene of wall + tube (geometry id 0; primitive ids = triangle rows)."""
        from cystomap.geometry.raycast import scene_of

        return scene_of(self.vertices, self.triangles)


def _ring_dirs(psi: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Directions at angle ``psi`` from the neck axis (-z) and azimuth ``phi``."""
    s = np.sin(psi)
    return np.stack(np.broadcast_arrays(s * np.cos(phi), s * np.sin(phi), -np.cos(psi)), -1)


def _rim_angle(shape: StarShape, phi: np.ndarray, radius: float) -> np.ndarray:
    """Angle from the neck axis where the wall meets the cylinder of the aperture radius."""
    lo = np.full_like(phi, 1e-4)
    hi = np.full_like(phi, math.pi / 2)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        d = _ring_dirs(mid, phi)
        inside = shape.radius(d) * np.sin(mid) < radius
        lo = np.where(inside, mid, lo)
        hi = np.where(inside, hi, mid)
    return 0.5 * (lo + hi)


def _grid_triangles(rows: np.ndarray) -> np.ndarray:
    """Quads between consecutive rows of vertex indices (each row a closed loop) → triangles."""
    a, b = rows[:-1], rows[1:]
    a1, b1 = np.roll(a, -1, axis=1), np.roll(b, -1, axis=1)
    t1 = np.stack([a, a1, b1], -1).reshape(-1, 3)
    t2 = np.stack([a, b1, b], -1).reshape(-1, 3)
    return np.concatenate([t1, t2])


def triangle_normals(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Unnormalised triangle normals (length = 2 x area)."""
    return np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])


def vertex_normals(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    fn = triangle_normals(v, t)
    n = np.zeros_like(v)
    for k in range(3):
        for c in range(3):
            n[:, c] += np.bincount(t[:, k], weights=fn[:, c], minlength=len(v))
    return unit(n + 1e-30)


def closed_volume_centroid(v: np.ndarray, t: np.ndarray) -> tuple[float, np.ndarray]:
    """Volume and centroid of a closed, outward-oriented triangle surface."""
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    total = vol.sum()
    centroid = ((a + b + c) / 4.0 * vol[:, None]).sum(0) / total
    return float(total), centroid


def _build_mesh(cfg: PhantomConfig, shape: StarShape) -> dict:
    ra = cfg.aperture_mm / 2
    a, b, _ = shape.semi_axes
    circ = math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))
    n_phi = math.ceil(circ / cfg.mesh_edge_mm / 8.0) * 8
    phi = np.arange(n_phi) * (2 * math.pi / n_phi)
    psi_rim = _rim_angle(shape, phi, ra)
    # meridian length (rim to top pole), longest over azimuth → number of rings
    tau_f = np.linspace(0, 1, 400)[:, None]
    psi_f = psi_rim[None, :] + tau_f * (math.pi - psi_rim[None, :])
    d_f = _ring_dirs(psi_f, phi[None, :])
    p_f = shape.radius(d_f)[..., None] * d_f
    arc = np.linalg.norm(np.diff(p_f, axis=0), axis=-1).sum(0).max()
    n_tau = math.ceil(arc / cfg.mesh_edge_mm)
    tau = np.arange(n_tau) / n_tau  # ring 0 = rim; the top pole is a separate vertex
    psi = psi_rim[None, :] + tau[:, None] * (math.pi - psi_rim[None, :])
    d = _ring_dirs(psi, phi[None, :])
    rings = shape.radius(d)[..., None] * d  # (n_tau, n_phi, 3)
    # snap the rim exactly onto the aperture cylinder
    rings[0, :, 0] = ra * np.cos(phi)
    rings[0, :, 1] = ra * np.sin(phi)
    top = np.array([0.0, 0.0, 1.0])
    pole = shape.radius(top[None])[0] * top
    wall_v = np.concatenate([rings.reshape(-1, 3), pole[None]])
    idx = np.arange(n_tau * n_phi).reshape(n_tau, n_phi)
    tris = [_grid_triangles(idx)]
    last = idx[-1]
    pole_i = n_tau * n_phi
    tris.append(np.stack([last, np.roll(last, -1), np.full_like(last, pole_i)], -1))
    wall_t = np.concatenate(tris).astype(np.int64)
    # urethra tube: its own vertices (so its normals do not blend with the wall's)
    z_rim = rings[0, :, 2]
    z_end = z_rim.min() - cfg.urethra_length_mm
    n_z = max(4, math.ceil((z_rim.max() - z_end) / (2 * cfg.mesh_edge_mm)))
    s = np.linspace(0, 1, n_z + 1)[:, None]
    tube = np.empty((n_z + 1, n_phi, 3))
    tube[..., 0] = ra * np.cos(phi)
    tube[..., 1] = ra * np.sin(phi)
    tube[..., 2] = z_rim[None, :] + s * (z_end - z_rim[None, :])
    nv = len(wall_v)
    tidx = nv + np.arange((n_z + 1) * n_phi).reshape(n_z + 1, n_phi)
    tube_t = _grid_triangles(tidx).astype(np.int64)
    verts = np.concatenate([wall_v, tube.reshape(-1, 3)])
    # orient: wall normals point away from the centre; tube normals away from its axis
    fn = triangle_normals(verts, wall_t)
    if np.einsum("ij,ij->i", fn, verts[wall_t].mean(1)).mean() < 0:
        wall_t = wall_t[:, ::-1]
    fn = triangle_normals(verts, tube_t)
    cen = verts[tube_t].mean(1)
    if np.einsum("ij,ij->i", fn[:, :2], cen[:, :2]).mean() < 0:
        tube_t = tube_t[:, ::-1]
    return {
        "vertices": verts, "wall_t": wall_t, "tube_t": tube_t, "n_wall_verts": nv,
        "rim": idx[0].copy(), "n_phi": n_phi, "n_tau": n_tau,
    }


def _cap_triangles(v: np.ndarray, rim: np.ndarray, wall_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A fan closing the aperture (for volume and centroid only), consistently oriented."""
    centre = v[rim].mean(0)
    vv = np.concatenate([v, centre[None]])
    ci = len(v)
    cap = np.stack([rim, np.roll(rim, -1), np.full_like(rim, ci)], -1)
    # the wall triangle holding rim edge (rim[0], rim[1]) uses it in one direction; the cap
    # must use it in the opposite direction.
    a0, a1 = int(rim[0]), int(rim[1])
    t = wall_t
    forward = ((t[:, 0] == a0) & (t[:, 1] == a1)) | ((t[:, 1] == a0) & (t[:, 2] == a1)) | (
        (t[:, 2] == a0) & (t[:, 0] == a1))
    if forward.any():
        cap = cap[:, ::-1]
    return vv, np.concatenate([wall_t, cap])


def _measure(v: np.ndarray, rim: np.ndarray, wall_t: np.ndarray) -> tuple[float, np.ndarray, float]:
    vv, closed = _cap_triangles(v, rim, wall_t)
    vol, cen = closed_volume_centroid(vv, closed)
    area = float(np.linalg.norm(triangle_normals(v, wall_t), axis=1).sum() / 2)
    return vol, cen, area


def _check_star(v: np.ndarray, wall_t: np.ndarray, centre: np.ndarray, what: str) -> None:
    fn = triangle_normals(v, wall_t)
    rel = v[wall_t].mean(1) - centre
    cos = np.einsum("ij,ij->i", unit(fn), unit(rel))
    if cos.min() <= 0.05:
        raise InputError(
            f"phantom: {what} is not star-shaped about its barycentre (min cos {cos.min():.3f});"
            " lower irregularity or deformation"
        )


@functools.lru_cache(maxsize=4)
def _base_bladder_cached(key: tuple) -> Bladder:
    cfg = PhantomConfig(**dict(key))
    shape = make_star_shape(cfg)
    m = _build_mesh(cfg, shape)
    v = m["vertices"]
    vol, cen, area = _measure(v, m["rim"], m["wall_t"])
    v = v - cen
    _check_star(v, m["wall_t"], np.zeros(3), "the bladder")
    tris = np.concatenate([m["wall_t"], m["tube_t"]]).astype(np.int32)
    nw = m["n_wall_verts"]
    normals = np.concatenate([vertex_normals(v[:nw], m["wall_t"]),
                              vertex_normals(v, m["tube_t"])[nw:]])
    b = Bladder(
        vertices=v, triangles=tris, n_wall_tris=len(m["wall_t"]), n_wall_verts=nw,
        material=v.copy(), rim=m["rim"], barycentre=np.zeros(3), volume_mm3=vol,
        wall_area_mm2=area, normals=normals,
        info={"construction_offset_mm": (-cen).tolist(), "semi_axes_mm": shape.semi_axes.tolist(),
              "n_phi": m["n_phi"], "n_tau": m["n_tau"]},
    )
    for arr in (b.vertices, b.triangles, b.material, b.normals, b.rim):
        arr.setflags(write=False)
    return b


GEOMETRY_KEYS = ("seed", "size_mm", "aperture_mm", "irregularity", "urethra_length_mm",
                 "mesh_edge_mm")


def base_bladder(cfg: PhantomConfig) -> Bladder:
    """Session-1 bladder (cached; arrays are read-only)."""
    return _base_bladder_cached(tuple((k, getattr(cfg, k)) for k in GEOMETRY_KEYS))


def _relief(cfg: PhantomConfig, base: Bladder) -> np.ndarray | None:
    """Vertex displacement of session 2's raised (papillary) lesions, None without any."""
    if "papillary" not in cfg.lesion_kinds or not cfg.lesion_diameters_mm:
        return None
    from cystomap.phantom.lesions import lesion_relief, place_lesions

    return lesion_relief(cfg, base, place_lesions(cfg, base, base.scene()))


def session_bladder(cfg: PhantomConfig, session: int) -> Bladder:
    """The bladder of ``session`` (1 or 2) in its world frame; session 2 is deformed."""
    if session not in (1, 2):
        raise InputError(f"phantom: session must be 1 or 2, got {session!r}")
    base = base_bladder(cfg)
    relief = _relief(cfg, base) if session == 2 else None
    if session == 1 or (cfg.deformation == 0 and relief is None):
        return base
    deform = make_deformation(cfg)
    v = deform.apply(base.vertices if relief is None else base.vertices + relief)
    wall_t = base.wall_triangles
    vol, cen, area = _measure(v, base.rim, wall_t)
    _check_star(v, wall_t, cen, "the deformed bladder")
    nw = base.n_wall_verts
    normals = np.concatenate([vertex_normals(v[:nw], wall_t),
                              vertex_normals(v, base.triangles[base.n_wall_tris:])[nw:]])
    info = dict(base.info)
    info["deformation"] = deform.to_dict()
    if relief is not None:
        info["relief_max_mm"] = float(np.linalg.norm(relief, axis=1).max())
    return Bladder(
        vertices=v, triangles=base.triangles, n_wall_tris=base.n_wall_tris, n_wall_verts=nw,
        material=base.material, rim=base.rim, barycentre=cen, volume_mm3=vol,
        wall_area_mm2=area, normals=normals, info=info,
    )


def wall_extent(vertices: np.ndarray) -> float:
    """Largest distance between two points of the wall (attained at mesh vertices), exact.

    A lower bound L comes from a few farthest-point iterations; a pair at distance >= L has
    both points at least L - R from the box centre (R = largest radius), which leaves few
    candidates for the exhaustive search.
    """
    v = np.asarray(vertices, dtype=np.float64)
    c = 0.5 * (v.max(0) + v.min(0))
    r = np.linalg.norm(v - c, axis=1)
    p = v[int(r.argmax())]
    best = 0.0
    for _ in range(4):
        d = np.linalg.norm(v - p, axis=1)
        i = int(d.argmax())
        best = max(best, float(d[i]))
        p = v[i]
    cand = v[r >= best - r.max() - 1e-6]
    for i in range(0, len(cand), 1024):
        d = np.linalg.norm(cand[i:i + 1024, None, :] - cand[None, :, :], axis=-1)
        best = max(best, float(d.max()))
    return best


def wall_bbox(vertices: np.ndarray) -> list[float]:
    return (vertices.max(0) - vertices.min(0)).tolist()
