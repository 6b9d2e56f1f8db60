"""Small helpers shared by the Snakemake adapters in ``scripts/``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, TypeVar

from cystomap.camera import Camera
from cystomap.settings import from_mapping

T = TypeVar("T")


def camera_param(param: Mapping[str, Any]) -> Camera:
    """A rule's ``camera`` param (the config entry plus its ``name``) as a Camera."""
    entry = dict(param)
    return Camera.from_config(entry, name=str(entry.pop("name", "camera")))


def with_threads(section: Mapping[str, Any], key: str, threads: int) -> dict[str, Any]:
    """A stage's config ``section`` with its threads ``key`` set to the job's ``threads``.

    A rule's ``threads:`` is read from that same key, and Snakemake may lower it (``--cores``)
    or override it (``--set-threads``); the stage then uses what the job was given.
    """
    return {**section, key: max(1, int(threads))}


def job_config(cls: type[T], section: Mapping[str, Any] | None, key: str, threads: int,
               threads_key: str = "threads") -> T:
    """The typed config of a stage from its ``section`` (``key`` names it in errors), its
    threads set to the job's (see :func:`with_threads`)."""
    return from_mapping(cls, with_threads(section or {}, threads_key, threads), key)
