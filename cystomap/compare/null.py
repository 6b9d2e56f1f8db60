"""The pair's own null for the compare decision: candidate clusters of the significance, the
exponential tails of their peak and excess-mass statistics fitted to the pair's noise
clusters, the share of those that would be reported (they pass the checks a region must
pass), each cluster's expected number of reportable false look-alikes, and clusters cut at
the saddles of their significance (see :mod:`cystomap.compare.changes` for the whole
decision).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cystomap.compare.morphology import label_wrapped, pole_neighbours
from cystomap.stats import weighted_median

log = logging.getLogger(__name__)


# candidate clusters are the connected excursions of the significance above
# median + CANDIDATE_MADS · 1.4826 · MAD on the compared wall: a level the pair's own noise
# crosses often (about 4 % of a chi(3) field's area), so that its noise clusters are many
# and their strength distribution can be estimated; it sets what is tested, not what is
# reported (that is false_alarm_rate's job)
CANDIDATE_MADS = 2.0
# the null's tail (generalised Pareto, peaks over threshold) is fitted to the strongest
# TAIL_SHARE of the null clusters, at least TAIL_MIN of them; the strongest CENSOR_SHARE of
# those enter the fit only by their number (right-censored: "this many are stronger"), so
# that changes among them (a few of a pair's clusters, but many of its strongest) cannot
# make the null's tail heavier than its noise clusters show
TAIL_SHARE = 0.25
TAIL_MIN = 20
CENSOR_SHARE = 0.4
# clusters the null expects fewer than this many of (or false_alarm_rate, if lower) are taken
# out of the null sample before it is fitted again: the changes must not inflate their own
# null, but at a high rate, taking out what the null itself predicts would thin its tail
# round after round
PEEL_EXPECTED = 0.1


@dataclass
class NullTail:
    """Expected number of the pair's null (no-change) clusters at least as strong as a value:
    of all of them (:meth:`count`), and of those that would be reported (:meth:`expected`).

    Below ``v`` the count of null clusters is used as is; above it, ``k`` null clusters'
    excesses follow an exponential tail of scale ``sigma``. The count of reportable ones
    (those that pass the checks a region must pass to be reported, ``reportable`` in the
    order of ``stats``) is that count times their share among the null clusters at least as
    strong (:func:`reportable_share`).
    """

    stats: np.ndarray  # sorted strengths of the null clusters (ascending)
    v: float
    k: int
    sigma: float
    reportable: np.ndarray | None = None  # (len(stats),) bool, None: every cluster counts

    def count(self, t: np.ndarray | float) -> np.ndarray:
        """Expected number of null clusters at least as strong as ``t``, reportable or not."""
        t = np.asarray(t, np.float64)
        n_above = len(self.stats) - np.searchsorted(self.stats, t, side="left")
        tail = self.k * np.exp(-np.maximum(t - self.v, 0.0) / self.sigma)
        return np.where(t > self.v, tail, n_above.astype(np.float64))

    def share(self, t: np.ndarray | float) -> np.ndarray:
        """The reportable share of the null clusters at least as strong as ``t`` (see
        :func:`reportable_share`)."""
        t = np.asarray(t, np.float64)
        if self.reportable is None:
            return np.ones_like(t)
        return reportable_share(self.stats, self.reportable, t)

    def expected(self, t: np.ndarray | float) -> np.ndarray:
        """Expected number of null clusters at least as strong as ``t`` that would be
        reported: their count times their reportable share."""
        return self.count(t) * self.share(t)

    def level(self, rate: float, reported: bool = True) -> float:
        """The strength beyond the null clusters at which ``rate`` of them are expected (at or
        above): of those that would be reported, or (``reported`` False) of all."""
        if self.k <= 0:
            return float(self.stats[-1]) if len(self.stats) else 0.0
        q = float(self.share(np.inf)) if reported else 1.0
        return self.v - self.sigma * math.log(min(rate / (self.k * q), 1.0))


def reportable_share(stats: np.ndarray, reportable: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Share of the null clusters (``stats`` ascending, ``reportable`` in that order) at least
    as strong as ``t`` that are reportable, as Jeffreys' estimate of a binomial share (half a
    cluster more of one more: none of n is about one in 2n + 2, and beyond the strongest null
    cluster, where nothing was seen, one half).

    Local, not pooled over the tail: reportable noise is not spread evenly over strength (on
    a mottled wall, or a pale one with colour residue, the strongest noise clusters are the
    patches that would be reported), and a pooled share would thin the strongest ones'
    count by the weak ones' share."""
    n = len(stats)
    start = np.searchsorted(stats, t, side="left")
    after = np.concatenate([np.cumsum(reportable[::-1])[::-1], [0]])
    return (after[start] + 0.5) / (n - start + 1.0)


def _censored_scale(excess: np.ndarray) -> tuple[float, int]:
    """Total excess (the strongest CENSOR_SHARE counted at the censoring point) and the
    uncensored count of a sorted (ascending) sample of exponential excesses."""
    k = len(excess)
    n_cens = int(CENSOR_SHARE * k)
    c = float(excess[k - n_cens - 1]) if n_cens and k > n_cens else 0.0
    return float(excess[:k - n_cens].sum()) + n_cens * c, k - n_cens


def _fit_tail(null: np.ndarray, reportable: np.ndarray | None = None) -> NullTail:
    """Exponential tail of the null sample ``null`` (peaks over threshold; each cluster's
    ``reportable`` kept in its order): the strongest ``TAIL_SHARE`` (at least ``TAIL_MIN``),
    their scale the maximum likelihood with the strongest ``CENSOR_SHARE`` right-censored."""
    order = np.argsort(null, kind="stable")
    null = np.asarray(null, np.float64)[order]
    rep = None if reportable is None else np.asarray(reportable, bool)[order]
    n = len(null)
    k = min(n, max(TAIL_MIN, round(TAIL_SHARE * n)))
    v = float(null[n - k - 1]) if k < n else 0.0
    excess = np.maximum(null[n - k:] - v, 0.0)
    total, m = _censored_scale(excess)
    sigma = max(total / max(m, 1), 1e-12)
    return NullTail(null, v, k, sigma, rep)


def fit_null(stats: np.ndarray, rate: float, iterations: int = 10,
             reportable: np.ndarray | None = None,
             ) -> tuple[list[NullTail], np.ndarray, np.ndarray]:
    """The null tails of the clusters' statistics ``stats`` (n, m) and the clusters above.

    Most candidate clusters of a pair are noise (registration residue, photometric residue,
    painting noise): their statistics are the pair's null sample. A cluster's expected null
    count is ``m`` × the least over its statistics of the expected number of null clusters
    at least as strong in that statistic (Bonferroni over the m statistics: at most ``rate``
    null clusters are flagged in all). Clusters whose expected null count is at most
    ``min(rate, PEEL_EXPECTED)`` are taken out of the sample and the tails fitted again
    (until nothing changes), so the changes themselves do not inflate their own null.
    Returns the tails, each cluster's expected null count and whether it is a change
    (expected count at most ``rate``).
    """
    stats = np.asarray(stats, np.float64).reshape(len(stats), -1)
    n_all, m = stats.shape
    rep = np.ones(n_all, bool) if reportable is None else np.asarray(reportable, bool)
    peel = min(rate, PEEL_EXPECTED)
    flagged = np.zeros(n_all, bool)
    tails: list[NullTail] = []
    expected = np.full(n_all, np.inf)
    for _ in range(iterations):
        null = ~flagged
        if int(null.sum()) < 3:  # no null to speak of: nothing is unlikely under it
            log.warning("changes: only %d candidate cluster(s) of noise: no null fitted, no "
                        "change reported", int(null.sum()))
            empty = NullTail(np.zeros(0), 0.0, 0, 1.0)
            return [empty] * m, np.full(n_all, np.inf), np.zeros(n_all, bool)
        tails = [_fit_tail(stats[null, j], None if reportable is None else reportable[null])
                 for j in range(m)]
        expected = m * np.min([t.expected(stats[:, j]) for j, t in enumerate(tails)], axis=0)
        # a cluster that would not be reported as it is may still be one change with others
        # (pieces joined) or be one after cleaning: it is a candidate change by the count of
        # all null clusters at least as strong, as if every one of them were reported
        count = m * np.min([t.count(stats[:, j]) for j, t in enumerate(tails)], axis=0)
        decision = np.where(rep, expected, count)
        # taken out of the null only when unlikely among all its clusters: among the
        # reportable ones alone the strongest reportable noise would take itself out
        new = count <= peel
        if np.array_equal(new, flagged):
            break
        flagged = new
    return tails, expected, decision <= rate


@dataclass
class Candidates:
    """The pair's candidate clusters, their statistics and the null fitted to them."""

    labels: np.ndarray  # (H, W) int32, 0 = none
    level: float  # candidate level of the significance (median + CANDIDATE_MADS · MAD)
    stats: np.ndarray  # (n, 2) peak and root excess mass of each cluster (label i + 1)
    tails: list[NullTail]  # the null tail of each statistic
    expected: np.ndarray  # (n,) expected number of null clusters at least as strong
    flagged: np.ndarray  # (n,) bool: expected null count at most the false-alarm rate
    info: dict[str, Any]
    reportable: np.ndarray | None = None  # (n,) bool: would pass the checks as it is

    def statistics(self, sig: np.ndarray, area: np.ndarray) -> np.ndarray:
        """Peak and root of the excess mass of a set of pixels (their significance and wall
        areas)."""
        return np.array([float(sig.max()) if len(sig) else 0.0,
                         math.sqrt(float((np.maximum(sig - self.level, 0.0) * area).sum()))])

    def expected_false(self, stats: np.ndarray, reported: bool = True) -> float:
        """Expected number of the pair's null clusters at least as strong as ``stats`` that
        would be reported (``reported`` False: reported or not)."""
        return float(len(self.tails) * min(float(t.expected(x) if reported else t.count(x))
                                           for t, x in zip(self.tails, stats, strict=True)))

    def score(self, stats: np.ndarray, rate: float) -> float:
        """How far ``stats`` exceed the levels at which ``rate`` null clusters are expected
        (largest ratio over the statistics; > 1 for a change)."""
        m = len(self.tails)
        return max(float(x) / max(t.level(rate / m), 1e-12)
                   for t, x in zip(self.tails, stats, strict=True))


def candidates(sig: np.ndarray, joint: np.ndarray, area: np.ndarray, rate: float,
               reportable: Callable[[np.ndarray, int], np.ndarray] | None = None,
               ) -> Candidates:
    """Candidate clusters of the significance, scored against the pair's own null.

    Two statistics per cluster: its peak significance (a strong change, however small) and
    its excess mass above the candidate level on the wall, ``sum (s - level) · area`` (noise
    units × mm²: a faint but large change, a flat low-contrast patch, whose peak the noise
    matches).
    """
    # quantiles of the wall, not of the atlas's pixels (they crowd towards the poles)
    s, wa = sig[joint], area[joint]
    med = weighted_median(s, wa)
    mad = 1.4826 * weighted_median(np.abs(s - med), wa)
    level = med + CANDIDATE_MADS * mad
    lab, n = label_wrapped(joint & (sig > level))
    flat = lab.ravel()
    mass = np.bincount(flat, weights=(np.maximum(sig - level, 0) * area).ravel(),
                       minlength=n + 1)[1:]
    peak = np.zeros(n + 1)
    np.maximum.at(peak, flat, sig.ravel())
    stats = np.stack([peak[1:], np.sqrt(mass)], axis=1)
    rep = np.ones(n, bool) if reportable is None else np.asarray(reportable(lab, n), bool)
    tails, expected, flagged = fit_null(stats, rate, reportable=rep)
    info: dict[str, Any] = {
        "median": med, "mad_sigma": mad, "candidate_level": level, "candidates": n,
        "reportable": int(rep.sum()), "flagged": int(flagged.sum()), "false_alarm_rate": rate,
        "null_clusters": len(tails[0].stats),
        "null_tails": {name: {"from": t.v, "clusters": t.k, "scale": t.sigma,
                              "level_at_rate": t.level(rate / len(tails)),
                              "level_at_rate_any": t.level(rate / len(tails), reported=False),
                              "reportable_share": float(t.share(np.inf))}
                       for name, t in zip(("peak", "root_mass"), tails, strict=True)}}
    return Candidates(lab, level, stats, tails, expected, flagged, info, rep)


def split_at_saddles(sig: np.ndarray, mask: np.ndarray, area: np.ndarray, null: Candidates,
                     rate: float) -> tuple[np.ndarray, int]:
    """Labels (joined across the azimuth seam and the poles) of ``mask`` split into separate
    changes.

    A connected cluster can hold several changes linked by a ridge of noise (two neighbouring
    lesions, one lesion and the registration residue of a vessel beside it). Its basins of
    significance (watershed from its maxima) are merged in the order of the saddles between
    them, highest first (the component tree of the significance), unless the two groups
    they would join are separate changes by the pair's own null: each group is a change
    above the saddle, its peak overshoot and excess mass *above the saddle* as unlikely as a
    change's above the candidate level (expected null count at most ``rate``), and the
    saddle itself is no change (its height alone would not be flagged at ``rate``: the ridge
    between them is the wall's noise, not a crevice inside one lesion).
    """
    from scipy.ndimage import label as nd_label
    from scipy.ndimage import maximum_filter
    from skimage.segmentation import watershed

    h, w = mask.shape
    s = np.where(mask, sig, 0.0).astype(np.float64)
    m = mask
    a = area

    peaks = m & (s >= maximum_filter(s, size=3, mode="nearest"))
    markers, n_markers = nd_label(peaks, structure=np.ones((3, 3)))
    if n_markers == 0:
        lab, n = label_wrapped(mask)
        return lab, n
    ws = watershed(-s, markers, mask=m, connectivity=2)
    # a basin's pixels that the seam-joined labelling would also join stay one cluster: the
    # watershed does not wrap, so the seam's neighbours are linked below as saddles
    # saddles: for each pair of touching basins, the highest of min(s_p, s_q) over their
    # touching pixel pairs
    pa, pb, pv = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r0, r1 = (0, h - dr)
        c0, c1 = (max(0, -dc), w - max(0, dc))
        la = ws[r0:r1, c0:c1]
        lb = ws[r0 + dr:r1 + dr, c0 + dc:c1 + dc]
        ok = (la > 0) & (lb > 0) & (la != lb)
        if ok.any():
            va = s[r0:r1, c0:c1][ok]
            vb = s[r0 + dr:r1 + dr, c0 + dc:c1 + dc][ok]
            x, y = la[ok], lb[ok]
            pa.append(np.minimum(x, y))
            pb.append(np.maximum(x, y))
            pv.append(np.minimum(va, vb))
    for dr in (-1, 0, 1):  # across the azimuth seam (last column to the first)
        r0, r1 = max(0, -dr), h - max(0, dr)
        la, lb = ws[r0:r1, -1], ws[r0 + dr:r1 + dr, 0]
        ok = (la > 0) & (lb > 0) & (la != lb)
        if ok.any():
            x, y = la[ok], lb[ok]
            pa.append(np.minimum(x, y))
            pb.append(np.maximum(x, y))
            pv.append(np.minimum(s[r0:r1, -1][ok], s[r0 + dr:r1 + dr, 0][ok]))
    for row in (0, h - 1):  # across the poles (a pole row's column to the opposite azimuth)
        for ca, cb in pole_neighbours(w):
            la, lb = ws[row, ca], ws[row, cb]
            ok = (la > 0) & (lb > 0) & (la != lb)
            if ok.any():
                x, y = la[ok], lb[ok]
                pa.append(np.minimum(x, y))
                pb.append(np.maximum(x, y))
                pv.append(np.minimum(s[row, ca][ok], s[row, cb][ok]))
    parent = np.arange(n_markers + 1)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    if pa:
        ea, eb, ev = np.concatenate(pa), np.concatenate(pb), np.concatenate(pv)
        order = np.lexsort((-ev, eb, ea))
        ea, eb, ev = ea[order], eb[order], ev[order]
        first = np.ones(len(ea), bool)
        first[1:] = (ea[1:] != ea[:-1]) | (eb[1:] != eb[:-1])
        ea, eb, ev = ea[first], eb[first], ev[first]  # highest saddle per pair
        flat = ws.ravel()
        idx = np.argsort(flat, kind="stable")
        bounds = np.searchsorted(flat[idx], np.arange(n_markers + 2))
        members: dict[int, np.ndarray] = {
            i: idx[bounds[i]:bounds[i + 1]] for i in range(1, n_markers + 1)}
        sflat, aflat = s.ravel(), a.ravel()
        # what the pair's noise clusters reach in height at the rate, reportable or not
        ridge_level = (null.tails[0].level(rate / len(null.tails), reported=False)
                       if null.tails else math.inf)

        def separate(pix: np.ndarray, saddle: float) -> bool:
            v = sflat[pix]
            above = v > saddle
            stats = np.array([null.level + float(v.max()) - saddle,
                              math.sqrt(float(((v[above] - saddle) * aflat[pix][above]).sum()))])
            # as strong as the noise's clusters reach, reportable or not: a piece is not
            # measured, so not known to pass the checks
            return null.expected_false(stats, reported=False) <= rate

        for i in np.argsort(-ev, kind="stable"):
            gi, gj = find(int(ea[i])), find(int(eb[i]))
            if gi == gj:
                continue
            sd = float(ev[i])
            if sd < ridge_level and separate(members[gi], sd) and separate(members[gj], sd):
                continue
            parent[max(gi, gj)] = min(gi, gj)
            members[min(gi, gj)] = np.concatenate([members[gi], members[gj]])
            members.pop(max(gi, gj))
    roots = np.array([find(i) for i in range(n_markers + 1)])
    _, new = np.unique(roots, return_inverse=True)
    lab = new[ws].astype(np.int32)
    lab[~mask] = 0
    return lab, int(lab.max())


def changed_mask(sig: np.ndarray, joint: np.ndarray, area: np.ndarray, rate: float,
                 ) -> np.ndarray:
    """Pixels of the clusters flagged as changes at ``rate`` (illumination's second pass; every
    null cluster counted: the checks need the matched colours this pass computes)."""
    c = candidates(sig, joint, area, rate)
    return np.isin(c.labels, np.nonzero(c.flagged)[0] + 1)
