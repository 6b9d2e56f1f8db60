"""Snakemake adapter: score a phantom subject's outputs against the ground truth."""

from pathlib import Path

from cystomap.evaluate import EvalConfig, comparisons_from_lists, evaluate_subject, sessions_from_lists
from cystomap.logs import log_to
from cystomap.settings import from_mapping

sm = snakemake  # type: ignore[name-defined]  # noqa: F821
with log_to(sm.log[0]):
    inputs = dict(sm.input.items())
    sessions = sessions_from_lists(
        sm.params.sessions,
        inputs["truth"],
        sfm=inputs.get("sfm"),
        meshes=inputs.get("mesh"),
        atlases=inputs.get("atlas"),
    )
    comparisons = comparisons_from_lists(
        [Path(p).name for p in inputs.get("changes", [])],
        inputs.get("changes_truth", []),
        inputs.get("changes_sfm", []),
        [str(Path(p) / "changes.csv") for p in inputs.get("changes", [])],
    )
    cfg = from_mapping(EvalConfig, sm.params.evaluate, "evaluate")
    evaluate_subject(Path(sm.output.json).parent, sessions, comparisons, cfg)
