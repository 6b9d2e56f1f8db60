# Shared set-up: config and sessions-sheet validation, wildcard constraints, target lists.
import re
import sys
from pathlib import Path

import pandas as pd
from snakemake.exceptions import WorkflowError
from snakemake.logging import logger
from snakemake.utils import validate

# The library is installed into .venv by `make setup`; this also finds it in a plain checkout.
REPO = Path(workflow.basedir).resolve()
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from cystomap.sessions import anatomy_overrides, phantom_sessions, read_sessions  # noqa: E402


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

def _local_cores():
    """--cores of a local run, None on a cluster executor or without --cores (a lint)."""
    if workflow.remote_exec or not workflow.local_exec:
        return None
    try:
        return int(workflow.cores)
    except WorkflowError:
        return None


# Threads a per-session job gets at most on a local run (config share_cores): --cores shared
# among the sessions, which then run side by side (the stages use a second core only in part,
# so sessions at one thread each finish sooner than one after the other at two). None: each
# job gets its stage's threads.
LOCAL_CORES = _local_cores()
SESSION_THREADS = (
    max(1, LOCAL_CORES // len(SESSIONS)) if config["share_cores"] and LOCAL_CORES else None
)
if SESSION_THREADS is not None and SESSION_THREADS < LOCAL_CORES:
    logger.info(
        f"cystomap: {len(SESSIONS)} sessions on {LOCAL_CORES} cores: each per-session job gets at "
        f"most {SESSION_THREADS} thread(s), so that sessions run side by side (share_cores: false "
        "turns this off)"
    )


def session_threads(threads):
    """Threads of a per-session job: its stage's ``threads``, at most SESSION_THREADS."""
    threads = max(1, int(threads))
    return threads if SESSION_THREADS is None else min(threads, SESSION_THREADS)


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


def session_anatomy(wildcards):
    """The sheet's overrides of the session's anatomical frame (entry_roll_deg, neck_xyz,
    anterior_xyz; None where empty)."""
    return anatomy_overrides(session_row(wildcards).to_dict())


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
    """Consecutive sessions of a subject, ordered by date, then the config's `comparisons:`
    for that subject: [(a, b), ...] without repeats."""
    rows = SESSIONS[SESSIONS["subject"] == subject].reset_index(drop=True).sort_values(["date", "session"])
    names = list(rows["session"])
    pairs = list(zip(names[:-1], names[1:]))
    for item in config["comparisons"]:
        if item["subject"] == subject and (item["a"], item["b"]) not in pairs:
            pairs.append((item["a"], item["b"]))
    return pairs


def _check_comparisons():
    """Each extra comparison names two different existing sessions of its subject."""
    for i, item in enumerate(config["comparisons"]):
        where = f"config comparisons[{i}] ({item['subject']}: {item['a']} vs {item['b']})"
        for key in ("a", "b"):
            if (item["subject"], item[key]) not in SESSIONS.index:
                raise ValueError(f"{where}: {key} = {item[key]!r} is not a session of subject "
                                 f"{item['subject']!r} (sessions sheet or phantom study)")
        if item["a"] == item["b"]:
            raise ValueError(f"{where}: a and b are the same session")
    for i, item in enumerate(config["landmarks"]):
        if (item["subject"], item["session"]) not in SESSIONS.index:
            raise ValueError(f"config landmarks[{i}] ({item['name']}): {item['subject']}/{item['session']} "
                             "is not a session (sessions sheet or phantom study)")


_check_comparisons()


def landmarks_of(subject, session):
    """The config's landmarks marked in one session: [{name, col, row} or {name, x, y, z}]."""
    return [{k: v for k, v in item.items() if k not in ("subject", "session")}
            for item in config["landmarks"] if item["subject"] == subject and item["session"] == session]


def comparison_inputs(wildcards):
    inputs = {}
    for key, session in (("a", wildcards.a), ("b", wildcards.b)):
        root = f"results/{wildcards.subject}/{session}"
        inputs |= {f"{key}_sfm": f"{root}/sfm", f"{key}_preprocessed": f"{root}/preprocessed",
                   f"{key}_mesh": f"{root}/mesh/surface.ply", f"{key}_atlas": f"{root}/atlas",
                   f"{key}_frames": f"{root}/frames"}
    return inputs


def report_sessions(subject):
    """The subject's sessions in date order, as [{"name", "date"}, ...] (the report's order)."""
    rows = SESSIONS[SESSIONS["subject"] == subject].reset_index(drop=True).sort_values(["date", "session"])
    return [{"name": str(r.session), "date": str(r.date)} for r in rows.itertuples()]


def report_inputs(wildcards):
    """Per session (in report_sessions order) its frames, sfm, mesh and atlas outputs; per
    comparison (comparison_pairs order) its compare directory; the phantom's evaluation."""
    root = f"results/{wildcards.subject}"
    names = [s["name"] for s in report_sessions(wildcards.subject)]
    inputs = {key: [f"{root}/{s}/{path}" for s in names]
              for key, path in (("frames", "frames"), ("sfm", "sfm"), ("mesh", "mesh/surface.ply"),
                                ("atlas", "atlas"))}
    inputs["compare"] = [f"{root}/compare/{a}_vs_{b}" for a, b in comparison_pairs(wildcards.subject)]
    if wildcards.subject in PHANTOM_SUBJECTS:
        inputs["evaluation"] = [f"{root}/evaluation.json"]
    return inputs


def all_targets():
    targets = []
    for subject, session in SESSIONS.index:
        targets.append(f"results/{subject}/{session}/atlas")
    for subject in SESSIONS["subject"].unique():
        targets += [f"results/{subject}/compare/{a}_vs_{b}" for a, b in comparison_pairs(subject)]
    targets += [f"results/{subject}/evaluation.json" for subject in PHANTOM_SUBJECTS]
    targets += [f"results/{subject}/report.html" for subject in SESSIONS["subject"].unique()]
    if config["report"]["pdf"]:  # needs headless Chromium (rule report_pdf)
        targets += [f"results/{subject}/report.pdf" for subject in SESSIONS["subject"].unique()]
    return targets
