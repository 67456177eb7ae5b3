"""The assessment's items, read from ``bonesim/data/assessment.toml``, and how
an item's measured quantities become a score.

An item (:class:`Item`) has a measurement (``measure``, taken on ``target``),
criteria (a quantity against a ``done`` and a ``partial`` threshold, lower or
higher better) and violations (a quantity above ``max``). Scoring
(:meth:`Item.score`):

* a violated item scores 0 and is ``"violated"``;
* otherwise each criterion scores 2 (at most ``done``; ``"higher"``: at
  least), 1 (at most ``partial``) or 0, and the item takes the lowest; an item
  without criteria scores 2;
* a missing quantity (NaN) scores its criterion 0.

Outcomes: 2 ``"done"``, 1 ``"partial"``, 0 ``"missed"`` or ``"violated"``;
an item whose target the case lacks is ``"n/a"`` and leaves the total.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

from bonesim.errors import BonesimError

__all__ = ["MEASURES", "OUTCOMES", "Criterion", "Violation", "Item", "Scale", "load_scale"]

#: The measurements an item may name (:mod:`metrics.assessment_measure`) and
#: the quantities each gives.
MEASURES = {
    "sightlines": ("overhang_mm3", "hidden_wall_share", "wall_voxels"),
    "cover": ("thinnest_mm", "exposed_mm2", "thinned_mm2", "surface_mm2"),
    "angle": ("gap_mm",),
    "antrum": ("gap_mm", "opening_mm2"),
    "reach": ("gap_mm",),
    "tip": ("gap_mm",),
    "injury": ("removed_mm3", "exposed_mm2"),
}
#: Outcomes, best first.
OUTCOMES = ("done", "partial", "missed", "violated", "n/a")
#: ``[measure]`` keys (all numbers >= 0).
MEASURE_KEYS = ("box_pad_mm", "hull_mm", "opened_reach_mm", "step_voxels",
                "occluder_depth_voxels", "canal_radius_extra_mm", "canal_skip_mm",
                "canal_length_mm", "antrum_extra_mm", "antrum_estimated_radius_mm",
                "lateral_canal_near_mm", "min_area_mm2")


@dataclass(frozen=True)
class Criterion:
    """One quantity against two thresholds (module docstring)."""

    quantity: str
    better: str
    done: float
    partial: float

    def score(self, value) -> int:
        v = float("nan") if value is None else float(value)
        if math.isnan(v):
            return 0
        if self.better == "lower":
            return 2 if v <= self.done else 1 if v <= self.partial else 0
        return 2 if v >= self.done else 1 if v >= self.partial else 0


@dataclass(frozen=True)
class Violation:
    """A quantity that must stay at most ``max``."""

    quantity: str
    max: float

    def broken(self, value) -> bool:
        return value is not None and not math.isnan(float(value)) and float(value) > self.max


@dataclass(frozen=True)
class Item:
    """One item of the scale.

    Attributes
    ----------
    name, title : str
    measure : str
        Key of :data:`MEASURES`.
    target : str
        Structure group or landmark the measurement is taken on.
    criteria : tuple of Criterion
    violations : tuple of Violation
    advice : dict of str -> str
        One sentence per outcome (``done``, ``partial``, ``missed``,
        ``violated``).
    against : str
        What a ``cover`` is measured to: ``"cavity"`` (the drilled voxels and
        the air they opened) or ``"drilled"`` (the drilled voxels alone).
    """

    name: str
    title: str
    measure: str
    target: str
    criteria: tuple
    violations: tuple
    advice: dict
    against: str = "cavity"

    def score(self, quantities: dict) -> tuple[int, str]:
        """``(score, outcome)`` of measured ``quantities`` (module docstring)."""
        if any(v.broken(quantities.get(v.quantity)) for v in self.violations):
            return 0, "violated"
        s = min((c.score(quantities.get(c.quantity)) for c in self.criteria), default=2)
        return s, ("missed", "partial", "done")[s]


@dataclass(frozen=True)
class Scale:
    """The items (in file order) and the ``[measure]`` parameters."""

    items: tuple
    measure: dict
    path: Path

    def item(self, name: str) -> Item:
        for it in self.items:
            if it.name == name:
                return it
        raise KeyError(name)


def _num(tab, key, path, where, *, minimum=0.0):
    from bonesim.tomlfile import get_number

    return float(get_number(tab, key, path, where, minimum=minimum))


def _item(name, tab, path) -> Item:
    from bonesim.tomlfile import check_keys, get_str

    where = f"items.{name}"
    check_keys(tab, ("title", "measure", "target", "against", "criteria", "violations",
                     "advice"), path, where, required=("title", "measure", "target", "advice"))
    measure = get_str(tab, "measure", path, where)
    if measure not in MEASURES:
        raise BonesimError(f"unknown measure {measure!r} (one of {', '.join(MEASURES)})",
                           path, f"{where}.measure")
    known = MEASURES[measure]
    crit = []
    for q, c in enumerate(tab.get("criteria", [])):
        w = f"{where}.criteria[{q}]"
        check_keys(c, ("quantity", "better", "done", "partial"), path, w,
                   required=("quantity", "better", "done", "partial"))
        quantity, better = get_str(c, "quantity", path, w), get_str(c, "better", path, w)
        if quantity not in known:
            raise BonesimError(f"measure {measure!r} gives no {quantity!r} (it gives "
                               f"{', '.join(known)})", path, w)
        if better not in ("lower", "higher"):
            raise BonesimError(f"'better' must be \"lower\" or \"higher\", got {better!r}",
                               path, w)
        done, partial = _num(c, "done", path, w), _num(c, "partial", path, w)
        if (better == "lower" and partial < done) or (better == "higher" and partial > done):
            raise BonesimError(f"'partial' ({partial:g}) must be on the worse side of "
                               f"'done' ({done:g})", path, w)
        crit.append(Criterion(quantity, better, done, partial))
    viol = []
    for q, v in enumerate(tab.get("violations", [])):
        w = f"{where}.violations[{q}]"
        check_keys(v, ("quantity", "max"), path, w, required=("quantity", "max"))
        quantity = get_str(v, "quantity", path, w)
        if quantity not in known:
            raise BonesimError(f"measure {measure!r} gives no {quantity!r}", path, w)
        viol.append(Violation(quantity, _num(v, "max", path, w)))
    adv = tab["advice"]
    check_keys(adv, OUTCOMES[:4], path, f"{where}.advice", required=OUTCOMES[:4])
    advice = {k: get_str(adv, k, path, f"{where}.advice") for k in OUTCOMES[:4]}
    against = get_str(tab, "against", path, where, default="cavity",
                      choices=("cavity", "drilled"))
    return Item(name, get_str(tab, "title", path, where), measure,
                get_str(tab, "target", path, where), tuple(crit), tuple(viol), advice, against)


@functools.lru_cache(maxsize=4)
def _load(path: str) -> Scale:
    from bonesim.tomlfile import check_keys, read_toml

    p = Path(path)
    doc = read_toml(p)
    check_keys(doc, ("measure", "items"), p, "top level", required=("measure", "items"))
    check_keys(doc["measure"], MEASURE_KEYS, p, "measure", required=MEASURE_KEYS)
    measure = {k: _num(doc["measure"], k, p, "measure") for k in MEASURE_KEYS}
    if not measure["step_voxels"] > 0:
        raise BonesimError("'step_voxels' must be > 0", p, "measure")
    items = tuple(_item(name, tab, p) for name, tab in doc["items"].items())
    if not items:
        raise BonesimError("no items", p, "items")
    return Scale(items, measure, p)


def load_scale(path: str | Path | None = None) -> Scale:
    """Read ``assessment.toml`` (default: the shipped one; cached).

    Raises
    ------
    BonesimError
        Naming the file and the item or key that is missing, unknown or out
        of range.
    """
    if path is None:
        from bonesim.resources import data_path

        path = data_path("assessment.toml")
    return _load(str(Path(path).resolve()))
