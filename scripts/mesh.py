"""Snakemake adapter: closed surface mesh of one session."""

from pathlib import Path

from cystomap.logs import log_to
from cystomap.mesh import MeshConfig, build_mesh
from cystomap.settings import from_mapping

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    build_mesh(Path(sm.input.sfm), Path(sm.output.ply).parent, from_mapping(MeshConfig, sm.params.mesh, "mesh"))
