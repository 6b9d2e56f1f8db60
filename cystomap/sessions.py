"""The sessions sheet: which videos make up a study, and the built-in phantom's sessions."""

from __future__ import annotations

import datetime as dt
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jsonschema
import pandas as pd
import yaml

from cystomap.errors import InputError

log = logging.getLogger(__name__)

COLUMNS = ["subject", "session", "video", "date", "camera", "extent_mm", "volume_ml",
           "entry_roll_deg", "neck_xyz", "anterior_xyz"]
#: Optional columns that override a session's anatomical frame (cystomap.anatomy.AnatomyHint).
ANATOMY_COLUMNS = ("entry_roll_deg", "neck_xyz", "anterior_xyz")
#: Keys of the config's ``phantom:`` section that are not PhantomConfig fields.
PHANTOM_STUDY_KEYS = ("enabled", "subject", "camera")
PHANTOM_SESSIONS = {"s1": ("2026-01-05", 1), "s2": ("2026-04-20", 2)}


def read_sessions(config: Mapping[str, Any], schema_path: str | os.PathLike[str]) -> pd.DataFrame:
    """Read and validate the sheet named by ``config["sessions"]`` (empty frame if none is named)."""
    path = config.get("sessions") or ""
    if not path:
        return pd.DataFrame(columns=COLUMNS)
    return load_sheet(Path(path), config.get("cameras", {}), schema_path)


def load_sheet(
    path: Path, cameras: Mapping[str, Any], schema_path: str | os.PathLike[str]
) -> pd.DataFrame:
    """Load a sessions TSV, validate every row against the schema, and cross-check cameras."""
    if not path.is_file():
        raise InputError(f"sessions sheet {path}: file not found (config key `sessions`)")
    try:
        df = pd.read_csv(path, sep="\t", dtype=str, comment="#", keep_default_na=False)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError) as exc:
        raise InputError(f"sessions sheet {path}: cannot be read as TSV ({exc})") from exc
    df.columns = [c.strip() for c in df.columns]
    schema = yaml.safe_load(Path(schema_path).read_text())
    missing = [c for c in schema.get("required", []) if c not in df.columns]
    if missing:
        raise InputError(
            f"sessions sheet {path}: missing column(s) {', '.join(missing)}; "
            f"found {', '.join(df.columns) or 'none'} (is it tab-separated?)"
        )
    if df.empty:
        raise InputError(f"sessions sheet {path}: no rows")
    validator = jsonschema.Draft202012Validator(schema)
    rows = []
    for i, rec in enumerate(df.to_dict("records"), start=2):  # line 1 is the header
        row = {k: _typed(k, v.strip()) for k, v in rec.items() if v.strip() != ""}
        err = jsonschema.exceptions.best_match(validator.iter_errors(row))
        if err is not None:
            where = ".".join(str(p) for p in err.absolute_path) or "row"
            raise InputError(f"sessions sheet {path}, line {i}, column {where}: {err.message}")
        _check_date(row["date"], path, i)
        if row["camera"] not in cameras:
            raise InputError(
                f"sessions sheet {path}, line {i}: camera {row['camera']!r} is not a key of the "
                f"config's `cameras:` (known: {', '.join(cameras) or 'none'})"
            )
        rows.append(row)
    return pd.DataFrame(rows).reindex(columns=COLUMNS)


def phantom_sessions(config: Mapping[str, Any]) -> pd.DataFrame:
    """Rows of the built-in phantom study (two sessions), when ``phantom.enabled`` is true."""
    ph = config.get("phantom", {})
    if not ph.get("enabled", False):
        return pd.DataFrame(columns=COLUMNS)
    from cystomap.phantom import PhantomConfig, bladder_extent_mm
    from cystomap.settings import from_mapping

    cfg = from_mapping(PhantomConfig, phantom_settings(ph), "phantom")
    if ph["camera"] not in config.get("cameras", {}):
        raise InputError(f"config phantom.camera: {ph['camera']!r} is not a key of `cameras:`")
    rows = []
    for name, (date, index) in PHANTOM_SESSIONS.items():
        rows.append({
            "subject": ph["subject"], "session": name,
            "video": f"results/{ph['subject']}/phantom/{name}/video.mp4",
            "date": date, "camera": ph["camera"],
            "extent_mm": round(bladder_extent_mm(cfg, index), 3), "volume_ml": None,
        })
    return pd.DataFrame(rows, columns=COLUMNS)


def phantom_settings(section: Mapping[str, Any]) -> dict[str, Any]:
    """The ``phantom:`` section without its study keys: the PhantomConfig fields."""
    return {k: v for k, v in section.items() if k not in PHANTOM_STUDY_KEYS}


def _typed(column: str, value: str) -> Any:
    if column in ("extent_mm", "volume_ml", "entry_roll_deg"):
        try:
            return float(value)
        except ValueError:
            return value  # the schema reports it
    return value


def anatomy_overrides(row: Mapping[str, Any]) -> dict[str, Any]:
    """A session row's anatomical-frame overrides (None where the sheet leaves them empty)."""
    out: dict[str, Any] = {}
    for k in ANATOMY_COLUMNS:
        v = row.get(k)
        out[k] = None if v is None or (isinstance(v, float) and v != v) or v == "" else v
    if out["entry_roll_deg"] is not None:
        out["entry_roll_deg"] = float(out["entry_roll_deg"])
    return out


def _check_date(value: str, path: Path, line: int) -> None:
    try:
        dt.date.fromisoformat(value)
    except ValueError:
        raise InputError(
            f"sessions sheet {path}, line {line}, column date: {value!r} is not an ISO date (YYYY-MM-DD)"
        ) from None
