"""Stage ``frames``: decode a cystoscopy video, score every frame, keep the useful ones as PNGs.

Every frame is scored on a grey copy downscaled to ``analysis_width``, inside the field of view
(FOV: the lit circle/octagon of endoscope video, detected from the video itself; static overlays
inside it such as text or lens dirt, found by their low temporal variation, are left out):

* ``sharpness``: mean squared Laplacian of Gaussian (sigma ``sharpness_sigma``) of the grey image
  rescaled to a mean of 100 inside the FOV (so auto-exposure changes do not look like blur),
  specular glints and their halos excluded;
* ``saturated`` / ``dark``: share of FOV pixels at or above ``saturation_level`` / below the
  video's dark level (``dark_rel`` times its typical brightness, at least ``black_level``);
* motion: consecutive frames are tracked (gain-normalised grey, Lucas-Kanade on corners away
  from glints and the FOV rim, started where the last step would take them if that fails,
  forward-backward checked, a similarity transform fitted with RANSAC) and the transforms
  chained; the motion between two frames is the median displacement of a grid of FOV points
  under the chained transform (``motion_px``, in full-resolution pixels). Pan, rotation and
  zoom all count; hand tremor back and forth cancels. Dark or overexposed frames are tracked
  through but never become the reference. A frame that cannot be tracked (the camera moved
  too far, a bad frame in between) starts a new segment at once: the gap is information for
  SfM, not a reason to drop a sharp frame. For ``max_track_gap`` frames after a break the
  reference from before it is tried first, so one bad frame does not split a segment. Only a
  well-exposed frame with nothing to track in it (no corners: fogged, featureless) is dropped
  as *untracked*.

Thresholds are relative to the video itself. The raw sharpness of a frame depends on what it
shows (vessels or a smooth patch, near or far) as much as on blur, so frames are compared on the
content they share: each frame against the frames 1, 2, 4, 8, ... before it in its segment (up
to ``blur_window_s``), both measured on the cells of the scene they both see, normalised by each
cell's brightness; a robust least-squares fit of all these ratios gives a content-matched
sharpness per frame. A frame is *blurred* when that falls below ``blur_rel`` times the
``blur_percentile`` of its segment's frames within ±``blur_window_s`` (or below
``blur_global_rel`` times that of the whole segment: long blurred stretches); a frame matched
with no other (tracking failed on both sides) only when its raw sharpness falls below
``blur_unmatched_rel`` times that of its neighbours. The redundancy threshold is a fraction of
the image diagonal. Frames are kept greedily: a good frame is kept when the scene moved at
least ``min_motion`` since the last kept frame; a sharper frame among the next ``lookahead``
may be taken instead only while the motion stays within twice ``min_motion``, and after a jump
(dropped frames, a tracking break) the last frame before it is kept too when that splits the
gap. ``max_frames`` raises the spacing until the selection fits, so kept frames still cover
the whole video.

The video is decoded three times, streaming (FOV/brightness probe on a sample, scoring, writing
the kept frames), so memory grows only by a few numbers per frame.

Outputs in ``out_dir`` (written atomically): ``f000123.png`` per kept frame (0-based index of the
frame in the video, BGR as decoded), ``frames.csv`` with one row per decoded frame
(``frame,time_s,sharpness,saturated,dark,motion_px,kept,reason``; ``kept`` is True/False;
``reason`` one of kept, outside_range, dark, overexposed, blurred, untracked, redundant,
over_limit; ``motion_px`` is relative to the last kept frame before it, empty when unknown), and
``frames.json`` (derived thresholds, FOV and static-overlay shares, counts, settings, timing).
"""

from __future__ import annotations

import csv
import logging
import math
import time
from array import array
from collections import Counter
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from cystomap.camera import Camera
from cystomap.errors import InputError, StageError
from cystomap.outputs import atomic_dir, software_versions, write_json
from cystomap.video import (
    erode,
    fov_mask,
    frame_time,
    open_video,
    ordered_map,
    static_pixels,
    temporal_std,
)

log = logging.getLogger(__name__)

CSV_COLUMNS = ("frame", "time_s", "sharpness", "saturated", "dark", "motion_px", "kept", "reason")
REASONS = ("kept", "outside_range", "dark", "overexposed", "blurred", "untracked", "redundant",
           "over_limit")
PROGRESS_EVERY_S = 5.0
_MIN_TRACK_POINTS = 8
# share of a frame's scored area two frames must share for a content-matched comparison
_MIN_OVERLAP = 0.25
# sharpness is compared on cells of this many analysis pixels a side
_CELL_PX = 4
# at most this many frames back for sharpness comparisons (memory: one cell map per frame)
_MAX_PAIR_REACH = 256
# weak pull of the content-matched log-sharpness towards the raw one; Huber scale of the fit
_QUALITY_PRIOR = 0.01
_QUALITY_HUBER = 0.2
# lookahead never lets the motion since the last kept frame exceed this times min_motion
_LOOKAHEAD_MAX_REL = 2.0


@dataclass(frozen=True)
class FramesConfig:
    """Settings of the ``frames`` stage (config section ``frames``)."""

    # Frames are scored on a grey copy downscaled to this width in pixels (never upscaled).
    analysis_width: int = 480
    # Field of view scored: "auto" = detect the lit area (black endoscope borders and overlaid
    # text excluded), "full" = the whole frame.
    fov: str = "auto"
    # Shrink the detected FOV by this many analysis pixels (drops the rim, its vignetting and
    # the compression ringing along it).
    fov_erode_px: int = 6
    # FOV pixels whose temporal std over the sampled frames is below static_rel times the
    # typical one (overlaid text, lens dirt) are not scored nor tracked (0 = keep them); not
    # applied when over 10% of the FOV is static (a still camera).
    static_rel: float = 0.25
    # Sharpness is measured on the analysis image smoothed by a Gaussian of this sigma (pixels):
    # a Laplacian-of-Gaussian band, so sensor noise and compression artefacts count less.
    sharpness_sigma: float = 1.5
    # Frames sampled evenly through the video to detect the FOV and the typical brightness.
    probe_samples: int = 64
    # A pixel is saturated at or above this grey level (8-bit clipping; glints, overexposure).
    saturation_level: int = 250
    # A pixel is dark below dark_rel times the video's typical brightness (75th percentile of
    # the sampled frames' mean FOV brightness) ...
    dark_rel: float = 0.25
    # ... and always below this grey level (black whatever the video).
    black_level: int = 12
    # Drop a frame as "dark" when more than this share of its FOV is dark.
    max_dark: float = 0.6
    # Drop a frame as "overexposed" when more than this share of its FOV is saturated.
    max_saturated: float = 0.3
    # Drop a frame as "blurred" when its sharpness is below blur_rel times the local reference:
    # the blur_percentile of the sharpness of well-exposed frames of its tracking segment within
    # ±blur_window_s, all compared on the scene content they share (see the module docstring).
    blur_rel: float = 0.4
    # Half-width in seconds of the window of the local sharpness reference (and how far back
    # frames are compared).
    blur_window_s: float = 2.0
    # Percentile of sharpness in the window used as the local reference ("sharp frames here").
    blur_percentile: float = 75.0
    # Also "blurred" below this times the blur_percentile of the sharpness of its whole tracking
    # segment (long blurred stretches).
    blur_global_rel: float = 0.2
    # A frame that could not be compared with any overlapping frame (tracking failed before and
    # after it) is "blurred" below this times the median raw sharpness of the two well-exposed
    # frames on each side (lower than blur_rel: their content differs).
    blur_unmatched_rel: float = 0.15
    # Target spacing: a good frame is "redundant" until the scene moved by this fraction of the
    # image diagonal since the last kept frame (median displacement of FOV points).
    min_motion: float = 0.03
    # Minimum distance between kept frames, in frames (1 = no constraint).
    min_gap: int = 1
    # Once min_motion (> 0) is reached at frame i, keep the sharpest eligible frame among
    # i .. i + lookahead whose motion since the last kept frame stays within twice min_motion
    # (0 = keep the first frame that moved enough).
    lookahead: int = 2
    # Keep at most this many frames (0 = no limit). If more qualify, the spacing is raised until
    # they fit; frames lost that way are marked "over_limit".
    max_frames: int = 0
    # A frame that cannot be tracked starts a new segment (and is kept if good); for this many
    # frames after such a break, tracking first tries the frame before it again (so a bad frame
    # or two in between does not split a segment).
    max_track_gap: int = 5
    # Corners tracked between consecutive frames.
    track_points: int = 200
    # Only frames with start_s <= time < end_s are considered (end_s 0 = to the end).
    start_s: float = 0.0
    end_s: float = 0.0
    # Threads writing PNGs.
    threads: int = 2

    def __post_init__(self) -> None:
        checks = [
            (self.analysis_width >= 32, "analysis_width must be >= 32"),
            (self.fov in ("auto", "full"), f"fov must be 'auto' or 'full', got {self.fov!r}"),
            (self.fov_erode_px >= 0, "fov_erode_px must be >= 0"),
            (0 <= self.static_rel < 1, "static_rel must be in [0, 1)"),
            (self.sharpness_sigma >= 0, "sharpness_sigma must be >= 0"),
            (self.probe_samples >= 1, "probe_samples must be >= 1"),
            (0 < self.saturation_level <= 255, "saturation_level must be in (0, 255]"),
            (0 <= self.dark_rel < 1, "dark_rel must be in [0, 1)"),
            (0 <= self.black_level < 255, "black_level must be in [0, 255)"),
            (0 < self.max_dark <= 1, "max_dark must be in (0, 1]"),
            (0 < self.max_saturated <= 1, "max_saturated must be in (0, 1]"),
            (0 <= self.blur_rel < 1, "blur_rel must be in [0, 1)"),
            (self.blur_window_s > 0, "blur_window_s must be > 0"),
            (0 < self.blur_percentile <= 100, "blur_percentile must be in (0, 100]"),
            (0 <= self.blur_global_rel < 1, "blur_global_rel must be in [0, 1)"),
            (0 <= self.blur_unmatched_rel < 1, "blur_unmatched_rel must be in [0, 1)"),
            (self.min_motion >= 0, "min_motion must be >= 0"),
            (self.min_gap >= 1, "min_gap must be >= 1"),
            (self.lookahead >= 0, "lookahead must be >= 0"),
            (self.max_frames >= 0, "max_frames must be >= 0 (0 = no limit)"),
            (self.max_track_gap >= 1, "max_track_gap must be >= 1"),
            (self.track_points >= _MIN_TRACK_POINTS,
             f"track_points must be >= {_MIN_TRACK_POINTS}"),
            (self.start_s >= 0 and self.end_s >= 0, "start_s and end_s must be >= 0"),
            (self.end_s == 0 or self.end_s > self.start_s, "end_s must be 0 or > start_s"),
            (self.threads >= 1, "threads must be >= 1"),
        ]
        for ok, message in checks:
            if not ok:
                raise InputError(f"frames: {message}")


def extract_frames(
    video: str | Path, out_dir: str | Path, cfg: FramesConfig | None = None,
    camera: Camera | None = None,
) -> Path:
    """Score every frame of ``video``, write the kept ones and ``frames.csv`` into ``out_dir``.

    Raises :class:`InputError` naming the video if it is missing, not a decodable video, has no
    usable frame, or its frame size differs from ``camera``. Nothing is left at ``out_dir`` on
    failure (an earlier result there is kept).
    """
    cfg = cfg or FramesConfig()
    video, out_dir = Path(video), Path(out_dir)
    t0 = time.perf_counter()
    probe = _probe(video, cfg, camera)
    log.info("frames: %s: %dx%d, %.3g fps, FOV %.0f%% of the frame, typical brightness %.0f "
             "(probe %.1f s)", video.name, probe.width, probe.height, probe.fps,
             100 * probe.fov_share, probe.brightness, time.perf_counter() - t0)
    scores = _score(video, cfg, probe)
    n = len(scores.time_s)
    sel = _select(scores, cfg, probe)
    counts = Counter(sel.reason)
    log.info("frames: %d decoded, %d kept (%s), motion threshold %.1f px",
             n, len(sel.kept), ", ".join(f"{k} {v}" for k, v in sorted(counts.items())),
             sel.threshold_px)
    if not sel.kept:
        detail = ", ".join(f"{v} {k}" for k, v in sorted(counts.items()))
        raise InputError(f"{video}: no usable frame among {n} decoded ({detail})")
    with atomic_dir(out_dir) as tmp:
        _write_frames(video, tmp, sel.kept, n, cfg.threads)
        _write_csv(tmp / "frames.csv", scores, sel)
        write_json(tmp / "frames.json", {
            "video": str(video),
            "width": probe.width, "height": probe.height, "fps": probe.fps,
            "frames_decoded": n, "frames_kept": len(sel.kept),
            "reasons": {r: counts.get(r, 0) for r in REASONS},
            "fov_share": round(probe.fov_share, 4),
            "software": software_versions(),
            "static_share": round(probe.static_share, 4),
            "analysis_size": [probe.aw, probe.ah],
            "thresholds": {
                "brightness": round(probe.brightness, 2),
                "dark_level": round(probe.dark_level, 2),
                "saturation_level": cfg.saturation_level,
                "sharpness_median": round(sel.sharp_median, 4),
                "min_motion_px": round(sel.base_threshold_px, 2),
                "motion_threshold_px": round(sel.threshold_px, 2),
            },
            "segments": int(scores.segment.max() + 1) if n else 0,
            "settings": asdict(cfg),
            "elapsed_s": round(time.perf_counter() - t0, 3),
        })
    log.info("frames: wrote %d frames to %s in %.1f s", len(sel.kept), out_dir,
             time.perf_counter() - t0)
    return out_dir


# --------------------------------------------------------------------------- pass 1: probe


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

    def to_analysis(self, frame: np.ndarray) -> np.ndarray:
        grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
        if (grey.shape[1], grey.shape[0]) != (self.aw, self.ah):
            grey = cv2.resize(grey, (self.aw, self.ah), interpolation=cv2.INTER_AREA)
        return grey


def _probe(video: Path, cfg: FramesConfig, camera: Camera | None) -> _Probe:
    """Validate the video and derive the FOV and typical brightness from a sample of frames."""
    cap, info = open_video(video)
    try:
        ok, first = cap.read()
        if not ok or first is None:
            raise InputError(f"{video}: no decodable frame (not a video, or corrupt)")
        h, w = first.shape[:2]
        if camera is not None and (w, h) != (camera.width, camera.height):
            raise InputError(f"{video}: frame size {w}x{h} does not match camera "
                             f"{camera.name!r} ({camera.width}x{camera.height})")
        aw = min(cfg.analysis_width, w)
        ah = max(8, round(h * aw / w))
        probe = _Probe(w, h, info.fps, aw, ah, np.ones((ah, aw), bool),
                       np.full((ah, aw), 255, np.uint8), np.zeros((0, 2)), 1.0, 0.0, 0.0)
        # Sample evenly without knowing the length: keep every `stride`-th frame, and halve the
        # sample (doubling the stride) whenever it reaches twice the wanted size.
        samples = [probe.to_analysis(first)]
        stride, index = 1, 0
        while True:
            index += 1
            if index % stride:
                if not cap.grab():
                    break
                continue
            ok, frame = cap.read()
            if not ok or frame is None:
                break
            samples.append(probe.to_analysis(frame))
            if len(samples) >= 2 * cfg.probe_samples:
                samples, stride = samples[::2], stride * 2
    finally:
        cap.release()

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


# --------------------------------------------------------------------------- pass 2: scores


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


def _score(video: Path, cfg: FramesConfig, probe: _Probe) -> _Scores:
    cap, info = open_video(video)
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
    try:
        index = 0
        while True:
            ok, frame = cap.read()
            if not ok or frame is None:
                break
            if (frame.shape[1], frame.shape[0]) != (probe.width, probe.height):
                raise InputError(f"{video}: frame {index} is {frame.shape[1]}x{frame.shape[0]}, "
                                 f"frame 0 was {probe.width}x{probe.height}")
            grey = probe.to_analysis(frame)
            values = grey[probe.score_mask]
            mean = float(values.mean())
            saturated_px = grey >= cfg.saturation_level
            sat.append(float(np.count_nonzero(saturated_px & probe.score_mask)) / values.size)
            dark.append(float(np.count_nonzero(values < probe.dark_level)) / values.size)
            valid = probe.score_mask
            glints = None
            if saturated_px.any():
                glints = cv2.dilate(saturated_px.view(np.uint8), kernel) > 0
                valid = valid & ~glints
            usable = dark[-1] <= cfg.max_dark and sat[-1] <= cfg.max_saturated
            look = None
            if mean >= 1.0 and valid.any():
                smooth = grey.astype(np.float32)
                if cfg.sharpness_sigma > 0:
                    smooth = cv2.GaussianBlur(smooth, (0, 0), cfg.sharpness_sigma)
                energy = np.square(cv2.Laplacian(smooth, cv2.CV_32F))
                sharp.append(float(np.mean(energy[valid])) * (100.0 / mean) ** 2)
                if usable:
                    look = _Look.of(energy, valid, grey, sharp[-1])
            else:
                sharp.append(0.0)
            seg, transform = tracker.add(grey, glints, usable, look)
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
            times.append(frame_time(cap, index, info.fps))
            index += 1
            now = time.perf_counter()
            if now - last_log > PROGRESS_EVERY_S:
                last_log = now
                log.info("frames: scored %d frames (%.0f fps), %.1f s", index,
                         index / (now - t0), now - t0)
    finally:
        cap.release()
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
            look: _Look | None = None) -> tuple[int, np.ndarray]:
        """Track ``grey``; returns (segment, transform), (-1, NaNs) if untracked.

        ``glints`` (bool image, optional) marks specular highlights: no corners there.
        ``usable`` False (a dark or overexposed frame) is tracked if possible but never becomes
        the reference nor starts a segment; neither does a frame without ``look``.
        """
        mean = float(grey[self.mask > 0].mean()) if self.mask.any() else float(grey.mean())
        if mean >= 1.0:  # gain-normalise: auto-exposure steps must not break Lucas-Kanade
            grey = cv2.convertScaleAbs(grey, alpha=128.0 / mean)
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
            if usable and look is not None and not (
                    ref.look is not None
                    and _matched_ratio(ref.look, look, step) < self.keep_rel):
                pts = self._corners(grey, glints)
                if pts is not None:
                    self.ref = _Ref(grey, pts, transform, ref.segment, look, self.index)
            return ref.segment, transform
        pts = self._corners(grey, glints) if usable and look is not None else None
        if pts is None:  # dark, overexposed or featureless: stay untracked
            return -1, np.full((3, 3), np.nan)
        if self.held is None and self.ref is not None:
            self.held, self.held_age = self.ref, 0
        self.segment += 1
        self.ref = _Ref(grey, pts, np.eye(3), self.segment, look, self.index)
        return self.segment, np.eye(3)


# --------------------------------------------------------------------------- selection


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
        return kept

    diagonal = math.hypot(probe.width, probe.height)
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


# --------------------------------------------------------------------------- pass 3: write


def _write_frames(video: Path, out: Path, kept: list[int], n_expected: int, threads: int) -> None:
    wanted = set(kept)
    cap, _ = open_video(video)
    t0 = last_log = time.perf_counter()
    written = 0

    def save(item: tuple[int, np.ndarray]) -> None:
        index, frame = item
        path = out / f"f{index:06d}.png"
        if not cv2.imwrite(str(path), frame):
            raise StageError(f"{path}: cannot write PNG")

    def frames() -> Iterator[tuple[int, np.ndarray]]:
        index = 0
        try:
            while index <= kept[-1]:
                if index in wanted:
                    ok, frame = cap.read()
                    if not ok or frame is None:
                        break
                    yield index, frame
                elif not cap.grab():
                    break
                index += 1
        finally:
            cap.release()

    for _ in ordered_map(save, frames(), threads):
        written += 1
        now = time.perf_counter()
        if now - last_log > PROGRESS_EVERY_S:
            last_log = now
            log.info("frames: wrote %d/%d frames, %.1f s", written, len(kept), now - t0)
    if written != len(kept):
        raise StageError(f"{video}: decoding is not repeatable: wrote {written} of {len(kept)} "
                         f"kept frames (of {n_expected} decoded before)")


def _write_csv(path: Path, s: _Scores, sel: _Selection) -> None:
    kept = set(sel.kept)
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_COLUMNS)
        for i in range(len(s.time_s)):
            m = sel.motion_px[i]
            writer.writerow([
                i, f"{s.time_s[i]:.4f}", f"{s.sharpness[i]:.4f}", f"{s.saturated[i]:.5f}",
                f"{s.dark[i]:.5f}", "" if math.isnan(m) else f"{m:.2f}",
                "True" if i in kept else "False", sel.reason[i],
            ])


def read_frames_csv(path: str | Path) -> list[dict[str, Any]]:
    """Rows of a ``frames.csv`` as dicts with typed values (motion_px None when unknown)."""
    rows = []
    with Path(path).open(newline="") as fh:
        for row in csv.DictReader(fh):
            rows.append({
                "frame": int(row["frame"]), "time_s": float(row["time_s"]),
                "sharpness": float(row["sharpness"]), "saturated": float(row["saturated"]),
                "dark": float(row["dark"]),
                "motion_px": float(row["motion_px"]) if row["motion_px"] else None,
                "kept": row["kept"] == "True", "reason": row["reason"],
            })
    return rows
