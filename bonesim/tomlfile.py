"""Reading and checking TOML manifests (cases, burrs, materials).

The helpers here turn every malformed or unexpected entry into a
:class:`~bonesim.errors.BonesimError` naming the file and the key.
"""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Iterable

from bonesim.errors import BonesimError

__all__ = ["read_toml", "check_keys", "get_number", "get_str", "get_vector"]


def read_toml(path: str | Path) -> dict:
    """Parse a TOML file, raising a clear error if it is missing or malformed."""
    path = Path(path)
    if not path.is_file():
        raise BonesimError("file not found", path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise BonesimError(f"malformed TOML: {exc}", path) from None
    except OSError as exc:
        raise BonesimError(f"cannot read: {exc.strerror}", path) from None


def check_keys(table: dict, allowed: Iterable[str], path: Path, where: str,
               required: Iterable[str] = ()) -> None:
    """Reject unknown keys and report missing required keys of one table.

    Parameters
    ----------
    table : dict
        The parsed table.
    allowed : iterable of str
        Keys that may appear.
    path : Path
        The manifest, for the message.
    where : str
        The table's name in the manifest (``"volume"``, ``"structures[2]"``).
    required : iterable of str
        Keys that must appear.
    """
    if not isinstance(table, dict):
        raise BonesimError(f"expected a table, got {type(table).__name__}", path, where)
    allowed = set(allowed)
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise BonesimError(
            f"unknown key(s) {', '.join(map(repr, unknown))}; allowed: "
            f"{', '.join(sorted(allowed))}", path, where)
    missing = [k for k in required if k not in table]
    if missing:
        raise BonesimError(f"missing required key(s) {', '.join(map(repr, missing))}",
                           path, where)


def get_number(table: dict, key: str, path: Path, where: str, default: Any = None,
               minimum: float | None = None, maximum: float | None = None,
               integer: bool = False) -> Any:
    """Fetch a numeric value, checking its type and range."""
    if key not in table:
        if default is None:
            raise BonesimError(f"missing required key '{key}'", path, where)
        return default
    value = table[key]
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok:
        kind = "an integer" if integer else "a number"
        raise BonesimError(f"'{key}' must be {kind}, got {value!r}", path, where)
    if minimum is not None and value < minimum:
        raise BonesimError(f"'{key}' must be >= {minimum}, got {value}", path, where)
    if maximum is not None and value > maximum:
        raise BonesimError(f"'{key}' must be <= {maximum}, got {value}", path, where)
    return value


def get_str(table: dict, key: str, path: Path, where: str, default: str | None = None,
            choices: Iterable[str] | None = None) -> str:
    """Fetch a string value, optionally one of ``choices``."""
    if key not in table:
        if default is None:
            raise BonesimError(f"missing required key '{key}'", path, where)
        return default
    value = table[key]
    if not isinstance(value, str):
        raise BonesimError(f"'{key}' must be a string, got {value!r}", path, where)
    if choices is not None:
        choices = list(choices)
        if value not in choices:
            raise BonesimError(f"'{key}' must be one of {choices}, got {value!r}",
                               path, where)
    return value


def get_vector(table: dict, key: str, path: Path, where: str, length: int = 3,
               default: Any = None, integer: bool = False) -> tuple:
    """Fetch a fixed-length list of numbers (e.g. ``[x, y, z]`` in mm)."""
    if key not in table:
        if default is None:
            raise BonesimError(f"missing required key '{key}'", path, where)
        return tuple(default)
    value = table[key]
    kinds = (int,) if integer else (int, float)
    if (not isinstance(value, list) or len(value) != length
            or any(isinstance(v, bool) or not isinstance(v, kinds) for v in value)):
        kind = "integers" if integer else "numbers"
        raise BonesimError(f"'{key}' must be a list of {length} {kind}, got {value!r}",
                           path, where)
    return tuple(value)
