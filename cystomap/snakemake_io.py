"""Small helpers shared by the Snakemake adapters in ``scripts/``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from cystomap.camera import Camera


def camera_param(param: Mapping[str, Any]) -> Camera:
    """A rule's ``camera`` param (the config entry plus its ``name``) as a Camera."""
    entry = dict(param)
    return Camera.from_config(entry, name=str(entry.pop("name", "camera")))
