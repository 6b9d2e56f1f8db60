"""Lesions added to session 2: painted into its albedo, papillary ones also raised.

Each lesion is a disc on the wall (material frame) of the configured diameter with a
slightly irregular outline (mean radius = diameter / 2). Kinds (``cfg.lesion_kinds``):

* ``painted`` (default): whitish-pink fronds separated by dark red crevices, each frond with
  a red vascular core, and a faint reddish halo (1.5 mm) around it; flat (colour only);
* ``papillary``: the same look, raised into the cavity (a lobed dome of height
  ``PAPILLARY_HEIGHT * diameter``, at most PAPILLARY_MAX_MM) in session 2's geometry;
* ``cis``: flat red velvety patch (carcinoma in situ): a low-contrast reddening with a
  fine velvety grain and a soft edge;
* ``scar``: pale, elongated (axes 1.35 : 1 / 1.35 about the mean radius) fibrous patch;
* ``perivascular``: a red patch right beside a vessel (~0.9 mm wide, painted in both
  sessions, so only the patch is new).

Sites (``cfg.lesion_sites``): ``any`` (random, >= 25 deg beyond the aperture), ``seam`` (centre
within 0.3 lesion radii of the atlas's +-180 deg azimuth seam, so the lesion spans it),
``pole`` (within 0.3 radii of the top pole), ``neck`` (edge ~4 deg beyond the aperture).
Centres are random (seeded), away from the aperture and from each other.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from cystomap.errors import InputError
from cystomap.phantom.config import PhantomConfig
from cystomap.phantom.cubemap import MARGIN, CubeMap, _face_grid, face_dirs
from cystomap.phantom.geometry import STREAM_LESIONS, Bladder, az_el, direction, rng, unit
from cystomap.phantom.wall_rays import cast, interpolate_hit

log = logging.getLogger(__name__)

HALO_MM = 1.5
MIN_GAP_MM = 15.0
APERTURE_CLEARANCE_DEG = 25.0
NECK_CLEARANCE_DEG = 4.0  # "neck" lesions: edge this far beyond the aperture's angular radius
PAPILLARY_HEIGHT = 0.35  # relief height / diameter
PAPILLARY_MAX_MM = 6.0
SITE_VESSEL_WIDTH_MM = 0.9
PALE_SCAR = np.array([0.95, 0.84, 0.78])
SCAR_BLEND = 0.45  # share of the wall's colour replaced by PALE_SCAR inside a scar


@dataclass(frozen=True)
class Lesion:
    id: int
    diameter_mm: float
    triangle: int  # wall triangle holding the centre
    uv: tuple[float, float]  # barycentric (u, v) of the centre in that triangle (open3d order)
    material: np.ndarray  # centre, session-1 frame
    normal: np.ndarray  # outward normal at the centre, session-1 frame
    outline_amp: np.ndarray  # outline harmonics k = 2..5
    outline_phase: np.ndarray
    pattern_seed: int
    kind: str = "painted"
    site: str = "any"
    height_mm: float = 0.0  # relief (papillary), mm into the cavity


def _per_lesion(values: tuple[str, ...], n: int, default: str, g: np.random.Generator) -> list[str]:
    """One value per lesion: ``values`` as given when one per lesion, drawn from it otherwise."""
    if not values:
        return [default] * n
    if len(values) == n:
        return list(values)
    return [str(v) for v in g.choice(list(values), size=n)]


def lesion_kinds_and_sites(cfg: PhantomConfig) -> tuple[list[str], list[str]]:
    """Kind and site of each lesion (config order), seeded."""
    n = len(cfg.lesion_diameters_mm)
    g = rng(cfg, STREAM_LESIONS, 1)
    return (_per_lesion(cfg.lesion_kinds, n, "painted", g),
            _per_lesion(cfg.lesion_sites, n, "any", g))


def _about(axis: np.ndarray, angle_deg: float, azimuth: float) -> np.ndarray:
    """Unit direction at ``angle_deg`` from ``axis``, azimuth ``azimuth`` (rad) about it."""
    a1 = unit(np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0]))
    a2 = np.cross(axis, a1)
    t = math.radians(angle_deg)
    return unit(math.cos(t) * axis + math.sin(t) * (math.cos(azimuth) * a1 + math.sin(azimuth) * a2))


def aperture_cone(bladder: Bladder) -> tuple[np.ndarray, float]:
    """Direction (from the barycentre) and angular radius (deg) of the aperture."""
    rel = bladder.vertices[bladder.rim] - bladder.barycentre
    axis = unit(rel.mean(0))
    ang = np.degrees(np.arccos(np.clip(unit(rel) @ axis, -1, 1))).max()
    return axis, float(ang)


def place_lesions(cfg: PhantomConfig, bladder: Bladder, scene) -> list[Lesion]:
    """Random lesion sites on the session-1 wall (seeded; lesions bound to a site, then larger
    lesions, placed first)."""
    g = rng(cfg, STREAM_LESIONS)
    ap_dir, ap_ang = aperture_cone(bladder)
    kinds, sites = lesion_kinds_and_sites(cfg)
    # lesions bound to a site (seam, pole, neck: a small window each) first, so that a large
    # lesion placed anywhere cannot take the window; then larger before smaller
    order = sorted(range(len(cfg.lesion_diameters_mm)),
                   key=lambda i: (sites[i] == "any", -cfg.lesion_diameters_mm[i]))
    placed: dict[int, Lesion] = {}

    def wall_radius(u: np.ndarray) -> float:
        t = cast(scene, bladder.barycentre[None], u[None])["t_hit"][0]
        return float(t) if np.isfinite(t) else 50.0

    for idx in order:
        diam = float(cfg.lesion_diameters_mm[idx])
        site = sites[idx]
        for _attempt in range(5000):
            if site == "any":
                u = unit(g.normal(size=3))
            elif site == "seam":
                el = g.uniform(-25.0, 55.0)
                ang = math.degrees(diam / 2 / wall_radius(direction(180.0, el)))
                u = direction(180.0 + g.uniform(-0.3, 0.3) * ang, el)
            elif site == "pole":
                ang = math.degrees(diam / 2 / wall_radius(np.array([0.0, 0.0, 1.0])))
                u = _about(np.array([0.0, 0.0, 1.0]), g.uniform(0, 0.3) * ang, g.uniform(0, 2 * np.pi))
            else:  # neck
                phi = g.uniform(0, 2 * np.pi)
                ang = math.degrees(diam / 2 / wall_radius(_about(ap_dir, ap_ang + 10.0, phi)))
                u = _about(ap_dir, ap_ang + NECK_CLEARANCE_DEG + ang * g.uniform(1.05, 1.3), phi)
            hit = cast(scene, bladder.barycentre[None], u[None])
            if not np.isfinite(hit["t_hit"][0]):
                continue
            _, mat, wall, nrm = interpolate_hit(bladder, hit, with_normals=True)
            if not wall[0]:
                continue
            m = mat[0]
            ang_r = math.degrees(diam / 2 / np.linalg.norm(m))
            clearance = NECK_CLEARANCE_DEG if site == "neck" else APERTURE_CLEARANCE_DEG
            if math.degrees(math.acos(float(np.clip(u @ ap_dir, -1, 1)))) < (
                    ap_ang + clearance + ang_r):
                continue
            if any(np.linalg.norm(m - o.material) < (diam + o.diameter_mm) / 2 + MIN_GAP_MM
                   for o in placed.values()):
                continue
            placed[int(idx)] = Lesion(
                id=int(idx) + 1, diameter_mm=diam, triangle=int(hit["primitive_ids"][0]),
                uv=(float(hit["primitive_uvs"][0, 0]), float(hit["primitive_uvs"][0, 1])),
                material=m, normal=nrm[0], outline_amp=g.normal(0, 0.035, size=4),
                outline_phase=g.uniform(0, 2 * np.pi, size=4),
                pattern_seed=int(g.integers(0, 2**31 - 1)), kind=kinds[idx], site=site,
                height_mm=(min(PAPILLARY_HEIGHT * diam, PAPILLARY_MAX_MM)
                           if kinds[idx] == "papillary" else 0.0),
            )
            break
        else:
            raise InputError(f"phantom: cannot place a {diam} mm lesion; fewer or smaller lesions")
    return [placed[i] for i in sorted(placed)]


def lesion_rows(lesions: list[Lesion], bladder: Bladder) -> list[dict]:
    """lesions.csv rows: centre and outward normal in ``bladder``'s (session) world frame."""
    rows = []
    for les in lesions:
        tri = bladder.triangles[les.triangle]
        u, v = les.uv
        w = np.array([1 - u - v, u, v])
        p = w @ bladder.vertices[tri]
        n = unit(w @ bladder.normals[tri])
        az, el = az_el(p - bladder.barycentre)
        rows.append({"id": les.id, "x": p[0], "y": p[1], "z": p[2], "nx": n[0], "ny": n[1],
                     "nz": n[2], "diameter_mm": les.diameter_mm, "azimuth_deg": float(az),
                     "elevation_deg": float(el), "kind": les.kind, "site": les.site,
                     "height_mm": les.height_mm})
    return rows


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0, 1)
    return t * t * (3 - 2 * t)


def _worley(centres: np.ndarray, x: np.ndarray, y: np.ndarray):
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(centres).query(np.stack([x, y], 1), k=2)
    return dist[:, 0], dist[:, 1], idx[:, 0]


def _jittered(g: np.random.Generator, ext: float, sp: float) -> np.ndarray:
    grid = np.arange(-ext, ext + sp, sp)
    cx, cy = np.meshgrid(grid, grid)
    pts = np.stack([cx.ravel(), cy.ravel()], 1)
    return pts + g.uniform(-0.4, 0.4, size=pts.shape) * sp


def _pattern(les: Lesion, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RGB (0..1), opacity and halo weight at local coordinates (mm) of one lesion.

    Papillary look: irregular (domain-warped) fronds at two scales, bright pink-white tips,
    red crevices and a red vascular core per frond, a darker base along the outline."""
    g = np.random.default_rng(les.pattern_seed)
    rad = les.diameter_mm / 2
    r = np.hypot(x, y)
    th = np.arctan2(y, x)
    k = np.arange(2, 6)
    outline = rad * (1 + (les.outline_amp * np.cos(np.outer(th, k) + les.outline_phase)).sum(1))
    alpha = np.clip((outline - r) / 0.4 + 0.5, 0, 1)
    halo = np.exp(-np.clip(r - outline, 0, None) / (HALO_MM / 2)) * (r > outline - 0.2)
    sp = float(np.clip(0.7 + 0.03 * les.diameter_mm, 0.8, 1.5))
    # domain warp (smooth random displacement ~ 0.4 frond)
    wx = np.zeros_like(x)
    wy = np.zeros_like(y)
    for _ in range(4):
        kv = g.normal(size=2) / sp * 1.2
        ph = g.uniform(0, 2 * np.pi, size=2)
        amp = 0.2 * sp
        wx += amp * np.sin(x * kv[0] + y * kv[1] + ph[0])
        wy += amp * np.sin(x * kv[1] - y * kv[0] + ph[1])
    xw, yw = x + wx, y + wy
    ext = rad * 1.3 + 3 * sp
    f1, f2, idx = _worley(_jittered(g, ext, sp), xw, yw)
    sp_b = 0.45 * sp
    g1, g2, _ = _worley(_jittered(g, ext, sp_b), xw * 1.1 + wy, yw * 1.1 - wx)
    h_a = np.clip(1 - (f1 / (0.6 * sp)) ** 2, 0, 1)
    h_b = np.clip(1 - (g1 / (0.6 * sp_b)) ** 2, 0, 1)
    shade = 0.62 + 0.24 * np.sqrt(h_a) + 0.14 * np.sqrt(h_b)
    n_fr = int(idx.max()) + 1
    mix = g.uniform(0, 1, size=(n_fr, 1))
    tints = np.array([0.97, 0.76, 0.72]) * (1 - mix) + np.array([0.92, 0.56, 0.53]) * mix
    col = tints[idx] * shade[:, None]
    crevice = (1 - _smoothstep(0, 0.35 * sp, f2 - f1)) * 0.75 + (
        1 - _smoothstep(0, 0.3 * sp_b, g2 - g1)) * 0.15
    col = col + (np.array([0.66, 0.24, 0.24]) - col) * np.clip(crevice, 0, 1)[:, None]
    core = 0.55 * np.exp(-((f1 / (0.16 * sp)) ** 2))[:, None]
    col = col + (np.array([0.84, 0.33, 0.32]) - col) * core
    base = 0.82 + 0.18 * _smoothstep(0, 1.2, outline - r)
    return col * base[:, None], alpha, halo


def _outline(les: Lesion, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from the centre and the irregular outline radius at local coordinates."""
    r = np.hypot(x, y)
    th = np.arctan2(y, x)
    k = np.arange(2, 6)
    return r, les.diameter_mm / 2 * (1 + (les.outline_amp * np.cos(np.outer(th, k) + les.outline_phase)).sum(1))


def _waves(g: np.random.Generator, x: np.ndarray, y: np.ndarray, n: int,
           wavelength_mm: tuple[float, float]) -> np.ndarray:
    """Sum of ``n`` random plane waves in local coordinates, unit std (deterministic in g)."""
    lam = g.uniform(*wavelength_mm, size=n)
    ang = g.uniform(0, np.pi, size=n)
    ph = g.uniform(0, 2 * np.pi, size=n)
    out = np.zeros_like(x)
    for k in range(n):
        out += np.cos((x * math.cos(ang[k]) + y * math.sin(ang[k])) * (2 * np.pi / lam[k]) + ph[k])
    return out * math.sqrt(2.0 / n)


def _paint_painted(les: Lesion, x: np.ndarray, y: np.ndarray, cur: np.ndarray) -> np.ndarray:
    col, alpha, halo = _pattern(les, x, y)
    cur = cur * (1 - 0.22 * halo[:, None] * np.array([0.0, 1.0, 0.9]))
    return cur * (1 - alpha[:, None]) + col * alpha[:, None]


def _paint_red_patch(les: Lesion, x: np.ndarray, y: np.ndarray, cur: np.ndarray,
                     gain: np.ndarray, edge_mm: float, velvet: float) -> np.ndarray:
    """Multiply the wall's colour by ``gain`` inside the outline (soft edge, velvety grain)."""
    g = np.random.default_rng([les.pattern_seed, 1])
    r, outline = _outline(les, x, y)
    alpha = np.clip((outline - r) / edge_mm + 0.5, 0, 1)
    grain = _waves(g, x, y, 24, (0.3, 1.2))
    factor = 1 + alpha[:, None] * ((gain - 1) * (1 + velvet * grain)[:, None])
    return cur * factor


def _paint_cis(les: Lesion, x: np.ndarray, y: np.ndarray, cur: np.ndarray) -> np.ndarray:
    return _paint_red_patch(les, x, y, cur, np.array([1.02, 0.915, 0.93]), 1.2, 0.2)


def _paint_perivascular(les: Lesion, x: np.ndarray, y: np.ndarray, cur: np.ndarray) -> np.ndarray:
    return _paint_red_patch(les, x, y, cur, np.array([1.02, 0.76, 0.79]), 0.6, 0.15)


def _paint_scar(les: Lesion, x: np.ndarray, y: np.ndarray, cur: np.ndarray) -> np.ndarray:
    g = np.random.default_rng([les.pattern_seed, 2])
    phi = g.uniform(0, np.pi)
    c, s = math.cos(phi), math.sin(phi)
    u, v = (c * x + s * y) / 1.35, (-s * x + c * y) * 1.35
    r, outline = _outline(les, u, v)
    alpha = np.clip((outline - r) / 0.8 + 0.5, 0, 1)
    fibres = 1 + 0.03 * _waves(g, u * 0.15, v, 8, (0.4, 1.2))  # streaks along the long axis
    target = PALE_SCAR[None, :] * fibres[:, None]
    return cur + (SCAR_BLEND * alpha)[:, None] * (target - cur)


PAINTERS = {"painted": _paint_painted, "papillary": _paint_painted, "cis": _paint_cis,
            "scar": _paint_scar, "perivascular": _paint_perivascular}


def _site_vessel(les: Lesion, vessel_rgb: np.ndarray):
    """Painter of the vessel passing beside a perivascular lesion (both sessions)."""
    g = np.random.default_rng([les.pattern_seed, 3])
    rad = les.diameter_mm / 2
    half_w = SITE_VESSEL_WIDTH_MM / 2
    offset = rad * (1 + np.abs(les.outline_amp).sum()) + 0.3 + half_w
    length = rad + 14.0
    phase = g.uniform(0, 2 * np.pi)
    side = g.choice([-1.0, 1.0])

    def paint(x: np.ndarray, y: np.ndarray, cur: np.ndarray) -> np.ndarray:
        path = side * (offset + 0.8 * (1 - np.cos(x / 6.0 + phase)) * np.clip(np.abs(x) / rad - 0.8, 0, None))
        core = np.clip((half_w - np.abs(y - path)) / 0.15 + 0.5, 0, 1)
        fade = np.clip((length - np.abs(x)) / 4.0, 0, 1)
        a = (0.8 * core * fade)[:, None]
        return cur + a * (vessel_rgb[None, :] - cur)

    return paint, length + 2.0


def _paint(cube: CubeMap, items: list, bladder: Bladder, scene) -> None:
    """Paint (centre, normal, reach_mm, depth_mm, painter) items into level 0 of ``cube``: wall
    texels within reach (tangent plane) and depth (along the normal) of the centre; a painter
    maps local tangent-plane coordinates (mm) and the current RGB (0..1) to the new RGB."""
    n = cube.n
    tile = cube.tile
    level0 = cube.levels[0]
    for centre, nrm, rmax, depth, painter in items:
        centre_dir = unit(centre - bladder.barycentre)
        cos_cone = math.cos(min(1.2, 1.6 * rmax / float(np.linalg.norm(centre))))
        e1 = unit(np.cross(nrm, [0.0, 0.0, 1.0] if abs(nrm[2]) < 0.9 else [1.0, 0.0, 0.0]))
        e2 = np.cross(nrm, e1)
        for face in range(6):
            d2, side2 = _face_grid(face, n, 2, 0)
            inside = (d2 @ centre_dir > cos_cone).reshape(side2, side2)
            if not inside.any():
                continue
            rows = np.flatnonzero(inside.any(1))
            cols = np.flatnonzero(inside.any(0))
            y0, y1 = max(0, 4 * rows[0] - 4), min(tile, 4 * rows[-1] + 8)
            x0, x1 = max(0, 4 * cols[0] - 4), min(tile, 4 * cols[-1] + 8)
            xs = np.arange(x0, x1)
            ys = np.arange(y0, y1)
            sc = ((xs - MARGIN) + 0.5) * (2.0 / n) - 1.0
            tc = ((ys - MARGIN) + 0.5) * (2.0 / n) - 1.0
            d = unit(face_dirs(face, sc[None, :], tc[:, None]).reshape(-1, 3))
            hit = cast(scene, np.broadcast_to(bladder.barycentre, d.shape), d)
            _, mat, wall = interpolate_hit(bladder, hit)
            ok = wall & np.isfinite(mat[:, 0])
            rel = mat - centre
            lx, ly = rel @ e1, rel @ e2
            near = ok & (np.hypot(lx, ly) < rmax) & (np.abs(rel @ nrm) < depth)
            if not near.any():
                continue
            r0, c0 = (face // 3) * tile + y0, (face % 3) * tile + x0
            block = level0[r0:r0 + len(ys), c0:c0 + len(xs)].reshape(-1, 3).astype(np.float64) / 255
            block[near] = painter(lx[near], ly[near], block[near])
            level0[r0:r0 + len(ys), c0:c0 + len(xs)] = np.clip(
                block * 255 + 0.5, 0, 255).astype(np.uint8).reshape(len(ys), len(xs), 3)


def paint_site_vessels(cube: CubeMap, lesions: list[Lesion], bladder: Bladder, scene) -> int:
    """Paint the vessels beside perivascular lesions (every session; rebuilds the mips)."""
    vessel_rgb = np.asarray(cube.params.vessel_rgb if cube.params is not None else (0.60, 0.15, 0.13))
    items = []
    for les in lesions:
        if les.kind == "perivascular":
            paint, reach = _site_vessel(les, vessel_rgb)
            items.append((les.material, les.normal, reach, 8.0, paint))
    if items:
        _paint(cube, items, bladder, scene)
        cube.rebuild_mips()
    return len(items)


def paint_lesions(cube: CubeMap, lesions: list[Lesion], bladder: Bladder, scene) -> None:
    """Paint lesions into level 0 of ``cube`` (session-1 bladder and scene), rebuild mips."""
    items = []
    for les in lesions:
        rmax = les.diameter_mm / 2 * (1 + np.abs(les.outline_amp).sum()) + HALO_MM * 3 + 0.5
        if les.kind == "scar":
            rmax = les.diameter_mm / 2 * 1.35 * (1 + np.abs(les.outline_amp).sum()) + 1.5
        painter = PAINTERS[les.kind]
        items.append((les.material, les.normal, rmax, 5.0,
                      lambda x, y, cur, les=les, painter=painter: painter(les, x, y, cur)))
    _paint(cube, items, bladder, scene)
    cube.rebuild_mips()
    log.info("painted %d lesions", len(lesions))


def lesion_relief(cfg: PhantomConfig, bladder: Bladder, lesions: list[Lesion]) -> np.ndarray | None:
    """Displacement (V, 3) of ``bladder``'s vertices raising the papillary lesions into the
    cavity: a lobed dome ``h = height * (1 - s^2)^2 * (1 + 0.15 cos(3 theta + phase))`` over
    the lesion's outline (s = distance / outline radius), along -normal; None without any."""
    raised = [les for les in lesions if les.height_mm > 0]
    if not raised:
        return None
    nw = bladder.n_wall_verts
    wall = bladder.vertices[:nw]
    disp = np.zeros_like(bladder.vertices)
    for les in raised:
        g = np.random.default_rng([les.pattern_seed, 4])
        phase = g.uniform(0, 2 * np.pi)
        nrm = les.normal
        e1 = unit(np.cross(nrm, [0.0, 0.0, 1.0] if abs(nrm[2]) < 0.9 else [1.0, 0.0, 0.0]))
        e2 = np.cross(nrm, e1)
        rel = wall - les.material
        near = np.flatnonzero(np.linalg.norm(rel, axis=1) < les.diameter_mm)
        x, y = rel[near] @ e1, rel[near] @ e2
        r, outline = _outline(les, x, y)
        sq = np.clip(1 - (r / outline) ** 2, 0, None)
        lobes = 1 + 0.15 * np.cos(3 * np.arctan2(y, x) + phase)
        h = les.height_mm * sq * sq * lobes / 1.15
        disp[near] -= h[:, None] * nrm
    return disp
