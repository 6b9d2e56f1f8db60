"""Frame-to-frame tracking for the ``frames`` stage (:mod:`cystomap.frames`).

:class:`_Tracker` follows the scene between consecutive frames (Lucas-Kanade on corners away
from glints and the FOV rim, forward-backward checked, a similarity fitted with RANSAC);
:class:`_Look` keeps a frame's sharpness on a grid of cells so that two frames are compared on
the content they share (:func:`_matched_ratio`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from cystomap.frame_scoring import _Probe
    from cystomap.frames import FramesConfig

_MIN_TRACK_POINTS = 8
# share of a frame's scored area two frames must share for a content-matched comparison
_MIN_OVERLAP = 0.25
# sharpness is compared on cells of this many analysis pixels a side
_CELL_PX = 4

# a frame's gain-normalised grey and its corners (see _Tracker.prepare)
Prepared = tuple[np.ndarray, np.ndarray | None]


@dataclass
class _Look:
    """A frame's sharpness map on a grid of cells, for comparisons on shared content."""

    energy: np.ndarray  # float32 cells: mean squared LoG x share of valid pixels
    weight: np.ndarray  # float32 cells: share of valid pixels (FOV, no glints)
    grey2: np.ndarray  # float32 cells: squared mean grey x share of valid pixels
    to_px: np.ndarray  # 3x3: cell coordinates -> analysis pixels
    sharpness: float

    @staticmethod
    def of(energy: np.ndarray, valid: np.ndarray, grey: np.ndarray, sharpness: float) -> _Look:
        h, w = valid.shape
        cw, ch = max(1, w // _CELL_PX), max(1, h // _CELL_PX)
        v = valid.astype(np.float32)

        def cells(a: np.ndarray) -> np.ndarray:
            return cv2.resize(a, (cw, ch), interpolation=cv2.INTER_AREA)

        sx, sy = w / cw, h / ch
        to_px = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0, 0, 1]])
        weight = cells(v)
        mean = cells(grey.astype(np.float32) * v) / np.maximum(weight, 1e-6)
        return _Look(cells(energy * v), weight, np.square(mean) * weight, to_px, sharpness)


def _matched_ratio(a: _Look, b: _Look, step: np.ndarray) -> float:
    """Sharpness of ``b`` over that of ``a``, both measured on the part of the scene they share.

    ``step`` (3x3) maps ``a``'s analysis pixels to ``b``'s. NaN when they share less than
    _MIN_OVERLAP of either frame's scored area. The same mucosa seen twice has the same detail:
    a ratio well below 1 means ``b`` is blurred, whatever the content (a featureless patch is
    not mistaken for blur, nor a vessel-rich one for sharpness).
    """
    ch, cw = a.weight.shape
    m = np.linalg.inv(a.to_px) @ step @ a.to_px
    va, vb = a.weight > 0.5, b.weight > 0.5
    a_in_b = cv2.warpAffine(va.view(np.uint8), m[:2], (cw, ch), flags=cv2.INTER_NEAREST) > 0
    b_in_a = cv2.warpAffine(vb.view(np.uint8), np.linalg.inv(m)[:2], (cw, ch),
                            flags=cv2.INTER_NEAREST) > 0
    oa, ob = va & b_in_a, vb & a_in_b
    if (np.count_nonzero(oa) < _MIN_OVERLAP * np.count_nonzero(va)
            or np.count_nonzero(ob) < _MIN_OVERLAP * np.count_nonzero(vb)):
        return math.nan

    def energy(look: _Look, cells: np.ndarray) -> float:
        # normalised by the brightness of each cell: the same mucosa lit differently (the
        # vignetting, the light falling off) keeps its value
        grey2 = float(look.grey2[cells].sum())
        return float(look.energy[cells].sum()) / grey2 * 1e4 if grey2 > 0 else 0.0

    ea = energy(a, oa)
    return energy(b, ob) / ea if ea > 0 else math.nan


@dataclass
class _Ref:
    """A reference frame of the tracker."""

    grey: np.ndarray  # gain-normalised analysis grey
    pts: np.ndarray  # corners to track from it
    transform: np.ndarray  # segment start -> this frame (analysis px)
    segment: int
    look: _Look | None
    index: int  # frame number


class _Tracker:
    """Chains frame-to-frame similarity transforms into segments.

    Every frame is tracked against the reference (the last good frame). A usable frame that
    cannot be tracked starts a new segment at once: it is not lost, only the motion between it
    and the frames before is unknown. For ``max_track_gap`` frames after such a break the
    reference from before the break is tried first, so a bad frame or two in between does not
    split a segment. Dark or overexposed frames, and frames much less sharp than the reference
    on the content they share (ratio below ``blur_rel``), are tracked through but never become
    the reference.
    """

    def __init__(self, probe: _Probe, cfg: FramesConfig) -> None:
        self.mask = probe.track_mask
        self.max_points = cfg.track_points
        self.min_distance = max(3.0, probe.aw / 60)
        self.max_gap = cfg.max_track_gap
        self.keep_rel = cfg.blur_rel
        # tolerance of the similarity fit: the parallax of a curved wall seen from close up
        self.ransac_px = max(1.5, probe.aw / 160)
        self.ref: _Ref | None = None
        self.held: _Ref | None = None  # the reference from before a tracking break
        self.held_age = 0
        self.segment = -1
        self.index = -1
        self.velocity: np.ndarray | None = None  # last step between consecutive frames
        self.lk = {"winSize": (21, 21), "maxLevel": 3,
                   "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)}

    def prepare(self, grey: np.ndarray, glints: np.ndarray | None, corners: bool) -> Prepared:
        """The gain-normalised ``grey`` and, when ``corners``, the corners it would be tracked
        from as a reference (None: too few). Reads only the tracker's settings, so a worker
        thread can prepare frames ahead of :meth:`add`."""
        mean = float(grey[self.mask > 0].mean()) if self.mask.any() else float(grey.mean())
        if mean >= 1.0:  # gain-normalise: auto-exposure steps must not break Lucas-Kanade
            grey = cv2.convertScaleAbs(grey, alpha=128.0 / mean)
        return grey, self._corners(grey, glints) if corners else None

    def _corners(self, grey: np.ndarray, glints: np.ndarray | None) -> np.ndarray | None:
        mask = self.mask if glints is None else np.where(glints, 0, self.mask).astype(np.uint8)
        # a low quality level: the strongest corners win anyway, and one glint left over
        # (compression ringing) must not push the relative threshold above all mucosa corners
        pts = cv2.goodFeaturesToTrack(grey, self.max_points, 1e-3, self.min_distance,
                                      mask=mask, blockSize=5)
        if pts is None or len(pts) < _MIN_TRACK_POINTS:
            return None
        return pts.astype(np.float32)

    def _track(self, ref: _Ref, grey: np.ndarray, guess: np.ndarray | None = None,
               ) -> np.ndarray | None:
        """Similarity transform (3x3) from ``ref`` to ``grey``, or None.

        ``guess`` (3x3, optional) is where the corners are expected to have gone.
        """
        if guess is None:
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(ref.grey, grey, ref.pts, None, **self.lk)
        else:
            start = cv2.transform(ref.pts, guess[:2]).astype(np.float32)
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(ref.grey, grey, ref.pts, start,
                                                  flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self.lk)
        if p1 is None:
            return None
        p0, st2, _ = cv2.calcOpticalFlowPyrLK(grey, ref.grey, p1, None, **self.lk)
        if p0 is None:
            return None
        fb = np.linalg.norm((p0 - ref.pts).reshape(-1, 2), axis=1)
        good = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < 1.0)
        if np.count_nonzero(good) < _MIN_TRACK_POINTS:
            return None
        src, dst = ref.pts[good].reshape(-1, 2), p1[good].reshape(-1, 2)
        a, inliers = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC,
                                                 ransacReprojThreshold=self.ransac_px)
        if a is None or inliers is None:
            return None
        n_in = int(np.count_nonzero(inliers))
        if n_in < max(_MIN_TRACK_POINTS, 0.3 * len(src)):
            return None
        return np.vstack([a, [0.0, 0.0, 1.0]])

    def add(self, grey: np.ndarray, glints: np.ndarray | None = None, usable: bool = True,
            look: _Look | None = None,
            prepared: Prepared | None = None) -> tuple[int, np.ndarray]:
        """Track ``grey``; returns (segment, transform), (-1, NaNs) if untracked.

        ``glints`` (bool image, optional) marks specular highlights: no corners there.
        ``usable`` False (a dark or overexposed frame) is tracked if possible but never becomes
        the reference nor starts a segment; neither does a frame without ``look``.
        ``prepared``: :meth:`prepare`'s result for this frame (with corners when ``usable`` and
        ``look``), computed here when not given.
        """
        wants = usable and look is not None
        grey, pts = prepared if prepared is not None else self.prepare(grey, glints, wants)
        if not wants:
            pts = None
        self.index += 1
        if self.held is not None:
            self.held_age += 1
            if self.held_age > self.max_gap:
                self.held = None
        for ref in (self.held, self.ref):
            if ref is None:
                continue
            step = self._track(ref, grey)
            consecutive = ref.index == self.index - 1
            if step is None and consecutive and self.velocity is not None:
                # a fast, steady sweep: look where the last step would have taken the corners
                step = self._track(ref, grey, self.velocity)
            if step is None:
                continue
            if consecutive:
                self.velocity = step
            if ref is self.held:  # back on the scene from before the break
                self.ref, self.held = ref, None
            transform = step @ ref.transform
            if wants and not (
                    ref.look is not None
                    and _matched_ratio(ref.look, look, step) < self.keep_rel):
                if pts is not None:
                    self.ref = _Ref(grey, pts, transform, ref.segment, look, self.index)
            return ref.segment, transform
        if pts is None:  # dark, overexposed or featureless: stay untracked
            return -1, np.full((3, 3), np.nan)
        if self.held is None and self.ref is not None:
            self.held, self.held_age = self.ref, 0
        self.segment += 1
        self.ref = _Ref(grey, pts, np.eye(3), self.segment, look, self.index)
        return self.segment, np.eye(3)
