"""Which frames the ``frames`` stage keeps (:mod:`cystomap.frames`): exposure and blur
verdicts against each segment's own sharpness, then greedy selection by motion."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from cystomap.frame_scoring import _Probe, _Scores

if TYPE_CHECKING:
    from cystomap.frames import FramesConfig

# lookahead never lets the motion since the last kept frame exceed this times min_motion
_LOOKAHEAD_MAX_REL = 2.0


@dataclass
class _Selection:
    kept: list[int]
    reason: list[str]
    motion_px: np.ndarray
    sharp_median: float
    base_threshold_px: float
    threshold_px: float


def _select(s: _Scores, cfg: FramesConfig, probe: _Probe) -> _Selection:
    n = len(s.time_s)
    reason = np.array([""] * n, dtype=object)
    if cfg.start_s > 0 or cfg.end_s > 0:
        outside = s.time_s < cfg.start_s - 1e-9
        if cfg.end_s > 0:
            outside |= s.time_s >= cfg.end_s - 1e-9
        reason[outside] = "outside_range"
    reason[(reason == "") & (s.dark > cfg.max_dark)] = "dark"
    reason[(reason == "") & (s.saturated > cfg.max_saturated)] = "overexposed"

    exposed = np.flatnonzero(reason == "")
    sharp_median = float(np.median(s.sharpness[exposed])) if len(exposed) else 0.0
    if len(exposed):
        fps = probe.fps
        if fps <= 0 and n > 1 and s.time_s[-1] > s.time_s[0]:
            fps = (n - 1) / (s.time_s[-1] - s.time_s[0])
        half = max(1, round(cfg.blur_window_s * (fps if fps > 0 else 25.0)))
        reason[exposed[_blurred(s, exposed, half, cfg)]] = "blurred"
    # usable but nothing to track in it (no corners: featureless, fogged)
    reason[(reason == "") & (s.segment < 0)] = "untracked"

    eligible = np.flatnonzero(reason == "")
    inv = np.full_like(s.transform, np.nan)
    tracked = s.segment >= 0
    if tracked.any():
        inv[tracked] = np.linalg.inv(s.transform[tracked])
    grid_h = np.column_stack([probe.grid, np.ones(len(probe.grid))]).T  # 3 x N
    full_scale = probe.width / probe.aw

    def motion(k: int, i: int) -> float:
        """Median displacement (full-res px) of FOV points from frame k to frame i."""
        if s.segment[k] < 0 or s.segment[k] != s.segment[i]:
            return math.inf
        moved = (s.transform[i] @ inv[k]) @ grid_h
        return float(np.median(np.hypot(moved[0] - grid_h[0], moved[1] - grid_h[1]))) * full_scale

    def greedy(thr: float) -> list[int]:
        kept: list[int] = []
        last = -1
        p = 0
        while p < len(eligible):
            i = int(eligible[p])
            moved = motion(last, i) if last >= 0 else math.inf
            if last >= 0 and (i - last < cfg.min_gap or moved < thr):
                p += 1
                continue
            bound = _LOOKAHEAD_MAX_REL * thr
            if thr > 0 and moved > bound and p > 0:
                # a jump (frames in between dropped, fast motion, a tracking break): keep the
                # last frame before it as well when that splits the gap (both parts clearly
                # shorter) or, across a break, when it moved on from the last kept frame
                prev = int(eligible[p - 1])
                before = motion(last, prev)
                splits = (max(before, motion(prev, i)) <= 0.8 * moved if math.isfinite(moved)
                          else 0.5 * thr <= before < math.inf)
                if splits and prev > last and prev - last >= cfg.min_gap \
                        and i - prev >= cfg.min_gap:
                    kept.append(prev)
                    last = prev
                    continue
            # a sharper frame a little later may replace i, as long as the gap from the last
            # kept frame stays within _LOOKAHEAD_MAX_REL times the threshold
            best, best_p, q = i, p, p + 1
            while thr > 0 and moved <= bound and q < len(eligible) \
                    and eligible[q] <= i + cfg.lookahead:
                j = int(eligible[q])
                if (s.segment[j] == s.segment[i] and s.quality[j] > s.quality[best]
                        and thr <= motion(last, j) <= bound):
                    best, best_p = j, q
                q += 1
            kept.append(best)
            last, p = best, best_p + 1
        # the video's last frame shows the end of the sweep, wall no later frame will show:
        # kept when it moved on from the last kept frame (as across a break, above)
        if thr > 0 and kept and len(eligible):
            end = int(eligible[-1])
            if end - kept[-1] >= cfg.min_gap and 0.5 * thr <= motion(kept[-1], end) < math.inf:
                kept.append(end)
        return kept

    # the spacing scales with the lit field of view, not the frame (black borders, a round
    # scope image in a wide frame)
    diagonal = probe.fov_diagonal or math.hypot(probe.width, probe.height)
    base_thr = cfg.min_motion * diagonal
    base = greedy(base_thr)
    kept, thr = base, base_thr
    if cfg.max_frames and len(base) > cfg.max_frames:
        hi = 4.0 * diagonal
        kept_hi = greedy(hi)
        if len(kept_hi) > cfg.max_frames:  # more tracking segments than allowed frames
            kept, thr = _thin(kept_hi, cfg.max_frames), hi
        else:
            lo = max(base_thr, 1e-3)
            kept, thr = kept_hi, hi
            for _ in range(30):
                mid = math.sqrt(lo * hi)
                trial = greedy(mid)
                if len(trial) > cfg.max_frames:
                    lo = mid
                else:
                    kept, thr, hi = trial, mid, mid
                if hi / lo < 1.005:
                    break
    kept_set = set(kept)
    base_set = set(base)
    motion_px = np.full(n, np.nan)
    last = -1
    for i in range(n):
        if last >= 0:
            m = motion(last, i)
            motion_px[i] = m if math.isfinite(m) else np.nan
        if reason[i] == "":
            if i in kept_set:
                reason[i] = "kept"
            else:
                reason[i] = "over_limit" if i in base_set else "redundant"
        if i in kept_set:
            last = i
    return _Selection(sorted(kept), [str(r) for r in reason], motion_px, sharp_median,
                      base_thr, thr)


def _blurred(s: _Scores, exposed: np.ndarray, half: int, cfg: FramesConfig) -> np.ndarray:
    """Which of the well-exposed frames ``exposed`` are blurred (bool per entry).

    A frame compared with overlapping frames of its segment, two or more of them within
    ±``half`` frames, is judged on its content-matched ``quality``: below ``blur_rel`` times
    the ``blur_percentile`` of theirs, or below ``blur_global_rel`` times that of the whole
    segment (long blurred stretches). Any other frame (tracking failed before and after it) is
    judged on its raw sharpness against the two exposed frames on each side outside its segment
    and not blurred themselves (``blur_unmatched_rel``).
    """
    seg, quality, sharp = s.segment[exposed], s.quality[exposed], s.sharpness[exposed]
    matched = s.matched[exposed]
    seg_ref = {int(g): float(np.percentile(quality[(seg == g) & matched], cfg.blur_percentile))
               for g in np.unique(seg[matched])}
    lo = np.searchsorted(exposed, exposed - half, side="left")
    hi = np.searchsorted(exposed, exposed + half, side="right")
    out = np.zeros(len(exposed), bool)
    unmatched = []
    for k in range(len(exposed)):
        g = int(seg[k])
        if matched[k]:
            window = slice(lo[k], hi[k])
            same = quality[window][(seg[window] == g) & matched[window]]
            if len(same) >= 3:
                local = float(np.percentile(same, cfg.blur_percentile))
                out[k] = bool(quality[k] < cfg.blur_rel * local
                              or quality[k] < cfg.blur_global_rel * seg_ref[g])
                continue
        unmatched.append(k)
    # the others against their neighbours outside their segment; a neighbour found blurred is
    # no reference (two bad frames in a row), hence a few rounds
    for _ in range(3):
        changed = False
        for k in unmatched:
            if out[k]:
                continue
            g = int(seg[k])
            a, b = max(0, k - 16), min(len(exposed), k + 17)
            other = ((seg[a:b] != g) | (g < 0)) & ~out[a:b]
            before = a + np.flatnonzero(other[:k - a])[-2:]
            after = k + 1 + np.flatnonzero(other[k + 1 - a:])[:2]
            near = sharp[np.r_[before, after]]
            if len(near) and sharp[k] < cfg.blur_unmatched_rel * float(np.median(near)):
                out[k] = changed = True
        if not changed:
            break
    return out


def _thin(kept: list[int], m: int) -> list[int]:
    """``m`` of ``kept`` spread evenly."""
    picks = np.unique(np.round(np.linspace(0, len(kept) - 1, m)).astype(int))
    return [kept[p] for p in picks]
