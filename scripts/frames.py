"""Snakemake adapter: select frames from one session's video."""

from pathlib import Path

from cystomap.frames import FramesConfig, extract_frames
from cystomap.logs import log_to
from cystomap.settings import from_mapping
from cystomap.snakemake_io import camera_param, with_threads

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    extract_frames(
        Path(sm.input.video),
        Path(sm.output.frames),
        from_mapping(FramesConfig, with_threads(sm.params.frames, "threads", sm.threads), "frames"),
        camera_param(sm.params.camera),
    )
