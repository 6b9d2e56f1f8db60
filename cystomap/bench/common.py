"""Timing and table helpers shared by the benchmarks."""

from __future__ import annotations

import os
import platform
import resource
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd


@dataclass
class Timing:
    """Wall-clock seconds of repeated runs of one step."""

    name: str
    seconds: list[float] = field(default_factory=list)
    cpu_seconds: list[float] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def median(self) -> float:
        return statistics.median(self.seconds)

    def row(self) -> dict[str, Any]:
        return {"step": self.name, "median_s": round(self.median, 2), "min_s": round(min(self.seconds), 2),
                "max_s": round(max(self.seconds), 2), "median_cpu_s": round(statistics.median(self.cpu_seconds), 2),
                "runs": len(self.seconds), **self.extra}


def timed(name: str, fn: Callable[[int], Any], repeats: int) -> tuple[Timing, Any]:
    """Run ``fn(i)`` ``repeats`` times; return the timing and the last result."""
    timing, result = Timing(name), None
    for i in range(repeats):
        t0, c0 = time.perf_counter(), _cpu()
        result = fn(i)
        timing.seconds.append(time.perf_counter() - t0)
        timing.cpu_seconds.append(_cpu() - c0)
    return timing, result


def _cpu() -> float:
    """CPU seconds of this process and its waited-for children (user + system)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def machine() -> dict[str, Any]:
    load = os.getloadavg()
    return {"cores": os.cpu_count(), "load_1min": round(load[0], 2), "python": platform.python_version(),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}


def write_table(rows: list[dict[str, Any]], out: Path, name: str, title: str) -> pd.DataFrame:
    """Write ``name.tsv`` and ``name.md`` under ``out``; return the frame."""
    out.mkdir(parents=True, exist_ok=True)
    df = pd.DataFrame(rows)
    df.to_csv(out / f"{name}.tsv", sep="\t", index=False)
    info = ", ".join(f"{k} {v}" for k, v in machine().items())
    (out / f"{name}.md").write_text(f"# {title}\n\n{df.to_markdown(index=False)}\n\nMachine: {info}\n")
    return df
