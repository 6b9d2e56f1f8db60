"""Shared fixtures: the repository root, a Snakemake runner for workflow tests, and the phantom
study run once at test size for every test that needs real stage outputs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


# The slow tier: tests that render phantom sessions, run SfM or run Snakemake (``make test``
# runs everything, ``make test-fast`` leaves them out with ``-m "not slow"``). A test is slow
# when it uses one of these fixtures, is marked ``workflow``, or is marked ``slow`` itself.
SLOW_FIXTURES = {"phantom_study", "workflow_factory", "sessions", "small_session", "phantom_videos",
                 "glint_session", "pair"}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if SLOW_FIXTURES & set(getattr(item, "fixturenames", ())) or item.get_closest_marker("workflow"):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(autouse=True)
def _unit_tier_runs_no_sfm(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """A test that runs pycolmap's incremental mapping but is not marked slow fails, naming the marker, so the
    unit tier (``make test-fast``) stays free of SfM as new tests are added."""
    if request.node.get_closest_marker("slow"):
        return
    import pycolmap

    def refuse(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("SfM mapping in a test not marked slow: add @pytest.mark.slow or a slow "
                             "fixture (tests/conftest.py SLOW_FIXTURES)")

    # incremental mapping of a session; a few registrations on a synthetic model stay allowed
    monkeypatch.setattr(pycolmap, "incremental_mapping", refuse)


class Workflow:
    """A Snakemake working directory with its own config file (merged over config.yaml)."""

    def __init__(self, workdir: Path, config: dict) -> None:
        self.workdir = workdir
        self.configfile = workdir / "test_config.yaml"
        self.write_config(config)

    def write_config(self, config: dict) -> None:
        self.configfile.write_text(yaml.safe_dump(config, sort_keys=False))

    def run(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        cmd = [
            sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"),
            "--directory", str(self.workdir), "--configfile", str(self.configfile),
            "--cores", "2", "--nocolor", *args,
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=self.workdir, timeout=1200)
        if check and proc.returncode != 0:
            raise AssertionError(f"snakemake failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}")
        return proc

    def planned_jobs(self, *targets: str) -> dict[str, int]:
        """Rule -> job count that a dry run would execute."""
        proc = self.run(*targets, "-n", "--quiet", "rules")
        return parse_job_counts(proc.stdout + proc.stderr)


def parse_job_counts(text: str) -> dict[str, int]:
    counts: dict[str, int] = {}
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.strip().startswith("job") and "count" in line:
            for row in lines[i + 2 :]:
                parts = row.split()
                if len(parts) != 2 or not parts[1].isdigit():
                    break
                if parts[0] != "total":
                    counts[parts[0]] = int(parts[1])
            break
    return counts


@pytest.fixture
def workflow_factory(tmp_path: Path):
    def make(config: dict) -> Workflow:
        return Workflow(tmp_path, config)

    return make


# The default study (the built-in phantom) at test size: 640x360 frames, a 1024x512 atlas.
HALF_CAMERA = {"width": 640, "height": 360, "fx": 469.932, "fy": 469.932, "cx": 319.5, "cy": 179.5,
               "k1": -0.12, "k2": 0.02}


def phantom_config(**phantom) -> dict:
    return {"cameras": {"phantom_half": HALF_CAMERA},
            # lossless: mp4v at 640x360 wipes out the fine texture SfM needs (see PhantomConfig)
            "phantom": {"enabled": True, "camera": "phantom_half", "lossless_video": True, **phantom},
            "atlas": {"width": 1024, "height": 512},
            # a site marked on session s1's atlas (its centre), found back in s2 by compare
            "landmarks": [{"subject": "phantom", "session": "s1", "name": "centre", "col": 512,
                           "row": 256}]}


@pytest.fixture(scope="session")
def phantom_study(tmp_path_factory) -> Workflow:
    """The whole phantom DAG run once (about 3-4 min on 2 cores), shared by the workflow and
    report tests. Tests must leave its config as phantom_config() and its outputs unchanged."""
    wf = Workflow(tmp_path_factory.mktemp("phantom_study"), phantom_config())
    wf.run()
    return wf
