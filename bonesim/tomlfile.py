"""Reading and checking TOML manifests (cases, burrs, materials).

The helpers here turn every malformed or unexpected entry into a
:class:`~bonesim.errors.BonesimError` naming the file and the key.
"""
from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any, Iterable

from bonesim.errors import BonesimError

__all__ = ["read_toml", "parse_toml_bytes", "check_keys", "get_number", "get_str", "get_vector"]


def read_toml(path: str | Path) -> dict:
    """Parse a TOML file, raising a clear error if it is missing, not UTF-8
    text (a binary file given as a manifest) or malformed."""
    path = Path(path)
    if not path.is_file():
        raise BonesimError("file not found", path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise BonesimError(f"cannot read: {exc.strerror}", path) from None
    return parse_toml_bytes(raw, path)


def parse_toml_bytes(raw: bytes, path: str | Path) -> dict:
    """Parse the bytes of a TOML file named ``path`` (for the messages).

    Raises
    ------
    BonesimError
        One line: not UTF-8 (with the byte offset), a NUL byte (a binary
        file), or malformed TOML.
    """
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise BonesimError(f"not a UTF-8 text (TOML) file: byte {exc.start} is "
                           f"0x{raw[exc.start]:02x}", path) from None
    if "\x00" in text:
        raise BonesimError("not a text (TOML) file: it holds NUL bytes (a binary file?)",
                           path)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise BonesimError(f"malformed TOML: {exc}", path) from None


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
               integer: bool = False, finite: bool = True) -> Any:
    """Fetch a numeric value, checking its type and range.

    NaN is always refused; ``inf`` too unless ``finite`` is False (a field
    where infinity means something, such as a slope of vertical walls).
    """
    if key not in table:
        if default is None:
            raise BonesimError(f"missing required key '{key}'", path, where)
        return default
    value = table[key]
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok:
        kind = "an integer" if integer else "a number"
        raise BonesimError(f"'{key}' must be {kind}, got {value!r}", path, where)
    if isinstance(value, float) and (math.isnan(value) or (finite and math.isinf(value))):
        raise BonesimError(f"'{key}' must be finite, got {value!r}", path, where)
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
    if not all(math.isfinite(v) for v in value):
        raise BonesimError(f"'{key}' must hold finite numbers, got {value!r}", path, where)
    return tuple(value)
