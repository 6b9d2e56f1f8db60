"""Papillary lesions painted into session 2's albedo (no geometry change).

Each lesion is a disc on the wall (material frame) of the configured diameter with a
slightly irregular outline (mean radius = diameter / 2), filled with whitish-pink fronds
separated by dark red crevices, each frond with a red vascular core, and a faint reddish
halo (1.5 mm) around it. Centres are random (seeded), away from the aperture and from each
other.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from cystomap.errors import InputError
from cystomap.phantom.config import PhantomConfig
from cystomap.phantom.geometry import STREAM_LESIONS, Bladder, az_el, rng, unit
from cystomap.phantom.texture import MARGIN, CubeMap, _face_grid, cast, face_dirs, interpolate_hit

log = logging.getLogger(__name__)

HALO_MM = 1.5
MIN_GAP_MM = 15.0
APERTURE_CLEARANCE_DEG = 25.0


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


def aperture_cone(bladder: Bladder) -> tuple[np.ndarray, float]:
    """Direction (from the barycentre) and angular radius (deg) of the aperture."""
    rel = bladder.vertices[bladder.rim] - bladder.barycentre
    axis = unit(rel.mean(0))
    ang = np.degrees(np.arccos(np.clip(unit(rel) @ axis, -1, 1))).max()
    return axis, float(ang)


def place_lesions(cfg: PhantomConfig, bladder: Bladder, scene) -> list[Lesion]:
    """Random lesion sites on the session-1 wall (seeded; larger lesions placed first)."""
    g = rng(cfg, STREAM_LESIONS)
    ap_dir, ap_ang = aperture_cone(bladder)
    order = np.argsort(-np.asarray(cfg.lesion_diameters_mm), kind="stable")
    placed: dict[int, Lesion] = {}
    for idx in order:
        diam = float(cfg.lesion_diameters_mm[idx])
        for _attempt in range(5000):
            u = unit(g.normal(size=3))
            hit = cast(scene, bladder.barycentre[None], u[None])
            if not np.isfinite(hit["t_hit"][0]):
                continue
            _, mat, wall, nrm = interpolate_hit(bladder, hit, with_normals=True)
            if not wall[0]:
                continue
            m = mat[0]
            ang_r = math.degrees(diam / 2 / np.linalg.norm(m))
            if math.degrees(math.acos(float(np.clip(u @ ap_dir, -1, 1)))) < (
                    ap_ang + APERTURE_CLEARANCE_DEG + ang_r):
                continue
            if any(np.linalg.norm(m - o.material) < (diam + o.diameter_mm) / 2 + MIN_GAP_MM
                   for o in placed.values()):
                continue
            placed[int(idx)] = Lesion(
                id=int(idx) + 1, diameter_mm=diam, triangle=int(hit["primitive_ids"][0]),
                uv=(float(hit["primitive_uvs"][0, 0]), float(hit["primitive_uvs"][0, 1])),
                material=m, normal=nrm[0], outline_amp=g.normal(0, 0.035, size=4),
                outline_phase=g.uniform(0, 2 * np.pi, size=4),
                pattern_seed=int(g.integers(0, 2**31 - 1)),
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
                     "elevation_deg": float(el)})
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


def paint_lesions(cube: CubeMap, lesions: list[Lesion], bladder: Bladder, scene) -> None:
    """Paint lesions into level 0 of ``cube`` (session-1 bladder and scene), rebuild mips."""
    n = cube.n
    tile = cube.tile
    level0 = cube.levels[0]
    for les in lesions:
        centre_dir = unit(les.material - bladder.barycentre)
        rmax = les.diameter_mm / 2 * (1 + np.abs(les.outline_amp).sum()) + HALO_MM * 3 + 0.5
        cos_cone = math.cos(min(1.2, 1.6 * rmax / float(np.linalg.norm(les.material))))
        nrm = les.normal
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
            rel = mat - les.material
            lx, ly = rel @ e1, rel @ e2
            near = ok & (np.hypot(lx, ly) < rmax) & (np.abs(rel @ nrm) < 5.0)
            if not near.any():
                continue
            col, alpha, halo = _pattern(les, lx[near], ly[near])
            r0, c0 = (face // 3) * tile + y0, (face % 3) * tile + x0
            block = level0[r0:r0 + len(ys), c0:c0 + len(xs)].reshape(-1, 3).astype(np.float64) / 255
            cur = block[near]
            cur = cur * (1 - 0.22 * halo[:, None] * np.array([0.0, 1.0, 0.9]))
            cur = cur * (1 - alpha[:, None]) + col * alpha[:, None]
            block[near] = cur
            level0[r0:r0 + len(ys), c0:c0 + len(xs)] = np.clip(
                block * 255 + 0.5, 0, 255).astype(np.uint8).reshape(len(ys), len(xs), 3)
    cube.rebuild_mips()
    log.info("painted %d lesions", len(lesions))
