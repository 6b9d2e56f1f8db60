"""A second mapping with finer features when the first model is short, flagged or failed.

SIFT at ``max_image_size`` (640 px) is fast and, on most video, as good as full size. But
on some sessions the coarse features leave the model so sparse that the mapper cannot place
the next frame although every neighbouring pair is verified: held-out phantom seed 4
(1280x720 mp4v) gave three pieces of 47, 39 and 37 frames sharing one or two frames each, at
640 px only 16 of frame 24's 479 keypoints had a 3-D point, and the largest piece was 2.1 mm
off with a 55 % scale error. Joining the pieces afterwards did not work (a handful of matched
3-D points between them; one shared frame's pose drifted the rotation). Mapped again at
1280 px the same session gave 124 of 124 frames, 0.07 mm.

So when the first model holds fewer than ``retry_registered_share`` of the frames, a
self-check flags it (a flag of the rotation check alone only with ``retry_on_rotation_flag``:
on the phantom those flags were false and the second mapping did not help), or the mapping
fails, and the features were detected below the lit
field's size, the session is mapped again beside the output (``<out>.retry``) with
``max_image_size`` doubled; the better model is kept (:func:`better`) and quality.json's
``attempts`` lists both runs with their size, frames, flags and seconds. When the features
were at the lit field's full size already (640x360 video), a model short of frames or a
failed mapping is mapped again on the image doubled instead (``first_octave`` one finer,
guided matching), unless the plain-frame rule detected it so already: family-B phantom
sessions at 640x360 split into pieces of 66, 37 and 12 frames that way and map whole (log:
"Short models mapped again on the image doubled").

Which model is better: a model that maps is better than a failed one; of two that map, one
holding fewer than ``retry_registered_share`` of the other's frames loses them for certain,
while a self-check's flag is a warning (on held-out seed 4 the flagged 640-px glints model
held 113 frames at 0.46 mm, the unflagged 1280-px one 78 at 1.42 mm), so frames decide
first; between models of about the same size (each within that share of the other), the
one the self-checks pass, then the larger, then the first.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cystomap.errors import StageError
from cystomap.outputs import write_json
from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)

SUFFIX = ".retry"

#: one mapping of a session: (output directory, settings) -> quality.json's contents
Attempt = Callable[[Path, SfmConfig], dict[str, Any]]


@dataclasses.dataclass
class Run:
    """What one mapping gave: its quality figures or its error, and its cost."""

    max_image_size: int
    quality: dict[str, Any] | None
    error: StageError | None
    failed_dir: Path
    time_s: float
    cpu_s: float
    first_octave: int = 0  # SfmConfig.first_octave of the mapping

    @property
    def registered(self) -> int:
        if self.quality is not None:
            return int(self.quality.get("registered") or 0)
        try:  # a failed run lists what did reconstruct beside the outputs
            sizes = json.loads((self.failed_dir / "quality.json").read_text())["model_sizes"]
        except (OSError, ValueError, KeyError, TypeError):
            return 0
        return int(sizes[0]) if sizes else 0

    @property
    def doubled(self) -> bool:
        """Whether the features were detected on the image doubled (``first_octave`` -1, or
        the plain-frame rule: quality.json ``doubled_frames``)."""
        return self.first_octave < 0 or bool((self.quality or {}).get("doubled_frames"))

    @property
    def features(self) -> str:
        """The features' size in words (for the log)."""
        return f"{self.max_image_size} px" + (" on the image doubled" if self.doubled else "")

    @property
    def flagged(self) -> bool:
        c = (self.quality or {}).get("consistency")
        return isinstance(c, dict) and c.get("consistent") is False

    def record(self) -> dict[str, Any]:
        return {"max_image_size": self.max_image_size, "image_doubled": self.doubled,
                "registered": self.registered,
                "flagged": self.flagged, "failed": self.error is not None,
                "time_s": round(self.time_s, 3), "cpu_s": round(self.cpu_s, 3)}


def flagged_by(quality: dict[str, Any]) -> list[str]:
    """The self-checks that flagged a model: "halves", "rotation", or "other"."""
    c = quality.get("consistency")
    if not isinstance(c, dict) or c.get("consistent") is not False:
        return []
    halves, rotation = c.get("halves"), c.get("rotation")
    by = []
    if isinstance(halves, dict) and halves.get("consistent") is False:
        by.append("halves")
    if isinstance(rotation, dict) and rotation.get("flagged") is True:
        by.append("rotation")
    return by or ["other"]


def reason(run: Run, share: float, on_rotation_flag: bool = False) -> str | None:
    """Why ``run`` should be mapped again (None: it need not be). A flag of the rotation
    check alone counts only with ``on_rotation_flag`` (SfmConfig.retry_on_rotation_flag)."""
    if share <= 0:
        return None
    if run.error is not None:
        return f"the mapping failed ({str(run.error).split(';')[0]})"
    q = run.quality or {}
    if run.flagged:
        if on_rotation_flag or flagged_by(q) != ["rotation"]:
            return f"the self-check flagged the model ({q['consistency'].get('reason')})"
        log.info("sfm: only the rotation self-check flagged the model: that alone does not call "
                 "for a second mapping (sfm.retry_on_rotation_flag); the flag stays in "
                 "quality.json")
    n = mappable(q)
    if run.registered < share * n:
        return (f"only {run.registered} of the {n} frames with features are in the model (less "
                f"than retry_registered_share {share:g})")
    return None


#: dropped frames that no mapping can place, whatever its features' size: black or unreadable
UNMAPPABLE = ("too few features", "could not be read")


def mappable(quality: dict[str, Any]) -> int:
    """The frames a mapping could place: those given, less the black and unreadable ones
    (quality.json's ``dropped_reasons``; the frames stage drops them from a video, but a
    directory of frames may hold them)."""
    reasons = quality.get("dropped_reasons") or {}
    return int(quality.get("frames_in") or 0) - sum(int(reasons.get(r, 0)) for r in UNMAPPABLE)


def short_model(run: Run, share: float) -> dict[str, Any] | None:
    """quality.json's ``short_model`` when the model handed on holds fewer than ``share`` of
    the frames a mapping could place (None otherwise), and a warning in the log: the stage
    succeeds, but the wall only the other frames saw is missing from the mesh and atlas, and
    compare and the report name the session."""
    n = mappable(run.quality or {})
    if not (share > 0 and n and run.registered < share * n):
        return None
    log.warning("sfm: the model holds only %d of the %d frames with features (%.0f %%, under "
                "retry_registered_share %g): the wall that only the others saw is missing "
                "from the mesh and atlas; quality.json dropped_frames says why each is out",
                run.registered, n, 100.0 * run.registered / n, share)
    return {"registered": run.registered, "frames_with_features": n,
            "share": round(run.registered / n, 4), "retry_registered_share": share}


def better(new: Run, old: Run, share: float) -> bool:
    """Whether ``new`` should replace ``old`` (see the module: frames first, then the flags)."""
    if (new.error is None) != (old.error is None):
        return new.error is None
    if new.registered < share * old.registered:
        return False
    if old.registered < share * new.registered:
        return True
    return (not new.flagged, new.registered) > (not old.flagged, old.registered)


def finer(cfg: SfmConfig, working_scale: float, first: Run | None = None,
          share: float = 0.0) -> SfmConfig | None:
    """The settings of the second mapping: ``max_image_size`` doubled while the features were
    detected below the lit field's full size. At full size already, a model short of frames
    (under ``share`` of those with features) or a failed mapping is mapped again on the image
    doubled (``first_octave`` one finer, guided matching), unless ``first`` was detected so
    already (its quality.json ``doubled_frames``: the plain-frame rule): on a pale, plain wall
    at 640x360 the pieces a model splits into join when each frame has the fine detail the
    working size blurs away (log: "Short models mapped again on the image doubled"). None:
    there is nothing finer to try."""
    if cfg.max_image_size > 0 and working_scale < 1.0:
        return dataclasses.replace(cfg, max_image_size=2 * cfg.max_image_size)
    if first is None or first.doubled:
        return None
    if first.error is None and first.registered >= share * mappable(first.quality or {}):
        return None  # flagged only: a finer detection is no cure for that
    return dataclasses.replace(cfg, first_octave=cfg.first_octave - 1, guided_matching=True)


def _timed(attempt: Attempt, out: Path, cfg: SfmConfig, failed_dir: Path) -> Run:
    t, c = time.perf_counter(), time.process_time()
    quality, error = None, None
    try:
        quality = attempt(out, cfg)
    except StageError as exc:
        error = exc
    return Run(cfg.max_image_size, quality, error, failed_dir,
               time.perf_counter() - t, time.process_time() - c, cfg.first_octave)


def _replace(src: Path, dst: Path) -> None:
    """Move directory ``src`` onto ``dst`` (renames; ``dst``'s old content is removed last)."""
    old = dst.with_name(f".{dst.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    if dst.exists():
        dst.rename(old)
    src.rename(dst)
    shutil.rmtree(old, ignore_errors=True)


def map_with_retry(attempt: Attempt, out_dir: Path, cfg: SfmConfig, working_scale: float,
                   failed_dir: Callable[[Path], Path]) -> Path:
    """Run ``attempt`` into ``out_dir``; map again with finer features where :func:`reason`
    says so and :func:`finer` can; keep the better model in ``out_dir`` (see the module)."""
    first = _timed(attempt, out_dir, cfg, failed_dir(out_dir))
    why = reason(first, cfg.retry_registered_share, cfg.retry_on_rotation_flag)
    second_cfg = finer(cfg, working_scale, first, cfg.retry_registered_share) if why else None
    if second_cfg is None:
        if why:
            log.info("sfm: %s, and there are no finer features to try (the lit field's full "
                     "size%s): not mapped again", why,
                     ", on the image doubled" if first.doubled else "")
        if first.error is not None:
            raise first.error
        short = short_model(first, cfg.retry_registered_share)
        if short is not None:  # first.quality is what the attempt wrote
            write_json(out_dir / "quality.json", {**(first.quality or {}), "short_model": short})
        return out_dir
    log.warning("sfm: %s; mapping again with features at %d px%s (were %s)", why,
                second_cfg.max_image_size,
                " on the image doubled" if second_cfg.first_octave < 0 else "", first.features)
    retry_dir = out_dir.with_name(out_dir.name + SUFFIX)
    second = _timed(attempt, retry_dir, second_cfg, failed_dir(retry_dir))
    if second.error is not None:
        log.warning("sfm: the mapping at %s failed: %s", second.features, second.error)
    keep = second if better(second, first, cfg.retry_registered_share) else first
    runs = [first.record(), second.record()]
    if keep.error is not None:  # both failed: the second's pieces go beside the first's
        dest = failed_dir(out_dir) / "retry"
        if failed_dir(retry_dir).exists() and failed_dir(out_dir).exists():
            shutil.rmtree(dest, ignore_errors=True)
            failed_dir(retry_dir).rename(dest)
        msg = str(second.error).replace(str(failed_dir(retry_dir)), str(dest))
        raise StageError(f"{first.error}. Mapped again with features at "
                         f"{second.features}: {msg}")
    if keep is second:
        _replace(retry_dir, out_dir)
        shutil.rmtree(failed_dir(out_dir), ignore_errors=True)
    shutil.rmtree(retry_dir, ignore_errors=True)
    shutil.rmtree(failed_dir(retry_dir), ignore_errors=True)
    q = dict(keep.quality or {})
    q["attempts"] = {"kept": 1 if keep is second else 0, "reason": why, "runs": runs}
    for key in ("time_s", "cpu_s"):
        if isinstance(q.get(key), dict):
            q[key] = {**q[key], "attempts_total": round(sum(r[key] for r in runs), 3)}
    short = short_model(keep, cfg.retry_registered_share)
    if short is not None:
        q["short_model"] = short
    write_json(out_dir / "quality.json", q)
    other = first if keep is second else second
    log.info("sfm: kept the %s mapping (%d frames at %s; the other: %s at %s)",
             "second" if keep is second else "first", keep.registered, keep.features,
             "failed" if other.error is not None else f"{other.registered} frames",
             other.features)
    return out_dir
