"""The probe and the scoring of the ``frames`` stage (:mod:`cystomap.frames`).

The probe (:func:`_new_probe` from the first frame, :func:`_finish_probe` from an even sample
of analysis greys gathered by :class:`_Sampler` while decoding) finds the field of view, static
overlays and typical brightness; :func:`_score` measures the sharpness, saturation and darkness
of every frame's analysis grey and the motion chained by the tracker, and :func:`_quality` turns
the pairwise content-matched sharpness ratios into one sharpness per frame (robust least
squares).
"""

from __future__ import annotations

import logging
import math
import time
from array import array
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from cystomap.camera import Camera
from cystomap.errors import InputError
from cystomap.frame_tracking import Prepared, _Look, _matched_ratio, _Tracker
from cystomap.parallel import prefetch
from cystomap.video import erode, fov_mask, static_pixels, temporal_std

if TYPE_CHECKING:
    from cystomap.frames import FramesConfig

log = logging.getLogger(__name__)

PROGRESS_EVERY_S = 5.0
# at most this many frames back for sharpness comparisons (memory: one cell map per frame)
_MAX_PAIR_REACH = 256
# frames measured ahead of the tracking (in a worker thread)
_DECODE_AHEAD = 16
# weak pull of the content-matched log-sharpness towards the raw one; Huber scale of the fit
_QUALITY_PRIOR = 0.01
_QUALITY_HUBER = 0.2


@dataclass
class _Probe:
    width: int
    height: int
    fps: float
    aw: int
    ah: int
    score_mask: np.ndarray  # bool, analysis size: pixels scored
    track_mask: np.ndarray  # uint8, analysis size: where corners are detected
    grid: np.ndarray  # (N, 2) float64 analysis px: points whose displacement measures motion
    fov_share: float
    brightness: float
    dark_level: float
    static_share: float = 0.0
    # diagonal of the lit field of view's bounding box, full-resolution pixels (the scale of
    # the spacing between kept frames)
    fov_diagonal: float = 0.0



def analysis_size(width: int, height: int, cfg: FramesConfig) -> tuple[int, int]:
    """Size (w, h) of the grey copy frames are scored on: ``analysis_width`` wide at most."""
    aw = min(cfg.analysis_width, width)
    return aw, max(8, round(height * aw / width))


def to_analysis(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The analysis grey of a decoded frame (BGR or grey), INTER_AREA-downscaled to ``size``."""
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
    if (grey.shape[1], grey.shape[0]) != size:
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    return grey


class _Sampler:
    """An even sample of a stream of unknown length: every ``stride``-th frame, the sample
    halved (the stride doubled) whenever it reaches twice the wanted size ``n``."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.stride = 1
        self.samples: list[np.ndarray] = []

    def add(self, index: int, grey: np.ndarray) -> None:
        if index % self.stride:
            return
        self.samples.append(grey)
        if len(self.samples) >= 2 * self.n:
            self.samples, self.stride = self.samples[::2], self.stride * 2


def _new_probe(video: Path, first: np.ndarray, fps: float, cfg: FramesConfig,
               camera: Camera | None) -> _Probe:
    """The probe's frame geometry from the first decoded frame (InputError on a size that
    does not match ``camera``); the rest comes from :func:`_finish_probe`."""
    h, w = first.shape[:2]
    if camera is not None and (w, h) != (camera.width, camera.height):
        raise InputError(f"{video}: frame size {w}x{h} does not match camera "
                         f"{camera.name!r} ({camera.width}x{camera.height})")
    aw, ah = analysis_size(w, h, cfg)
    return _Probe(w, h, fps, aw, ah, np.ones((ah, aw), bool),
                  np.full((ah, aw), 255, np.uint8), np.zeros((0, 2)), 1.0, 0.0, 0.0)


def _finish_probe(video: Path, probe: _Probe, samples: list[np.ndarray],
                  cfg: FramesConfig) -> _Probe:
    """Derive the FOV, static overlays and typical brightness from the sampled analysis greys."""
    aw, ah, w, h = probe.aw, probe.ah, probe.width, probe.height
    variation = temporal_std(samples) if len(samples) >= 8 else None
    mask = None
    if cfg.fov == "auto":
        mask = fov_mask(np.percentile(np.stack(samples), 75, axis=0), variation)
        if mask is None:
            log.warning("frames: %s: no field of view found (dark video?); scoring the whole "
                        "frame", video.name)
    if mask is None:
        mask = np.full((ah, aw), 255, np.uint8)
    probe.fov_share = float(np.count_nonzero(mask)) / mask.size
    ys, xs = np.nonzero(mask)
    probe.fov_diagonal = math.hypot((xs.max() - xs.min() + 1) * w / aw,
                                    (ys.max() - ys.min() + 1) * h / ah)
    score = erode(mask, cfg.fov_erode_px)
    static = static_pixels(variation, score > 0, cfg.static_rel)
    if static is not None:
        probe.static_share = float(np.count_nonzero(static)) / max(1, np.count_nonzero(score))
        # also the reach of the Laplacian of Gaussian around them: the crisp edges of an
        # overlay must not leak into the sharpness
        reach = 2 * math.ceil(2 * cfg.sharpness_sigma) + 1
        static = cv2.dilate(static.view(np.uint8), cv2.getStructuringElement(
            cv2.MORPH_ELLIPSE, (reach, reach))) > 0
        score = np.where(static, 0, score).astype(np.uint8)
    # one more pixel for the Laplacian's support
    probe.score_mask = erode(score, 1) > 0
    if not probe.score_mask.any():
        probe.score_mask = mask > 0
    # corners near the FOV rim would see the static rim, not the scene: keep clear of it
    probe.track_mask = erode(score, 12)
    if not probe.track_mask.any():
        probe.track_mask = score
    means = np.array([s[probe.score_mask].mean() for s in samples])
    probe.brightness = float(np.percentile(means, 75))
    probe.dark_level = max(cfg.dark_rel * probe.brightness, float(cfg.black_level))
    gy, gx = np.mgrid[0:ah:ah / 12, 0:aw:aw / 16]
    gy, gx = gy + ah / 24, gx + aw / 32
    inside = probe.score_mask[gy.astype(int).clip(0, ah - 1), gx.astype(int).clip(0, aw - 1)]
    probe.grid = np.column_stack([gx[inside], gy[inside]]).astype(np.float64)
    if len(probe.grid) < 4:
        ys, xs = np.nonzero(probe.score_mask)
        probe.grid = np.column_stack([xs, ys])[:: max(1, len(xs) // 64)].astype(np.float64)
    return probe


@dataclass
class _Scores:
    time_s: np.ndarray
    sharpness: np.ndarray
    saturated: np.ndarray
    dark: np.ndarray
    transform: np.ndarray  # (n, 3, 3) analysis px, segment start -> frame; NaN = untracked
    segment: np.ndarray  # int, -1 = untracked
    # content-matched sharpness (see _quality); equal to sharpness where unmatched
    quality: np.ndarray
    matched: np.ndarray  # bool: compared with at least one overlapping frame of its segment


@dataclass
class _Measure:
    """What one frame shows, measured on its own (no other frame needed)."""

    sharpness: float
    saturated: float
    dark: float
    usable: bool  # neither dark nor overexposed
    glints: np.ndarray | None  # bool image: saturated blobs and their halos
    look: _Look | None


def _measure(grey: np.ndarray, cfg: FramesConfig, probe: _Probe, kernel: np.ndarray,
             ) -> _Measure:
    values = grey[probe.score_mask]
    mean = float(values.mean())
    saturated_px = grey >= cfg.saturation_level
    sat = float(np.count_nonzero(saturated_px & probe.score_mask)) / values.size
    dark = float(np.count_nonzero(values < probe.dark_level)) / values.size
    valid = probe.score_mask
    glints = None
    if saturated_px.any():
        glints = cv2.dilate(saturated_px.view(np.uint8), kernel) > 0
        valid = valid & ~glints
    usable = dark <= cfg.max_dark and sat <= cfg.max_saturated
    look = None
    sharpness = 0.0
    if mean >= 1.0 and valid.any():
        smooth = grey.astype(np.float32)
        if cfg.sharpness_sigma > 0:
            smooth = cv2.GaussianBlur(smooth, (0, 0), cfg.sharpness_sigma)
        energy = np.square(cv2.Laplacian(smooth, cv2.CV_32F))
        sharpness = float(np.mean(energy[valid])) * (100.0 / mean) ** 2
        if usable:
            look = _Look.of(energy, valid, grey, sharpness)
    return _Measure(sharpness, sat, dark, usable, glints, look)


def _score(greys: Iterable[tuple[int, float, np.ndarray]], cfg: FramesConfig, probe: _Probe,
           ) -> _Scores:
    """Score the analysis greys ``(index, time_s, grey)`` of every frame, in order: each
    frame measured on its own in a worker thread, tracked and compared here."""
    times: list[float] = []
    sharp: list[float] = []
    sat: list[float] = []
    dark: list[float] = []
    transforms: list[np.ndarray] = []
    segments: list[int] = []
    tracker = _Tracker(probe, cfg)
    # sharpness comparisons: each frame against the frames 1, 2, 4, 8, ... before it in its
    # segment, up to blur_window_s back (the local sharpness reference window)
    fps = probe.fps if probe.fps > 0 else 25.0
    reach = min(_MAX_PAIR_REACH, max(1, round(cfg.blur_window_s * fps)))
    offsets = [1 << e for e in range(reach.bit_length()) if 1 << e <= reach]
    recent: dict[int, tuple[int, np.ndarray, _Look]] = {}
    # (earlier frame, frame, log sharpness ratio) per comparison
    pairs = (array("q"), array("q"), array("d"))
    # specular glints (saturated blobs) and their halos: excluded from sharpness and tracking
    k = 2 * max(2, round(probe.aw / 60)) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    t0 = last_log = time.perf_counter()

    def measured() -> Iterator[tuple[int, float, np.ndarray, _Measure, Prepared]]:
        for index, time_s, grey in greys:
            m = _measure(grey, cfg, probe, kernel)
            # the tracker's corners too: the main thread is the bottleneck (tracking, chained)
            yield (index, time_s, grey, m,
                   tracker.prepare(grey, m.glints, m.usable and m.look is not None))

    for index, time_s, grey, m, prepared in prefetch(measured(), _DECODE_AHEAD):
        sat.append(m.saturated)
        dark.append(m.dark)
        sharp.append(m.sharpness)
        look = m.look
        seg, transform = tracker.add(grey, m.glints, m.usable, look, prepared)
        segments.append(seg)
        transforms.append(transform)
        recent.pop(index - reach - 1, None)
        if seg >= 0 and look is not None:
            for off in offsets:
                earlier = recent.get(index - off)
                if earlier is not None and earlier[0] == seg:
                    ratio = _matched_ratio(earlier[2], look,
                                           transform @ np.linalg.inv(earlier[1]))
                    if ratio > 0:
                        pairs[0].append(index - off)
                        pairs[1].append(index)
                        pairs[2].append(math.log(ratio))
            recent[index] = (seg, transform, look)
        times.append(time_s)
        now = time.perf_counter()
        if now - last_log > PROGRESS_EVERY_S:
            last_log = now
            log.info("frames: scored %d frames (%.0f fps), %.1f s", index + 1,
                     (index + 1) / (now - t0), now - t0)
    n = len(times)
    sharpness = np.asarray(sharp)
    quality, matched = _quality(sharpness, pairs)
    return _Scores(
        np.asarray(times), sharpness, np.asarray(sat), np.asarray(dark),
        np.stack(transforms) if n else np.zeros((0, 3, 3)), np.asarray(segments, dtype=int),
        quality, matched,
    )


def _quality(sharpness: np.ndarray, pairs: tuple[array, array, array],
             ) -> tuple[np.ndarray, np.ndarray]:
    """Content-matched sharpness: the values whose ratios best agree with the measured ones.

    Each comparison (j, i, log r) in ``pairs`` says "frame i is r times as sharp as frame j on
    the content they share". Log-sharpness values q are fitted to all pairs (robust least squares, Huber
    weights), with a weak pull towards the raw log-sharpness that fixes each segment's overall
    level. Many overlapping pairs per frame keep the scale from drifting along a segment the
    way a chain of consecutive ratios would. Returns (quality, matched).
    """
    n = len(sharpness)
    raw = np.log(np.maximum(sharpness, 1e-12))
    matched = np.zeros(n, bool)
    if not pairs[0]:
        return np.exp(raw), matched
    j, i, r = (np.frombuffer(a, dtype=a.typecode) for a in pairs)
    matched[i] = matched[j] = True
    idx = np.flatnonzero(matched)
    pos = np.full(n, -1)
    pos[idx] = np.arange(len(idx))
    rows = np.arange(len(r))
    d = sp.csr_matrix((np.r_[np.ones(len(r)), -np.ones(len(r))],
                       (np.r_[rows, rows], np.r_[pos[i], pos[j]])), shape=(len(r), len(idx)))
    prior = _QUALITY_PRIOR * sp.identity(len(idx), format="csr")
    w = np.ones(len(r))
    q = raw[idx]
    for _ in range(4):
        dw = d.T.multiply(w)
        q = spla.spsolve((dw @ d + prior).tocsc(), dw @ r + _QUALITY_PRIOR * raw[idx])
        res = np.abs(d @ q - r)
        w = np.minimum(1.0, _QUALITY_HUBER / np.maximum(res, 1e-12))
    out = np.exp(raw)
    out[idx] = np.exp(q)
    return out, matched
