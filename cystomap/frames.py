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
gap; the video's last good frame (the end of the sweep, which no later frame shows) is kept
when it moved at least half ``min_motion`` since the last kept frame. ``max_frames`` raises
the spacing until the selection fits, so kept frames still cover the whole video.

The video is decoded once, streaming, in a worker thread: each frame is reduced to its
analysis grey, which goes to a file in the output's temporary directory (a few hundred bytes of
memory per frame, 127 kB of disk at 480x270) and, every so many frames, into an even sample for
the probe of the FOV, static overlays and brightness (the sample is halved whenever it grows to
twice ``probe_samples``: the same frames as if the length were known). Scoring needs that probe,
so it runs on the stored greys after the decoding (each frame measured in a worker thread while
the previous one is tracked). The full-resolution frames are needed only for the kept ones,
known at the end: when writing a PNG costs less CPU than decoding a frame (measured on the
first frames; FFV1 at 640x360: 6 ms against 12 ms) and every frame's PNG fits in half the
free disk space, every frame is written as PNG while decoding and the dropped ones are
deleted; otherwise (mp4v, H.264: decoding is cheap) the kept frames are decoded again (up to
the last kept one, the others skipped without colour conversion, PNGs written by ``threads``
threads). Both give the same files.

Outputs in ``out_dir`` (written atomically): ``f000123.png`` per kept frame (0-based index of the
frame in the video, BGR as decoded), ``frames.csv`` with one row per decoded frame
(``frame,time_s,sharpness,saturated,dark,motion_px,kept,reason``; ``kept`` is True/False;
``reason`` one of kept, outside_range, dark, overexposed, blurred, untracked, redundant,
over_limit; ``motion_px`` is relative to the last kept frame before it, empty when unknown), and
``frames.json`` (derived thresholds, FOV and static-overlay shares, counts, settings, timing).

This module holds the settings, the stage and its outputs; the passes are in
:mod:`cystomap.frame_decoding` (the decoding pass, writing again),
:mod:`cystomap.frame_scoring` (probe, scores), :mod:`cystomap.frame_tracking` (motion) and
:mod:`cystomap.frame_selection` (verdicts, selection).
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from cystomap.camera import Camera
from cystomap.errors import InputError
from cystomap.frame_decoding import _decode_pass, _png_path, _write_frames
from cystomap.frame_scoring import (
    _finish_probe,
    _score,
    _Scores,
)
from cystomap.frame_selection import _select, _Selection
from cystomap.frame_tracking import _MIN_TRACK_POINTS
from cystomap.outputs import atomic_dir, software_versions, write_json
from cystomap.settings import setting, validate

log = logging.getLogger(__name__)

CSV_COLUMNS = ("frame", "time_s", "sharpness", "saturated", "dark", "motion_px", "kept", "reason")
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
    # (median displacement of FOV points): of a pause only the first frame is kept. The
    # video's last good frame is kept too when it moved half this since the last kept frame.
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
