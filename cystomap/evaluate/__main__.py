"""Command line: ``python -m cystomap.evaluate --out DIR --session NAME TRUTH [key=path …] …``.

    --session s1 results/p/phantom/s1/truth sfm=results/p/s1/sfm mesh=… atlas=…
    --compare s1_s2 results/p/phantom/s2/truth sfm=results/p/s2/sfm changes=…/changes.csv
    --config evaluate.yaml   (a mapping of EvalConfig fields, or one under the key `evaluate`)

``sfm=`` may be repeated. Writes evaluation.json, evaluation.tsv and evaluation.md in --out.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from cystomap.errors import CystomapError, InputError
from cystomap.evaluate.config import EvalConfig
from cystomap.evaluate.session import ComparisonInputs, SessionInputs, evaluate_subject

SESSION_KEYS = ("sfm", "mesh", "atlas")
COMPARE_KEYS = ("sfm", "changes")


def _parse(spec: Sequence[str], keys: tuple[str, ...], flag: str) -> tuple[str, str, dict]:
    if len(spec) < 2:
        raise InputError(f"{flag}: give NAME TRUTH_DIR [key=path …], got {' '.join(spec)!r}")
    name, truth, *rest = spec
    values: dict[str, list[str]] = {}
    for item in rest:
        key, sep, value = item.partition("=")
        if not sep or key not in keys:
            raise InputError(f"{flag} {name}: expected one of {', '.join(keys)} as key=path, "
                             f"got {item!r}")
        values.setdefault(key, []).append(value)
    for key, vals in values.items():
        if key != "sfm" and len(vals) > 1:
            raise InputError(f"{flag} {name}: {key}= given more than once")
    return name, truth, values


def _config(path: str | None) -> EvalConfig:
    if not path:
        return EvalConfig()
    import yaml

    from cystomap.settings import from_mapping

    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise InputError(f"{path}: cannot read YAML ({exc})") from exc
    if isinstance(data, dict) and isinstance(data.get("evaluate"), dict):
        data = data["evaluate"]
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of evaluate settings")
    return from_mapping(EvalConfig, data, "evaluate")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m cystomap.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="directory for evaluation.json/.tsv/.md")
    ap.add_argument("--session", nargs="+", action="append", default=[], metavar="ARG")
    ap.add_argument("--compare", nargs="+", action="append", default=[], metavar="ARG")
    ap.add_argument("--config", help="YAML with EvalConfig fields")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        sessions = []
        for spec in args.session:
            name, truth, v = _parse(spec, SESSION_KEYS, "--session")
            sessions.append(SessionInputs(name, truth, v.get("sfm"), *(
                v.get(k, [None])[0] for k in ("mesh", "atlas"))))
        comparisons = []
        for spec in args.compare:
            name, truth, v = _parse(spec, COMPARE_KEYS, "--compare")
            comparisons.append(ComparisonInputs(name, truth, v.get("sfm"),
                                                v.get("changes", [None])[0]))
        evaluate_subject(args.out, sessions, comparisons, _config(args.config))
    except CystomapError as exc:
        logging.getLogger("cystomap").error("%s", exc)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
