"""Generate the stage sections of the config schema from the config dataclasses.

Each stage's dataclass is the one source of a key: its type and default (the annotation and the
value), the values it accepts (:func:`cystomap.settings.setting`) and its meaning (the comment
block right above the field, as Sphinx reads ``#:`` comments; a field with none is described as
"See <the previous field>."; a ``# --- group ---`` line heads a group and is not part of any
description). ``python -m cystomap.configschema --write`` rewrites the ``$defs`` of those sections in
``workflow/schemas/config.schema.yaml`` (the file Snakemake validates the config against; the
keys without a dataclass — sessions, cameras, comparisons, landmarks, phantom.enabled/subject/
camera — are written there by hand), and a test fails when the file is not what this generates.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
import textwrap
import types
import typing
from pathlib import Path
from typing import Any

import yaml

from cystomap.settings import _parse_check

SCHEMA = Path(__file__).resolve().parents[1] / "workflow/schemas/config.schema.yaml"
_FIELD = re.compile(r"^    (\w+)\s*:")
_GROUP = re.compile(r"^\s*---.*---\s*$")


def sections() -> dict[str, type]:
    """Config section name → its dataclass (imported here: the stages import heavy libraries)."""
    from cystomap.atlas import AtlasConfig
    from cystomap.compare import CompareConfig
    from cystomap.evaluate import EvalConfig
    from cystomap.frames import FramesConfig
    from cystomap.mesh import MeshConfig
    from cystomap.phantom import PhantomConfig
    from cystomap.preprocess import PreprocessConfig
    from cystomap.report import ReportConfig
    from cystomap.sfm import SfmConfig

    return {
        "phantom": PhantomConfig, "frames": FramesConfig, "preprocess": PreprocessConfig,
        "evaluate": EvalConfig, "mesh": MeshConfig, "atlas": AtlasConfig, "sfm": SfmConfig,
        "compare": CompareConfig, "report": ReportConfig,
    }


def field_docs(cls: type) -> dict[str, str]:
    """Each field's description: the comment lines right above it in the class body."""
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    docs: dict[str, str] = {}
    comment: list[str] = []
    previous = ""
    for line in textwrap.dedent(inspect.getsource(cls)).splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            text = stripped.lstrip("#:").strip()
            if not _GROUP.match(text):
                comment.append(text)
            continue
        m = _FIELD.match(line)
        if m and m.group(1) in names:
            name = m.group(1)
            if comment:
                docs[name] = " ".join(comment)
            elif previous:
                docs[name] = f"See {previous}."
            previous = name
            comment = []
        elif not stripped:
            comment = []
        elif line.startswith("    def "):
            break
    missing = [n for n in names if n not in docs]
    if missing:
        raise ValueError(f"{cls.__name__}: no comment above field(s) {', '.join(missing)}")
    return docs


def _type(hint: Any) -> dict[str, Any]:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        if len(inner) != 1:
            raise TypeError(f"unsupported union {hint}")
        out = _type(inner[0])
        out["type"] = [out["type"], "null"]
        return out
    if origin is tuple:
        item = _type(args[0])
        out = {"type": "array", "items": item}
        if not (len(args) == 2 and args[1] is Ellipsis):
            out["minItems"] = out["maxItems"] = len(args)
        return out
    names = {bool: "boolean", int: "integer", float: "number", str: "string"}
    if hint not in names:
        raise TypeError(f"unsupported config type {hint}")
    return {"type": names[hint]}


def _bounds(check: str) -> dict[str, float]:
    lo, hi = _parse_check(check)
    words = {">=": "minimum", ">": "exclusiveMinimum", "<=": "maximum", "<": "exclusiveMaximum"}
    out: dict[str, float] = {}
    for bound in (lo, hi):
        if bound:
            value = bound[1]
            out[words[bound[0]]] = int(value) if value.is_integer() else value
    return out


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def section_schema(cls: type, description: str) -> dict[str, Any]:
    """The JSON schema of one config dataclass."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    props: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        prop = _type(hints[f.name])
        check, choices = f.metadata.get("check"), f.metadata.get("choices")
        target = prop["items"] if "items" in prop else prop  # a list's range is its items'
        if check:
            target.update(_bounds(check))
        if choices is not None:
            target["enum"] = [_plain(c) for c in choices]
        prop["default"] = _plain(f.default)
        prop["description"] = docs[f.name]
        props[f.name] = prop
    return {"type": "object", "additionalProperties": False, "description": description,
            "properties": props}


def generate(schema: dict[str, Any]) -> dict[str, Any]:
    """``schema`` with every dataclass section's ``$defs`` entry regenerated (the keys written
    by hand, such as the phantom study's ``enabled``/``subject``/``camera``, are kept first)."""
    out = dict(schema)
    defs = dict(schema["$defs"])
    for name, cls in sections().items():
        old = defs[name]
        new = section_schema(cls, old.get("description") or (cls.__doc__ or "").split("\n")[0])
        manual = {k: v for k, v in old["properties"].items() if k not in new["properties"]
                  and k in _hand_written(name)}
        new["properties"] = {**manual, **new["properties"]}
        defs[name] = {**old, **new}  # keeps cross-key rules (e.g. allOf) written by hand
    out["$defs"] = defs
    return out


def _hand_written(section: str) -> tuple[str, ...]:
    from cystomap.sessions import PHANTOM_STUDY_KEYS

    return PHANTOM_STUDY_KEYS if section == "phantom" else ()


class _Dumper(yaml.SafeDumper):
    pass


def _str(dumper: yaml.SafeDumper, value: str) -> yaml.Node:
    folded = len(value) > 80 and "\n" not in value  # long descriptions as folded blocks
    return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=">" if folded else None)


_Dumper.add_representer(str, _str)


def dump(schema: dict[str, Any]) -> str:
    header = ("# Generated in part: the stage sections under $defs come from the config dataclasses\n"
              "# (python -m cystomap.configschema --write). Edit those in cystomap/, not here.\n")
    return header + yaml.dump(schema, Dumper=_Dumper, sort_keys=False, width=100, allow_unicode=True)


def text(path: Path = SCHEMA) -> str:
    """What the schema file must hold: its hand-written parts plus the generated sections."""
    return dump(generate(yaml.safe_load(path.read_text())))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write", action="store_true", help=f"rewrite {SCHEMA.name} in place")
    args = parser.parse_args()
    new = text()
    if args.write:
        SCHEMA.write_text(new)
    else:
        print(new, end="")


if __name__ == "__main__":
    main()
