"""Tool paths planned from a case: the scripted demo mastoidectomy.

:func:`plan_mastoidectomy` plans a cortical mastoidectomy for a loaded case as
a surgeon drills it (:mod:`bonesim.io.mastoid_plan`: the cavity from the
landmarks, a cutting burr for the bulk and a diamond burr near the sinus and
the tegmen, strokes along the walls, rinses between passes);
:func:`demo_trajectory` is the same plan drilled with one burr. The plan's
tunables are in ``bonesim/data/demo_plan.toml`` (:class:`DemoPlan`); the moves
and their clearance proofs are :mod:`bonesim.io.path_moves`.

The path is returned as a :class:`~bonesim.io.trajectory.Trajectory` (case
frame, mm) for ``bonesim simulate``; its ``burr`` column indexes
:attr:`PlannedRun.burrs`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path

from bonesim.errors import BonesimError
from bonesim.tomlfile import check_keys, get_number, get_str, read_toml
from bonesim.io.trajectory import Trajectory

__all__ = ["DemoPlan", "PlannedRun", "default_plan_path", "load_demo_plan",
           "plan_mastoidectomy", "demo_trajectory"]


@dataclass(frozen=True)
class DemoPlan:
    """Parameters of the demo mastoidectomy (``demo_plan.toml``; lengths [mm],
    speeds [mm/s], times [s]).

    Attributes
    ----------
    burr_radius_mm : float
        Radius of the cutting (bulk) burr [mm] (from the burr).
    speed_rpm : float
        Its spindle speed [rpm] (from the burr).
    finish_radius_mm : float
        Radius of the finishing burr [mm] (from :attr:`finish_burr`).
    finish_rpm : float
        Its spindle speed [rpm].
    line_overlap, column_mm, layer_mm, n_layers, margin_mm, speed_mm_s,
    travel_mm_s, plunge_mm_s, sample_hz, rinse_every_s, rinse_gap_mm,
    uncut_mm, suction_mm_s, irrigation_mm_s, irrigation_lift_mm,
    irrigation_every, region_radius_mm
        ``[plan]``: see the file.
    wall_slope, steep_slope, canal_wall_mm, sinus_over_mm, tegmen_keep_mm, tip_keep_mm,
    below_antrum_mm, edge_mm
        ``[cavity]``: the outline and the saucer.
    bulk_margin_mm, bulk_thin_mm, bulk_canal_mm
        ``[bulk]``: the cutting burr's margins.
    finish_burr, thin_margin_mm, canal_margin_mm, finish_layer_mm,
    finish_speed_mm_s, finish_gain_mm
        ``[finish]``: the finishing burr and its margins.
    """

    burr_radius_mm: float = 2.5
    speed_rpm: float = 60000.0
    finish_radius_mm: float = 1.5
    finish_rpm: float = 60000.0
    line_overlap: float = 0.5
    column_mm: float = 0.5
    layer_mm: float = 1.5
    n_layers: int = 24
    margin_mm: float = 1.0
    speed_mm_s: float = 25.0
    travel_mm_s: float = 60.0
    plunge_mm_s: float = 10.0
    sample_hz: float = 100.0
    rinse_every_s: float = 60.0
    rinse_gap_mm: float = 0.5
    uncut_mm: float = 1.0
    suction_mm_s: float = 40.0
    irrigation_mm_s: float = 60.0
    irrigation_lift_mm: float = 2.0
    irrigation_every: int = 2
    region_radius_mm: float = 0.0
    wall_slope: float = 1.2
    steep_slope: float = math.inf
    canal_wall_mm: float = 0.5
    sinus_over_mm: float = 1.0
    tegmen_keep_mm: float = 0.0
    tip_keep_mm: float = 4.0
    below_antrum_mm: float = 0.0
    edge_mm: float = 2.0
    bulk_margin_mm: float = 1.6
    bulk_thin_mm: float = 1.3
    bulk_canal_mm: float = 1.5
    finish_burr: str = "diamond-3mm"
    thin_margin_mm: float = 0.6
    canal_margin_mm: float = 1.0
    finish_layer_mm: float = 0.75
    finish_speed_mm_s: float = 12.0
    finish_gain_mm: float = 0.3


@dataclass(frozen=True)
class PlannedRun:
    """A planned mastoidectomy.

    Attributes
    ----------
    trajectory : Trajectory
        Burr centres [mm], case frame; its ``burr`` column indexes ``burrs``.
    burrs : tuple of str
        Burr names: the cutting burr, then the finishing burr (one name when
        the plan drills with one burr).
    summary : dict
        What was planned (strokes, volumes, margins), JSON-ready.
    """

    trajectory: Trajectory
    burrs: tuple
    summary: dict


#: File tables and their keys (the burrs give their radii and speeds).
_TABLES = {
    "plan": ("line_overlap", "column_mm", "layer_mm", "n_layers", "margin_mm",
             "speed_mm_s", "travel_mm_s", "plunge_mm_s", "sample_hz", "rinse_every_s",
             "rinse_gap_mm", "uncut_mm", "suction_mm_s", "irrigation_mm_s",
             "irrigation_lift_mm", "irrigation_every", "region_radius_mm"),
    "cavity": ("wall_slope", "steep_slope", "canal_wall_mm", "sinus_over_mm", "tegmen_keep_mm",
               "tip_keep_mm", "below_antrum_mm", "edge_mm"),
    "bulk": ("bulk_margin_mm", "bulk_thin_mm", "bulk_canal_mm"),
    "finish": ("finish_burr", "thin_margin_mm", "canal_margin_mm", "finish_layer_mm",
               "finish_speed_mm_s", "finish_gain_mm"),
}
#: Keys that are whole numbers >= 1.
_INTEGER_KEYS = ("n_layers", "irrigation_every")
#: Keys that must be > 0 (the other numbers >= 0).
_POSITIVE_KEYS = ("column_mm", "layer_mm", "speed_mm_s", "travel_mm_s", "plunge_mm_s",
                  "sample_hz", "rinse_every_s", "suction_mm_s", "irrigation_mm_s",
                  "wall_slope", "steep_slope", "finish_layer_mm", "finish_speed_mm_s")
assert {k for ks in _TABLES.values() for k in ks} | {
    "burr_radius_mm", "speed_rpm", "finish_radius_mm", "finish_rpm"} == \
    {f.name for f in fields(DemoPlan)}


def default_plan_path() -> Path:
    """Path of the shipped ``demo_plan.toml``."""
    from bonesim.resources import data_path

    return data_path("demo_plan.toml")


def load_demo_plan(path: str | Path | None = None) -> DemoPlan:
    """Read and check a demo-plan file.

    Parameters
    ----------
    path : str or Path, optional
        Default: the shipped ``bonesim/data/demo_plan.toml``.

    Returns
    -------
    DemoPlan
        With the default burr radii and speeds (:func:`plan_mastoidectomy`
        replaces them by the burrs').

    Raises
    ------
    BonesimError
        Naming the file and the table for a missing, unknown or out-of-range
        key.
    """
    path = default_plan_path() if path is None else Path(path)
    doc = read_toml(path)
    check_keys(doc, tuple(_TABLES), path, "top level", required=tuple(_TABLES))
    values = {}
    for table, keys in _TABLES.items():
        tab = doc[table]
        check_keys(tab, keys, path, table, required=keys)
        for name in keys:
            if name == "finish_burr":
                values[name] = get_str(tab, name, path, table)
                continue
            integer = name in _INTEGER_KEYS
            v = get_number(tab, name, path, table, integer=integer,
                           minimum=1 if integer else 0.0,
                           maximum=0.99 if name == "line_overlap" else None,
                           finite=False)       # checked just below, steep_slope may be inf
            finite = math.isfinite(v) or (name == "steep_slope" and v == math.inf)
            if not integer and (not finite or (name in _POSITIVE_KEYS and v <= 0)):
                raise BonesimError(f"'{name}' must be a finite number > 0, got {v}", path,
                                   table)
            values[name] = int(v) if integer else float(v)
    return DemoPlan(**values)


def _burr(b):
    from bonesim.io.burrs import load_burr

    return load_burr(b) if isinstance(b, (str, Path)) else b


def plan_mastoidectomy(case, burr="cutting-5mm", finish_burr: str | None = "plan",
                       plan: DemoPlan | None = None, *,
                       until_s: float | None = None) -> PlannedRun:
    """The demo mastoidectomy of a loaded case.

    Parameters
    ----------
    case : bonesim.io.case.Case
        Its volume gives the bone (engine grid) and the structures' clearance
        (the label map at source resolution); its landmarks the cavity; its
        camera the approach.
    burr : str or Burr
        The cutting burr (burr 0): name (``"cutting-5mm"``), path or a loaded
        burr; its radius and default speed replace the plan's.
    finish_burr : str, Burr or None
        The finishing burr (burr 1): ``"plan"`` for the plan's
        ``finish_burr``; None to finish with the cutting burr too (one burr).
    plan : DemoPlan, optional
        Default: :func:`load_demo_plan` of the shipped file.
    until_s : float, optional
        Plan only the run's first ``until_s`` [s]: its samples are those of
        the whole plan up to that time, to the bit, and it is planned in a
        fraction of the time when that is short.

    Returns
    -------
    PlannedRun

    Raises
    ------
    BonesimError
        A landmark the plan needs is missing (named), or no bone is reachable.
    """
    from bonesim.io.mastoid_plan import plan_case

    b = _burr(burr)
    plan = load_demo_plan() if plan is None else plan
    fb = None
    if finish_burr is not None:
        fb = _burr(plan.finish_burr if finish_burr == "plan" else finish_burr)
    plan = replace(plan, burr_radius_mm=float(b.radius_mm),
                   speed_rpm=float(b.default_speed_rpm),
                   finish_radius_mm=float((fb or b).radius_mm),
                   finish_rpm=float((fb or b).default_speed_rpm))
    if until_s is not None and not until_s >= 0.0:
        raise ValueError(f"until_s must be a time >= 0 [s], got {until_s}")
    traj, summary = plan_case(case, plan, two_burrs=fb is not None, until_s=until_s)
    names = (b.name,) if fb is None else (b.name, fb.name)
    return PlannedRun(traj, names, summary)


def demo_trajectory(case, burr, plan: DemoPlan | None = None) -> Trajectory:
    """The demo mastoidectomy of a loaded case drilled with one burr.

    Parameters
    ----------
    case : bonesim.io.case.Case
    burr : str or Burr
        Burr name (``"cutting-5mm"``), path, or a loaded burr.
    plan : DemoPlan, optional
        Default: :func:`load_demo_plan` of the shipped file.

    Returns
    -------
    Trajectory
        Its ``burr`` column is 0 throughout.
    """
    return plan_mastoidectomy(case, burr, None, plan).trajectory
