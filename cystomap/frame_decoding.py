"""The one decoding pass of the ``frames`` stage (:mod:`cystomap.frames`), and the writing of
the kept frames when they were not written while decoding.

:func:`_decode_pass` decodes the video once in a worker thread: each frame's analysis grey goes
to a :class:`_GreyStore` file in the output's temporary directory, an even sample of them to
the probe, and, when writing a PNG costs less CPU than decoding a frame (measured on the first
frames) and every frame's PNG fits in half the free disk space, every frame as PNG (the dropped
ones are deleted after the selection). Otherwise :func:`_write_frames` decodes the kept frames
again.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

import cv2
import numpy as np

from cystomap.camera import Camera
from cystomap.errors import InputError, StageError
from cystomap.frame_scoring import (
    PROGRESS_EVERY_S,
    _new_probe,
    _Probe,
    _Sampler,
    analysis_size,
    to_analysis,
)
from cystomap.images import PNG_WRITE
from cystomap.parallel import ordered_map, prefetch
from cystomap.video import frame_time, open_video

if TYPE_CHECKING:
    from cystomap.frames import FramesConfig

log = logging.getLogger(__name__)

# frames decoded ahead of the main thread (in a worker thread)
_DECODE_AHEAD = 16
# the first frames are held and written as PNGs whatever it costs: the CPU time of writing them
# against that of decoding them decides whether the rest is (see _write_while_decoding)
_COST_FRAMES = 8


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
    if not cv2.imwrite(str(path), frame, PNG_WRITE):
        raise StageError(f"{path}: cannot write PNG")
    return time.thread_time() - c0


def _write_while_decoding(decode_s: float, png_s: float) -> bool:
    """Write every frame as PNG as it is decoded (and delete the dropped ones later) when that
    takes less time than decoding the video again for the kept ones (FFV1: a PNG 6 ms, a decode
    12 ms; mp4v: 5 ms against 0.3 ms)."""
    return png_s < decode_s


def _png_fits(out: Path, png_bytes: float, frame_count: int) -> bool:
    """Every frame's PNG (``png_bytes`` each, ``frame_count`` frames as the container says,
    unknown = 0) fits in half the disk space free at ``out``: a lossless 1080p recording of
    minutes would otherwise fill the disk with frames to be deleted."""
    if frame_count <= 0:
        return False
    return png_bytes * frame_count < 0.5 * shutil.disk_usage(out).free


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
                        png_bytes = float(np.mean([_png_path(out, i).stat().st_size
                                                   for i, _ in held]))
                        held.clear()
                        fits = _png_fits(out, png_bytes, info.frame_count)
                        write_now = fits and _write_while_decoding(decode_s, png_s)
                        log.info("frames: decoding a frame %.1f CPU-ms, writing it %.1f (%.2f MB"
                                 "%s): %s", 1e3 * decode_s, 1e3 * png_s, png_bytes / 1e6,
                                 "" if fits else ", not every frame's PNG fits on the disk",
                                 "writing every frame while decoding" if write_now
                                 else "decoding the kept frames again")
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
