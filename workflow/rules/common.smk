# Shared set-up: config and sessions-sheet validation, wildcard constraints, target lists.
import re
import sys
from pathlib import Path

import pandas as pd
from snakemake.utils import validate

# The library is installed into .venv by `make setup`; this also finds it in a plain checkout.
REPO = Path(workflow.basedir).resolve()
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from cystomap.sessions import phantom_sessions, read_sessions  # noqa: E402


validate(config, str(REPO / "workflow/schemas/config.schema.yaml"))

SESSIONS = pd.concat(
    [read_sessions(config, REPO / "workflow/schemas/sessions.schema.yaml"), phantom_sessions(config)],
    ignore_index=True,
)
if SESSIONS.empty:
    raise ValueError(
        "config: no sessions to run: name a sessions sheet with `sessions:` or set `phantom.enabled: true`"
    )
SESSIONS = SESSIONS.set_index(["subject", "session"], drop=False).sort_index()
if SESSIONS.index.duplicated().any():
    dup = SESSIONS.index[SESSIONS.index.duplicated()].unique().tolist()
    raise ValueError(f"sessions: duplicate (subject, session) rows: {dup}")

PHANTOM = config["phantom"]
PHANTOM_SUBJECTS = [PHANTOM["subject"]] if PHANTOM["enabled"] else []
CONDA_ENV = "../envs/cystomap.yaml"

# Outputs the phantom scorer reads, per session; each stage's issue adds its own here.
SCORED_OUTPUTS = {
    "sfm": "results/{subject}/{session}/sfm",
    "mesh": "results/{subject}/{session}/mesh/surface.ply",
    "atlas": "results/{subject}/{session}/atlas",
}


def _alternatives(values):
    return "|".join(sorted({re.escape(str(v)) for v in values}))


wildcard_constraints:
    subject=_alternatives(SESSIONS["subject"]),
    session=_alternatives(SESSIONS["session"]),
    a=_alternatives(SESSIONS["session"]),
    b=_alternatives(SESSIONS["session"]),


def session_row(wildcards):
    return SESSIONS.loc[(wildcards.subject, wildcards.session)]


def session_video(wildcards):
    return session_row(wildcards)["video"]


def session_camera(wildcards):
    """The camera entry (a dict) of the session's `camera` key, with its name."""
    name = session_row(wildcards)["camera"]
    return {"name": name, **config["cameras"][name]}


def session_scale(wildcards):
    """Known size of the session's bladder for metric scale (None when the sheet has none)."""
    row = session_row(wildcards)
    return {k: (None if pd.isna(row[k]) else float(row[k])) for k in ("extent_mm", "volume_ml")}


def phantom_camera():
    name = PHANTOM["camera"]
    return {"name": name, **config["cameras"].get(name, {})}


def phantom_session_names(subject):
    return [s for (subj, s) in SESSIONS.index if subj == subject]


def evaluation_inputs(wildcards):
    """Truth per session, plus every scored output that the workflow produces so far."""
    sessions = phantom_session_names(wildcards.subject)
    inputs = {"truth": [f"results/{wildcards.subject}/phantom/{s}/truth" for s in sessions]}
    for key, pattern in SCORED_OUTPUTS.items():
        inputs[key] = [pattern.format(subject=wildcards.subject, session=s) for s in sessions]
    pairs = comparison_pairs(wildcards.subject)
    inputs["changes"] = [f"results/{wildcards.subject}/compare/{a}_vs_{b}" for a, b in pairs]
    inputs["changes_sfm"] = [f"results/{wildcards.subject}/{b}/sfm" for a, b in pairs]
    inputs["changes_truth"] = [f"results/{wildcards.subject}/phantom/{b}/truth" for a, b in pairs]
    return inputs


def comparison_pairs(subject):
    """Consecutive sessions of a subject, ordered by date: [(a, b), ...]."""
    rows = SESSIONS[SESSIONS["subject"] == subject].reset_index(drop=True).sort_values(["date", "session"])
    names = list(rows["session"])
    return list(zip(names[:-1], names[1:]))


def comparison_inputs(wildcards):
    inputs = {}
    for key, session in (("a", wildcards.a), ("b", wildcards.b)):
        root = f"results/{wildcards.subject}/{session}"
        inputs |= {f"{key}_sfm": f"{root}/sfm", f"{key}_preprocessed": f"{root}/preprocessed",
                   f"{key}_mesh": f"{root}/mesh/surface.ply", f"{key}_atlas": f"{root}/atlas"}
    return inputs


def all_targets():
    targets = []
    for subject, session in SESSIONS.index:
        targets.append(f"results/{subject}/{session}/atlas")
    for subject in SESSIONS["subject"].unique():
        targets += [f"results/{subject}/compare/{a}_vs_{b}" for a, b in comparison_pairs(subject)]
    targets += [f"results/{subject}/evaluation.json" for subject in PHANTOM_SUBJECTS]
    return targets
