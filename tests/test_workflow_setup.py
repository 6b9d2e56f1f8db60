"""Workflow set-up, checked without running a job: the default profile is found by a plain
``snakemake``, and each rule's ``threads`` come from the stage's threads key and reach it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from snakemake.cli import parse_args

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("where", ["repository", "elsewhere"])
def test_plain_snakemake_uses_the_default_profile(where, monkeypatch, capsys, tmp_path) -> None:
    if where == "repository":
        monkeypatch.chdir(REPO)
        argv = ["--cores", "2"]  # `snakemake --cores 2` in the checkout
    else:
        monkeypatch.chdir(tmp_path)
        argv = ["-s", str(REPO / "Snakefile"), "--cores", "2"]
    _, args = parse_args(argv)
    found = re.search(r"workflow specific profile (\S+) for", capsys.readouterr().err)
    assert found, "no workflow profile found"
    assert Path(found.group(1)).resolve() == REPO / "profiles" / "default"
    assert args.rerun_incomplete and args.show_failed_logs  # set only by the profile


def test_rule_threads_flow_into_the_stage() -> None:
    rules = {}
    for smk in sorted((REPO / "workflow" / "rules").glob("*.smk")):
        for block in re.split(r"\nrule ", "\n" + smk.read_text())[1:]:
            name = block.split(":", 1)[0]
            threads = re.search(r"\n    threads: (.+)", block)
            script = re.search(r'\n    script:\n        "(?:\.\./)+(scripts/\w+\.py)"', block)
            if threads and script:
                rules[name] = (threads.group(1), REPO / script.group(1))
    keyed = {n: r for n, r in rules.items() if "config[" in r[0]}
    assert {"phantom_session", "frames", "preprocess", "sfm", "atlas", "compare"} <= set(keyed)
    for name, (threads, script) in keyed.items():
        # per-session stages: session_threads(config[...]) (the cores shared among sessions)
        section, key = re.fullmatch(r'(?:session_threads\()?config\["(\w+)"\]\["(\w+)"\]\)?(?: or \d)?(?:  #.*)?',
                                    threads.strip()).groups()
        text = script.read_text()
        tail = ")" if key == "threads" else f', "{key}")'
        helper = 'job_config(' in text and f'sm.params.{section}, "{section}", sm.threads{tail}' in text
        given = helper or re.search(rf'with_threads\([^\n]*sm\.params\.{section}\b[^\n]*"{key}", sm\.threads\)', text)
        assert given, f"rule {name}: {script.name} does not give the stage its job's threads ({section}.{key})"
    for name, (threads, _) in rules.items():
        if name not in keyed:
            assert threads.strip() in ("1", "2", "session_threads(2)"), name


def test_with_threads_sets_the_key() -> None:
    from cystomap.snakemake_io import with_threads

    section = {"threads": 2, "other": 1}
    assert with_threads(section, "threads", 1) == {"threads": 1, "other": 1}
    assert section["threads"] == 2  # the config itself is left alone


def test_job_config_gives_the_stage_the_job_threads() -> None:
    from cystomap.frames import FramesConfig
    from cystomap.snakemake_io import job_config

    cfg = job_config(FramesConfig, {"threads": 2, "max_frames": 9}, "frames", 1)
    assert cfg.threads == 1 and cfg.max_frames == 9


def test_constraints_pin_every_direct_dependency_at_the_installed_version() -> None:
    import tomllib
    from importlib.metadata import version

    from packaging.requirements import Requirement

    from cystomap.outputs import software_versions

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    direct = [Requirement(r).name.lower() for r in
              project["dependencies"] + project["optional-dependencies"]["dev"]]
    pins = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, _, pinned = line.partition("==")
            pins[name.strip().lower()] = pinned.strip()
    assert sorted(pins) == sorted(direct)
    for name, pinned in pins.items():
        assert version(name) == pinned, name
    recorded = software_versions()
    assert recorded["cystomap"] and all(recorded[k] == pins[k] for k in recorded if k in pins)


@pytest.mark.parametrize(("sessions", "cores", "share", "expected"), [
    (2, 2, True, 1),  # the default study on 2 cores: the two sessions side by side
    (2, 2, False, 2),
    (1, 2, True, 2),  # one session keeps its stages' threads
    (2, 4, True, 2),
])
def test_per_session_jobs_share_the_cores_among_sessions(tmp_path, sessions, cores, share,
                                                         expected) -> None:
    import subprocess
    import sys

    import pandas as pd
    import yaml

    rows = [{"subject": "p01", "session": s, "video": f"{s}.mp4", "date": f"2026-0{i + 1}-01",
             "camera": "phantom_76"} for i, s in enumerate("ab"[:sessions])]
    for row in rows:
        (tmp_path / row["video"]).write_bytes(b"")
    pd.DataFrame(rows).to_csv(tmp_path / "sessions.tsv", sep="\t", index=False)
    config = yaml.safe_load((REPO / "config.yaml").read_text())
    config.update(sessions="sessions.tsv", phantom={"enabled": False}, share_cores=share)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    proc = subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
         str(tmp_path), "--configfile", str(tmp_path / "config.yaml"), "--cores", str(cores),
         "-n", "--nocolor", "--workflow-profile", "none", "results/p01/a/atlas"],
        capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = re.split(r"\n(?=rule |localrule )", proc.stdout + proc.stderr)
    for rule in ("frames", "preprocess", "sfm", "mesh", "atlas"):
        block = next(j for j in jobs if re.match(rf"(local)?rule {rule}:", j))
        threads = re.search(r"\n\s+threads: (\d+)", block)  # not shown when 1
        assert (int(threads.group(1)) if threads else 1) == expected, (rule, block)
