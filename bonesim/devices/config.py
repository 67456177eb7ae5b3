"""The user's device configuration: settings and calibrations in one TOML file.

The file is ``$BONESIM_DEVICES_CONFIG`` if set, else
``$XDG_CONFIG_HOME/bonesim/devices.toml`` (``~/.config/bonesim/devices.toml``).
It need not exist. Layout::

    [devices.spacemouse]            # settings of a backend (its own keys)
    translation_mm_s = 40.0

    [calibration.adu100-handle.default]     # per backend, per device id
    channels = [0, 1]
    open = [12.0, 240.0]            # raw readings, fully open
    closed = [230.0, 15.0]          # raw readings, fully closed
    open_deg = 0.0
    closed_deg = 30.0

:func:`load_config` reads and checks it (errors name the file and the key);
:func:`save_config` writes it back (a small TOML writer for these tables:
nested tables of strings, numbers, booleans and flat lists).
"""
from __future__ import annotations

import math
import os
import re
from pathlib import Path

from bonesim.errors import BonesimError
from bonesim.tomlfile import read_toml

__all__ = ["CONFIG_ENV", "config_path", "load_config", "save_config", "device_settings",
           "calibration", "set_calibration", "dump_toml"]

#: Environment variable naming the config file (tests, several set-ups).
CONFIG_ENV = "BONESIM_DEVICES_CONFIG"
_TOP = ("devices", "calibration")
_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def config_path() -> Path:
    """Where the device configuration lives (see the module docstring)."""
    p = os.environ.get(CONFIG_ENV)
    if p:
        return Path(p)
    xdg = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(xdg) / "bonesim" / "devices.toml"


def load_config(path=None) -> dict:
    """The configuration (``{"devices": {...}, "calibration": {...}}``); empty
    tables when the file does not exist."""
    path = config_path() if path is None else Path(path)
    if not path.exists():
        return {"devices": {}, "calibration": {}}
    data = read_toml(path)
    for k in data:
        if k not in _TOP:
            raise BonesimError(f"unknown table {k!r} (expected {', '.join(_TOP)})", path, k)
    for k in _TOP:
        data.setdefault(k, {})
        if not isinstance(data[k], dict):
            raise BonesimError("must be a table", path, k)
        for name, v in data[k].items():
            if not isinstance(v, dict):
                raise BonesimError("must be a table", path, f"{k}.{name}")
            _check_finite(v, path, f"{k}.{name}")
    return data


def _check_finite(value, path: Path, where: str) -> None:
    """Refuse NaN and infinity anywhere in a settings or calibration table
    (a device would turn them into a NaN pose or force)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise BonesimError(f"must be a finite number, got {value!r}", path, where)
    if isinstance(value, dict):
        for key, v in value.items():
            _check_finite(v, path, f"{where}.{key}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _check_finite(v, path, f"{where}[{i}]")


def save_config(cfg: dict, path=None) -> Path:
    """Write ``cfg`` (atomically: a temporary file renamed over it)."""
    path = config_path() if path is None else Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(dump_toml(cfg))
    os.replace(tmp, path)
    return path


def device_settings(name: str, cfg: dict | None = None) -> dict:
    """The ``[devices.NAME]`` table (empty if none)."""
    cfg = load_config() if cfg is None else cfg
    return dict(cfg["devices"].get(name, {}))


def calibration(name: str, device_id: str = "default", cfg: dict | None = None) -> dict | None:
    """The calibration of backend ``name``'s device ``device_id``, or None."""
    cfg = load_config() if cfg is None else cfg
    c = cfg["calibration"].get(name, {}).get(device_id)
    return None if c is None else dict(c)


def set_calibration(name: str, device_id: str, values: dict, path=None) -> Path:
    """Store a calibration (replacing the device's previous one); returns the file."""
    cfg = load_config(path)
    cfg["calibration"].setdefault(name, {})[device_id] = dict(values)
    return save_config(cfg, path)


def _key(k: str) -> str:
    return k if _BARE.match(k) else '"' + k.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _value(v, where: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return ("-inf" if v < 0 else "inf") if v == v else "nan"
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x, where) for x in v) + "]"
    raise TypeError(f"{where}: cannot write {type(v).__name__} to TOML")


def dump_toml(data: dict, _prefix: str = "") -> str:
    """TOML text of nested dicts of scalars and flat lists."""
    lines, subs = [], []
    for k, v in data.items():
        if isinstance(v, dict):
            subs.append((k, v))
        else:
            lines.append(f"{_key(k)} = {_value(v, _prefix + k)}")
    out = []
    if lines:
        if _prefix:
            out.append(f"[{_prefix.rstrip('.')}]")
        out += lines
        out.append("")
    for k, v in subs:
        out.append(dump_toml(v, _prefix + _key(k) + "."))
    return "\n".join(x for x in out if x is not None)
