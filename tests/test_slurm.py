"""The Slurm profile (workflow/profiles/slurm) on a one-node Slurm cluster started on localhost.

Installs Debian's slurm-wlm and munge when they are missing (as root, or with passwordless
sudo), starts a private munged, slurmctld and slurmd on free ports with every file in a
temporary directory (no accounting database, no cgroups), runs the small user-sheet study of
test_workflow through ``snakemake --executor slurm --workflow-profile workflow/profiles/slurm``
and the same study locally, checks that every job went through Slurm and that both runs wrote
the same files, and stops exactly the daemons it started, whatever the outcome.

Without root or passwordless sudo the test is skipped, with the reason, except under CI (the CI
environment variable set), where that is a failure; so is a cluster that cannot be installed or
started, anywhere.
"""

from __future__ import annotations

import filecmp
import json
import os
import pwd
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml
from test_workflow import TARGETS, study_config, write_study

pytestmark = pytest.mark.workflow

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "workflow/profiles/slurm"
DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("sbatch", "srun", "squeue", "sinfo", "scontrol", "scancel")
# the study's jobs: (rule, session)
STUDY_JOBS = {("frames", "a"), ("frames", "b"), ("preprocess", "a"), ("preprocess", "b")}


def _no_privilege(reason: str):
    """A skip, except under CI: the test must run there."""
    if os.environ.get("CI"):
        pytest.fail(f"Slurm test cluster unavailable under CI: {reason}")
    pytest.skip(reason)


def _privilege() -> list[str] | None:
    """Command prefix that runs as root: [] as root, sudo -n with passwordless sudo, else None."""
    if os.geteuid() == 0:
        return []
    if shutil.which("sudo") and subprocess.run(["sudo", "-n", "true"], capture_output=True).returncode == 0:
        return ["sudo", "-n"]
    return None


def _which(name: str) -> str | None:
    return shutil.which(name, path=os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/sbin"]))


def _install(priv: list[str]) -> None:
    """apt-get install slurm-wlm and munge without starting their system services."""
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    policy = Path("/usr/sbin/policy-rc.d")
    own_policy = not policy.exists()
    steps = [
        ["apt-get", "update", "-qq"],
        ["apt-get", "-o", "DPkg::Lock::Timeout=900", "install", "-y", "-qq", "--no-install-recommends",
         "slurm-wlm", "munge"],
    ]
    try:
        if own_policy:  # keep the packages' postinst from starting system-wide daemons
            subprocess.run([*priv, "sh", "-c", f"printf '#!/bin/sh\\nexit 101\\n' > {policy} && chmod 755 {policy}"],
                           check=True)
        for cmd in steps:
            proc = subprocess.run([*priv, *(["env", "DEBIAN_FRONTEND=noninteractive"] if priv else []), *cmd],
                                  env=env, capture_output=True, text=True, timeout=1500)
            if proc.returncode != 0:
                pytest.fail(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    finally:
        if own_policy:
            subprocess.run([*priv, "rm", "-f", str(policy)], check=False)


def _free_ports(n: int) -> list[int]:
    sockets = [socket.socket() for _ in range(n)]
    try:
        for s in sockets:  # all bound at once: n different ports
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def _mem_mb() -> int:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) // 1024
    return 4000


class LocalCluster:
    """munged + slurmctld + slurmd for one node on localhost, all state under ``root``."""

    def __init__(self, root: Path, priv: list[str]) -> None:
        self.root = root
        self.priv = priv
        self.host = socket.gethostname().split(".")[0]
        self.conf = root / "slurm.conf"
        self.bin = root / "bin"
        self.procs: dict[str, subprocess.Popen] = {}
        self.env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "SBATCH_", "SRUN_"))}
        self.env["SLURM_CONF"] = str(self.conf)
        # snakemake-executor-plugin-slurm-jobstep drops every SLURM_* variable (SLURM_CONF too)
        # before it calls srun inside a job; this srun keeps the test cluster's configuration.
        self.env["PATH"] = f"{self.bin}{os.pathsep}{os.environ.get('PATH', '')}"

    def write_config(self) -> None:
        root = self.root
        for sub in ("munge", "state", "spool", "log", "bin"):
            (root / sub).mkdir(mode=0o755)
        srun = self.bin / "srun"
        srun.write_text(f'#!/bin/sh\nSLURM_CONF={self.conf} exec {_which("srun")} "$@"\n')
        srun.chmod(0o755)
        (root / "plugstack.conf").write_text("")
        cpus = max(2, os.cpu_count() or 1)
        ctld_port, slurmd_port = _free_ports(2)
        self.conf.write_text(f"""\
# one-node test cluster written by tests/test_slurm.py
ClusterName=cystomap-test
SlurmctldHost={self.host}(127.0.0.1)
SlurmctldPort={ctld_port}
SlurmdPort={slurmd_port}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={root}/munge/munge.socket
StateSaveLocation={root}/state
SlurmdSpoolDir={root}/spool
SlurmctldPidFile={root}/slurmctld.pid
SlurmdPidFile={root}/slurmd.pid
SlurmctldLogFile={root}/log/slurmctld.log
SlurmdLogFile={root}/log/slurmd.log
PlugStackConfig={root}/plugstack.conf
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SwitchType=switch/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SlurmdParameters=config_overrides
ReturnToService=2
MinJobAge=3600
NodeName={self.host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={_mem_mb()} State=UNKNOWN
PartitionName=test Nodes={self.host} Default=YES MaxTime=INFINITE State=UP
""")

    def _start(self, name: str, *args: str) -> None:
        log = open(self.root / "log" / f"{name}.out", "w")
        self.procs[name] = subprocess.Popen([*self.priv, _which(name), *args], stdout=log, stderr=subprocess.STDOUT,
                                            stdin=subprocess.DEVNULL, env=self.env, start_new_session=True)
        log.close()

    def start(self) -> None:
        self.write_config()
        munge = self.root / "munge"
        subprocess.run([*self.priv, "sh", "-c", f"head -c 1024 /dev/urandom > {munge}/munge.key && "
                                                f"chmod 600 {munge}/munge.key"], check=True)
        self._start("munged", "--foreground", "--force", f"--socket={munge}/munge.socket",
                    f"--key-file={munge}/munge.key", f"--pid-file={munge}/munged.pid",
                    f"--seed-file={munge}/munged.seed", f"--log-file={self.root}/log/munged.log")
        self._wait(lambda: (munge / "munge.socket").exists(), "munged to create its socket", 20)
        self._start("slurmctld", "-D", "-i", "-f", str(self.conf))
        self._start("slurmd", "-D", "-N", self.host, "-f", str(self.conf))
        self._wait(self.node_idle, f"node {self.host} to be idle", 90)

    def node_idle(self) -> bool:
        proc = self.client("sinfo", "-h", "-N", "-o", "%T", check=False)
        return proc.stdout.strip() == "idle"

    def client(self, *cmd: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        proc = subprocess.run([_which(cmd[0]), *cmd[1:]], env=self.env, capture_output=True, text=True, timeout=60)
        if check and proc.returncode != 0:
            raise AssertionError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr}")
        return proc

    def _wait(self, ready, what: str, timeout: float) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for name, proc in self.procs.items():
                if proc.poll() is not None:
                    raise RuntimeError(f"{name} exited ({proc.returncode}) while waiting for {what}\n{self.logs()}")
            if ready():
                return
            time.sleep(0.5)
        raise RuntimeError(f"timed out after {timeout:.0f} s waiting for {what}\n{self.logs()}")

    def logs(self) -> str:
        out = []
        for path in sorted((self.root / "log").glob("*")):
            lines = path.read_text(errors="replace").splitlines()[-15:]
            out.append(f"--- {path.name}\n" + "\n".join(lines))
        return "\n".join(out)

    def stop(self) -> None:
        """Cancel what is left of the test's jobs, then stop slurmd, slurmctld, munged (by pid)."""
        if "slurmctld" in self.procs and self.procs["slurmctld"].poll() is None:
            self.client("scancel", "--full", "--user", pwd.getpwuid(os.getuid()).pw_name, check=False)
            self._wait_for(lambda: not self.client("squeue", "-h", "-t", "R,CG,PD", check=False).stdout.strip(), 20)
        for name in ("slurmd", "slurmctld", "munged"):
            proc = self.procs.pop(name, None)
            if proc is None:
                continue
            self._signal(proc, signal.SIGTERM)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self._signal(proc, signal.SIGKILL)
                proc.wait(timeout=10)

    def _signal(self, proc: subprocess.Popen, sig: signal.Signals) -> None:
        if proc.poll() is not None:
            return
        if self.priv:  # sudo relays the signal to the daemon
            subprocess.run([*self.priv, "kill", f"-{sig.name[3:]}", str(proc.pid)], check=False)
        else:
            proc.send_signal(sig)

    @staticmethod
    def _wait_for(done, timeout: float) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end and not done():
            time.sleep(0.5)


@pytest.fixture(scope="module")
def cluster():
    priv = _privilege()
    if priv is None:
        _no_privilege("starting slurmd needs root or passwordless sudo")
    if not all(_which(name) for name in (*DAEMONS, *CLIENTS)):
        _install(priv)
        missing = [name for name in (*DAEMONS, *CLIENTS) if not _which(name)]
        if missing:
            pytest.fail(f"still missing after installing slurm-wlm and munge: {missing}")
    root = Path(tempfile.mkdtemp(prefix="cystomap-slurm-"))
    root.chmod(0o755)  # munged wants its socket's directories searchable by all
    test_cluster = LocalCluster(root, priv)
    try:
        test_cluster.start()
        yield test_cluster
    finally:
        test_cluster.stop()
        subprocess.run([*priv, "rm", "-rf", str(root)], check=False)


def snakemake(workdir: Path, *args: str, env: dict | None = None) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--configfile", str(workdir / "test_config.yaml"), "--nocolor", *args, *TARGETS]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=workdir, env=env, timeout=1200)
    if proc.returncode != 0:
        raise AssertionError(f"snakemake failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-8000:]}")
    return proc


def make_study(root: Path) -> Path:
    root.mkdir()
    write_study(root)
    # each job with its stage's threads locally too, as on Slurm: share_cores would give the
    # two sessions' jobs one thread each on 2 cores, and their outputs record their threads
    config = study_config(share_cores=False)
    (root / "test_config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    return root


TIMING_KEYS = {"elapsed_s", "timing"}  # frames.json's "timing": seconds per pass, decoded_fps


def without_timings(value):
    """A stage summary without its wall times, which differ from run to run."""
    if isinstance(value, dict):
        return {k: without_timings(v) for k, v in value.items() if k not in TIMING_KEYS}
    if isinstance(value, list):
        return [without_timings(v) for v in value]
    return value


def files_under(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()}


def test_profile_runs_the_study_through_slurm_like_a_local_run(cluster, tmp_path):
    on_slurm = make_study(tmp_path / "slurm")
    local = make_study(tmp_path / "local")
    proc = snakemake(
        on_slurm, "--workflow-profile", str(PROFILE),
        # no accounting database: job states come from slurmctld via squeue (MinJobAge=3600)
        "--slurm-status-command", "squeue", "--slurm-init-seconds-before-status-checks", "2",
        "--slurm-keep-successful-logs", env=cluster.env,
    )
    log = proc.stdout + proc.stderr
    snakemake(local, "--cores", "2")

    # every job was submitted with sbatch and ran to completion as a Slurm job
    run_id = re.search(r"SLURM run ID: (\S+)", log).group(1)
    submitted = dict(re.findall(r"Job (\d+) has been submitted with SLURM jobid (\d+)", log))
    queue = cluster.client("squeue", "-h", "-t", "all", "--name", run_id, "-o", "%i|%T|%k").stdout.split()
    states = {job_id: (state, comment) for job_id, state, comment in (row.split("|") for row in queue)}
    assert sorted(states) == sorted(submitted.values()) and len(states) == len(STUDY_JOBS)
    assert {s for s, _ in states.values()} == {"COMPLETED"}, states
    assert {re.fullmatch(r"rule_(\w+)_wildcards_p01_(\w+)", c).groups() for _, c in states.values()} == STUDY_JOBS
    for job_id, (_, comment) in states.items():
        rule, session = re.fullmatch(r"rule_(\w+)_wildcards_p01_(\w+)", comment).groups()
        slurm_log = (on_slurm / f".snakemake/slurm_logs/rule_{rule}/p01_{session}/{job_id}.log").read_text()
        assert f"rule {rule}:" in slurm_log and f"session={session}" in slurm_log
    # with the profile's resources (measured needs; see its header)
    profile = yaml.safe_load((PROFILE / "config.yaml").read_text())
    for rule in ("frames", "preprocess"):
        job_id = next(j for j, (_, c) in states.items() if c.startswith(f"rule_{rule}_"))
        info = cluster.client("scontrol", "show", "job", job_id).stdout
        want = {key: eval(str(value), {"attempt": 1})  # first attempt
                for key, value in {**profile["default-resources"], **profile["set-resources"][rule]}.items()}
        assert f"MinMemoryNode={want['mem_mb']}M" in info, info
        assert re.search(rf"TimeLimit=(\d+-)?0*{want['runtime'] // 60}:{want['runtime'] % 60:02d}:00", info), info

    # the same outputs as the local run: the same files, byte for byte but for the stages' timings
    for tree in ("results", "logs", "benchmarks"):
        assert files_under(on_slurm / tree) == files_under(local / tree)
    names = sorted(files_under(local / "results"))
    assert any(n.endswith(".png") for n in names) and "p01/a/frames/frames.csv" in names
    for name in names:
        a, b = on_slurm / "results" / name, local / "results" / name
        if name.endswith(".json"):
            assert without_timings(json.loads(a.read_text())) == without_timings(json.loads(b.read_text())), name
        else:
            assert filecmp.cmp(a, b, shallow=False), name


def test_profile_sets_resources_for_every_rule_that_runs_a_job():
    proc = subprocess.run([sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--list-rules"],
                          capture_output=True, text=True, cwd=REPO, timeout=300, check=True)
    rules = set(proc.stdout.split()) - {"all"}
    profile = yaml.safe_load((PROFILE / "config.yaml").read_text())
    assert rules and set(profile["set-resources"]) == rules
    assert profile["executor"] == "slurm"
