"""Snakemake adapter: undistort, mask, level and enhance one session's frames."""

from pathlib import Path

from cystomap.logs import log_to
from cystomap.preprocess import PreprocessConfig, preprocess_frames
from cystomap.settings import from_mapping
from cystomap.snakemake_io import camera_param, with_threads

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    preprocess_frames(
        Path(sm.input.frames),
        Path(sm.output.preprocessed),
        camera_param(sm.params.camera),
        from_mapping(PreprocessConfig, with_threads(sm.params.preprocess, "threads", sm.threads), "preprocess"),
    )
