"""Timing of a recording-like phantom session (``phantom.trajectory: recording``).

A urologist does not sweep the bladder at constant speed: the scope is moved slowly over the
wall, held still on a spot for a second or more, taken back over the stretch just seen, and
bent fast from one region to the next. :func:`recording_timing` turns the session's path
(:mod:`cystomap.phantom.trajectory`) into such a timing: stretches of slow scan
(``SCAN_S`` seconds each) alternate with events drawn in a seeded random order, each of the
three once per round:

* ``pause``: the scope held still for ``PAUSE_S`` seconds (only the hand tremor moves it);
* ``bend``: ``BEND_S`` seconds at ``BEND_SPEED`` times the scan speed (motion blur, with
  ``phantom.motion_blur_px`` > 0, is proportional to the image speed, so it falls here);
* ``back``: ``RETURN_S`` seconds back along the path at ``RETURN_SPEED`` times the scan speed;
  the scan then resumes over the wall just seen (a return to sites already seen).

The scan speed is whatever makes the whole path (entry, dome, side wall, neck, return, exit)
fit in the recording, so a longer recording is a slower scan of the same bladder. Speed
changes are smoothed over ``SMOOTH_S`` (the scope accelerates); pauses stay still. A hand
tremor (``TREMOR_DEG`` rms, smooth over ``TREMOR_S``) is added to every frame's rotation; it is
part of the ground-truth poses.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

log = logging.getLogger(__name__)

EVENTS = ("pause", "bend", "back")
SCAN_S = (3.0, 7.0)
PAUSE_S = (1.2, 3.0)
BEND_S = (0.4, 0.9)
BEND_SPEED = 3.0
RETURN_S = (0.6, 1.5)
RETURN_SPEED = -2.0
SMOOTH_S = 0.12
TREMOR_DEG = 0.05
TREMOR_S = 0.25
# no event starts within this many seconds of the end (the recording ends on the scan)
END_SCAN_S = 2.0


def _segments(duration: float, g: np.random.Generator) -> list[tuple[str, float, float]]:
    """(label, seconds, speed relative to the scan) from the start to past ``duration``."""
    segs: list[tuple[str, float, float]] = []
    order: list[str] = []
    t = 0.0
    while t < duration:
        d = float(g.uniform(*SCAN_S))
        segs.append(("scan", d, 1.0))
        t += d
        if not order:
            order = [str(e) for e in g.permutation(EVENTS)]
        event = order.pop()
        if event == "pause":
            seg = ("pause", float(g.uniform(*PAUSE_S)), 0.0)
        elif event == "bend":
            seg = ("bend", float(g.uniform(*BEND_S)), BEND_SPEED)
        else:
            seg = ("back", float(g.uniform(*RETURN_S)), RETURN_SPEED)
        if t + seg[1] + END_SCAN_S >= duration:
            order.append(event)
            continue
        segs.append(seg)
        t += seg[1]
    return segs


def recording_timing(n: int, fps: float, g: np.random.Generator) -> tuple[np.ndarray, list[str]]:
    """Position along the path (share of its length, in [0, 1]) and motion label of each of
    ``n`` frames at ``fps``."""
    duration = n / fps
    segs = _segments(duration, g)
    ends = np.cumsum([s[1] for s in segs])
    t = np.arange(n) / fps
    which = np.searchsorted(ends, t, side="right").clip(0, len(segs) - 1)
    labels = [segs[k][0] for k in which]
    speed = np.array([segs[k][2] for k in which], np.float64)
    speed = gaussian_filter1d(speed, max(SMOOTH_S * fps, 1e-3), mode="nearest")
    pause = np.array([lab == "pause" for lab in labels])
    speed[pause] = 0.0
    pos = np.r_[0.0, np.cumsum(speed[1:])]
    top = float(pos.max())
    if top <= 0:
        raise ValueError(f"recording of {n} frames at {fps} fps never moves forward")
    share = np.clip(pos / top, 0.0, 1.0)
    counts = {e: sum(1 for s in segs if s[0] == e and s[1] > 0) for e in ("scan", *EVENTS)}
    log.info("recording timing: %.1f s, %d frames: %s; %.0f %% of the frames paused", duration,
             n, ", ".join(f"{v} {k}" for k, v in counts.items()), 100 * pause.mean())
    return share, labels


def with_tremor(rotations: np.ndarray, fps: float, g: np.random.Generator) -> np.ndarray:
    """``rotations`` (camera-to-world) turned by a smooth hand tremor about the camera axes."""
    n = len(rotations)
    sigma = max(TREMOR_S * fps, 1e-3)
    noise = gaussian_filter1d(g.normal(size=(n, 3)), sigma, axis=0, mode="nearest")
    rms = float(np.sqrt(np.mean(np.square(noise)))) or 1.0
    angles = np.radians(TREMOR_DEG) * noise / rms
    return np.einsum("nij,njk->nik", rotations, Rotation.from_rotvec(angles).as_matrix())
