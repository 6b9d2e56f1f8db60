"""Exceptions raised by the library (never ``sys.exit``)."""


class CystomapError(Exception):
    """Base class of every error cystomap raises on purpose."""


class InputError(CystomapError, ValueError):
    """Bad input: the message names the file or config key and what is wrong with it."""


class StageError(CystomapError, RuntimeError):
    """A stage ran but could not produce a usable result (e.g. too few frames registered)."""
