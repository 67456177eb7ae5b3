"""Physical bounds of size-like inputs and the machine's memory, checked
before anything is allocated.

The bounds live in one data file, ``bonesim/data/limits.toml``: for each
quantity a ``min``, ``max``, ``unit`` and ``why``. :func:`check` refuses a
value outside them (or not a finite number) with one line naming the file
and field it came from, the bounds and the data file. :func:`check_memory`
refuses an estimate beyond the memory this process can still get
(:func:`available_memory`), with the estimate in the message.
"""
from __future__ import annotations

import math
import os
import resource
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from bonesim.errors import BonesimError
from bonesim.resources import data_path
from bonesim.tomlfile import read_toml

__all__ = ["LIMITS_FILE", "Bound", "bound", "check", "check_grid", "check_burr_lattice", "setting", "available_memory",
           "format_bytes", "check_memory"]

#: The data file holding the bounds.
LIMITS_FILE = "limits.toml"
_SETTINGS = ("memory", "reading", "network")


@dataclass(frozen=True)
class Bound:
    """One quantity's physical bounds.

    Attributes
    ----------
    name : str
        Its table in ``limits.toml``.
    min, max : float
        Inclusive bounds, in ``unit``.
    unit : str
        ``mm``, ``rpm``, ``s``, ``px``, ...
    why : str
        Where the bounds come from.
    """

    name: str
    min: float
    max: float
    unit: str
    why: str

    def text(self) -> str:
        """``0.2 .. 12 mm``."""
        return f"{self.min:g} .. {self.max:g} {self.unit}"


@lru_cache(maxsize=None)
def _table() -> dict:
    path = data_path(LIMITS_FILE)
    doc = read_toml(path)
    out = {}
    for name, tab in doc.items():
        if name in _SETTINGS:
            continue
        try:
            b = Bound(name, float(tab["min"]), float(tab["max"]), str(tab["unit"]),
                      str(tab["why"]))
        except (KeyError, TypeError, ValueError):
            raise BonesimError("needs min, max (numbers), unit and why", path, name) \
                from None
        if not (math.isfinite(b.min) and math.isfinite(b.max) and b.min <= b.max):
            raise BonesimError("min and max must be finite with min <= max", path, name)
        out[name] = b
    return out


def bound(name: str) -> Bound:
    """The bounds of quantity ``name`` (a table of ``limits.toml``)."""
    try:
        return _table()[name]
    except KeyError:
        raise KeyError(f"{name!r} is not in {LIMITS_FILE}") from None


def setting(table: str, key: str) -> float:
    """A number of ``limits.toml``'s ``[memory]`` or ``[reading]`` tables."""
    return read_toml(data_path(LIMITS_FILE))[table][key]


def check(name: str, value, path: str | Path | None = None, field: str | None = None,
          what: str | None = None) -> float:
    """``value`` if it is a finite number within the bounds of ``name``.

    Parameters
    ----------
    name : str
        The quantity (a table of ``limits.toml``).
    value : float or int
        In the quantity's unit.
    path, field : optional
        The file and field (or the command-line option) it came from.
    what : str, optional
        How to call it in the message (default ``name``).

    Returns
    -------
    float

    Raises
    ------
    BonesimError
        Not a number, NaN or infinite, or outside the bounds.
    """
    b = bound(name)
    label = name if what is None else what
    lead = f"{label} " if label else ""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise BonesimError(f"{lead}must be a number [{b.unit}], got {value!r}", path,
                           field) from None
    if not math.isfinite(v):
        raise BonesimError(f"{lead}must be a finite number [{b.unit}], got {value!r}",
                           path, field)
    if not b.min <= v <= b.max:
        raise BonesimError(f"{lead}{v:g} {b.unit} is outside the physical bounds "
                           f"{b.text()} ({b.why}; bonesim/data/{LIMITS_FILE})", path, field)
    return v


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _cgroup_available() -> int | None:
    base = Path("/sys/fs/cgroup")
    try:
        limit = (base / "memory.max").read_text().strip()
        if limit == "max":
            return None
        return int(limit) - int((base / "memory.current").read_text())
    except (OSError, ValueError):
        return None


def _address_space_left() -> int | None:
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmSize:"):
                    return soft - int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return soft


def available_memory() -> int | None:
    """Bytes this process can still allocate: the least of the machine's
    available memory (``MemAvailable``), its control group's headroom and its
    address-space limit (``RLIMIT_AS``) less what it maps already; None if
    none is known."""
    known = [v for v in (_meminfo_available(), _cgroup_available(),
                         _address_space_left()) if v is not None]
    return max(min(known), 0) if known else None


def format_bytes(n: float) -> str:
    """``524 GiB``, ``7.1 PiB``, ``310 MiB``."""
    n = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            break
        n /= 1024
    if unit == "PiB" and n >= 1e4:
        return f"{n:.3g} PiB"
    return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"


def check_memory(estimate_bytes: float, what: str, path: str | Path | None = None,
                 field: str | None = None) -> None:
    """Refuse work whose memory ``estimate_bytes`` exceeds what is available.

    Raises
    ------
    BonesimError
        ``<what> needs about 524 GiB of memory; 20.1 GiB are available``.
    """
    free = available_memory()
    if free is not None and estimate_bytes > free:
        raise BonesimError(f"{what} needs about {format_bytes(estimate_bytes)} of memory; "
                           f"{format_bytes(free)} are available here", path, field)


def check_grid(extent_mm, voxel_mm: float, path: str | Path | None = None,
               field: str | None = None) -> int:
    """Refuse an isotropic grid too big to build, before it is allocated.

    Parameters
    ----------
    extent_mm : (3,) float
        The volume's physical extent per axis [mm] (each within
        ``case_extent_mm``).
    voxel_mm : float
        The engine's voxel edge [mm].
    path, field : optional
        Where extent and voxel come from, for the message.

    Returns
    -------
    int
        The grid's voxel count.

    Raises
    ------
    BonesimError
        An extent outside its bounds, more voxels than ``grid_voxels``
        allows, or an estimated memory (``[memory] engine_bytes_per_voxel``
        per voxel) beyond what is available.
    """
    extent = [check("case_extent_mm", e, path, field, what="the case's extent") for e in extent_mm]
    shape = [max(1, math.ceil(e / voxel_mm - 1e-9)) for e in extent]
    voxels = math.prod(shape)
    grid = " x ".join(str(n) for n in shape)
    b = bound("grid_voxels")
    if voxels > b.max:
        raise BonesimError(f"a {grid} grid ({voxels:.3g} voxels of {voxel_mm:g} mm over "
                           f"{' x '.join(f'{e:g}' for e in extent)} mm) is outside the "
                           f"physical bounds {b.text()} ({b.why}; bonesim/data/{LIMITS_FILE}); "
                           "use a coarser voxel_mm", path, field)
    check_memory(voxels * setting("memory", "engine_bytes_per_voxel"),
                 f"a {grid} grid of {voxel_mm:g} mm voxels", path, field)
    return voxels


def check_burr_lattice(diameter_mm: float, voxel_mm: float, oversample: int,
                       path: str | Path | None = None) -> int:
    """Refuse a burr whose sample lattice (``oversample`` samples per voxel
    edge across its diameter, a cube) would not fit in memory.

    Returns
    -------
    int
        The lattice's sample count.
    """
    check("oversample", oversample, field="oversample")
    per_axis = 2 * math.ceil(diameter_mm / 2 / (voxel_mm / oversample))
    samples = per_axis ** 3
    check_memory(samples * setting("memory", "burr_sample_bytes"),
                 f"the {diameter_mm:g} mm burr's sample lattice ({per_axis}^3 samples at "
                 f"{voxel_mm:g} mm voxels, oversample {oversample})", path, "burr")
    return samples
