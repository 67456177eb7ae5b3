"""Burr definitions: loading, checking and listing.

Burrs are declared in TOML. The shipped ones live in the :mod:`burrs` package
folder (one file per family: ``cutting.toml``, ``diamond.toml``); a user may
also pass the path of a file of their own.

File formats
------------
*Family file*: a ``[family]`` table with ``kind`` (``"cutting"`` or
``"diamond"``), an optional ``name`` (defaults to the file name's stem) and
any shared field values, followed by ``[[burr]]`` entries. Each entry needs
``diameter_mm`` and may override any shared field; every field of
:class:`Burr` must end up set by the entry or by the family::

    [family]
    kind = "cutting"
    r_max = 4.0
    falloff = 2.0
    # ...

    [[burr]]
    diameter_mm = 3.0
    k_low = 1.46
    # ...

*Single-burr file*: one ``[burr]`` table carrying ``kind``, ``diameter_mm``,
every field, and optionally ``family`` (defaults to the kind).

A burr is named ``<family>-<d>mm`` with ``d`` the diameter without trailing
zeros (``cutting-5mm``, ``cutting-2.5mm``). :func:`load_burr` takes either
such a name (looked up among the shipped burrs) or a path; a family file with
several burrs needs ``path#name``.

Force and removal laws (what the fields parameterize)
-----------------------------------------------------
With ``V`` the immersed burr volume [mm^3] and ``V_t = n_t_fraction *
volume_mm3`` the threshold volume, the contact force magnitude is
``k_low * V`` for ``V <= V_t`` and ``k_low * V_t + k_high * (V - V_t)``
above, clamped to ``max_force_n`` (see :meth:`Burr.force_n`). Each immersed
sample removes density from its voxel at ``f * max(0, r_max - falloff *
|pi/2 - theta|)`` per second, ``f`` the applied force [N] and ``theta`` the
angle between the drill axis and the sample's offset from the burr centre
(see :meth:`Burr.removal_per_n`).
"""
from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Iterable

import numpy as np

import burrs as _burr_package

from bonesim.errors import BonesimError
from bonesim.io.limits import check
from bonesim.tomlfile import check_keys, get_str, read_toml

__all__ = ["DEFAULT_BURR", "BURR_KINDS", "CONTACT_LEVELS", "Burr", "burr_folder", "load_burr", "load_burr_file",
           "list_burrs", "burr_table"]

#: Burr kinds the simulator models.
#: The burr a run starts with when none is named.
DEFAULT_BURR = "cutting-5mm"

BURR_KINDS = ("cutting", "diamond")

#: Contact levels reported by :meth:`Burr.contact_level`, weakest first.
CONTACT_LEVELS = ("none", "light", "firm")

# A family name: a letter, then letters, digits, '_' or '-'.
_FAMILY_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]*\Z")
# A burr name: "<family>-<number>mm".
_BURR_NAME = re.compile(r"(?P<family>[A-Za-z][A-Za-z0-9_-]*?)-(?P<d>[0-9.eE+-]+)mm\Z")
# Separates a file path from the burr picked inside it.
_PICK = "#"


@dataclass(frozen=True)
class Burr:
    """One burr: geometry, removal, contact force, vibration and sound data.

    Attributes
    ----------
    name : str
        ``<family>-<d>mm``, e.g. ``"cutting-5mm"``.
    family : str
        The family the burr came from (``"cutting"``, ``"diamond"`` or a
        user's own).
    kind : str
        ``"cutting"`` or ``"diamond"``.
    diameter_mm : float
        Head diameter [mm].
    r_max : float
        Maximum removal rate per unit applied force, reached at the burr's
        equator [1/(N*s)]: density units (1 = a whole voxel) removed per
        second per newton, per immersed sample.
    falloff : float
        Removal rate lost per radian away from the equator [1/(N*s*rad)]
        (written [1/rad] in the files, relative to ``r_max``'s unit).
    k_low : float
        Force gain per mm^3 of immersed burr volume below the threshold
        [N/mm^3].
    k_high : float
        Force gain per mm^3 above the threshold [N/mm^3]; ``>= k_low``.
    n_t_fraction : float
        Threshold volume as a fraction of the burr's volume, in (0, 1).
    k_tan : float
        Tangential (drag) gain [N/mm^4]: force per mm^3 of immersed volume
        per mm of distance from the drill axis.
    max_force_n : float
        Clamp on the contact force magnitude [N].
    vib_free_hz, vib_contact_hz : float
        Main vibration peak when free running and in bone contact [Hz].
    vib_amp_n : float
        Base vibration amplitude [N].
    vib_amp_per_n : float
        Growth of the vibration amplitude per newton of applied force [N/N].
    vib_harmonics : tuple of (float, float)
        Low-frequency components a ~1 kHz haptic loop can render, as
        ``(freq_hz, rel_amp)`` pairs (amplitude relative to the current
        vibration amplitude).
    sound_base_hz : float
        Fundamental of the drill sound with no load [Hz].
    sound_harmonics : tuple of (float, float)
        ``(multiple, rel_amp)`` pairs: partials at ``multiple`` times the
        current fundamental.
    sound_noise : float
        Share of broadband noise in the sound, 0 (tones only) to 1.
    sound_force_hz_per_n : float
        Shift of the fundamental per newton of applied force [Hz/N]
        (negative: the motor slows under load).
    sound_contact_light_n, sound_contact_firm_n : float
        Force thresholds [N] of the contact levels: below ``light`` there
        is no contact, from ``firm`` on the contact is firm.
    thin_bone_mm : float
        Bone thickness under the burr below which the pitch rises [mm].
    thin_bone_gain : float
        Relative pitch rise at zero thickness (0.3 = +30 %); the rise is
        linear in thickness between ``thin_bone_mm`` and 0.
    default_speed_rpm, max_speed_rpm : float
        Default and maximum rotation speed [rpm].
    source : Path or None
        The file the burr was read from (not compared).
    """

    name: str
    family: str
    kind: str
    diameter_mm: float
    r_max: float
    falloff: float
    k_low: float
    k_high: float
    n_t_fraction: float
    k_tan: float
    max_force_n: float
    vib_free_hz: float
    vib_contact_hz: float
    vib_amp_n: float
    vib_amp_per_n: float
    vib_harmonics: tuple
    sound_base_hz: float
    sound_harmonics: tuple
    sound_noise: float
    sound_force_hz_per_n: float
    sound_contact_light_n: float
    sound_contact_firm_n: float
    thin_bone_mm: float
    thin_bone_gain: float
    default_speed_rpm: float
    max_speed_rpm: float
    source: Path | None = field(default=None, compare=False)

    @property
    def radius_mm(self) -> float:
        """Head radius [mm]."""
        return self.diameter_mm / 2.0

    @property
    def volume_mm3(self) -> float:
        """Volume of the spherical head [mm^3]."""
        return 4.0 / 3.0 * math.pi * self.radius_mm ** 3

    @property
    def threshold_mm3(self) -> float:
        """Immersed volume where the force gain switches to ``k_high`` [mm^3]."""
        return self.n_t_fraction * self.volume_mm3

    def force_n(self, immersed_mm3):
        """Contact force magnitude for an immersed volume (multi-gain law).

        Parameters
        ----------
        immersed_mm3 : float or array_like
            Immersed burr volume [mm^3] (number of immersed samples times
            the volume per sample).

        Returns
        -------
        float or ndarray
            Force magnitude [N], clamped to ``max_force_n``.
        """
        v = np.maximum(np.asarray(immersed_mm3, dtype=float), 0.0)
        vt = self.threshold_mm3
        f = np.where(v <= vt, self.k_low * v, self.k_low * vt + self.k_high * (v - vt))
        f = np.minimum(f, self.max_force_n)
        return float(f) if f.ndim == 0 else f

    def removal_per_n(self, theta_rad):
        """Removal rate per newton at polar angle ``theta_rad`` [1/(N*s)].

        Parameters
        ----------
        theta_rad : float or array_like
            Angle between the drill axis and the sample's offset from the
            burr centre [rad]; pi/2 is the equator.

        Returns
        -------
        float or ndarray
            ``max(0, r_max - falloff * |pi/2 - theta|)``.
        """
        theta = np.asarray(theta_rad, dtype=float)
        rate = np.maximum(0.0, self.r_max - self.falloff * np.abs(np.pi / 2 - theta))
        return float(rate) if rate.ndim == 0 else rate

    def contact_level(self, force_n: float) -> str:
        """Sound contact level for an applied force [N]: none, light or firm."""
        if force_n < self.sound_contact_light_n:
            return CONTACT_LEVELS[0]
        if force_n < self.sound_contact_firm_n:
            return CONTACT_LEVELS[1]
        return CONTACT_LEVELS[2]


# --------------------------------------------------------------------------
# Field rules
# --------------------------------------------------------------------------

@dataclass(frozen=True)
class _Range:
    """Allowed range of a number: ``low``/``high`` bounds, open or closed."""

    low: float | None = None
    low_open: bool = False
    high: float | None = None
    high_open: bool = False

    def describe(self) -> str:
        parts = []
        if self.low is not None:
            parts.append(f"{'>' if self.low_open else '>='} {self.low:g}")
        if self.high is not None:
            parts.append(f"{'<' if self.high_open else '<='} {self.high:g}")
        return " and ".join(parts) if parts else "finite"

    def holds(self, x: float) -> bool:
        if self.low is not None and (x <= self.low if self.low_open else x < self.low):
            return False
        if self.high is not None and (x >= self.high if self.high_open else x > self.high):
            return False
        return True


@dataclass(frozen=True)
class _Pairs:
    """A list of ``[a, b]`` number pairs, each element with its range."""

    first: _Range
    second: _Range
    labels: tuple
    min_len: int = 0


_POSITIVE = _Range(0.0, low_open=True)
_NON_NEGATIVE = _Range(0.0)
_ANY = _Range()
_FRACTION_OPEN = _Range(0.0, True, 1.0, True)
_FRACTION_CLOSED = _Range(0.0, False, 1.0, False)

# Every field a family or a burr entry may set (diameter_mm only on entries).
_SHARED_FIELDS: dict[str, _Range | _Pairs] = {
    "r_max": _NON_NEGATIVE,
    "falloff": _NON_NEGATIVE,
    "k_low": _POSITIVE,
    "k_high": _POSITIVE,
    "n_t_fraction": _FRACTION_OPEN,
    "k_tan": _NON_NEGATIVE,
    "max_force_n": _POSITIVE,
    "vib_free_hz": _POSITIVE,
    "vib_contact_hz": _POSITIVE,
    "vib_amp_n": _NON_NEGATIVE,
    "vib_amp_per_n": _NON_NEGATIVE,
    "vib_harmonics": _Pairs(_POSITIVE, _NON_NEGATIVE, ("freq_hz", "rel_amp")),
    "sound_base_hz": _POSITIVE,
    "sound_harmonics": _Pairs(_POSITIVE, _NON_NEGATIVE, ("multiple", "rel_amp"),
                              min_len=1),
    "sound_noise": _FRACTION_CLOSED,
    "sound_force_hz_per_n": _ANY,
    "sound_contact_light_n": _POSITIVE,
    "sound_contact_firm_n": _POSITIVE,
    "thin_bone_mm": _POSITIVE,
    "thin_bone_gain": _NON_NEGATIVE,
    "default_speed_rpm": _POSITIVE,
    "max_speed_rpm": _POSITIVE,
}
_DIAMETER = ("diameter_mm", _POSITIVE)
# Fields checked against the physical bounds of bonesim/data/limits.toml.
_BOUNDED = {"diameter_mm": "burr_diameter_mm", "default_speed_rpm": "speed_rpm",
            "max_speed_rpm": "speed_rpm"}
_FAMILY_KEYS = ("name", "kind")
_SINGLE_KEYS = ("family", "kind")

# Pairs (lower, upper) of fields where lower <= upper must hold, with whether
# equality is allowed.
_ORDERED = (
    ("k_low", "k_high", True),
    ("sound_contact_light_n", "sound_contact_firm_n", False),
    ("default_speed_rpm", "max_speed_rpm", True),
)


def _check_value(key: str, value: Any, path: Path, where: str) -> Any:
    """Check one field value's type and range; return it normalized."""
    rule = _SHARED_FIELDS[key] if key in _SHARED_FIELDS else _DIAMETER[1]
    if isinstance(rule, _Pairs):
        return _check_pairs(key, value, rule, path, where)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise BonesimError(f"'{key}' must be a number, got {value!r}", path, where)
    if not math.isfinite(value):
        raise BonesimError(f"'{key}' must be finite, got {value!r}", path, where)
    if not rule.holds(value):
        raise BonesimError(f"'{key}' must be {rule.describe()}, got {value!r}",
                           path, where)
    if key in _BOUNDED:                 # physical bounds (bonesim/data/limits.toml)
        check(_BOUNDED[key], value, path, where, what=f"'{key}'")
    return float(value)


def _check_pairs(key: str, value: Any, rule: _Pairs, path: Path, where: str) -> tuple:
    shape = f"a list of [{rule.labels[0]}, {rule.labels[1]}] pairs"
    if not isinstance(value, list):
        raise BonesimError(f"'{key}' must be {shape}, got {value!r}", path, where)
    if len(value) < rule.min_len:
        raise BonesimError(f"'{key}' needs at least {rule.min_len} "
                           f"[{rule.labels[0]}, {rule.labels[1]}] pair(s)", path, where)
    out = []
    for i, pair in enumerate(value):
        if (not isinstance(pair, list) or len(pair) != 2
                or any(isinstance(v, bool) or not isinstance(v, (int, float))
                       or not math.isfinite(v) for v in pair)):
            raise BonesimError(f"'{key}' item {i} must be [{rule.labels[0]}, "
                               f"{rule.labels[1]}] (two finite numbers), got {pair!r}",
                               path, where)
        for v, r, label in zip(pair, (rule.first, rule.second), rule.labels):
            if not r.holds(v):
                raise BonesimError(f"'{key}' item {i}: {label} must be "
                                   f"{r.describe()}, got {v!r}", path, where)
        out.append((float(pair[0]), float(pair[1])))
    return tuple(out)


def _check_table(table: Any, allowed: Iterable[str], path: Path, where: str,
                 required: Iterable[str] = (), misplaced: dict[str, str] | None = None
                 ) -> dict:
    """Check a table's keys and field values; return the checked fields."""
    if isinstance(table, dict) and misplaced:
        for key, hint in misplaced.items():
            if key in table:
                raise BonesimError(f"'{key}' is not allowed here; {hint}", path, where)
    check_keys(table, allowed, path, where, required)
    return {k: _check_value(k, v, path, where) for k, v in table.items()
            if k in _SHARED_FIELDS or k == _DIAMETER[0]}


def _format_diameter(d: float) -> str:
    return f"{d:g}"


def _build(family: str, kind: str, values: dict, path: Path, where: str) -> Burr:
    """Make a :class:`Burr` from merged values, checking completeness."""
    name = f"{family}-{_format_diameter(values['diameter_mm'])}mm"
    where = f"{where} ({name})"
    missing = [k for k in _SHARED_FIELDS if k not in values]
    if missing:
        raise BonesimError(
            f"missing field(s) {', '.join(map(repr, missing))}; set them in "
            f"[family] or in this burr's entry", path, where)
    for low, high, equal_ok in _ORDERED:
        a, b = values[low], values[high]
        if a > b or (a == b and not equal_ok):
            rel = "<=" if equal_ok else "<"
            raise BonesimError(f"'{low}' ({a:g}) must be {rel} '{high}' ({b:g})",
                               path, where)
    lowest_hz = values["sound_base_hz"] + values["sound_force_hz_per_n"] * values["max_force_n"]
    if lowest_hz <= 0:
        raise BonesimError(
            f"'sound_force_hz_per_n' ({values['sound_force_hz_per_n']:g}) would drive "
            f"the sound to {lowest_hz:g} Hz at max_force_n; the pitch must stay > 0",
            path, where)
    return Burr(name=name, family=family, kind=kind, source=path, **values)


# --------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------

def burr_folder() -> Path:
    """Folder of the shipped burr family files (the :mod:`burrs` package)."""
    return _burr_package.folder()


def load_burr_file(path: str | Path) -> list[Burr]:
    """Read every burr defined in one family file or single-burr file.

    Parameters
    ----------
    path : str or Path
        A ``.toml`` family file (``[family]`` + ``[[burr]]`` entries) or a
        single-burr file (one ``[burr]`` table); see the module docstring.

    Returns
    -------
    list of Burr
        In file order.

    Raises
    ------
    BonesimError
        If the file is missing or malformed, has unknown keys, wrong types,
        out-of-range values, missing fields, or defines a name twice.
    """
    path = Path(path)
    doc = read_toml(path)
    if "family" in doc:
        return _read_family(doc, path)
    if isinstance(doc.get("burr"), dict):
        return [_read_single(doc, path)]
    if "burr" in doc:
        raise BonesimError("[[burr]] entries need a [family] table (with at least "
                           "'kind'); a single-burr file uses one [burr] table", path)
    raise BonesimError("no burr found: expected a [family] table with [[burr]] "
                       "entries, or a single [burr] table", path)


def _read_family(doc: dict, path: Path) -> list[Burr]:
    check_keys(doc, ("family", "burr"), path, "top level")
    fam = _check_table(
        doc["family"], (*_FAMILY_KEYS, *_SHARED_FIELDS), path, "family",
        required=("kind",),
        misplaced={"diameter_mm": "diameters go in the [[burr]] entries"})
    family_table = doc["family"]
    kind = get_str(family_table, "kind", path, "family", choices=BURR_KINDS)
    family = get_str(family_table, "name", path, "family", default=path.stem)
    if not _FAMILY_NAME.match(family):
        raise BonesimError(f"'name' must start with a letter and hold only letters, "
                           f"digits, '_' or '-', got {family!r}", path, "family")
    entries = doc.get("burr")
    if isinstance(entries, dict):
        raise BonesimError("a family file lists its burrs as [[burr]] entries "
                           "(double brackets), not one [burr] table", path, "burr")
    if not isinstance(entries, list) or not entries:
        raise BonesimError("a family file needs at least one [[burr]] entry "
                           "(with 'diameter_mm')", path, "burr")
    out: list[Burr] = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(entries):
        where = f"burr[{i}]"
        own = _check_table(
            entry, (_DIAMETER[0], *_SHARED_FIELDS), path, where,
            required=(_DIAMETER[0],),
            misplaced={"kind": "set 'kind' once in [family]",
                       "name": "burr names are made from the family and diameter",
                       "family": "set the family 'name' in [family]"})
        burr = _build(family, kind, {**fam, **own}, path, where)
        if burr.name in seen:
            raise BonesimError(f"duplicate burr '{burr.name}' (same diameter as "
                               f"burr[{seen[burr.name]}])", path, where)
        seen[burr.name] = i
        out.append(burr)
    return out


def _read_single(doc: dict, path: Path) -> Burr:
    check_keys(doc, ("burr",), path, "top level")
    table = doc["burr"]
    values = _check_table(table, (*_SINGLE_KEYS, _DIAMETER[0], *_SHARED_FIELDS),
                          path, "burr", required=("kind", _DIAMETER[0]))
    kind = get_str(table, "kind", path, "burr", choices=BURR_KINDS)
    family = get_str(table, "family", path, "burr", default=kind)
    if not _FAMILY_NAME.match(family):
        raise BonesimError(f"'family' must start with a letter and hold only "
                           f"letters, digits, '_' or '-', got {family!r}", path, "burr")
    return _build(family, kind, values, path, "burr")


def list_burrs() -> list[Burr]:
    """All shipped burrs, sorted by kind, then diameter, then name.

    Raises
    ------
    BonesimError
        If a shipped file is invalid or two files define the same name.
    """
    found: dict[str, Burr] = {}
    for path in sorted(burr_folder().glob("*.toml")):
        for burr in load_burr_file(path):
            if burr.name in found:
                raise BonesimError(f"duplicate burr '{burr.name}', also defined in "
                                   f"{found[burr.name].source}", path)
            found[burr.name] = burr
    return sorted(found.values(), key=lambda b: (b.kind, b.diameter_mm, b.name))


def _looks_like_path(text: str) -> bool:
    base = text.split(_PICK, 1)[0]
    return "/" in base or "\\" in base or base.lower().endswith(".toml")


def _canonical(name: str) -> str:
    """``cutting-5.0mm`` -> ``cutting-5mm``; other text is returned as is."""
    m = _BURR_NAME.match(name.strip())
    if not m:
        return name.strip()
    try:
        d = float(m.group("d"))
    except ValueError:
        return name.strip()
    return f"{m.group('family')}-{_format_diameter(d)}mm"


def _pick(burrs: list[Burr], name: str, path: Path) -> Burr:
    wanted = _canonical(name)
    for burr in burrs:
        if burr.name == wanted:
            return burr
    names = [b.name for b in burrs]
    close = difflib.get_close_matches(wanted, names, n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    raise BonesimError(f"unknown burr '{name}'{hint}; known burrs: {', '.join(names)}",
                       path)


def load_burr(name_or_path: str | Path) -> Burr:
    """Load one burr by name or from a file.

    Parameters
    ----------
    name_or_path : str or Path
        A shipped burr's name (``"cutting-5mm"``; ``"cutting-5.0mm"`` works
        too), the path of a single-burr file or of a family file defining one
        burr, or ``"path/to/family.toml#name"`` to pick one burr of a family
        file. Text is taken as a path if it contains a path separator or ends
        in ``.toml``.

    Returns
    -------
    Burr

    Raises
    ------
    BonesimError
        If the name is unknown (the message lists the known burrs) or the
        file is missing or invalid.
    """
    if isinstance(name_or_path, Path):
        text, is_path = str(name_or_path), True
    elif isinstance(name_or_path, str):
        text, is_path = name_or_path, _looks_like_path(name_or_path)
    else:
        raise BonesimError(f"a burr is given by name or path, got {name_or_path!r}")
    if not is_path:
        return _pick(list_burrs(), text, burr_folder())
    if isinstance(name_or_path, Path):
        path, wanted = name_or_path, ""
    else:
        file_part, sep, wanted = text.rpartition(_PICK)
        path = Path(file_part if sep else wanted)
        wanted = wanted if sep else ""
    burrs = load_burr_file(path)
    if wanted:
        return _pick(burrs, wanted, path)
    if len(burrs) == 1:
        return burrs[0]
    names = ", ".join(b.name for b in burrs)
    raise BonesimError(f"the file defines {len(burrs)} burrs ({names}); pick one "
                       f"with '{path}{_PICK}<name>'", path)


def burr_table(burrs: Iterable[Burr]) -> list[dict]:
    """Plain rows describing burrs, ready for JSON (``bonesim burrs --json``).

    Parameters
    ----------
    burrs : iterable of Burr

    Returns
    -------
    list of dict
        One dict per burr, in the given order: every :class:`Burr` field
        (pairs as lists, ``source`` as a string or None) plus ``radius_mm``.
    """
    rows = []
    for burr in burrs:
        row: dict[str, Any] = {}
        for f in fields(burr):
            value = getattr(burr, f.name)
            if f.name == "diameter_mm":
                row[f.name] = value
                row["radius_mm"] = burr.radius_mm
                continue
            if isinstance(value, tuple):
                value = [list(pair) for pair in value]
            elif isinstance(value, Path):
                value = str(value)
            row[f.name] = value
        rows.append(row)
    return rows
