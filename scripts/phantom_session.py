"""Snakemake adapter: render one phantom session (video + ground truth)."""

import os
from pathlib import Path

from cystomap.logs import log_to
from cystomap.phantom import PhantomConfig, generate_session
from cystomap.sessions import PHANTOM_SESSIONS, phantom_settings
from cystomap.settings import from_mapping
from cystomap.snakemake_io import camera_param, with_threads

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    camera = camera_param(sm.params.camera)
    cfg = from_mapping(PhantomConfig, with_threads(phantom_settings(sm.params.phantom), "threads", sm.threads),
                       "phantom")
    truth = Path(sm.output.truth)
    generate_session(truth, PHANTOM_SESSIONS[sm.wildcards.session][1], cfg, camera)
    os.replace(truth / "video.mp4", sm.output.video)
