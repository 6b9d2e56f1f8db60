"""Procedural content of the phantom's mucosa: smooth colour waves, 3-D noise (mottling), and
branching vessels grown on the wall and drawn on every cube face they cross."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cystomap.phantom.cubemap import MARGIN
from cystomap.phantom.geometry import unit
from cystomap.phantom.wall_rays import RadiusTable


@dataclass
class Waves:
    """Sum of plane waves cos(k.x + phase) in 3-D (a smooth random field, mm input)."""

    k: np.ndarray
    amp: np.ndarray
    phase: np.ndarray

    @classmethod
    def random(cls, g: np.random.Generator, n: int, wavelength_mm: tuple[float, float],
               std: float) -> Waves:
        lam = g.uniform(*wavelength_mm, size=n)
        k = unit(g.normal(size=(n, 3))) * (2 * np.pi / lam)[:, None]
        amp = g.normal(size=n) * std * math.sqrt(2.0 / n)
        return cls(k, amp, g.uniform(0, 2 * np.pi, size=n))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        out = np.zeros(len(x), np.float64)
        for k, a, p in zip(self.k, self.amp, self.phase, strict=True):
            out += a * np.cos(x @ k + p)
        return out


class NoiseVolume:
    """Gaussian-smoothed white noise on a 3-D grid, unit std, sampled trilinearly (mm input)."""

    def __init__(self, g: np.random.Generator, lo: np.ndarray, hi: np.ndarray, spacing: float,
                 sigma_cells: float) -> None:
        from scipy.ndimage import gaussian_filter

        self.lo = lo
        self.spacing = spacing
        shape = tuple(int(v) for v in np.ceil((hi - lo) / spacing) + 2)
        vol = g.standard_normal(shape, dtype=np.float32)
        vol = gaussian_filter(vol, sigma_cells, mode="wrap")
        vol /= vol.std()
        self.vol = vol

    def __call__(self, x: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        c = ((x - self.lo) / self.spacing).T
        return map_coordinates(self.vol, c, order=1, mode="nearest")


@dataclass
class Vessels:
    """Vessel segments on the unit sphere of material directions."""

    p0: np.ndarray
    p1: np.ndarray
    width_mm: np.ndarray
    deep: np.ndarray  # bool
    fade: np.ndarray  # opacity factor along the vessel (0 at its ends)

    def __len__(self) -> int:
        return len(self.width_mm)


def _rotate_tangent(h: np.ndarray, p: np.ndarray, angle: np.ndarray) -> np.ndarray:
    return h * np.cos(angle)[:, None] + np.cross(p, h) * np.sin(angle)[:, None]


def grow_vessels(g: np.random.Generator, radius: RadiusTable, area_mm2: float,
                 min_width_mm: float, density: float = 1.0) -> Vessels:
    """Branching random walks on the wall (trunks ~1 mm wide, branches down to min width);
    ``density`` multiplies the number of trunks."""
    n0 = max(6, round(area_mm2 / 700.0)) if density == 1.0 else max(3, round(area_mm2 * density / 700.0))
    p = unit(g.normal(size=(n0, 3)))
    h = unit(np.cross(p, unit(g.normal(size=(n0, 3)))))
    width = np.exp(g.uniform(np.log(max(0.3, min_width_mm)), np.log(1.1), size=n0))
    length = g.uniform(40, 110, size=n0) * np.sqrt(width)
    deep = g.random(n0) < 0.5
    segs: list[tuple[np.ndarray, ...]] = []
    generation = 0
    max_vessels = 60000
    total = n0
    while len(p) and generation < 12:
        curv = g.normal(0, 0.015, size=len(p))
        sigma = 0.10 + 0.30 * np.clip(0.6 - width, 0, 0.6)  # thin vessels are more tortuous
        travelled = np.zeros(len(p))
        w_start = width.copy()
        alive = np.ones(len(p), bool)
        kids: list[tuple[np.ndarray, ...]] = []
        spacing = np.clip(16.0 * width, 4.0, 14.0)
        while alive.any():
            i = np.flatnonzero(alive)
            frac = travelled[i] / length[i]
            w_now = w_start[i] * (1 - 0.6 * frac)
            step = np.clip(1.5 * w_now, 0.25, 1.0)
            rad = radius(p[i])
            p_new = unit(p[i] + h[i] * (step / rad)[:, None])
            hn = h[i] - np.einsum("ij,ij->i", h[i], p_new)[:, None] * p_new
            hn = unit(hn)
            turn = curv[i] * step + sigma[i] * np.sqrt(step) * g.standard_normal(len(i))
            hn = _rotate_tangent(hn, p_new, turn)
            # vessels emerge from / dive into the deeper tissue: fade in and out
            fade = np.clip(frac / 0.12, 0, 1) * np.clip((1 - frac) / 0.15, 0, 1)
            fade = fade * fade * (3 - 2 * fade)
            segs.append((p[i].copy(), p_new, w_now, deep[i], fade))
            p[i], h[i] = p_new, hn
            travelled[i] += step
            alive[i] = travelled[i] < length[i]
            # branching
            b = g.random(len(i)) < step / spacing[i]
            if b.any() and total < max_vessels:
                j = i[b]
                nb = len(j)
                ang = g.uniform(0.45, 1.3, size=nb) * g.choice([-1.0, 1.0], size=nb)
                cw = w_now[b] * g.uniform(0.45, 0.8, size=nb)
                keep = cw >= min_width_mm
                if keep.any():
                    j, ang, cw = j[keep], ang[keep], cw[keep]
                    ch = _rotate_tangent(h[j], p[j], ang)
                    cl = np.clip(g.uniform(12, 50, size=len(j)) * cw, 2.0, None)
                    cd = deep[j] & (cw > 0.25)
                    kids.append((p[j].copy(), ch, cw, cl, cd))
                    total += len(j)
        if not kids:
            break
        p = np.concatenate([k[0] for k in kids])
        h = np.concatenate([k[1] for k in kids])
        width = np.concatenate([k[2] for k in kids])
        length = np.concatenate([k[3] for k in kids])
        deep = np.concatenate([k[4] for k in kids])
        generation += 1
    return Vessels(*(np.concatenate([s[k] for s in segs]) for k in range(5)))


def draw_vessels(canvas: np.ndarray, face: int, n: int, vessels: Vessels, sel: np.ndarray,
                 radius: RadiusTable, opacity: np.ndarray) -> None:
    """Draw the selected segments into one face tile (uint8 canvas; value = opacity)."""
    k, sign = face // 2, (-1.0 if face % 2 else 1.0)
    p0, p1 = vessels.p0[sel], vessels.p1[sel]
    dn0, dn1 = sign * p0[:, k], sign * p1[:, k]
    ok = (dn0 > 0.45) & (dn1 > 0.45)
    if not ok.any():
        return
    p0, p1, dn0, dn1 = p0[ok], p1[ok], dn0[ok], dn1[ok]
    width = vessels.width_mm[sel][ok]
    alpha = opacity[ok]
    tile = n + 2 * MARGIN

    def px(p, dn):
        s = p[:, (k + 1) % 3] / dn
        t = p[:, (k + 2) % 3] / dn
        return MARGIN + (s + 1) * (0.5 * n) - 0.5, MARGIN + (t + 1) * (0.5 * n) - 0.5

    x0, y0 = px(p0, dn0)
    x1, y1 = px(p1, dn1)
    lo, hi = -8.0, tile + 8.0
    inside = ((np.minimum(x0, x1) < hi) & (np.maximum(x0, x1) > lo)
              & (np.minimum(y0, y1) < hi) & (np.maximum(y0, y1) > lo))
    if not inside.any():
        return
    x0, y0, x1, y1 = x0[inside], y0[inside], x1[inside], y1[inside]
    width, alpha, dn0 = width[inside], alpha[inside], dn0[inside]
    texel = radius(p0[inside]) * (2.0 / n) * dn0**1.5
    wpx = width / texel
    thick = np.maximum(1, np.round(wpx)).astype(int)
    value = np.clip(alpha * np.minimum(wpx, 1.0) * 255, 0, 255)
    vq = (np.round(value / 8) * 8).clip(0, 255).astype(int)
    shift = 4
    pts = np.stack([x0, y0, x1, y1], 1) * (1 << shift)
    pts = np.round(pts).astype(np.int32).reshape(-1, 2, 2)
    order = np.lexsort((thick, vq))
    keys = np.stack([vq[order], thick[order]], 1)
    starts = np.flatnonzero(np.r_[True, (np.diff(keys, axis=0) != 0).any(1)])
    ends = np.r_[starts[1:], len(order)]
    for a, b in zip(starts, ends, strict=True):
        if keys[a, 0] == 0:
            continue
        idx = order[a:b]
        cv2.polylines(canvas, list(pts[idx]), False, int(keys[a, 0]), int(keys[a, 1]),
                      cv2.LINE_AA, shift)
