"""Benchmark: whole recording-like phantom sessions, video to atlas, timed and scored.

    python -m cystomap.bench.recording --out results/bench [--lengths 60,120,180]
        [--size 1920x1080] [--scale 1] [--render-scale 1] [--fps 30]
        [--set preprocess.scale=0.5 ...] [--variants base,preprocess.scale=0.5]

Each length (seconds) is one phantom session with ``trajectory: recording`` (slow scan,
pauses, returns, fast bends with motion blur; :mod:`cystomap.phantom.recording`), rendered
once and cached under ``--cache`` (default ``results/bench/recording``; a render is reused
when its config matches). Each session then runs through the Snakemake workflow (a sessions
sheet naming the cached video, phantom study off) up to its atlas in ``--cache/run_<tag>``;
each stage's wall time, CPU time and peak memory come from Snakemake's ``benchmark:`` files.
The outputs are scored against the phantom's ground truth (:mod:`cystomap.evaluate`).
``--set KEY=VALUE`` (repeatable) overrides a workflow config key (dotted, value as YAML) for
every run; ``--variants`` runs each session once per variant (``base`` = no override, or
``KEY=VALUE[;KEY=VALUE]``), in turn on the same render, for a side-by-side table.
Writes ``recording.tsv`` and ``recording.md`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from cystomap.bench.common import write_table
from cystomap.phantom import PhantomConfig, default_camera, generate_session

log = logging.getLogger("cystomap.bench.recording")

REPO = Path(__file__).resolve().parents[2]
STAGES = ("frames", "preprocess", "sfm", "mesh", "atlas")
SUBJECT = "rec"
# motion blur of the fastest frames (the bends), relative to the frame width (16 px at 1280)
BLUR_REL = 0.0125
# below this width mp4v's fixed quantiser removes the fine texture (see phantom.lossless_video)
LOSSLESS_BELOW = 1280


def session_config(seconds: float, fps: float, width: int, seed: int,
                   render_scale: float = 1.0) -> PhantomConfig:
    """The phantom of one benchmark session."""
    return PhantomConfig(seed=seed, trajectory="recording", duration_s=seconds, fps=fps,
                         motion_blur_px=round(BLUR_REL * width, 2),
                         lossless_video=width < LOSSLESS_BELOW, render_scale=render_scale)


def render_cached(cache: Path, tag: str, cfg: PhantomConfig, width: int, height: int) -> Path:
    """Session 1 of ``cfg`` at ``width`` x ``height`` in ``cache/<tag>/truth`` (reused when its
    truth.json holds the same config)."""
    truth = cache / tag / "truth"
    meta = truth / "truth.json"
    if meta.is_file():
        saved = json.loads(meta.read_text())
        if (saved.get("config") == json.loads(json.dumps(asdict(cfg)))
                and (saved["width"], saved["height"]) == (width, height)):
            log.info("%s: cached render %s", tag, truth)
            return truth
    shutil.rmtree(truth, ignore_errors=True)
    log.info("%s: rendering %d frames at %dx%d", tag, cfg.frame_count, width, height)
    return generate_session(truth, 1, cfg, default_camera(width, height))


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``KEY=VALUE`` items (dotted keys, YAML values; off/on/yes/no stay strings) as a nested
    config dict."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set/--variants: {item!r} is not KEY=VALUE")
        node = out
        *parents, leaf = key.strip().split(".")
        for part in parents:
            node = node.setdefault(part, {})
        parsed = yaml.safe_load(value)
        # YAML 1.1 reads off/on/yes/no as booleans; the workflow's modes are strings
        if isinstance(parsed, bool) and value.strip().lower() not in ("true", "false"):
            parsed = value.strip()
        node[leaf] = parsed
    return out


def workflow_config(truth: Path, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The workflow config of a benchmark run on the session of ``truth`` (its camera, the
    sessions sheet, phantom study off), ``overrides`` merged over it key by key."""
    from snakemake.utils import update_config

    camera = json.loads((truth / "camera.json").read_text())
    cam = {k: camera[k] for k in ("width", "height", "fx", "fy", "cx", "cy",
                                  "k1", "k2", "p1", "p2", "k3")}
    config = {"sessions": "sessions.tsv", "cameras": {"phantom": cam},
              "phantom": {"enabled": False}}
    update_config(config, overrides or {})
    return config


def run_workflow(root: Path, truth: Path, cores: int,
                 overrides: dict[str, Any] | None = None) -> float:
    """Video to atlas for the session of ``truth`` in ``root`` (workflow config keys
    ``overrides`` on top); wall seconds of Snakemake."""
    meta = json.loads((truth / "truth.json").read_text())
    root.mkdir(parents=True, exist_ok=True)
    pd.DataFrame([{"subject": SUBJECT, "session": "s1", "video": str((truth / "video.mp4").resolve()),
                   "date": "2026-01-05", "camera": "phantom",
                   "extent_mm": meta["extent_mm"]}]).to_csv(root / "sessions.tsv", sep="\t",
                                                            index=False)
    (root / "config.yaml").write_text(yaml.safe_dump(workflow_config(truth, overrides)))
    stamp = root / "run.json"
    done_before = json.loads(stamp.read_text()) if stamp.is_file() else None
    if (done_before is not None and (root / "results" / SUBJECT / "s1" / "atlas").is_dir()
            and done_before.get("overrides", {}) == (overrides or {})):
        log.info("%s: reusing the finished run", root)
        return float(done_before["wall_s"])
    for d in ("results", "benchmarks", "logs", ".snakemake"):
        shutil.rmtree(root / d, ignore_errors=True)
    cmd = [sys.executable, "-m", "snakemake", f"results/{SUBJECT}/s1/atlas", "-s",
           str(REPO / "Snakefile"), "--directory", str(root), "--configfile",
           str(root / "config.yaml"), "--cores", str(cores)]
    t0 = time.perf_counter()
    with (root / "snakemake.log").open("w") as fh:
        done = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, check=False)
    wall = time.perf_counter() - t0
    if done.returncode:
        raise RuntimeError(f"snakemake failed ({done.returncode}); see {root / 'snakemake.log'}")
    stamp.write_text(json.dumps({"wall_s": wall, "cores": cores, "overrides": overrides or {}}))
    return wall


def stage_times(root: Path) -> dict[str, dict[str, float]]:
    """Per stage: wall s, CPU s and peak memory (MB) from Snakemake's benchmark files."""
    out = {}
    for stage in STAGES:
        tsv = root / "benchmarks" / SUBJECT / "s1" / f"{stage}.tsv"
        row = pd.read_csv(tsv, sep="\t").iloc[0]
        out[stage] = {"s": float(row["s"]), "cpu_s": float(row["cpu_time"]),
                      "max_rss_mb": float(row["max_rss"])}
    return out


def score(root: Path, truth: Path) -> dict[str, Any]:
    from cystomap.evaluate import evaluate_session

    res = root / "results" / SUBJECT / "s1"
    r = evaluate_session(truth, res / "sfm", res / "mesh/surface.ply", res / "atlas")
    frames = json.loads((res / "frames" / "frames.json").read_text())
    reg, traj = r.get("registration", {}), r.get("trajectory", {})
    return {
        "frames_decoded": frames["frames_decoded"], "frames_kept": frames["frames_kept"],
        "decoded_fps": frames.get("timing", {}).get("decoded_fps"),
        "registered": reg.get("n_registered"),
        "registered_share_of_kept": (reg.get("n_registered") or 0) / frames["frames_kept"],
        "models": reg.get("n_models"),
        "rmse_mm": traj.get("rmse_mm"),
        "scale_error_pct": 100 * traj["scale_error"] if "scale_error" in traj else None,
        "coverage_error_pp": r.get("atlas", {}).get("coverage_error_pp"),
        # the atlas against the true albedo (cystomap.evaluate.surface): structure, detail
        # in place, sharpness (1 = as sharp as the truth)
        **{f"atlas_{k}": r.get("atlas", {}).get(k)
           for k in ("ssim_stretched", "detail_correlation", "sharpness_ratio")},
    }


def bench(cache: Path, lengths: Sequence[float], fps: float, width: int, height: int,
          seed: int, cores: int, render_scale: float = 1.0, overrides: Sequence[str] = (),
          variants: Sequence[str] = ("base",)) -> list[dict[str, Any]]:
    """A table row per length and variant (see the module's doc)."""
    rows = []
    for seconds in lengths:
        for variant in variants:
            items = [*overrides, *([] if variant == "base" else variant.split(";"))]
            rows.append(bench_one(cache, seconds, fps, width, height, seed, cores, render_scale,
                                  items, variant))
    return rows


def bench_one(cache: Path, seconds: float, fps: float, width: int, height: int, seed: int,
              cores: int, render_scale: float, items: Sequence[str],
              variant: str) -> dict[str, Any]:
    """One length in one variant (config overrides ``items``): its table row."""
    tag = f"{seconds:g}s_{width}x{height}_{fps:g}fps_seed{seed}" + (
        "" if render_scale == 1 else f"_render{render_scale:g}")
    cfg = session_config(seconds, fps, width, seed, render_scale)
    t0 = time.perf_counter()
    truth = render_cached(cache, tag, cfg, width, height)
    render_s = json.loads((truth / "truth.json").read_text())["render_seconds"]
    log.info("%s: render %.0f s (this call %.0f s)", tag, render_s, time.perf_counter() - t0)
    suffix = "".join("_" + i.replace("=", "-").replace(".", "-").replace("/", "-")
                     for i in items)
    root = cache / f"run_{tag}{suffix}"
    row: dict[str, Any] = {"session": tag, "variant": variant, "overrides": ";".join(items),
                           "seconds": seconds, "render_s": render_s}
    try:
        row["video_to_atlas_s"] = round(
            run_workflow(root, truth, cores, parse_overrides(items)), 1)
    except RuntimeError as exc:
        log.error("%s: %s", tag, exc)
        return row
    times = stage_times(root)
    for stage, t in times.items():
        row[f"{stage}_s"] = round(t["s"], 1)
        row[f"{stage}_cpu_s"] = round(t["cpu_s"], 1)
        row[f"{stage}_mb"] = round(t["max_rss_mb"])
    row["stages_s"] = round(sum(t["s"] for t in times.values()), 1)
    row["peak_mb"] = round(max(t["max_rss_mb"] for t in times.values()))
    row["faster_than_recording"] = row["stages_s"] <= seconds
    row.update(score(root, truth))
    log.info("%s %s: %s", tag, variant, row)
    return row


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m cystomap.bench.recording", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("results/bench"), help="where the table goes")
    p.add_argument("--cache", type=Path, default=None,
                   help="renders and runs (default: OUT/recording)")
    p.add_argument("--lengths", default="60,120,180", help="recording lengths in seconds")
    p.add_argument("--size", default="1920x1080", help="frame size WxH")
    p.add_argument("--scale", type=float, default=1.0,
                   help="multiplies --size (1/3: 640x360) for quick runs")
    p.add_argument("--render-scale", type=float, default=1.0,
                   help="render at this share of the size and enlarge (phantom render_scale)")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--cores", type=int, default=2)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="workflow config override for every run (dotted key, YAML value)")
    p.add_argument("--variants", default="base",
                   help="comma-separated runs per session: base (no override) or "
                        "KEY=VALUE[;KEY=VALUE] (e.g. base,preprocess.scale=0.5)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    w, h = (int(v) for v in args.size.split("x"))
    width, height = round(w * args.scale / 2) * 2, round(h * args.scale / 2) * 2
    rows = bench(args.cache or args.out / "recording", [float(s) for s in args.lengths.split(",")],
                 args.fps, width, height, args.seed, args.cores, args.render_scale, args.set,
                 args.variants.split(","))
    write_table(rows, args.out, "recording",
                "Recording-like phantom sessions, video to atlas (Snakemake benchmark files; times "
                f"in s, wall and CPU of each job, memory = peak RSS in MB; {time.strftime('%Y-%m-%d')})")
    print((args.out / "recording.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
