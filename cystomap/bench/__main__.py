"""``python -m cystomap.bench --out results/bench``: run the benchmarks and write their tables."""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

from cystomap.bench.common import write_table

log = logging.getLogger("cystomap.bench")
SUITES = ("phantom", "pipeline", "compare", "froc")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("results/bench"))
    parser.add_argument("--only", choices=SUITES, action="append", help="run only these suites")
    parser.add_argument("--repeats", type=int, default=3, help="runs per timed step (median reported)")
    parser.add_argument("--work", type=Path, help="scratch directory (default: a temporary one)")
    parser.add_argument("--seeds", default="7,8,9",
                        help="phantom seeds scored by the pipeline and compare suites")
    parser.add_argument("--pairs", default="default,deformed,no_change", help="session pairs of the compare suite")
    parser.add_argument("--froc-pairs", type=int, default=30, help="froc: randomized pairs with lesions")
    parser.add_argument("--froc-no-change", type=int, default=10, help="froc: randomized pairs without change")
    parser.add_argument("--froc-size", default="1280x720", help="froc: frame size WxH")
    parser.add_argument("--froc-frames", type=int, default=124, help="froc: frames per session")
    parser.add_argument("--froc-rates", default="0.03,0.1,0.3,1",
                        help="froc: false_alarm_rate operating points")
    parser.add_argument("--froc-seed", type=int, default=100, help="froc: seed of the first pair")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    suites = args.only or list(SUITES)
    with tempfile.TemporaryDirectory(prefix="cystomap-bench-") as tmp:
        work = args.work or Path(tmp)
        if "phantom" in suites:
            from cystomap.bench.phantom import bench_phantom

            df = write_table(bench_phantom(work, args.repeats), args.out, "phantom", "Phantom rendering")
            log.info("phantom:\n%s", df.to_string(index=False))
        if "pipeline" in suites:
            from cystomap.bench.pipeline import bench_pipeline

            seeds = [int(s) for s in args.seeds.split(",")]
            times, scores = bench_pipeline(work, args.repeats, seeds)
            df = write_table(times, args.out, "pipeline_times", "Stage times, one full-size phantom session")
            log.info("pipeline times:\n%s", df.to_string(index=False))
            df = write_table(scores, args.out, "pipeline_scores",
                             "Scores against the phantom's ground truth, per seed (session 1, 1280x720)")
            log.info("pipeline scores:\n%s", df.to_string(index=False))
        if "compare" in suites:
            from cystomap.bench.compare import bench_compare

            rows = [row for seed in args.seeds.split(",")
                    for row in bench_compare(work, args.repeats, args.pairs.split(","), int(seed))]
            df = write_table(rows, args.out, "compare", "Compare stage on phantom session pairs (1280x720)")
            log.info("compare:\n%s", df.to_string(index=False))
        if "froc" in suites:
            from cystomap.bench.froc import bench_froc

            width, height = (int(v) for v in args.froc_size.split("x"))
            summary = bench_froc(work, args.out, args.froc_pairs, args.froc_no_change, width, height,
                                 args.froc_frames, tuple(float(r) for r in args.froc_rates.split(",")),
                                 args.froc_seed)
            log.info("froc: %d summary rows -> %s", len(summary), args.out / "froc.csv")


if __name__ == "__main__":
    main()
