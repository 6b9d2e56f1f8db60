"""Render the config schema as the README's configuration table.

``python -m cystomap.configdoc`` prints the table; ``--write README.md`` replaces the block
between the ``<!-- config-table -->`` markers. A test keeps the README in step with the schema.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

import yaml

SCHEMA = Path(__file__).resolve().parents[1] / "workflow/schemas/config.schema.yaml"
BEGIN, END = "<!-- config-table -->", "<!-- /config-table -->"


def rows(schema: dict[str, Any]) -> list[tuple[str, str, str]]:
    out = []
    for name, prop in schema["properties"].items():
        if "$ref" in prop:
            section = schema["$defs"][prop["$ref"].rsplit("/", 1)[1]]
            if "properties" in section and name != "cameras":
                for key, sub in section["properties"].items():
                    out.append((f"{name}.{key}", _default(sub), _text(sub)))
                continue
        out.append((name, _default(prop), _text(prop)))
    cam = schema["$defs"]["camera"]["properties"]
    for key, sub in cam.items():
        missing = "required" if key in ("width", "height") else "—"
        out.append((f"cameras.NAME.{key}", _default(sub, missing), _text(sub)))
    return out


def table(schema: dict[str, Any] | None = None) -> str:
    schema = schema or yaml.safe_load(SCHEMA.read_text())
    lines = ["| key | default | meaning |", "| --- | --- | --- |"]
    lines += [f"| `{k}` | {d} | {t} |" for k, d, t in rows(schema)]
    return "\n".join(lines)


def block() -> str:
    return f"{BEGIN}\n{table()}\n{END}"


def _default(prop: dict[str, Any], missing: str = "—") -> str:
    if "default" not in prop:
        return missing
    return f"`{json.dumps(prop['default'])}`"


def _text(prop: dict[str, Any]) -> str:
    return " ".join(str(prop.get("description", "")).split()).replace("|", "\\|")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--write", type=Path, help="README to update in place")
    args = parser.parse_args()
    if not args.write:
        print(table())
        return
    text = args.write.read_text()
    pattern = re.compile(re.escape(BEGIN) + ".*?" + re.escape(END), re.S)
    if not pattern.search(text):
        raise SystemExit(f"{args.write}: no {BEGIN} ... {END} block")
    args.write.write_text(pattern.sub(lambda _: block(), text))


if __name__ == "__main__":
    main()
