"""Co-registration of two sessions' 3-D points: descriptor matches, MSAC, thin-plate spline.

1. Putative matches: mutual nearest neighbours of the mean point descriptors (Euclidean
   distance of unit RootSIFT vectors) that also pass Lowe's ratio test both ways.
2. A robust similarity (or rigid) transform A → B by MSAC (truncated quadratic cost, inlier
   distance ``inlier_mm``, seeded sampling of 3 matches, Umeyama fit, refit on the inliers).
3. The non-rigid part: a regularised 3-D thin-plate spline (scipy ``RBFInterpolator``,
   ``thin_plate_spline`` kernel, degree-1 polynomial) on the residual displacement of the
   inliers, its smoothing chosen by k-fold cross-validation. Matches whose position the
   spline predicts within ``inlier_mm`` join the inliers and the spline is refitted (a few
   rounds): under deformation the rigid model keeps only the least deformed part of the wall.

Both directions are fitted on the same inliers: B → A (to pull session A's texture into
session B's atlas) and A → B (to carry landmarks marked in session A into session B).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cystomap.geometry.sim3 import Similarity, umeyama

log = logging.getLogger(__name__)

SMOOTHING_GRID = (0.0, 0.1, 1.0, 10.0, 100.0, 1e3, 1e4)
CV_FOLDS = 5
CV_MAX_POINTS = 400  # cross-validation on a spread subsample (cost grows as n³)


# --------------------------------------------------------------------------- matching


def mutual_matches(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float,
                   block: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i in A, j in B) of mutual nearest neighbours passing the ratio test both ways.

    Descriptors are unit vectors; distances are Euclidean.
    """
    na, nb = len(desc_a), len(desc_b)
    if na < 2 or nb < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    a = desc_a.astype(np.float32)
    b = desc_b.astype(np.float32)
    best_ab = np.empty(na, np.int64)
    d1_ab = np.empty(na)
    d2_ab = np.empty(na)
    # per B point: the two smallest distances so far and the A index of the smallest
    col_d = np.full((2, nb), np.inf)
    col_i = np.full(nb, -1, np.int64)
    for s in range(0, na, block):
        d = np.sqrt(np.maximum(2.0 - 2.0 * (a[s:s + block] @ b.T), 0.0))
        rows, cols = np.arange(len(d)), np.arange(nb)
        # the two smallest per row and per column: argmin, then the minimum without it
        best = d.argmin(axis=1)
        first = d[rows, best]
        d[rows, best] = np.inf
        best_ab[s:s + block] = best
        d1_ab[s:s + block] = first
        d2_ab[s:s + block] = d.min(axis=1)
        d[rows, best] = first
        best = d.argmin(axis=0)
        first = d[best, cols]
        d[best, cols] = np.inf
        second = d.min(axis=0) if len(d) > 1 else np.full(nb, np.inf)
        new_best = first < col_d[0]
        second = np.where(new_best, np.minimum(col_d[0], second),
                          np.minimum(col_d[1], first))
        col_i = np.where(new_best, best + s, col_i)
        col_d = np.vstack([np.minimum(col_d[0], first), second])
    i = np.arange(na)
    j = best_ab
    ok = (col_i[j] == i) & (d1_ab < ratio * d2_ab) & (col_d[0, j] < ratio * col_d[1, j])
    return i[ok], j[ok]


@dataclass(frozen=True)
class MsacResult:
    transform: Similarity
    inliers: np.ndarray  # bool (n,)
    cost: float
    iterations: int


def msac(src: np.ndarray, dst: np.ndarray, threshold: float, iterations: int, seed: int,
         with_scale: bool = True) -> MsacResult | None:
    """MSAC similarity src → dst: minimal samples of 3, truncated quadratic cost."""
    n = len(src)
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    t2 = threshold ** 2
    best: tuple[float, Similarity] | None = None
    extent = float(np.linalg.norm(src.max(0) - src.min(0))) or 1.0
    for _ in range(iterations):
        idx = rng.choice(n, 3, replace=False)
        s = src[idx]
        # skip near-collinear samples (ill-conditioned rotation)
        area = np.linalg.norm(np.cross(s[1] - s[0], s[2] - s[0]))
        if area < 1e-3 * extent ** 2:
            continue
        tr = umeyama(s, dst[idx], with_scale)
        if tr is None:
            continue
        r2 = ((tr.apply(src) - dst) ** 2).sum(1)
        cost = float(np.minimum(r2, t2).sum())
        if best is None or cost < best[0]:
            best = (cost, tr)
    if best is None:
        return None
    tr = best[1]
    inl = ((tr.apply(src) - dst) ** 2).sum(1) < t2
    for _ in range(5):  # local optimisation: refit on the inliers until stable
        if inl.sum() < 3:
            break
        ref = umeyama(src[inl], dst[inl], with_scale)
        if ref is None:
            break
        new = ((ref.apply(src) - dst) ** 2).sum(1) < t2
        if new.sum() < inl.sum():
            break
        tr = ref
        if np.array_equal(new, inl):
            break
        inl = new
    cost = float(np.minimum(((tr.apply(src) - dst) ** 2).sum(1), t2).sum())
    return MsacResult(tr, inl, cost, iterations)


# --------------------------------------------------------------------------- spline


def farthest_points(x: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """Indices of ``k`` points spread over ``x`` (greedy farthest-point sampling)."""
    n = len(x)
    if n <= k:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    chosen = [int(rng.integers(n))]
    d = np.linalg.norm(x - x[chosen[0]], axis=1)
    for _ in range(k - 1):
        i = int(d.argmax())
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(x - x[i], axis=1))
    return np.asarray(chosen)


class Warp:
    """p ↦ similarity(p) + thin-plate spline(p) (spline optional)."""

    def __init__(self, transform: Similarity, centres: np.ndarray | None = None,
                 displacement: np.ndarray | None = None, smoothing: float = 0.0) -> None:
        self.transform = transform
        self.smoothing = smoothing
        self.spline = None
        self.n_centres = 0
        if centres is not None and displacement is not None and len(centres) >= 5:
            from scipy.interpolate import RBFInterpolator

            self.spline = RBFInterpolator(centres, displacement, kernel="thin_plate_spline",
                                          smoothing=smoothing, degree=1)
            self.n_centres = len(centres)

    def __call__(self, p: np.ndarray, block: int = 65536) -> np.ndarray:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        out = self.transform.apply(p)
        if self.spline is not None:
            for s in range(0, len(p), block):
                out[s:s + block] += self.spline(p[s:s + block])
        return out


def _cv_error(x: np.ndarray, d: np.ndarray, smoothing: float, folds: np.ndarray) -> np.ndarray:
    """Held-out residual (n,) of the displacement spline with ``smoothing``."""
    from scipy.interpolate import RBFInterpolator

    err = np.zeros(len(x))
    for f in np.unique(folds):
        test = folds == f
        train = ~test
        if train.sum() < 5:
            err[test] = np.linalg.norm(d[test], axis=1)
            continue
        try:
            sp = RBFInterpolator(x[train], d[train], kernel="thin_plate_spline",
                                 smoothing=smoothing, degree=1)
            err[test] = np.linalg.norm(sp(x[test]) - d[test], axis=1)
        except (np.linalg.LinAlgError, ValueError):
            err[test] = np.inf
    return err


def choose_smoothing(x: np.ndarray, d: np.ndarray, seed: int) -> tuple[float, dict[str, float]]:
    """The smoothing of :data:`SMOOTHING_GRID` with the least k-fold held-out RMS residual.

    The smallest smoothing within 2 % of the best error wins ties (least bias).
    """
    rng = np.random.default_rng(seed)
    if len(x) > CV_MAX_POINTS:
        sub = farthest_points(x, CV_MAX_POINTS, seed)
        x, d = x[sub], d[sub]
    folds = rng.permutation(len(x)) % CV_FOLDS
    scores: dict[str, float] = {}
    for s in SMOOTHING_GRID:
        e = _cv_error(x, d, s, folds)
        scores[f"{s:g}"] = float(np.sqrt(np.mean(e ** 2))) if np.isfinite(e).all() else math.inf
    best = min(scores.values())
    for s in SMOOTHING_GRID:
        if scores[f"{s:g}"] <= best * 1.02:
            return float(s), scores
    return float(SMOOTHING_GRID[-1]), scores


def fit_warp(src: np.ndarray, dst: np.ndarray, transform: Similarity, smoothing: float,
             max_points: int, seed: int) -> tuple[Warp, dict[str, Any]]:
    """Similarity + thin-plate spline on the residual displacement src → dst."""
    info: dict[str, Any] = {}
    if len(src) < 10:
        return Warp(transform), {"spline": False, "reason": "fewer than 10 inliers"}
    sel = farthest_points(src, max_points, seed)
    x, d = src[sel], dst[sel] - transform.apply(src[sel])
    if smoothing < 0:
        smoothing, scores = choose_smoothing(x, d, seed)
        info["cv_rms_mm_by_smoothing"] = scores
        info["cv_rms_mm"] = scores[f"{smoothing:g}"]
        rigid = float(np.sqrt(np.mean((d ** 2).sum(1))))
        info["rigid_rms_mm"] = rigid
        if scores[f"{smoothing:g}"] >= rigid:  # the spline does not predict better: none
            return Warp(transform), {**info, "spline": False,
                                     "reason": "cross-validation: no spline beats the "
                                               "similarity"}
    info.update(spline=True, smoothing=smoothing, centres=len(sel))
    return Warp(transform, x, d, smoothing), info


# --------------------------------------------------------------------------- all together


@dataclass
class Registration:
    registered: bool
    reason: str
    n_points_a: int
    n_points_b: int
    matches: np.ndarray  # (m, 2) indices into A's and B's points
    inliers: np.ndarray  # bool (m,)
    transform: Similarity | None = None  # A → B
    warp_ab: Warp | None = None
    warp_ba: Warp | None = None
    info: dict[str, Any] = field(default_factory=dict)
    a_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # A's points
    b_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # B's points

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "registered": self.registered,
            "reason": self.reason,
            "points": {"a": self.n_points_a, "b": self.n_points_b},
            "matches": len(self.matches),
            "inliers": int(self.inliers.sum()) if len(self.inliers) else 0,
            "inlier_ratio": float(self.inliers.mean()) if len(self.inliers) else 0.0,
        }
        if self.transform is not None:
            out["transform_a_to_b"] = self.transform.to_json()
        out.update(self.info)
        return out


def _residual_stats(r: np.ndarray) -> dict[str, float]:
    if len(r) == 0:
        return {}
    return {"rms": float(np.sqrt(np.mean(r ** 2))), "median": float(np.median(r)),
            "p90": float(np.percentile(r, 90)), "max": float(r.max())}


def register(xyz_a: np.ndarray, desc_a: np.ndarray, xyz_b: np.ndarray, desc_b: np.ndarray,
             cfg: Any) -> Registration:
    """Match, MSAC and spline; ``registered`` False (with the reason) when too few inliers."""
    ia, ib = mutual_matches(desc_a, desc_b, cfg.ratio)
    matches = np.column_stack([ia, ib]) if len(ia) else np.zeros((0, 2), np.int64)
    m = len(matches)
    log.info("registration: %d mutual matches (ratio %.2f) between %d and %d points", m,
             cfg.ratio, len(xyz_a), len(xyz_b))
    fail = Registration(False, "", len(xyz_a), len(xyz_b), matches, np.zeros(m, bool),
                        a_points=xyz_a, b_points=xyz_b)
    need = max(cfg.min_inliers, 3)
    if m < need:
        fail.reason = (f"only {m} descriptor matches between the sessions' 3-D points "
                       f"(need at least {need} inliers)")
        return fail
    src, dst = xyz_a[ia], xyz_b[ib]
    res = msac(src, dst, cfg.inlier_mm, cfg.msac_iterations, cfg.seed,
               cfg.transform == "similarity")
    if res is None:
        fail.reason = f"no non-degenerate transform among {m} matches"
        return fail
    inl = res.inliers
    n_rigid = int(inl.sum())
    fail.inliers = inl
    fail.transform = res.transform
    log.info("registration: MSAC %s: %d of %d matches are inliers within %.1f mm (scale %.3f)",
             cfg.transform, n_rigid, m, cfg.inlier_mm, res.transform.scale)
    ratio = n_rigid / m
    if n_rigid < cfg.min_inliers or ratio < cfg.min_inlier_ratio:
        fail.reason = (f"only {n_rigid} of {m} descriptor matches ({100 * ratio:.0f}%) agree on "
                       f"one {cfg.transform} transform within {cfg.inlier_mm:g} mm (need "
                       f"{cfg.min_inliers} and {100 * cfg.min_inlier_ratio:.0f}%): the sessions "
                       f"could not be co-registered")
        return fail
    transform = res.transform
    r_sim = np.linalg.norm(transform.apply(src) - dst, axis=1)
    # non-rigid: spline on the inliers; matches the spline predicts well join in
    warp_ab, sinfo = fit_warp(src[inl], dst[inl], transform, cfg.spline_smoothing,
                              cfg.spline_max_points, cfg.seed)
    rounds = 0
    for _ in range(cfg.spline_rounds):
        if warp_ab.spline is None:
            break
        r = np.linalg.norm(warp_ab(src) - dst, axis=1)
        new = r < cfg.inlier_mm
        if new.sum() <= inl.sum() and np.array_equal(new | inl, inl):
            break
        inl = new
        rounds += 1
        refit = umeyama(src[inl], dst[inl], cfg.transform == "similarity")
        if refit is not None:
            transform = refit
        warp_ab, sinfo = fit_warp(src[inl], dst[inl], transform, cfg.spline_smoothing,
                                  cfg.spline_max_points, cfg.seed)
    inv = transform.inverse()
    warp_ba, sinfo_ba = fit_warp(dst[inl], src[inl], inv,
                                 sinfo.get("smoothing", cfg.spline_smoothing)
                                 if sinfo.get("spline") else -1.0,
                                 cfg.spline_max_points, cfg.seed)
    r_before = np.linalg.norm(transform.apply(src[inl]) - dst[inl], axis=1)
    r_after = np.linalg.norm(warp_ab(src[inl]) - dst[inl], axis=1)
    r_back = np.linalg.norm(warp_ba(dst[inl]) - src[inl], axis=1)
    info = {
        "transform_kind": cfg.transform,
        "inlier_mm": cfg.inlier_mm,
        "msac": {"iterations": res.iterations, "seed": cfg.seed, "inliers": n_rigid,
                 "residual_mm": _residual_stats(r_sim[res.inliers])},
        "spline_rounds": rounds,
        "spline": sinfo,
        "spline_b_to_a": {k: v for k, v in sinfo_ba.items() if k != "cv_rms_mm_by_smoothing"},
        "residual_mm": {
            "before_spline": _residual_stats(r_before),
            "after_spline": _residual_stats(r_after),
            "after_spline_b_to_a": _residual_stats(r_back),
            "held_out_after_spline_rms": sinfo.get("cv_rms_mm"),
            "note": "inlier matches; before = after the similarity only; after = similarity + "
                    "thin-plate spline (in-sample); held-out = k-fold cross-validated",
        },
    }
    log.info("registration: %d inliers after %d spline round(s); residual RMS %.2f mm → %.2f mm "
             "(held out %s)", int(inl.sum()), rounds, info["residual_mm"]["before_spline"]["rms"],
             info["residual_mm"]["after_spline"]["rms"],
             f"{sinfo['cv_rms_mm']:.2f} mm" if "cv_rms_mm" in sinfo else "n/a")
    return Registration(True, "", len(xyz_a), len(xyz_b), matches, inl, transform, warp_ab,
                        warp_ba, info, xyz_a, xyz_b)
