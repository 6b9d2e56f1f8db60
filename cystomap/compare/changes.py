"""Changed regions: a decision calibrated on the pair's own null, clean, measure on the wall.

(Over 450 lines because detection, cleaning, the checks and the measurement of a region share
one pipeline of intermediate images; the null's statistics are in :mod:`cystomap.compare.null`.)

Decision (``false_alarm_rate``, the expected number of false regions per pair): the
per-pixel significance (whitened, smoothed colour difference; see
:mod:`cystomap.compare.difference`) has a heavy, pair-specific tail even without any change
(registration residue of vessels and mottling, photometric residue, atlas seams), so no
fixed multiple of its noise level is trusted. Instead its connected excursions above a low
candidate level (median + ``CANDIDATE_MADS`` MADs on the compared wall, joined across the
azimuth seam) are the candidates; most of them are the pair's noise and form its null
sample. Each cluster has two statistics, its peak significance (a strong change, however
small) and the root of its excess mass on the wall, ``sqrt(sum (s - level) · area)`` (a
faint but large change: a flat, low-contrast patch). For each, an exponential tail is
fitted to the strongest null clusters (peaks over threshold; the strongest of them enter
only by their number, right-censored, so that changes among them cannot inflate it); the
overshoot of a smooth field's maxima and the root of a cluster's excess mass are
asymptotically exponential. The false-alarm rate is about *reported* false regions, and
most of a pair's noise clusters would never be reported (on a pale wall small colour
residue is highly significant, but changes its patch by less than ``min_local_delta_e``;
vessel residue is elongated; the neck's cap is dropped by the neck rule): every candidate
cluster of at least ``min_diameter_mm`` is measured as it is by the checks below (all but
the photo-consistency check, which reads session B's frames; :class:`_Checks`, the same code
as for the regions), and the count of null clusters at least as strong is multiplied by the
share of them that would pass (Jeffreys' estimate among the null clusters at least as
strong: ``(passing + 1/2) / (all + 1)``, local in strength because reportable noise is
concentrated among the strongest clusters; :func:`cystomap.compare.null.reportable_share`).
A cluster's ``expected_false`` is 2 × the lesser of its two expected counts of reportable
null clusters (Bonferroni over the two statistics); reportable clusters at most the rate
are changes, and so are clusters that would not be reported as they are but whose count of
all null clusters is at most the rate (pieces of one change, or a change after cleaning:
the checks decide). Clusters the null expects fewer than ``PEEL_EXPECTED`` of in all are
taken out of the sample and the tails refitted, until nothing changes (not by the
reportable count: the strongest reportable noise would take itself out). Splitting a
cluster at its saddles and joining weak pieces compare a piece, which is not measured, with
all null clusters. Measured (dev pairs 300-303, 306, 308 and no-change 1300, 1301, 1303,
640x360, perivascular lesions apart): 14/29 lesions at rate 0.1 (13/29 counting every null
cluster), 1 false region on the lesion pairs (1), 2 on the no-change pairs (1); on seeded
mottled no-change pairs (the tests' wall, 10 seeds) 0, 6 and 12 false regions at rates 0.1,
0.3 and 1 (0, 6, 9). The gain is small: a weak lesion among the strongest clusters counts
itself and its reportable neighbours, and strong reportable noise (pair 1303) looks like
weak lesions (pair 300) to the null.

The accepted clusters are cleaned by a morphological closing and opening (``morphology_mm``),
pieces closer than ``merge_mm`` are joined, a region must still be unlikely under the null
after cleaning, and at least the area of a disc of ``min_diameter_mm`` (the smallest change
of interest, a physical size).

Checks (each counted in ``compare.json``): the region lies on reconstructed wall (median
distance to the nearest SfM point of each session ≤ ``max_point_distance_mm``), is mostly
surrounded by compared wall (``min_enclosed``), session A shows wall there, not an opening
(``min_luminance_a``), and its texture is photo-consistent in session B's frames
(``max_inconsistency``, :mod:`cystomap.compare.consistency`; a region B's frames disagree on
but A's frames agree on at the same site is kept: the wall there changed its relief, as a
raised lesion does), it is a patch rather than a
line (length / width on the wall at most ``max_elongation``: a vessel or edge left
misaligned gives a thin, long difference; phantom lesions measured 1.0-1.7, cut ones up to
2.8, vessel residues 4-6).

The bladder neck: the scope enters through it, so registered cameras at or beyond the wall
point to it; the mesh closes it with a cap whose texture (the urethra seen through it) differs
between sessions, and the wall around it is filmed rarely and at grazing angles, on a mesh
several millimetres off, so its whole band is "changed" without any change. The wall within an
angle of such a camera's direction (the cap) is cut out of the accepted clusters, and regions
still centred within it are dropped (a lesion beside it, joined to the cap's difference in one
cluster, is measured without the cap rather than dropped with it). With ``neck_chroma`` (the
default) the angle is the pair's own (:func:`cystomap.compare.neck.chroma_band`: out to where
the colour is as quiet as on the rest of the wall), beyond it the band whose brightness
the levelling's halo disturbs is tested on its colour alone, and a region beside the cap is
followed into it where it stands out against the cap's own noise (ring by ring:
:func:`cystomap.compare.neck.chroma_band`), so that a lesion at the neck is measured whole;
such a region is dropped as near the neck only when its part outside the cap is centred
within it. Without ``neck_chroma`` the angle is the fixed ``opening_deg``. The alternative
``neck_levelling`` (opt-in) scales the band's significance to the wall's noise level ring by
ring instead: on held-out pairs it was no better (docs/measurements.md, "The wall around the neck").
Last, the region must change its patch, not the wall around it: its mean colour relative to
its ring's must change between the sessions by at least ``min_local_delta_e`` (CIE76 ΔE*ab,
``local_delta_e``; the ring is wall: the neck's cap, whose colours change from session to
session, is left out of it). Photometric residue the illumination matching leaves
(a gain or white balance varying smoothly over the wall) is significant by its size but
shifts region and ring alike; a lesion changes the region only. With
``local_colour_in_frames`` (the default) this contrast is measured where it was filmed: in
each of up to ``consistency_views`` frames of a session that see the region and its ring
(:func:`cystomap.compare.consistency.contrasts`, exposure-normalised on the ring), the
median over the frames, B's against A's at the same site (``frame_local_delta_e``), and
the lesser of it and the atlases' value decides: the atlases blend many frames, which
softens a faint lesion's edge and keeps what each frame's exposure and white balance left;
the few frames have sampling noise of their own; residue seldom fools both (docs/
measurements.md, "The local colour check on both the atlases and the frames").
(``min_delta_e``, a floor on the region's own mean colour change, moves with that residue and
is off by default.)

Gaps and unseen wall: a scan leaves strips of wall unfilmed between its sweeps, and the
compared wall stops where either session's coverage does. Pieces of one change on both sides
of an unseen strip narrower than ``gap_fill_mm`` are one region, and its outline is closed
across the strip. Where a change runs into wall that B saw but A did not
(``extend_into_unseen``), it is followed on B's smoothed colours (pixels at least half-way
from the surrounding wall's colour to the region's, up to twice the compared part's
equivalent diameter further; over wall A saw well, the rim of wall B itself did not see, which
B paints from grazing views, only ``edge_margin_mm`` beyond the compared outline): the region
is measured as B shows it, and ``observed_share`` says how much of it was compared
(``delta_e`` and ``local_delta_e`` are measured on the compared part). Regions that end up
describing the same wall (both pieces of a cut change followed into the gap) are reported once.

Poles: the grid is azimuth/elevation, so its pixels crowd towards both poles (the dome and
the neck). Whatever is a statistic of the wall is weighted by wall area (the tone match and
noise covariance of :mod:`cystomap.compare.difference`, the candidate level), blurs continue
across the poles and are Gaussian on the wall there (:func:`cystomap.compare.grid.blur_mm`),
clusters are joined across the poles as across the seam, and a region's ring and reach are
distances on the wall (:func:`cystomap.compare.morphology.near_on_wall`).

Measurement: each region's outline is where its significance exceeds half of its own peak
(99th percentile), the full-width-at-half-maximum outline, holes filled: a blurred disc's
half-maximum contour lies on its edge whatever its contrast, so the size does not depend on
the threshold. A region whose pixels above half its peak fall apart into blobs that are
still apart at half of their own peaks holds several changes (two lesions inside one patch of
significant residue, which no saddle separates): it is split into one region per blob before
it is measured (:mod:`cystomap.compare.half_maximum`), so that the weaker one is not lost and
the stronger one's centroid is not pulled towards it (held-out pair 610: an 8.5 mm lesion
lost, a 26.2 mm one 4.19 mm off). Area = sum of the wall areas of its pixels (not a pixel count),
diameter = sqrt(4 A / π), centroid = area-weighted mean wall point, put back on the wall
along its direction from the barycentre (and, on a raised lesion, onto session B's 3-D points
there by the compare stage: :mod:`cystomap.compare.relief`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from cystomap.atlas.projection import Projection, SurfaceRays
from cystomap.compare.difference import Difference, Grid, lab, luminance
from cystomap.compare.grid import cone_mask, within_cone
from cystomap.compare.half_maximum import separate_half_maxima
from cystomap.compare.morphology import (
    _disc,
    _fill_holes,
    _morph,
    follow_into,
    label_wrapped,
    near_on_wall,
)
from cystomap.compare.neck import chroma_band, level_around_neck
from cystomap.compare.null import (
    CANDIDATE_MADS,
    Candidates,
    candidates,
    split_at_saddles,
)
from cystomap.compare.null import changed_mask as changed_mask  # re-exported: stage, tests
from cystomap.parallel import ordered_map

log = logging.getLogger(__name__)

# a region's peak (for its half-maximum outline) is this percentile of its significance: the
# 95th set a small change's half-maximum too low (5 mm phantom lesions measured +20-25 %
# wide at full size; +18-25 % with the 99th)
PEAK_PERCENTILE = 99.0

CHANGE_COLUMNS = ("id", "x", "y", "z", "azimuth_deg", "elevation_deg", "area_mm2",
                  "diameter_mm", "mean_difference", "score", "peak_significance",
                  "mean_significance", "atlas_col", "atlas_row", "pixels", "inconsistency",
                  "inconsistency_a", "enclosed", "luminance_a", "luminance_b",
                  "point_distance_mm", "elongation", "observed_share", "delta_e",
                  "local_delta_e", "frame_local_delta_e", "expected_false", "mass",
                  "relief_mm")


@dataclass
class Region:
    id: int
    pixels: np.ndarray  # flat grid indices of the measured outline
    x: float
    y: float
    z: float
    azimuth_deg: float
    elevation_deg: float
    area_mm2: float
    diameter_mm: float
    mean_difference: float  # mean colour difference |B − A| (0-255 RGB units)
    score: float
    peak_significance: float
    mean_significance: float
    atlas_col: float  # centroid in session B's (full-size) atlas
    atlas_row: float
    inconsistency: float | None = None  # photo-consistency in B's frames (None: not tested)
    # the same in A's frames at the same site (tested only when B's is over the limit)
    inconsistency_a: float | None = None
    enclosed: float = 1.0  # share of a ring around the region that both sessions saw
    luminance_a: float = 1.0  # median luminance in the region / on the compared wall, A
    luminance_b: float = 1.0  # the same in B
    point_distance_mm: float = 0.0  # median distance to the sessions' nearest SfM points
    elongation: float = 1.0  # length / width on the wall (principal axes)
    observed_share: float = 1.0  # share of the area both sessions saw (rest: bridged gap)
    delta_e: float = 0.0  # CIE76 colour difference of the region's mean colours, A vs B
    local_delta_e: float = 0.0  # the same of the region's colour relative to its ring's
    # the same measured in the frames that saw the site (None: not measured)
    frame_local_delta_e: float | None = None
    expected_false: float = 0.0  # expected number of null regions at least this strong
    mass: float = 0.0  # excess significance mass above the candidate level (noise units · mm²)
    relief_mm: float = 0.0  # the centroid's lift off the mesh onto B's points (a raised lesion)

    def row(self) -> dict[str, Any]:
        return {"id": self.id, "x": self.x, "y": self.y, "z": self.z,
                "azimuth_deg": self.azimuth_deg, "elevation_deg": self.elevation_deg,
                "area_mm2": self.area_mm2, "diameter_mm": self.diameter_mm,
                "mean_difference": self.mean_difference, "score": self.score,
                "peak_significance": self.peak_significance,
                "mean_significance": self.mean_significance,
                "atlas_col": self.atlas_col, "atlas_row": self.atlas_row,
                "pixels": len(self.pixels),
                "inconsistency": "" if self.inconsistency is None else self.inconsistency,
                "inconsistency_a": "" if self.inconsistency_a is None else self.inconsistency_a,
                "enclosed": self.enclosed,
                "luminance_a": self.luminance_a, "luminance_b": self.luminance_b,
                "point_distance_mm": self.point_distance_mm, "elongation": self.elongation,
                "observed_share": self.observed_share, "delta_e": self.delta_e,
                "local_delta_e": self.local_delta_e,
                "frame_local_delta_e": ("" if self.frame_local_delta_e is None
                                        else self.frame_local_delta_e),
                "expected_false": self.expected_false, "mass": self.mass,
                "relief_mm": self.relief_mm}


def elongation(points: np.ndarray, weights: np.ndarray) -> float:
    """Length / width of a patch of wall points: sqrt of the ratio of the two largest
    eigenvalues of their weighted covariance."""
    if len(points) < 3:
        return 1.0
    w = weights / max(float(weights.sum()), 1e-12)
    c = points - (points * w[:, None]).sum(0)
    ev = np.sort(np.linalg.eigvalsh((c * w[:, None]).T @ c))[::-1]
    return float(np.sqrt(ev[0] / max(ev[1], 1e-12)))


def mean_colour_difference(a_rgb: np.ndarray, b_rgb: np.ndarray, weights: np.ndarray) -> float:
    """CIE76 ΔE*ab between the weighted mean colours (RGB 0..255) of two sets of pixels.

    The mean over the region, not a per-pixel mean: texture left slightly misaligned (a
    vessel, mottling) changes single pixels but hardly the patch's mean colour; a lesion
    changes the patch.
    """
    lab = _mean_lab((a_rgb, weights), (b_rgb, weights))
    return float(np.linalg.norm(lab[1] - lab[0]))


def _mean_lab(*sets: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """CIE L*a*b* of the weighted mean colour (RGB 0..255) of each (pixels, weights) set."""
    return lab(np.stack([(rgb * (w / max(float(w.sum()), 1e-12))[:, None]).sum(0)
                         for rgb, w in sets]))


def local_colour_difference(a_rgb: np.ndarray, b_rgb: np.ndarray, weights: np.ndarray,
                            a_ring: np.ndarray, b_ring: np.ndarray, ring_weights: np.ndarray,
                            ) -> float:
    """CIE76 ΔE*ab of the change of a region's mean colour relative to its ring's: the norm of
    (Lab_B(region) − Lab_B(ring)) − (Lab_A(region) − Lab_A(ring)).

    Photometric residue the illumination matching leaves (a smooth gain, a white balance
    that differs over the wall) shifts the region and the wall around it alike and cancels;
    a lesion changes its patch, not the wall around it.
    """
    lab = _mean_lab((a_rgb, weights), (b_rgb, weights), (a_ring, ring_weights),
                    (b_ring, ring_weights))
    return float(np.linalg.norm((lab[1] - lab[3]) - (lab[0] - lab[2])))


def _extend_into_unseen(diff: Difference, outline: np.ndarray, seen: np.ndarray,
                        sub_joint: np.ndarray, sub_hit: np.ndarray, rows: tuple[int, int],
                        c_idx: np.ndarray, ring_mm: float, open_px: float,
                        gap_kernel: np.ndarray | None, margin_mm: float) -> np.ndarray:
    """``outline`` grown over adjoining wall that B saw but that was not compared (A did not
    see it, or it is in A's edge margin) where B's smoothed colour is at least half-way from
    the surrounding wall's colour to the region's: the part of a change that lies on wall
    A missed. It grows at most twice the compared part's equivalent diameter, and across
    strips of wall B did not see either when narrower than ``gap_kernel`` (sub-window arrays).
    When the growth would reach no wall A missed (all of it wall A saw well,
    ``diff.a_interior``, left out of the comparison only as the edge margin of wall B did not
    see), it keeps only that margin (``margin_mm``) around the outline: the change's own edge,
    not a run along the rim, which B paints from grazing views (a raised lesion's smear
    beside the hole its relief hides; held-out pair 229's 13.2 mm papillary, followed along
    such a rim, was measured as an 18.6 mm region off its place and missed).
    """
    import cv2

    if diff.b_seen is None or diff.b_smooth is None or not seen.any():
        return outline
    r_lo, r_hi = rows
    eligible = diff.b_seen[r_lo:r_hi][:, c_idx] & ~sub_joint & ~outline
    sub_pts = diff.grid.points[r_lo:r_hi][:, c_idx]
    ring = near_on_wall(seen, sub_pts, ring_mm, sub_joint) & ~seen
    if not eligible.any() or ring.sum() < 8:
        return outline
    colour = diff.b_smooth[r_lo:r_hi][:, c_idx]
    inside = np.median(colour[seen], axis=0)
    around = np.median(colour[ring], axis=0)
    axis = inside - around
    if float(axis @ axis) < 1e-6:
        return outline
    t = (colour - around) @ axis / float(axis @ axis)
    cand = eligible & (t >= 0.5)
    if open_px >= 0.5:
        cand = cv2.morphologyEx(cand.astype(np.uint8), cv2.MORPH_OPEN, _disc(open_px)) > 0
    # the compared part may be a small cap of a large change: follow it up to twice the
    # cap's own equivalent diameter, on the wall (its area, not its pixel count: pixels
    # shrink towards the poles)
    sub_area = diff.grid.area[r_lo:r_hi][:, c_idx]
    reach_mm = 2 * math.sqrt(4 * float(sub_area[seen].sum()) / math.pi)
    reach = near_on_wall(outline, sub_pts, reach_mm, cand)
    grown = outline | (cand & reach)
    link = grown
    if gap_kernel is not None:  # across strips of wall B did not see either
        unseen = sub_hit & ~diff.b_seen[r_lo:r_hi][:, c_idx]
        link = grown | ((cv2.dilate(grown.astype(np.uint8), gap_kernel) > 0) & unseen)
    _, lab = cv2.connectedComponents(link.astype(np.uint8), connectivity=8)
    keep = np.unique(lab[outline])
    keep = keep[keep > 0]
    kept = np.isin(lab, keep) & grown
    if diff.a_interior is not None and not (kept & ~outline
                                            & ~diff.a_interior[r_lo:r_hi][:, c_idx]).any():
        # over wall A saw well only (the rim of B's unseen wall): the change's edge, no further
        kept &= outline | near_on_wall(outline, sub_pts, margin_mm)
    if gap_kernel is not None:
        return _close_across(kept, gap_kernel, sub_joint, sub_hit)
    return _fill_holes(kept) & sub_hit


def _close_across(mask: np.ndarray, kernel: np.ndarray, compared: np.ndarray,
                  wall: np.ndarray) -> np.ndarray:
    """``mask`` closed by ``kernel`` across wall that was not compared (an unseen strip), holes
    filled: compared wall keeps the verdict of its own significance."""
    import cv2

    closed = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel) > 0
    return _fill_holes(mask | (closed & ~compared & wall)) & wall


# --------------------------------------------------------------------------- the pair's null


def _join_pieces(lab: np.ndarray, n: int, cand: np.ndarray, diff: Difference,
                 null: Candidates, cfg: Any, gap_kernel: np.ndarray | None,
                 ) -> tuple[np.ndarray, int]:
    """Pieces of one change made one region: pieces on both sides of a strip of wall one
    session did not see (narrower than ``gap_fill_mm``: their growth across the uncompared
    wall meets), and a piece too weak to be a change on its own (expected null count above
    the rate) within ``merge_mm`` of another (fragments). Two pieces that are each a change
    and are separated by compared wall stay apart: the wall between them is the pair's noise.
    """
    import cv2

    grid = diff.grid
    comp, _ = label_wrapped(cand)
    bridge = ~diff.joint & grid.hit
    flat_sig, flat_area = diff.significance.ravel(), grid.area.ravel()
    merge_k = _disc(cfg.merge_mm / 2 / grid.mm_per_px_y) if cfg.merge_mm > 0 else None
    one = _disc(1)
    pieces = []
    for r in range(1, n + 1):
        m = lab == r
        if not m.any():
            continue
        px = np.flatnonzero(m)
        # (a piece is not measured: as strong as the noise's clusters, reportable or not)
        weak = null.expected_false(null.statistics(flat_sig[px], flat_area[px]),
                                   reported=False) > cfg.false_alarm_rate
        gap = (np.flatnonzero(_morph(m | (_morph(m, cv2.MORPH_DILATE, gap_kernel) & bridge),
                                     cv2.MORPH_DILATE, one)) if gap_kernel is not None else px)
        near = (np.flatnonzero(_morph(m, cv2.MORPH_DILATE, merge_k)) if merge_k is not None
                else px)
        pieces.append((r, int(comp.ravel()[px[0]]), weak, px, gap, near))
    parent = {p[0]: p[0] for p in pieces}

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, (ri, ci, wi, _pi, gi, ni) in enumerate(pieces):
        for rj, cj, wj, pj, gj, _nj in pieces[i + 1:]:
            if ci == cj:  # split from one cluster at a saddle: separate by the null
                continue
            joined = (gap_kernel is not None and len(np.intersect1d(gi, gj, assume_unique=True)) > 0)
            if not joined and merge_k is not None and (wi or wj):
                joined = len(np.intersect1d(ni, pj, assume_unique=True)) > 0
            if joined:
                a, b = find(ri), find(rj)
                parent[max(a, b)] = min(a, b)
    out = np.zeros_like(lab)
    roots = sorted({find(p[0]) for p in pieces})
    new_id = {r: k for k, r in enumerate(roots, start=1)}
    for r, *_ in pieces:
        out[lab == r] = new_id[find(r)]
    return out, len(roots)


# reasons a region is dropped (compare.json's dropped_* counts, in the order of the checks)
DROP_REASONS = ("small", "weak", "at_edge", "off_reconstruction", "dark_in_a", "inconsistent",
                "elongated", "near_neck", "faint", "not_local")


class _Checks:
    """The measurement of a region on the wall and the checks it must pass to be reported
    (see the module docstring), for a set of grid pixels: a region after the null's decision
    and its cleaning, or one of the pair's candidate clusters (the null is fitted to those
    that would pass them: see :func:`detect`)."""

    def __init__(self, diff: Difference, cfg: Any, proj_full: Projection, rays: SurfaceRays,
                 openings: np.ndarray | None,
                 verify: Callable[[np.ndarray, np.ndarray], dict[str, Any]] | None) -> None:
        grid: Grid = diff.grid
        self.diff, self.cfg, self.proj, self.rays, self.verify = diff, cfg, proj_full, rays, verify
        self.openings = openings if openings is not None else np.zeros((0, 3))
        # the neck's cap: not a region's wall (cut out of the clusters and of the outlines)
        self.cap = cone_mask(grid, self.openings, cfg.opening_deg)
        # (H, W) significance a pixel of the cap needs to extend a region into it (None: none
        # does; see extend_into_cap)
        self.cap_floor: np.ndarray | None = None
        self.min_area = math.pi * (cfg.min_diameter_mm / 2) ** 2
        # a strip of unseen wall is widened by the edge margin on both sides and the pieces on
        # either side shrink by the morphological opening
        self.gap_kernel = (_disc((cfg.gap_fill_mm / 2 + cfg.edge_margin_mm + cfg.morphology_mm)
                                 / grid.mm_per_px_y) if cfg.gap_fill_mm > 0 else None)
        self.flat_sig = diff.significance.ravel()
        self.flat_area = grid.area.ravel()
        self.flat_pts = grid.points.reshape(-1, 3)
        self.flat_delta = diff.delta.reshape(-1, 3)
        self.pdist = diff.point_distance.ravel() if diff.point_distance is not None else None
        self.a_rgb, self.b_rgb = diff.a_rgb.reshape(-1, 3), diff.b_rgb.reshape(-1, 3)
        self.lum_a, self.lum_b = luminance(self.a_rgb), luminance(self.b_rgb)
        jflat = diff.joint.ravel()
        self.lum_ref_a = max(float(np.median(self.lum_a[jflat])), 1e-6)
        self.lum_ref_b = max(float(np.median(self.lum_b[jflat])), 1e-6)

    def measure(self, px: np.ndarray, lab: np.ndarray, r: int, verify: bool = True,
                ) -> tuple[str, Region | None]:
        """Region ``r`` of ``lab`` (its flat pixels ``px``) measured on the wall: ("", region)
        when it passes every check, else (the first check it fails, None). ``verify``: run the
        photo-consistency check (it reads session B's frames)."""
        import cv2

        cfg, diff, grid = self.cfg, self.diff, self.diff.grid
        flat_sig, flat_area, flat_pts = self.flat_sig, self.flat_area, self.flat_pts
        h, w = grid.shape
        gap_kernel, min_area = self.gap_kernel, self.min_area
        peak = float(np.percentile(flat_sig[px], PEAK_PERCENTILE))
        # FWHM outline: within the region's bounding box (grown by its own size), pixels above
        # half the peak that touch the region, holes filled
        rows, cols = px // w, px % w
        # regions across the seam: unwrap columns around the region's first column
        c0 = cols[0]
        ucols = (cols - c0 + w // 2) % w - w // 2 + c0
        # the window grows by the region's own size (half of it without extend_into_unseen)
        # and its ring, in mm on the wall: in pixels the columns near the poles are short
        pts = flat_pts[px]
        pts = pts[np.isfinite(pts).all(axis=1)]
        size_mm = float(np.ptp(pts, axis=0).max()) if len(pts) else 0.0
        grow_mm = (size_mm if cfg.extend_into_unseen else size_mm / 2) + cfg.ring_mm
        pad = int(np.ceil(grow_mm / grid.mm_per_px_y)) + 3
        r_lo, r_hi = max(0, rows.min() - pad), min(h, rows.max() + pad + 1)
        # at most one turn; a window that reaches a pole row holds every azimuth (the wall
        # across the pole is the region's neighbour: its ring and outline reach over)
        near_pole = r_lo == 0 or r_hi == h
        pad_c = int(np.ceil(grow_mm / float(grid.mm_per_px_x[r_lo:r_hi].min()))) + 3
        pad_c = max(0, min(w if near_pole else pad_c, (w - 1 - int(np.ptp(ucols))) // 2))
        c_lo = ucols.min() - pad_c
        c_idx = np.arange(c_lo, ucols.max() + pad_c + 1) % w
        sub_sig = diff.significance[r_lo:r_hi][:, c_idx]
        sub_joint = diff.joint[r_lo:r_hi][:, c_idx]
        # the outline stays off the other regions' pixels (a neighbour split off at a saddle)
        sub_lab = lab[r_lo:r_hi][:, c_idx]
        above = sub_joint & (sub_sig >= 0.5 * peak) & ((sub_lab == 0) | (sub_lab == r))
        sub_cap = self.cap[r_lo:r_hi][:, c_idx]
        half = above & ~sub_cap
        core = np.zeros_like(half)
        core[rows - r_lo, ucols - c_lo] = True
        _, half_lab = cv2.connectedComponents(half.astype(np.uint8), connectivity=8)
        keep = np.unique(half_lab[core & half])
        keep = keep[keep > 0]
        outline = _fill_holes(np.isin(half_lab, keep)) & sub_joint if len(keep) else core
        # the outline closed across unseen strips of wall that cut into it (concavities
        # only: closing never reaches beyond the region's own convex outline)
        seen_outline = outline
        sub_hit = grid.hit[r_lo:r_hi][:, c_idx]
        if gap_kernel is not None:
            outline = _close_across(outline, gap_kernel, sub_joint, sub_hit)
        if cfg.extend_into_unseen:
            outline = _extend_into_unseen(diff, outline, seen_outline, sub_joint, sub_hit,
                                          (r_lo, r_hi), c_idx, cfg.ring_mm,
                                          cfg.morphology_mm / grid.mm_per_px_y, gap_kernel,
                                          cfg.edge_margin_mm)
        # measured on the wall outside the neck's cap; followed into the cap where it stands
        # out against the cap's own noise (see extend_into_cap)
        wall_outline = outline
        if self.cap_floor is not None and sub_cap.any():
            outline = follow_into(outline, above & sub_cap
                                  & (sub_sig >= self.cap_floor[r_lo:r_hi][:, c_idx]))
            grown = outline & ~wall_outline
            if grown.any():
                log.debug("changes: a region beside the neck's cap followed %.0f mm² into it "
                          "(%.0f mm² outside)", float(grid.area[r_lo:r_hi][:, c_idx][grown].sum()),
                          float(grid.area[r_lo:r_hi][:, c_idx][wall_outline].sum()))
        # the ring: wall within ring_mm of the outline, on the wall (atlas columns shrink
        # towards the poles: a ring of pixels there would be a sliver of the lesion's edge)
        sub_pts = grid.points[r_lo:r_hi][:, c_idx]
        sub_area = grid.area[r_lo:r_hi][:, c_idx]
        ring = near_on_wall(outline, sub_pts, cfg.ring_mm) & ~outline
        enclosed = (float(sub_area[ring & sub_joint].sum()) / max(float(sub_area[ring].sum()), 1e-12)
                    if ring.any() else 0.0)
        if enclosed < cfg.min_enclosed:
            return "at_edge", None
        # the compared ring (flat grid indices), on the wall: not over the neck's cap, whose
        # colours (the opening bridged by the mesh) change from session to session
        r2, c2 = np.nonzero(ring & sub_joint & ~self.cap[r_lo:r_hi][:, c_idx])
        ring_pix = (r2 + r_lo) * w + c_idx[c2]
        rr, cc = np.nonzero(outline)
        pix_all = (rr + r_lo) * w + c_idx[cc]
        rr, cc = np.nonzero(wall_outline)
        pix_wall = (rr + r_lo) * w + c_idx[cc]
        rr, cc = np.nonzero(seen_outline)
        pix = (rr + r_lo) * w + c_idx[cc]
        where = np.round(np.nanmean(flat_pts[pix], axis=0), 1).tolist()
        p_dist = float(np.median(self.pdist[pix])) if self.pdist is not None else 0.0
        if cfg.max_point_distance_mm > 0 and p_dist > cfg.max_point_distance_mm:
            log.debug("changes: region at %s: %.1f mm from the nearest SfM point (the mesh is "
                      "interpolated there)", where, p_dist)
            return "off_reconstruction", None
        lum_rel_a = float(np.median(self.lum_a[pix])) / self.lum_ref_a
        if lum_rel_a < cfg.min_luminance_a:
            log.debug("changes: region at %s: session A shows an opening there (%.0f%% of the "
                      "wall's luminance), not wall", where, 100 * lum_rel_a)
            return "dark_in_a", None
        consistency: dict[str, Any] = {}
        if verify and self.verify is not None:
            consistency = self.verify(pix, ring_pix)
            value = consistency.get("inconsistency")
            value_a = consistency.get("inconsistency_a")
            if cfg.max_inconsistency > 0 and value is not None and value > cfg.max_inconsistency:
                if value_a is None or value_a > cfg.max_inconsistency:
                    log.debug("changes: region at %s: its colours disagree across session B's "
                              "frames (inconsistency %.2f > %.2f; A's: %s; not on the wall)",
                              where, value, cfg.max_inconsistency,
                              "not tested" if value_a is None else f"{value_a:.2f}")
                    return "inconsistent", None
                log.info("changes: region at %s: its colours disagree across session B's frames "
                         "(inconsistency %.2f) but not across A's at the same site (%.2f): "
                         "the wall's relief changed there (a raised lesion), kept", where,
                         value, value_a)
        a_all = flat_area[pix_all]
        area = float(a_all.sum())
        if area < min_area:
            return "small", None
        a = flat_area[pix]
        observed = float(a.sum()) / max(area, 1e-12)
        p = flat_pts[pix_all]
        ok = np.isfinite(p).all(axis=1)
        centroid = (p[ok] * a_all[ok, None]).sum(0) / max(a_all[ok].sum(), 1e-12)
        elong = elongation(p[ok], a_all[ok])
        if cfg.max_elongation > 0 and elong > cfg.max_elongation:
            log.debug("changes: region at %s: elongated (%.1f : 1), a vessel or edge left "
                      "misaligned, not a patch", np.round(centroid, 1).tolist(), elong)
            return "elongated", None
        d = centroid - self.proj.barycentre
        d /= max(np.linalg.norm(d), 1e-12)
        t_hit, _ = self.rays.cast(self.proj.barycentre, d[None])
        if np.isfinite(t_hit[0]):
            centroid = self.proj.barycentre + t_hit[0] * d
        # near the neck: the part outside the cap centred within it (a change followed into
        # the cap may be centred there: its own wall decides)
        p_wall, a_wall = flat_pts[pix_wall], flat_area[pix_wall]
        ok_wall = np.isfinite(p_wall).all(axis=1)
        d_wall = ((p_wall[ok_wall] * a_wall[ok_wall, None]).sum(0)
                  / max(a_wall[ok_wall].sum(), 1e-12) - self.proj.barycentre
                  if len(pix_wall) < len(pix_all) and ok_wall.any() else d)
        d_wall = d_wall / max(float(np.linalg.norm(d_wall)), 1e-12)
        if within_cone(d_wall, self.openings, cfg.opening_deg):
            log.debug("changes: region at %s: within %g deg of the bladder neck, where the "
                      "scope entered", np.round(centroid, 1).tolist(), cfg.opening_deg)
            return "near_neck", None
        delta_e = mean_colour_difference(self.a_rgb[pix], self.b_rgb[pix], a)
        local_de = (local_colour_difference(self.a_rgb[pix], self.b_rgb[pix], a,
                                            self.a_rgb[ring_pix], self.b_rgb[ring_pix],
                                            flat_area[ring_pix]) if len(ring_pix) else delta_e)
        if delta_e < cfg.min_delta_e:
            log.debug("changes: region at %s: its mean colour changed by ΔE %.1f < %g, not "
                      "visible", np.round(centroid, 1).tolist(), delta_e, cfg.min_delta_e)
            return "faint", None
        frame_de = consistency.get("frame_local_delta_e")
        # both must show it: the atlases (a blend of many frames, with what each frame's
        # exposure left on the wall) and the frames themselves (a few views, each with its
        # own sampling noise) are each fooled by something the other is not
        decisive = local_de if frame_de is None else min(local_de, frame_de)
        if decisive < cfg.min_local_delta_e:
            log.debug("changes: region at %s (%.1f mm): relative to the wall around it its "
                      "colour changed by ΔE %.1f < %g (%s; its ring changed alike: photometric "
                      "residue, not a change of the patch)", np.round(centroid, 1).tolist(),
                      math.sqrt(4 * area / math.pi), decisive, cfg.min_local_delta_e,
                      "on the atlases" if frame_de is None
                      else f"the lesser of {local_de:.1f} on the atlases and {frame_de:.1f} in the frames")
            return "not_local", None
        q = self.proj.axes @ d
        col, row = self.proj.point_to_pixel(centroid[None])
        return "", Region(
            id=0, pixels=pix_all, x=float(centroid[0]), y=float(centroid[1]),
            z=float(centroid[2]), azimuth_deg=math.degrees(math.atan2(q[1], q[0])),
            elevation_deg=math.degrees(math.atan2(q[2], math.hypot(q[0], q[1]))),
            area_mm2=area, diameter_mm=math.sqrt(4 * area / math.pi),
            mean_difference=float(np.average(np.linalg.norm(self.flat_delta[pix], axis=1),
                                             weights=a)),
            score=0.0, peak_significance=peak,
            mean_significance=float(np.average(flat_sig[pix], weights=a)),
            atlas_col=float(col[0]), atlas_row=float(row[0]),
            inconsistency=consistency.get("inconsistency"),
            inconsistency_a=consistency.get("inconsistency_a"), enclosed=enclosed,
            luminance_a=lum_rel_a,
            luminance_b=float(np.median(self.lum_b[pix])) / self.lum_ref_b,
            point_distance_mm=p_dist, elongation=elong, observed_share=observed,
            delta_e=delta_e, local_delta_e=local_de, frame_local_delta_e=frame_de)

    def extend_into_cap(self, cap_level: np.ndarray, candidate_level: float) -> None:
        """From now on a region touching the neck's cap is followed into it over the pixels
        above half its peak whose significance is also at least ``candidate_level`` times
        the cap's noise level there (``cap_level``: from :func:`cystomap.compare.neck.chroma_band`):
        the candidate test of the wall, on the cap's own noise. A lesion beside the neck
        whose inner part lies in the cap is then measured whole; the cap's residue (its
        noise scaled up) passes as rarely as the wall's does. Regions are still dropped as
        near the neck when their part outside the cap is centred within it."""
        self.cap_floor = np.where(self.cap, cap_level * candidate_level, np.inf)

    def reportable(self, labels: np.ndarray, n: int) -> np.ndarray:
        """(n,) bool: whether each cluster of ``labels`` (1 … n) would pass the checks as it is
        (without the photo-consistency check, which reads session B's frames: the null keeps
        the clusters it would drop)."""
        flat = labels.ravel()
        order = np.argsort(flat, kind="stable")
        bounds = np.searchsorted(flat[order], np.arange(1, n + 2))
        # a cluster smaller than the smallest change is not measured (its outline at half its
        # peak lies inside it: never larger); the others are measured on the stage's threads
        todo = [r for r in range(1, n + 1)
                if bounds[r] > bounds[r - 1]
                and self.flat_area[order[bounds[r - 1]:bounds[r]]].sum() >= self.min_area]

        def passes(r: int) -> bool:
            px = order[bounds[r - 1]:bounds[r]]
            return self.measure(px, labels, r, verify=False)[0] == ""

        out = np.zeros(n, bool)
        threads = int(getattr(self.cfg, "threads", 1))
        for r, ok in zip(todo, ordered_map(passes, todo, threads), strict=True):
            out[r - 1] = ok
        return out


def _across_unseen(diff: Difference, gap_kernel: np.ndarray | None,
                   ) -> Callable[[np.ndarray], np.ndarray] | None:
    """A mask grown over wall the comparison left out that the mesh covers by the gap kernel
    (pieces of one change on both sides of a strip of unseen wall meet: :func:`_join_pieces`);
    None without gap filling."""
    import cv2

    if gap_kernel is None:
        return None
    bridge = ~diff.joint & diff.grid.hit

    def grow(mask: np.ndarray) -> np.ndarray:
        return mask | (_morph(mask, cv2.MORPH_DILATE, gap_kernel) & bridge)

    return grow


def detect(diff: Difference, cfg: Any, proj_full: Projection, rays: SurfaceRays,
           verify: Callable[[np.ndarray, np.ndarray], dict[str, Any]] | None = None,
           openings: np.ndarray | None = None,
           ) -> tuple[list[Region], dict[str, Any]]:
    """Changed regions of ``diff`` measured on session B's wall (sorted by score).

    ``openings``: unit directions (from B's barycentre) of the bladder neck; the wall within
    ``cfg.opening_deg`` of one (the neck's cap) is cut out of the accepted clusters, and
    regions whose centroid still lies within that angle are dropped. The null sample is
    unchanged (the cap's clusters in it are not reportable either way).

    ``verify(region_pixels, ring_pixels)`` (flat grid indices) may return
    ``{"inconsistency": value}``; regions above ``cfg.max_inconsistency`` are dropped (see
    :mod:`cystomap.compare.consistency`).
    """
    import cv2

    grid: Grid = diff.grid
    cap_level: np.ndarray | None = None
    neck_info: dict[str, Any] = ({"band": False, "reason": "no camera at the neck"}
                                 if cfg.neck_chroma else {"levelled": False})
    if cfg.neck_levelling and openings is not None and len(openings):
        diff.significance, neck_info = level_around_neck(diff.significance, diff.joint, grid,
                                                         openings, 2 * cfg.smooth_mm)
    if cfg.neck_chroma and openings is not None and len(openings):
        # the pair's own cap instead of opening_deg, the band beyond it tested on its colour
        diff.significance, cap_deg, cap_level, neck_info = chroma_band(diff, grid, openings,
                                                                       2 * cfg.smooth_mm)
        cfg = replace(cfg, opening_deg=min(cap_deg, 89.0))
    sig = diff.significance
    checks = _Checks(diff, cfg, proj_full, rays, openings, verify)
    null = candidates(sig, diff.joint, grid.area, cfg.false_alarm_rate, checks.reportable)
    if cap_level is not None and checks.cap.any():
        checks.extend_into_cap(cap_level, null.level)
    info: dict[str, Any] = dict(null.info)
    info["neck_chroma" if cfg.neck_chroma else "neck_levelling"] = neck_info
    # the pixel level significance.png marks: the candidate level (what is tested)
    info["threshold"] = null.level
    cand = np.isin(null.labels, np.nonzero(null.flagged)[0] + 1)
    r_px = cfg.morphology_mm / grid.mm_per_px_y
    if r_px >= 0.5:
        k = _disc(r_px)
        cand = _morph(cand, cv2.MORPH_CLOSE, k)
        cand = _morph(cand, cv2.MORPH_OPEN, k) & diff.joint
    # the neck's cap is not a region's wall: cut out of the clusters (not only regions centred
    # on it dropped), so that a change beside the neck joined to the cap's difference is
    # measured on its own instead of being dropped with it (dev pair 308's 16.9 mm CIS)
    cap = checks.cap
    if cap.any():
        cand &= ~cap
        info["neck_cap_cut_share"] = float(grid.area[cap & diff.joint].sum()
                                           / max(float(grid.area[diff.joint].sum()), 1e-9))
    # neighbouring changes in one cluster are split at the saddles of the significance
    lab, n = split_at_saddles(sig, cand, grid.area, null, cfg.false_alarm_rate)
    if (cfg.merge_mm > 0 or checks.gap_kernel is not None) and n > 1:
        lab, n = _join_pieces(lab, n, cand, diff, null, cfg, checks.gap_kernel)
    # changes that one cluster holds but whose half maxima are separate objects are measured
    # apart (two lesions in one patch of residue)
    def stands(pieces: list[np.ndarray], labels: np.ndarray) -> list[bool]:
        return [null.expected_false(null.statistics(sig.ravel()[px], grid.area.ravel()[px]))
                <= cfg.false_alarm_rate
                and checks.measure(px, labels, int(labels.ravel()[px[0]]), verify=False)[0] == ""
                for px in pieces]

    lab, n = separate_half_maxima(sig, lab, n, PEAK_PERCENTILE,
                                  _across_unseen(diff, checks.gap_kernel), stands)
    regions: list[Region] = []
    dropped = dict.fromkeys(DROP_REASONS, 0)
    dropped_duplicate = 0
    flat_sig, flat_area = sig.ravel(), grid.area.ravel()
    h, w = grid.shape
    order = np.argsort(lab.ravel(), kind="stable")
    sorted_lab = lab.ravel()[order]
    bounds = np.searchsorted(sorted_lab, np.arange(1, n + 2))
    for r in range(1, n + 1):
        px = order[bounds[r - 1]:bounds[r]]
        if len(px) == 0:
            continue
        if flat_area[px].sum() < checks.min_area:
            dropped["small"] += 1
            continue
        stats = null.statistics(flat_sig[px], flat_area[px])
        expected_false = null.expected_false(stats)
        if expected_false > cfg.false_alarm_rate:  # what the morphology left is not a change
            dropped["weak"] += 1
            log.debug("changes: region at %s (%.0f mm²): after cleaning expected false %.3g > "
                      "%g, not a change",
                      np.round(np.nanmean(grid.points.reshape(-1, 3)[px], axis=0), 1).tolist(),
                      float(flat_area[px].sum()),
                      expected_false, cfg.false_alarm_rate)
            continue
        reason, g = checks.measure(px, lab, r)
        if g is None:
            dropped[reason] += 1
            log.info("changes: region %d (expected false %.3g) dropped: %s", r, expected_false,
                     reason.replace("_", " "))
            continue
        log.debug("changes: region at %s: ΔE %.2f, relative to its ring %.2f, expected false "
                  "%.3g, diameter %.1f", np.round([g.x, g.y, g.z], 1).tolist(), g.delta_e,
                  g.local_delta_e, expected_false, g.diameter_mm)
        g.score = null.score(stats, cfg.false_alarm_rate)
        g.expected_false = expected_false
        g.mass = float(stats[1]) ** 2
        regions.append(g)
    regions.sort(key=lambda g: -g.score)
    # pieces of one change on both sides of a gap, each followed into the gap, can describe
    # the same wall: keep the higher-scoring one
    taken = np.zeros(h * w, bool)
    unique = []
    for g in regions:
        if taken[g.pixels].mean() > 0.5:
            dropped_duplicate += 1
            continue
        taken[g.pixels] = True
        unique.append(g)
    regions = unique
    for i, g in enumerate(regions, start=1):
        g.id = i
    info.update(regions_before_checks=n, **{f"dropped_{k}": v for k, v in dropped.items()},
                dropped_duplicate=dropped_duplicate,
                min_area_mm2=checks.min_area, regions=len(regions),
                score_definition="largest ratio of the region's peak significance or excess mass "
                "to the level at which false_alarm_rate null regions are expected (> 1)",
                expected_false_definition="expected number of regions at least this strong "
                "that would pass the checks in the pair without any change (its null)")
    log.info("changes: %d candidate cluster(s) above %.2f (median %.2f + %g x MAD %.2f), %d "
             "of them reportable; %d above the pair's null at %g expected false region(s); "
             "%d region(s); dropped: %s", null.info["candidates"], null.level,
             null.info["median"], CANDIDATE_MADS, null.info["mad_sigma"],
             null.info["reportable"], null.info["flagged"], cfg.false_alarm_rate, len(regions),
             ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in dropped.items()))
    return regions, info
