"""The wall around the bladder neck: its own noise level.

The scope enters through the neck and looks away from it, so the wall around it (the trigone,
where many tumours are) is filmed rarely and at grazing angles: its SfM points are sparse (the
median distance from the mesh to the nearest point falls from about 14 mm at the neck to the
rest of the wall's 2-3 mm only some 30° away from it), the mesh there bridges the funnel, and
both sessions' textures are painted on a surface several millimetres off. The whole band is
then "changed" without any change: on dev pairs 300, 306 and 308 (640x360) the median
significance of the compared wall in rings 15-30° from the neck was 5-35 noise units against
1.9-2.2 over the whole wall, while its spread relative to its level (90th percentile over
median: 1.2-3) was no wider than elsewhere. A single noise level for the wall leaves two
choices there, both bad: report the band (false regions) or cut it out (the fixed cone of
``opening_deg`` did, and missed every small lesion within 30° of the neck).

So the noise level is measured ring by ring around the neck (rings of wall about
``2 * smooth_mm`` wide, centred on the neck's directions from B's barycentre, each the
compared wall at those angles): starting at the first ring with compared wall, each ring whose
median significance is more than ``BAND_LEVEL`` times the whole compared wall's has its
significance scaled down by the ratio of the two (a wall-area weighted median: a lesion covers
a small share of a ring, whose length is 2π r sin θ), up to and including the first ring that
is not (the band's edge, scaled to the wall's level too); the scale is interpolated between
ring centres and reaches 1 one ring further out. Beyond that, and everywhere when no camera was found at the neck,
nothing changes. This is the heteroscedastic form of the whitening the significance already
is: a change must stand out against the noise where it is.

Opt-in (``compare.neck_levelling``, with ``opening_deg`` 0), because on held-out pairs it was
no better than the fixed cone (docs/measurements.md, "The wall around the neck"): on the family-C pairs it
was developed on (111, 120, 123) it found the three small neck lesions the cone cut out, but on
fresh ones it found none of the small ones either (5.2 mm, 3.6 mm; a 7.3 mm CIS only at rate
1), lost a 24.8 mm CIS the cone had kept (its part outside 30°) and added a false region on a
no-change pair. A lesion in the band must beat the band's noise, 5-50 times the wall's: what
would help is less noise there (a surface that follows the neck's funnel), not another scale.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from cystomap.compare.grid import Grid
from cystomap.stats import weighted_median

if TYPE_CHECKING:
    from cystomap.compare.difference import Difference

log = logging.getLogger(__name__)

# a ring's median needs this many compared pixels
MIN_RING_PIXELS = 50
# a ring belongs to the neck's band while its median significance is at least this many times
# the whole compared wall's (dev pairs 300, 306, 308: rings away from the neck 0.6-1.6 times,
# the band 3-50 times)
BAND_LEVEL = 2.0
# a ring's level in :func:`chroma_band` is the median of its sectors' levels (this many
# sectors of azimuth about the neck): a lesion beside the neck fills a few sectors of the
# rings it crosses and would otherwise lift their levels, widening the cap over itself
SECTORS = 8


def neck_angles(grid: Grid, openings: np.ndarray) -> np.ndarray:
    """(H, W) angle (degrees, from B's barycentre) of each pixel's direction to the nearest of
    the neck's directions ``openings`` (k, 3 unit vectors)."""
    dirs = grid.proj.grid_directions()
    cos = np.clip((dirs @ np.asarray(openings, np.float64).reshape(-1, 3).T).max(axis=-1), -1, 1)
    return np.degrees(np.arccos(cos))


def neck_sectors(grid: Grid, openings: np.ndarray, n: int) -> np.ndarray:
    """(H, W) sector index (0 to ``n`` - 1) of each pixel's azimuth about the neck's mean
    direction (``openings``: k, 3 unit vectors)."""
    axis = np.asarray(openings, np.float64).reshape(-1, 3).mean(axis=0)
    axis /= max(float(np.linalg.norm(axis)), 1e-12)
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    dirs = grid.proj.grid_directions()
    az = np.arctan2(dirs @ e2, dirs @ e1) % (2 * math.pi)
    return np.minimum((az / (2 * math.pi) * n).astype(np.int64), n - 1)


def sector_level(values: np.ndarray, sel: np.ndarray, sector: np.ndarray, area: np.ndarray,
                 n: int) -> float:
    """The median over the ``n`` sectors of the ring ``sel`` of each sector's wall-area
    weighted median of ``values`` (sectors with too few pixels left out)."""
    least = max(MIN_RING_PIXELS // n, 1)
    levels = [weighted_median(values[ss], area[ss])
              for ss in (sel & (sector == s) for s in range(n)) if ss.sum() >= least]
    return float(np.median(levels)) if levels else weighted_median(values[sel], area[sel])


def neck_rings(grid: Grid, ang: np.ndarray, ring_mm: float) -> tuple[np.ndarray, float]:
    """(H, W) ring index of each pixel around the neck (``ang``: its angle to the neck, from
    :func:`neck_angles`) and the rings' width in degrees: ``ring_mm`` on the wall at the
    median radius of B's wall, at least two grid rows."""
    radius = float(np.median(np.linalg.norm(grid.points[grid.hit] - grid.proj.barycentre,
                                            axis=1)))
    width = math.degrees(max(ring_mm, 2 * grid.mm_per_px_y) / max(radius, 1e-9))
    return np.floor(ang / width).astype(np.int64), width


def level_around_neck(sig: np.ndarray, joint: np.ndarray, grid: Grid, openings: np.ndarray,
                      ring_mm: float) -> tuple[np.ndarray, dict[str, Any]]:
    """``sig`` with the wall around the neck scaled to the whole compared wall's noise level
    (see the module's doc), and what was done (for ``compare.json``)."""
    openings = np.asarray(openings, np.float64).reshape(-1, 3)
    if not len(openings):
        return sig, {"levelled": False, "reason": "no camera at the neck"}
    area = grid.area
    ref = weighted_median(sig[joint], area[joint])
    ang = neck_angles(grid, openings)
    ring, width = neck_rings(grid, ang, ring_mm)
    centres, factors, medians = [], [], []
    started = False
    for k in range(math.ceil(90.0 / width)):
        sel = joint & (ring == k)
        if sel.sum() < MIN_RING_PIXELS:
            if started:
                break
            continue
        started = True
        med = weighted_median(sig[sel], area[sel])
        if med <= BAND_LEVEL * ref:
            # the band's edge: this ring on its own level, the next at the wall's
            centres += [(k + 0.5) * width, (k + 1.5) * width]
            factors += [min(1.0, ref / med), 1.0]
            medians.append(med)
            break
        centres.append((k + 0.5) * width)
        factors.append(ref / med)
        medians.append(med)
    if not factors or min(factors) >= 1.0:
        return sig, {"levelled": False, "reason": "the wall around the neck is at the level "
                     "of the rest", "reference": round(float(ref), 3)}
    scale = np.interp(ang, centres, factors, left=factors[0], right=1.0)
    out = np.where(joint, sig * scale, sig).astype(sig.dtype)
    info = {"levelled": True, "reference": round(float(ref), 3),
            "ring_deg": round(width, 3), "to_deg": round(centres[-1], 2),
            "ring_medians": [round(float(m), 3) for m in medians],
            "largest_factor": round(float(1 / min(factors)), 2)}
    log.info("compare: the wall within %.0f° of the neck is noisier than the rest (ring medians "
             "up to %.1f against %.2f): its significance is levelled ring by ring",
             centres[-1], max(medians), ref)
    return out, info


def ring_ratio(b_rgb: np.ndarray, a_rgb: np.ndarray, use: np.ndarray, grid: Grid,
               ang: np.ndarray, ring_mm: float) -> tuple[np.ndarray, dict[str, Any]]:
    """Per-pixel factor (H, W, 3) for A's ``colour + 8`` that matches B's colour to A's ring
    by ring around the neck (``ang``: each pixel's angle to it, from :func:`neck_angles`):
    each ring's wall-area weighted median of ``log((B + 8) / (A + 8))`` per channel over the
    wall ``use``, interpolated between ring centres, out to 90°; 1 beyond and in rings with
    too little wall. A ring around the neck is 2π r sin θ long (some 75 mm at 20° in a
    35 mm bladder), so a lesion holds a minor share of it and its median is the wall's."""
    ring, width = neck_rings(grid, ang, ring_mm)
    log_ratio = np.log(b_rgb + 8.0) - np.log(a_rgb + 8.0)
    area = grid.area
    centres, medians = [], []
    for k in range(math.ceil(90.0 / width)):
        sel = use & (ring == k)
        if sel.sum() < MIN_RING_PIXELS:
            continue
        centres.append((k + 0.5) * width)
        medians.append([weighted_median(log_ratio[sel, c], area[sel]) for c in range(3)])
    factor = np.ones(b_rgb.shape, np.float32)
    if len(centres) < 2:
        return factor, {"matched": False, "reason": "too little wall around the neck"}
    med = np.asarray(medians)
    # down to 0 at 90° (one ring beyond the last), so the correction ends smoothly
    xs = np.r_[centres, max(90.0, centres[-1] + width)]
    inside = ang < xs[-1]
    for c in range(3):
        curve = np.interp(ang[inside], xs, np.r_[med[:, c], 0.0])
        factor[inside, c] = np.exp(curve)
    lum = med @ np.array([0.299, 0.587, 0.114])
    info = {"matched": True, "ring_deg": round(width, 3), "from_deg": round(centres[0], 2),
            "largest_log_ratio": round(float(np.abs(med).max()), 4),
            "luminance_log_ratio_by_ring": [round(float(x), 4) for x in lum]}
    return factor, info


def chroma_band(diff: Difference, grid: Grid, openings: np.ndarray, ring_mm: float,
                ) -> tuple[np.ndarray, float, np.ndarray | None, dict[str, Any]]:
    """The significance with the wall around the neck tested on its colour alone, the angle
    (degrees) of the neck's cap to cut out, the cap's noise level (H, W: the significance's
    ring level relative to the wall's, interpolated between the cap's ring centres, at least
    1; 1 beyond the cap; None without a cap) and what was done (for ``compare.json``).

    Rings around the neck (as in :func:`level_around_neck`), each with two levels relative
    to the wall 90° or more from the neck: the median colour significance
    (``diff.significance_colour``: what no brightness change explains) and the median
    brightness part (``diff.brightness``), each the median of the ring's ``SECTORS``
    sectors' medians (a lesion beside the neck fills a few sectors of a ring: pair 551's
    26 mm lesion had widened the cap over itself, to 34.7° where the rest of the ring is
    quiet from 28.7°). The cap (the opening and the mesh that bridges
    it) reaches from the neck to the first ring at most ``BAND_LEVEL`` in colour beyond the
    ring noisiest in colour (when that one is above ``BAND_LEVEL``; rings inside the opening
    may be quiet: unseen by A, or a uniform view into the urethra). The band is the rings
    after the cap whose brightness level is above ``BAND_LEVEL``, up to the first that is
    not; there the significance is the smaller of itself and the colour significance in the
    wall's units (times the ratio of the two significances' wall medians)."""
    sig, joint = diff.significance, diff.joint
    sig_c, bright = diff.significance_colour, diff.brightness
    openings = np.asarray(openings, np.float64).reshape(-1, 3)
    if sig_c is None or bright is None or not len(openings):
        return sig, 0.0, None, {"band": False, "reason": "no camera at the neck"}
    area = grid.area
    ang = neck_angles(grid, openings)
    far = joint & (ang >= 90.0)
    if far.sum() < MIN_RING_PIXELS:
        far = joint
    ref_c = weighted_median(sig_c[far], area[far])
    ref_b = weighted_median(bright[far], area[far])
    ref = weighted_median(sig[far], area[far])
    ring, width = neck_rings(grid, ang, ring_mm)
    sector = neck_sectors(grid, openings, SECTORS)
    # each ring's colour, brightness and significance levels relative to the wall's, out to
    # 90 degrees
    rings: list[tuple[int, float, float, float]] = []
    for k in range(math.ceil(90.0 / width)):
        sel = joint & (ring == k)
        if sel.sum() >= MIN_RING_PIXELS:
            rings.append((k, sector_level(sig_c, sel, sector, area, SECTORS) / max(ref_c, 1e-9),
                          sector_level(bright, sel, sector, area, SECTORS) / max(ref_b, 1e-9),
                          sector_level(sig, sel, sector, area, SECTORS) / max(ref, 1e-9)))
    if not rings:
        return sig, 0.0, None, {"band": False, "reason": "no compared wall around the neck"}
    # the cap: out to the first ring at the wall's colour noise level beyond the noisiest
    # ring (the opening; rings inside it may be quiet: unseen by A, or a uniform view into
    # the urethra)
    cap_deg = rings[0][0] * width
    peak = max(range(len(rings)), key=lambda i: rings[i][1])
    cap_levels, band_levels = [], []
    first = 0  # the first ring after the cap
    if rings[peak][1] > BAND_LEVEL:
        first = next((i for i in range(peak + 1, len(rings)) if rings[i][1] <= BAND_LEVEL),
                     len(rings))
        cap_deg = (rings[first - 1][0] + 1) * width
        cap_levels = [round(float(r[1]), 2) for r in rings[:first]]
    band_deg = cap_deg
    for k, _, level, _ in rings[first:]:
        if level <= BAND_LEVEL:
            break
        band_deg = (k + 1) * width
        band_levels.append(round(float(level), 2))
    # the cap's own noise level, from its rings (a region beside it is followed into it where
    # it stands out against that: cystomap.compare.changes)
    cap_level = np.ones(sig.shape, np.float64)
    if first:
        inside = ang < cap_deg
        cap_level[inside] = np.maximum(np.interp(
            ang[inside], [(r[0] + 0.5) * width for r in rings[:first]],
            [r[3] for r in rings[:first]]), 1.0)
    info: dict[str, Any] = {"band": band_deg > cap_deg, "cap_deg": round(cap_deg, 2),
                            "band_to_deg": round(max(band_deg, cap_deg), 2),
                            "ring_deg": round(width, 3), "cap_colour_levels": cap_levels,
                            "band_brightness_levels": band_levels}
    if band_deg <= cap_deg:
        return sig, cap_deg, cap_level, info
    factor = ref / max(ref_c, 1e-9)
    band = joint & (ang >= cap_deg) & (ang < band_deg)
    out = np.where(band, np.minimum(sig, factor * sig_c), sig).astype(sig.dtype)
    info["colour_factor"] = round(float(factor), 3)
    log.info("compare: the wall %.0f-%.0f° from the neck is tested on its colour alone (its "
             "brightness up to %.1f times as noisy as the rest); cap cut out to %.0f°",
             cap_deg, band_deg, max(band_levels), cap_deg)
    return out, cap_deg, cap_level, info
