"""Logging set-up for the Snakemake adapters in ``scripts/``: one log file per job."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


@contextlib.contextmanager
def log_to(path: str | os.PathLike[str] | None, level: int = logging.INFO) -> Iterator[logging.Logger]:
    """Send log records to ``path`` and stderr for the duration of one job.

    An exception escaping the block is written to the log with its traceback, then re-raised,
    so Snakemake marks the job failed and the log says why.
    """
    root = logging.getLogger()
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(path, mode="w"))
    old_level = root.level
    root.setLevel(level)
    for h in handlers:
        h.setFormatter(logging.Formatter(FORMAT))
        root.addHandler(h)
    log = logging.getLogger("cystomap")
    try:
        yield log
    except Exception as exc:
        log.error("%s: %s", type(exc).__name__, exc, exc_info=not _is_input_error(exc))
        raise
    finally:
        for h in handlers:
            root.removeHandler(h)
            h.close()
        root.setLevel(old_level)


def _is_input_error(exc: BaseException) -> bool:
    from cystomap.errors import CystomapError

    return isinstance(exc, CystomapError)
