"""The nerve's activity law: firing rate from the burr's distance, force and
drill, and Poisson spike trains of those rates.

With ``d`` the distance from the burr's surface to the nearest voxel of the
nerve [mm], ``F`` the force the burr presses with [N] and the drill on or
off::

    drive = near_gain_hz * exp(-max(d, 0) / length_mm) + contact_hz * (d <= contact_mm)
    h     = force_floor + (1 - force_floor) * min(F / force_sat_n, 1)
    w     = 1 (drill running) or drill_off (stopped)
    rate  = min(max_hz, baseline_hz + w * h * drive)            [spikes/s]

:func:`activity` evaluates it with the parameters of ``bonesim/data/monitor.toml``
(:class:`ActivityParams`, :func:`load_activity_params`). Spikes are a Poisson
process of that rate, piecewise constant between updates
(:func:`poisson_spikes`), drawn from a generator the caller seeds. The
monitor that applies the law to a run is :mod:`bonesim.runtime.monitor`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.tomlfile import check_keys, get_number, read_toml

__all__ = ["ActivityParams", "load_activity_params", "default_params_path", "activity",
           "default_activity_params", "poisson_spikes"]

# ------------------------------------------------------------- parameters
@dataclass(frozen=True)
class ActivityParams:
    """Parameters of the activity law (see the module docstring and
    ``bonesim/data/monitor.toml``).

    Attributes
    ----------
    baseline_hz : float
        Spontaneous firing far from the burr [spikes/s].
    near_gain_hz : float
        Extra firing with the burr surface at the nerve, full drive [spikes/s].
    length_mm : float
        E-folding distance of the near-field irritation [mm].
    contact_mm : float
        Burr surface this close to the nerve (its voxels' boxes) is contact [mm].
    contact_hz : float
        Burst train added on contact, full drive [spikes/s].
    force_floor : float
        Share of the drive with no force applied (0 to 1).
    force_sat_n : float
        Force at which the drive saturates [N].
    drill_off : float
        Share of the drive with the drill stopped (0 to 1).
    max_hz : float
        Ceiling of the firing rate [spikes/s].
    warn_mm : float
        Warning distance for the console and the trace [mm].
    margin_mm : float
        Reach of the former cropped distance table [mm]; no longer used (the
        distances are exact everywhere), kept so that monitor files load.
    """

    baseline_hz: float = 4.0
    near_gain_hz: float = 150.0
    length_mm: float = 0.66
    contact_mm: float = 0.25
    contact_hz: float = 200.0
    force_floor: float = 0.25
    force_sat_n: float = 2.0
    drill_off: float = 0.1
    max_hz: float = 400.0
    warn_mm: float = 1.0
    margin_mm: float = 10.0


#: Keys whose value must be strictly positive; the others must be >= 0.
_POSITIVE = ("length_mm", "force_sat_n", "max_hz", "margin_mm")
#: Keys that are shares (0 to 1).
_SHARES = ("force_floor", "drill_off")


def default_params_path() -> Path:
    """Path of the shipped ``monitor.toml``."""
    from bonesim.resources import data_path

    return data_path("monitor.toml")


def load_activity_params(path: str | Path | None = None) -> ActivityParams:
    """Read and check the ``[activity]`` table of a monitor file.

    Parameters
    ----------
    path : str or Path, optional
        Default: the shipped ``bonesim/data/monitor.toml``.

    Raises
    ------
    BonesimError
        Naming the file and the key for a missing, unknown or out-of-range
        value.
    """
    path = default_params_path() if path is None else Path(path)
    doc = read_toml(path)
    check_keys(doc, ("activity",), path, "top level", required=("activity",))
    tab = doc["activity"]
    names = [f.name for f in fields(ActivityParams)]
    check_keys(tab, names, path, "activity", required=names)
    values = {}
    for name in names:
        v = float(get_number(tab, name, path, "activity", minimum=0.0,
                             maximum=1.0 if name in _SHARES else None))
        if not math.isfinite(v) or (name in _POSITIVE and v <= 0.0):
            raise BonesimError(f"'{name}' must be a finite number > 0, got {v}",
                               path, "activity")
        values[name] = v
    if values["baseline_hz"] > values["max_hz"]:
        raise BonesimError(f"'baseline_hz' ({values['baseline_hz']}) exceeds 'max_hz' "
                           f"({values['max_hz']})", path, "activity")
    return ActivityParams(**values)


# ------------------------------------------------------------ activity law
def activity(distance_mm, force_n, drill, params: ActivityParams | None = None):
    """Firing rate of a nerve bundle [spikes/s] (the law in the module docstring).

    Parameters
    ----------
    distance_mm : float or array
        Burr surface to the nearest nerve voxel [mm] (negative: inside).
    force_n : float or array
        Force the burr presses with [N] (magnitude; NaN counts as 0).
    drill : bool or array
        Drill running.
    params : ActivityParams, optional
        Default: :func:`load_activity_params` of the shipped file.

    Returns
    -------
    float or ndarray
        Broadcast over the inputs.
    """
    p = _default_params() if params is None else params
    d = np.asarray(distance_mm, dtype=np.float64)
    f = np.nan_to_num(np.abs(np.asarray(force_n, dtype=np.float64)), nan=0.0)
    on = np.asarray(drill, dtype=bool)
    drive = p.near_gain_hz * np.exp(-np.maximum(d, 0.0) / p.length_mm) \
        + p.contact_hz * (d <= p.contact_mm)
    h = p.force_floor + (1.0 - p.force_floor) * np.minimum(f / p.force_sat_n, 1.0)
    w = np.where(on, 1.0, p.drill_off)
    rate = np.minimum(p.max_hz, p.baseline_hz + w * h * drive)
    return float(rate) if rate.ndim == 0 else rate


_PARAMS_CACHE: list = []


def default_activity_params() -> ActivityParams:
    """The shipped parameters, read once per process."""
    if not _PARAMS_CACHE:
        _PARAMS_CACHE.append(load_activity_params())
    return _PARAMS_CACHE[0]


# ------------------------------------------------------------------ spikes
def poisson_spikes(rng: np.random.Generator, t_edges, rates):
    """Spikes of Poisson processes with piecewise-constant rates.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness (seeded by the caller).
    t_edges : (n + 1,) float
        Interval boundaries [s], non-decreasing.
    rates : (n, k) float
        Rate of each of ``k`` processes in each interval [spikes/s].

    Returns
    -------
    t_s : (m,) float64
        Spike times, sorted, each inside its interval.
    which : (m,) uint8
        Process (nerve) of each spike.
    """
    t_edges = np.asarray(t_edges, dtype=np.float64)
    rates = np.asarray(rates, dtype=np.float64)
    dt = np.maximum(np.diff(t_edges), 0.0)
    counts = rng.poisson(np.maximum(rates, 0.0) * dt[:, None])
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0), np.zeros(0, dtype=np.uint8)
    flat = counts.ravel()
    cell = np.repeat(np.arange(flat.size), flat)
    interval, which = np.divmod(cell, rates.shape[1])
    t = t_edges[interval] + rng.random(total) * dt[interval]
    order = np.argsort(t, kind="stable")
    return t[order], which[order].astype(np.uint8)
