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
the diagonal of the FOV's bounding box (a round scope image in a wide frame moves by the size
of what it shows, not of the frame). Frames are kept greedily: a good frame is kept when the scene moved at
least ``min_motion`` since the last kept frame; a sharper frame among the next ``lookahead``
may be taken instead only while the motion stays within twice ``min_motion``, and after a jump
(dropped frames, a tracking break) the last frame before it is kept too when that splits the
gap. ``max_frames`` raises the spacing until the selection fits, so kept frames still cover
the whole video.

The video is decoded once, streaming, in a worker thread: each frame is reduced to its
analysis grey, which goes to a file in the output's temporary directory (a few hundred bytes of
memory per frame, 127 kB of disk at 480x270) and, every so many frames, into an even sample for
the probe of the FOV, static overlays and brightness (the sample is halved whenever it grows to
twice ``probe_samples``: the same frames as if the length were known). Scoring needs that probe,
so it runs on the stored greys after the decoding (each frame measured in a worker thread while
the previous one is tracked). The full-resolution frames are needed only for the kept ones,
known at the end: when writing a PNG costs less CPU than decoding a frame (measured on the
first frames; FFV1 at 640x360: 6 ms against 12 ms), every frame is written as PNG while
decoding and the dropped ones are deleted; otherwise (mp4v, H.264: decoding is cheap) the kept
frames are decoded again (up to the last kept one, the others skipped without colour
conversion, PNGs written by ``threads`` threads). Both give the same files.

Outputs in ``out_dir`` (written atomically): ``f000123.png`` per kept frame (0-based index of the
frame in the video, BGR as decoded), ``frames.csv`` with one row per decoded frame
(``frame,time_s,sharpness,saturated,dark,motion_px,kept,reason``; ``kept`` is True/False;
``reason`` one of kept, outside_range, dark, overexposed, blurred, untracked, redundant,
over_limit; ``motion_px`` is relative to the last kept frame before it, empty when unknown), and
``frames.json`` (derived thresholds, FOV and static-overlay shares, counts, settings, timing).

This module holds the settings, the stage and its outputs; the passes are in
:mod:`cystomap.frame_scoring` (probe, scores), :mod:`cystomap.frame_tracking` (motion) and
:mod:`cystomap.frame_selection` (verdicts, selection).
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, BinaryIO

import cv2
import numpy as np

from cystomap.camera import Camera
from cystomap.errors import InputError, StageError
from cystomap.frame_scoring import (
    PROGRESS_EVERY_S,
    _finish_probe,
    _new_probe,
    _Probe,
    _Sampler,
    _score,
    _Scores,
    analysis_size,
    to_analysis,
)
from cystomap.frame_selection import _select, _Selection
from cystomap.frame_tracking import _MIN_TRACK_POINTS
from cystomap.outputs import atomic_dir, software_versions, write_json
from cystomap.parallel import ordered_map, prefetch
from cystomap.settings import setting, validate
from cystomap.video import frame_time, open_video

log = logging.getLogger(__name__)

CSV_COLUMNS = ("frame", "time_s", "sharpness", "saturated", "dark", "motion_px", "kept", "reason")
# frames decoded ahead of the main thread (in a worker thread)
_DECODE_AHEAD = 16
# the first frames are held and written as PNGs whatever it costs: the CPU time of writing them
# against that of decoding them decides whether the rest is (see _write_while_decoding)
_COST_FRAMES = 8
REASONS = ("kept", "outside_range", "dark", "overexposed", "blurred", "untracked", "redundant",
           "over_limit")


@dataclass(frozen=True)
class FramesConfig:
    """Settings of the ``frames`` stage (config section ``frames``)."""

    # Frames are scored on a grey copy downscaled to this width in pixels (never upscaled).
    analysis_width: int = setting(480, ">= 32")
    # Field of view scored: "auto" = detect the lit area (black endoscope borders and overlaid
    # text excluded), "full" = the whole frame.
    fov: str = setting("auto", choices=("auto", "full"))
    # Shrink the detected FOV by this many analysis pixels (drops the rim, its vignetting and
    # the compression ringing along it).
    fov_erode_px: int = setting(6, ">= 0")
    # FOV pixels whose temporal std over the sampled frames is below static_rel times the
    # typical one (overlaid text, lens dirt) are not scored nor tracked (0 = keep them); not
    # applied when over 10% of the FOV is static (a still camera).
    static_rel: float = setting(0.25, "[0, 1)")
    # Sharpness is measured on the analysis image smoothed by a Gaussian of this sigma (pixels):
    # a Laplacian-of-Gaussian band, so sensor noise and compression artefacts count less.
    sharpness_sigma: float = setting(1.5, ">= 0")
    # Frames sampled evenly through the video to detect the FOV and the typical brightness.
    probe_samples: int = setting(64, ">= 1")
    # A pixel is saturated at or above this grey level (8-bit clipping; glints, overexposure).
    saturation_level: int = setting(250, "(0, 255]")
    # A pixel is dark below dark_rel times the video's typical brightness (75th percentile of
    # the sampled frames' mean FOV brightness) ...
    dark_rel: float = setting(0.25, "[0, 1)")
    # ... and always below this grey level (black whatever the video).
    black_level: int = setting(12, "[0, 255)")
    # Drop a frame as "dark" when more than this share of its FOV is dark.
    max_dark: float = setting(0.6, "(0, 1]")
    # Drop a frame as "overexposed" when more than this share of its FOV is saturated.
    max_saturated: float = setting(0.3, "(0, 1]")
    # Drop a frame as "blurred" when its sharpness is below blur_rel times the local reference:
    # the blur_percentile of the sharpness of well-exposed frames of its tracking segment within
    # ±blur_window_s, all compared on the scene content they share (see the module docstring).
    blur_rel: float = setting(0.4, "[0, 1)")
    # Half-width in seconds of the window of the local sharpness reference (and how far back
    # frames are compared).
    blur_window_s: float = setting(2.0, "> 0")
    # Percentile of sharpness in the window used as the local reference ("sharp frames here").
    blur_percentile: float = setting(75.0, "(0, 100]")
    # Also "blurred" below this times the blur_percentile of the sharpness of its whole tracking
    # segment (long blurred stretches).
    blur_global_rel: float = setting(0.2, "[0, 1)")
    # A frame that could not be compared with any overlapping frame (tracking failed before and
    # after it) is "blurred" below this times the median raw sharpness of the two well-exposed
    # frames on each side (lower than blur_rel: their content differs).
    blur_unmatched_rel: float = setting(0.15, "[0, 1)")
    # Target spacing: a good frame is "redundant" until the scene moved by this fraction of the
    # diagonal of the FOV's bounding box (the image's with fov "full") since the last kept frame
    # (median displacement of FOV points): of a pause only the first frame is kept.
    min_motion: float = setting(0.03, ">= 0")
    # Minimum distance between kept frames, in frames (1 = no constraint).
    min_gap: int = setting(1, ">= 1")
    # Once min_motion (> 0) is reached at frame i, keep the sharpest eligible frame among
    # i .. i + lookahead whose motion since the last kept frame stays within twice min_motion
    # (0 = keep the first frame that moved enough).
    lookahead: int = setting(2, ">= 0")
    # Keep at most this many frames (0 = no limit). If more qualify, the spacing is raised until
    # they fit; frames lost that way are marked "over_limit".
    max_frames: int = setting(0, ">= 0")
    # A frame that cannot be tracked starts a new segment (and is kept if good); for this many
    # frames after such a break, tracking first tries the frame before it again (so a bad frame
    # or two in between does not split a segment).
    max_track_gap: int = setting(5, ">= 1")
    # Corners tracked between consecutive frames.
    track_points: int = setting(200, f">= {_MIN_TRACK_POINTS}")
    # Only frames with start_s <= time < end_s are considered (end_s 0 = to the end).
    start_s: float = setting(0.0, ">= 0")
    end_s: float = setting(0.0, ">= 0")
    # Threads writing PNGs.
    threads: int = setting(2, ">= 1")

    def __post_init__(self) -> None:
        extra = {"end_s 0 or > start_s": self.end_s == 0 or self.end_s > self.start_s}
        try:
            validate(self, "frames", extra)
        except ValueError as exc:
            raise InputError(str(exc)) from exc


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
    with atomic_dir(out_dir) as tmp:
        dec = _decode_pass(video, cfg, camera, tmp)
        t_decode = time.perf_counter()
        probe = _finish_probe(video, dec.probe, dec.samples, cfg)
        t_probe = time.perf_counter()
        n = len(dec.times)
        log.info("frames: %s: %dx%d, %.3g fps, %d frames decoded in %.1f s, FOV %.0f%% of the "
                 "frame, typical brightness %.0f", video.name, probe.width, probe.height,
                 probe.fps, n, t_decode - t0, 100 * probe.fov_share, probe.brightness)
        try:
            scores = _score(dec.greys.frames(dec.times), cfg, probe)
        finally:
            dec.greys.remove()
        t_score = time.perf_counter()
        sel = _select(scores, cfg, probe)
        t_select = time.perf_counter()
        counts = Counter(sel.reason)
        log.info("frames: %d decoded, %d kept (%s), motion threshold %.1f px",
                 n, len(sel.kept), ", ".join(f"{k} {v}" for k, v in sorted(counts.items())),
                 sel.threshold_px)
        if not sel.kept:
            detail = ", ".join(f"{v} {k}" for k, v in sorted(counts.items()))
            raise InputError(f"{video}: no usable frame among {n} decoded ({detail})")
        kept = set(sel.kept)
        for index in dec.written - kept:
            _png_path(tmp, index).unlink()
        missing = sorted(kept - dec.written)
        if missing:  # writing while decoding was dearer than decoding again
            _write_frames(video, tmp, missing, n, cfg.threads)
        t_write = time.perf_counter()
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
                "fov_diagonal_px": round(probe.fov_diagonal, 2),
                "min_motion_px": round(sel.base_threshold_px, 2),
                "motion_threshold_px": round(sel.threshold_px, 2),
            },
            "segments": int(scores.segment.max() + 1) if n else 0,
            "settings": asdict(cfg),
            "elapsed_s": round(time.perf_counter() - t0, 3),
            "timing": {
                "decode_s": round(t_decode - t0, 3), "probe_s": round(t_probe - t_decode, 3),
                "score_s": round(t_score - t_probe, 3), "select_s": round(t_select - t_score, 3),
                "write_s": round(t_write - t_select, 3),
                "decoder_s": round(dec.decoder_s, 3),
                "written_while_decoding": len(dec.written),
                "decoded_again": len(missing),
                "scored_fps": round(n / max(t_score - t_probe, 1e-9), 1),
                "decoded_fps": round(n / max(time.perf_counter() - t0, 1e-9), 1),
            },
        })
    elapsed = time.perf_counter() - t0
    log.info("frames: wrote %d frames to %s in %.1f s (%.0f frames decoded per second; "
             "decoding %.1f s, scoring %.1f s, writing %.1f s; %d PNGs written while decoding, "
             "%d frames decoded again)", len(sel.kept), out_dir, elapsed,
             n / max(elapsed, 1e-9), t_decode - t0, t_score - t_probe, t_write - t_select,
             len(dec.written), len(missing))
    return out_dir


# --------------------------------------------------------------------------- the decoding


class _GreyStore:
    """The analysis greys of every frame, in order, in a file (so memory does not grow with
    the video), read back in order."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fh: BinaryIO | None = path.open("wb")
        self.shape: tuple[int, int] | None = None
        self.count = 0

    def append(self, grey: np.ndarray) -> None:
        if self._fh is None:
            raise ValueError("grey store closed")
        self.shape = grey.shape[:2]
        self._fh.write(np.ascontiguousarray(grey, dtype=np.uint8).data)
        self.count += 1

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def frames(self, times: list[float]) -> Iterator[tuple[int, float, np.ndarray]]:
        """``(index, time_s, grey)`` of every stored frame."""
        self.close()
        if not self.count or self.shape is None:
            return
        with self.path.open("rb") as fh:
            for index in range(self.count):
                grey = np.empty(self.shape, np.uint8)
                if fh.readinto(memoryview(grey).cast("B")) != grey.nbytes:
                    raise StageError(f"{self.path}: analysis greys cut short at frame {index}")
                yield index, times[index], grey

    def remove(self) -> None:
        self.close()
        self.path.unlink(missing_ok=True)


@dataclass
class _Decoded:
    probe: _Probe  # frame geometry only (see _finish_probe)
    samples: list[np.ndarray]
    times: list[float]
    greys: _GreyStore
    written: set[int]  # frames already written as PNGs
    decoder_s: float  # seconds spent in the decoder


def _png_path(out: Path, index: int) -> Path:
    return out / f"f{index:06d}.png"


def _save_png(out: Path, index: int, frame: np.ndarray) -> float:
    """Write frame ``index`` as PNG; returns the CPU seconds it took."""
    c0 = time.thread_time()
    path = _png_path(out, index)
    if not cv2.imwrite(str(path), frame):
        raise StageError(f"{path}: cannot write PNG")
    return time.thread_time() - c0


def _write_while_decoding(decode_s: float, png_s: float) -> bool:
    """Write every frame as PNG as it is decoded (and delete the dropped ones later) when that
    takes less time than decoding the video again for the kept ones (FFV1: a PNG 6 ms, a decode
    12 ms; mp4v: 5 ms against 0.3 ms)."""
    return png_s < decode_s


def _decode_pass(video: Path, cfg: FramesConfig, camera: Camera | None, out: Path) -> _Decoded:
    """Decode the video once: the analysis grey of every frame into a store in ``out``, an even
    sample of them for the probe, and (when cheaper than decoding again) every frame as PNG."""
    cap, info = open_video(video)
    decoder_s = [0.0]

    def decoded() -> Iterator[tuple[int, float, np.ndarray, np.ndarray]]:
        """(index, time_s, bgr, analysis grey), in the worker thread."""
        size: tuple[int, int] | None = None
        index = 0
        try:
            while True:
                c0 = time.perf_counter()
                ok, frame = cap.read()
                decoder_s[0] += time.perf_counter() - c0
                if not ok or frame is None:
                    break
                if size is None:
                    size = analysis_size(frame.shape[1], frame.shape[0], cfg)
                yield index, frame_time(cap, index, info.fps), frame, to_analysis(frame, size)
                index += 1
        finally:
            cap.release()

    probe: _Probe | None = None
    sampler = _Sampler(cfg.probe_samples)
    times: list[float] = []
    written: set[int] = set()
    held: list[tuple[int, np.ndarray]] = []
    cpu_start = 0.0
    write_now: bool | None = None  # decided once the first frames were written
    greys = _GreyStore(out / ".greys.u8")
    t0 = last_log = time.perf_counter()
    try:
        with ThreadPoolExecutor(max_workers=cfg.threads) as pool:
            pending: deque[Future[float]] = deque()
            try:
                for index, time_s, frame, grey in prefetch(decoded(), _DECODE_AHEAD):
                    if probe is None:
                        probe = _new_probe(video, frame, info.fps, cfg, camera)
                    elif (frame.shape[1], frame.shape[0]) != (probe.width, probe.height):
                        raise InputError(f"{video}: frame {index} is {frame.shape[1]}x"
                                         f"{frame.shape[0]}, frame 0 was {probe.width}x"
                                         f"{probe.height}")
                    greys.append(grey)
                    sampler.add(index, grey)
                    times.append(time_s)
                    if write_now is None:
                        # the first frames are held: the CPU time of decoding them (frame 0
                        # opens the decoder) against that of writing them decides
                        held.append((index, frame))
                        if index == 1:
                            cpu_start = time.process_time()
                        if index < _COST_FRAMES:
                            continue
                        decode_s = (time.process_time() - cpu_start) / (_COST_FRAMES - 1)
                        png_s = float(np.median(list(pool.map(
                            lambda item: _save_png(out, *item), held))[1:]))
                        written.update(i for i, _ in held)
                        held.clear()
                        write_now = _write_while_decoding(decode_s, png_s)
                        log.info("frames: decoding a frame %.1f CPU-ms, writing it %.1f: %s",
                                 1e3 * decode_s, 1e3 * png_s, "writing every frame while "
                                 "decoding" if write_now else "decoding the kept frames again")
                    elif write_now:
                        pending.append(pool.submit(_save_png, out, index, frame))
                        written.add(index)
                        while len(pending) > 2 * cfg.threads:
                            pending.popleft().result()
                    now = time.perf_counter()
                    if now - last_log > PROGRESS_EVERY_S:
                        last_log = now
                        log.info("frames: decoded %d frames (%.0f fps), %.1f s", index + 1,
                                 (index + 1) / (now - t0), now - t0)
                for f in pending:
                    f.result()
                for index, frame in held:  # a video of a few frames
                    _save_png(out, index, frame)
                    written.add(index)
            finally:
                for f in pending:
                    f.cancel()
    except BaseException:
        greys.remove()
        raise
    greys.close()
    if probe is None:
        greys.remove()
        raise InputError(f"{video}: no decodable frame (not a video, or corrupt)")
    return _Decoded(probe, sampler.samples, times, greys, written, decoder_s[0])


# --------------------------------------------------------------------------- writing again


def _write_frames(video: Path, out: Path, kept: list[int], n_expected: int, threads: int) -> None:
    """Decode the video again up to the last of ``kept`` and write those frames as PNGs."""
    wanted = set(kept)
    cap, _ = open_video(video)
    t0 = last_log = time.perf_counter()
    written = 0

    def save(item: tuple[int, np.ndarray]) -> None:
        _save_png(out, *item)

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
