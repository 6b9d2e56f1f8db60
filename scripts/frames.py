"""Snakemake adapter: select frames from one session's video."""

from pathlib import Path

from cystomap.frames import FramesConfig, extract_frames
from cystomap.logs import log_to
from cystomap.snakemake_io import camera_param, job_config

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    extract_frames(
        Path(sm.input.video),
        Path(sm.output.frames),
        job_config(FramesConfig, sm.params.frames, "frames", sm.threads),
        camera_param(sm.params.camera),
    )
