"""Benchmark: render a full-size phantom session (issue target: 124 frames, 1280x720, <= 60 s)."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Any

from cystomap.bench.common import timed
from cystomap.phantom import PhantomConfig, default_camera, generate_session

log = logging.getLogger(__name__)


def bench_phantom(work: Path, repeats: int = 3, n_frames: int = 124, seed: int = 7) -> list[dict[str, Any]]:
    """Render session 1 ``repeats`` times (and session 2 once); return table rows."""
    camera = default_camera(1280, 720)
    cfg = PhantomConfig(seed=seed, n_frames=n_frames)
    rows = []
    for session, reps in ((1, repeats), (2, 1)):
        out = work / f"phantom_s{session}"

        def run(i: int, session: int = session, out: Path = out) -> Path:
            shutil.rmtree(out, ignore_errors=True)
            log.info("rendering phantom session %d (run %d)", session, i + 1)
            return generate_session(out, session, cfg, camera)

        timing, out_dir = timed(f"phantom session {session} ({n_frames} frames, 1280x720)", run, reps)
        truth = json.loads((Path(out_dir) / "truth.json").read_text())
        timing.extra = {"target_s": 60, "meets_target": timing.median <= 60,
                        "seen_fraction": round(truth["seen_fraction"], 4), "extent_mm": round(truth["extent_mm"], 1)}
        rows.append(timing.row())
    return rows
