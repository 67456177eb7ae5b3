"""Force and speed limits near a structure, per distance bin: the one law.

The research metrics (:mod:`metrics.forces`) learn per-bin limits from expert
runs and list where a trainee's run went above them; the live window warns a
resident the moment it happens. Both use the definitions here, so the warning
a resident sees is the exceedance a researcher later counts.

Definitions (SPEC "Safe forces", thesis section 3.5.2)
------------------------------------------------------
Distance [mm]
    From a removed voxel's centre, ``origin_mm + voxel_mm * ijk`` in the
    case's initial frame (the anatomical place: a body split off and moved
    does not change it), to the structure's voxels
    (:class:`bonesim.physics.clearance.Clearance`, 0 inside).
Force [N]
    :data:`FORCES` names the choices (:func:`force_magnitude`).
Bins
    Bin ``b`` holds distances in ``[b w, (b + 1) w)`` for width ``w``
    (:data:`BIN_MM`); the last bin also holds its upper edge
    (:func:`bin_edges`, :func:`bin_index`).
Over the limit
    A value above its bin's limit by more than :data:`AT_LIMIT_RTOL` of it
    (a force clamped at the device's maximum equals an expert's clamped force
    up to rounding: that is at the limit, not above it). A NaN limit (a bin
    the experts left too empty) flags no force or speed (:func:`over_limit`).
Closer than any expert
    In a bin without a force limit, a removal closer to the structure than
    the closest expert removal (:attr:`ForceLimits.closest_mm`) is over the
    limit of quantity ``"approach_mm"`` (value its distance, limit the
    experts' closest, excess how much closer): the bins the experts never
    reached are the most dangerous, so they flag any approach.
One report per step
    Per haptic step and quantity only the removal with the largest excess is
    reported (the closest for ``"approach_mm"``; the first on ties).
    :func:`judge` is this whole rule; :func:`metrics.forces.exceedances` (a
    recorded run) and :class:`ForceWatch` (the live window) both call it.

Limits files
------------
:func:`save_limits` writes a :class:`ForceLimits` as TOML (``bonesim metrics
limits`` makes one from expert runs); :func:`load_limits` reads one back
with an error naming the file and field for anything wrong. ``bonesim run
--force-limits FILE`` loads one into the window's :class:`ForceWatch`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bonesim.engine import events
from bonesim.errors import BonesimError
from bonesim.tomlfile import parse_toml_bytes

__all__ = ["DEFAULT_STRUCTURE", "MAX_DISTANCE_MM", "BIN_MM", "FORCES", "DEFAULT_FORCE",
           "AT_LIMIT_RTOL", "QUANTITIES", "UNITS", "WARN_HOLD_S", "LIMITS_FORMAT",
           "ForceLimits", "bin_edges", "bin_index", "force_magnitude", "structure_label",
           "limit_rows", "over_limit", "judge", "save_limits", "load_limits",
           "LimitWarning", "ForceWatch"]

#: Structure the forces are measured against by default.
DEFAULT_STRUCTURE = "chorda_tympani"
#: Removals farther than this from the structure are not measured [mm].
MAX_DISTANCE_MM = 30.0
#: Width of a distance bin [mm].
BIN_MM = 2.0
#: What "force" means: name -> description.
FORCES = {
    "applied": "|force_n - vibration_n|: rendered to the hand, vibration removed [N]",
    "device": "|force_n|: sent to the device, vibration included [N]",
    "normal": "mag_n: the multi-gain normal contact force [N]",
}
#: The default :data:`FORCES` entry.
DEFAULT_FORCE = "applied"
#: A value within this share of its limit is at the limit, not above it.
AT_LIMIT_RTOL = 1e-9
#: The quantities limited (a column of the haptic samples and of the tables).
QUANTITIES = ("force_n", "speed_rpm")
#: Unit of each quantity (``approach_mm``: closer than any expert, :func:`judge`).
UNITS = {"force_n": "N", "speed_rpm": "rpm", "approach_mm": "mm"}
#: The window keeps showing a warning this long after the last exceedance [s].
WARN_HOLD_S = 2.0
#: ``format`` written in a limits file and required on reading it.
LIMITS_FORMAT = "bonesim-force-limits-1"


def _positive(value, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return v


def bin_edges(bin_mm: float = BIN_MM, max_distance_mm: float = MAX_DISTANCE_MM) -> np.ndarray:
    """Bin edges [mm], ``(b + 1,)``: ``0, w, 2w, ...`` up to the first edge at or
    beyond ``max_distance_mm``.

    Raises
    ------
    ValueError
        If ``bin_mm`` or ``max_distance_mm`` is not a positive number.
    """
    w = _positive(bin_mm, "bin_mm")
    d = _positive(max_distance_mm, "max_distance_mm")
    nb = max(1, math.ceil(d / w - 1e-9))
    return w * np.arange(nb + 1, dtype=np.float64)


def bin_index(distance_mm, edges) -> np.ndarray:
    """Bin of each distance [mm] (``-1`` beyond the last edge or NaN)."""
    d = np.asarray(distance_mm, dtype=np.float64)
    edges = np.asarray(edges, dtype=np.float64)
    nb = len(edges) - 1
    with np.errstate(invalid="ignore"):
        idx = np.floor(np.nan_to_num(d, nan=-1.0, posinf=-1.0) / (edges[1] - edges[0]))
    idx = idx.astype(np.int64)
    idx = np.where(idx == nb, nb - 1, idx)            # the last edge closes the last bin
    return np.where((d >= 0) & (d <= edges[-1]) & (idx < nb), idx, -1)


def force_magnitude(samples: dict, force: str = DEFAULT_FORCE) -> np.ndarray:
    """The force [N] of each haptic sample, ``(n,)``, as :data:`FORCES` defines
    ``force`` (from the sample columns ``force_n``, ``vibration_n``, ``mag_n``).

    Raises
    ------
    ValueError
        On an unknown ``force``.
    """
    if force == "applied":
        return np.linalg.norm(np.asarray(samples["force_n"], np.float64)
                              - np.asarray(samples["vibration_n"], np.float64), axis=1)
    if force == "device":
        return np.linalg.norm(np.asarray(samples["force_n"], np.float64), axis=1)
    if force == "normal":
        return np.asarray(samples["mag_n"], dtype=np.float64)
    raise ValueError(f"force must be one of {sorted(FORCES)}, got {force!r}")


def structure_label(structures, name: str, case: str = "") -> int:
    """The label of structure ``name`` in a header's ``structures`` list
    (``{"label", "name", "kind"}`` records, or objects with ``name`` whose
    label is their position + 1, as :attr:`bonesim.engine.model.Model.structures`).

    Raises
    ------
    ValueError
        Naming the structure, the case and the structures it has.
    """
    names = []
    for q, st in enumerate(structures):
        nm = st["name"] if isinstance(st, dict) else st.name
        lab = int(st["label"]) if isinstance(st, dict) else q + 1
        names.append(nm)
        if nm == name:
            return lab
    raise ValueError(f"structure: {name!r} is not a structure of case {case!r} (it has "
                     f"{', '.join(names) or 'none'})")


# ------------------------------------------------------------------ limits
@dataclass(frozen=True)
class ForceLimits:
    """Per-bin force and speed limits learned from expert runs.

    Attributes
    ----------
    edges_mm : (b + 1,) float64
        Bin edges [mm].
    force_n : (b,) float64
        Force limit per bin [N] (NaN: no limit).
    speed_rpm : (b,) float64
        Speed limit per bin [rpm] (NaN: no limit).
    n : (b,) int64
        Expert rows per bin.
    percentile : float
        Of the pooled expert rows, per bin.
    structure, force : str
        Structure name; key of :data:`FORCES`.
    max_distance_mm : float
        Farthest removal measured [mm].
    case : str
        Case the limits were learned on ("" if not said).
    source : tuple of str
        The runs that trained them (file names).
    closest_mm : float
        The experts' closest approach [mm]: in a bin without a force limit a
        removal closer than this is over the limit (:func:`judge`); ``inf``
        checks no approach.
    """

    edges_mm: np.ndarray
    force_n: np.ndarray
    speed_rpm: np.ndarray
    n: np.ndarray
    percentile: float
    structure: str
    force: str
    max_distance_mm: float
    case: str = ""
    source: tuple = ()
    closest_mm: float = math.inf

    def __post_init__(self):
        e = np.asarray(self.edges_mm, np.float64).reshape(-1)
        if len(e) < 2 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0) or e[0] != 0:
            raise ValueError(f"edges_mm must rise from 0 with at least two edges, got {e}")
        nb = len(e) - 1
        object.__setattr__(self, "edges_mm", e)
        for col, dt in (("force_n", np.float64), ("speed_rpm", np.float64), ("n", np.int64)):
            a = np.asarray(getattr(self, col), dtype=dt).reshape(-1)
            if len(a) != nb:
                raise ValueError(f"{col} has {len(a)} bins, edges_mm {nb}")
            if col == "n" and np.any(a < 0):
                raise ValueError(f"n: expert rows per bin cannot be negative, got {a.min()}")
            if col != "n" and np.any(~np.isnan(a) & ~(a >= 0)):
                bad = a[~np.isnan(a) & ~(a >= 0)][0]
                raise ValueError(f"{col}: a limit must be >= 0 (or nan: no limit), got {bad}")
            object.__setattr__(self, col, a)
        if not (0.0 < float(self.percentile) <= 100.0):
            raise ValueError(f"percentile must lie in (0, 100], got {self.percentile}")
        if not (math.isfinite(self.max_distance_mm) and self.max_distance_mm > 0):
            raise ValueError(f"max_distance_mm must be a finite number > 0, got "
                             f"{self.max_distance_mm}")
        if self.force not in FORCES:
            raise ValueError(f"force must be one of {sorted(FORCES)}, got {self.force!r}")
        object.__setattr__(self, "source", tuple(str(s) for s in self.source))
        c = float(self.closest_mm)
        if math.isnan(c) or c < 0:
            raise ValueError(f"closest_mm must be >= 0 (or inf: no approach checked), got "
                             f"{self.closest_mm}")
        object.__setattr__(self, "closest_mm", c)

    def per_bin(self, quantity: str) -> np.ndarray:
        """The limits of ``quantity`` (a :data:`QUANTITIES` entry), ``(b,)``."""
        if quantity not in QUANTITIES:
            raise ValueError(f"quantity must be one of {QUANTITIES}, got {quantity!r}")
        return getattr(self, quantity)


def limit_rows(bins, per_bin) -> np.ndarray:
    """Each row's limit, ``(n,)``: ``per_bin[bins]``, NaN for a row outside
    every bin (``bins == -1``)."""
    b = np.asarray(bins, np.int64)
    per_bin = np.asarray(per_bin, np.float64)
    return np.where(b >= 0, per_bin[np.maximum(b, 0)], np.nan)


def over_limit(values, limits) -> np.ndarray:
    """Which values lie above their limit, ``(n,)`` bool: more than
    :data:`AT_LIMIT_RTOL` of the limit above it; a NaN limit flags nothing."""
    v = np.asarray(values, np.float64)
    lim = np.asarray(limits, np.float64)
    with np.errstate(invalid="ignore"):
        return v > lim + AT_LIMIT_RTOL * np.abs(lim)


def _one_per_step(rows, t_s, key):
    """Of ``rows``, per distinct ``t_s[rows]`` the one of the smallest ``key``
    (the first on ties), in time order."""
    if not len(rows):
        return rows
    order = np.lexsort((key, t_s[rows]))           # stable: the first on ties
    rows = rows[order]
    first = np.ones(len(rows), bool)
    first[1:] = t_s[rows[1:]] != t_s[rows[:-1]]
    return rows[first]


def judge(t_s, distance_mm, values: dict, limits: "ForceLimits") -> dict:
    """The one rule (module notes): which removals were over a limit.

    Parameters
    ----------
    t_s : (n,) float64
        Step time of each removal [s] (removals of one step share it).
    distance_mm : (n,) float64
        Each removed voxel's distance to ``limits.structure`` [mm]; NaN for a
        removal not measured (it flags nothing).
    values : dict
        ``quantity -> (n,) float64`` for each of :data:`QUANTITIES`: the
        step's force [N] (``limits.force``) and spindle speed [rpm].
    limits : ForceLimits

    Returns
    -------
    dict
        ``rows`` (m,) int64 indices of the reported removals, ``quantity``
        (m,) str, ``value``, ``limit``, ``excess`` (m,) float64 (``> 0``) and
        ``bin`` (m,) int64; ordered by time, then quantity.
    """
    t = np.asarray(t_s, np.float64).reshape(-1)
    d = np.asarray(distance_mm, np.float64).reshape(-1)
    d = np.where(d <= limits.max_distance_mm, d, np.nan)
    b = bin_index(d, limits.edges_mm)
    parts = []
    for q in QUANTITIES:
        val = np.asarray(values[q], np.float64).reshape(-1)
        lim = limit_rows(b, limits.per_bin(q))
        over = np.flatnonzero(over_limit(val, lim))
        rows = _one_per_step(over, t, -(val[over] - lim[over]))
        parts.append((rows, q, val[rows], lim[rows]))
    if math.isfinite(limits.closest_mm):
        bare = (b >= 0) & ~np.isfinite(limit_rows(b, limits.force_n))
        over = np.flatnonzero(bare & (d < limits.closest_mm))
        rows = _one_per_step(over, t, d[over])
        parts.append((rows, "approach_mm", d[rows], np.full(len(rows), limits.closest_mm)))
    rows = np.concatenate([p[0] for p in parts]).astype(np.int64)
    qty = np.concatenate([np.full(len(p[0]), p[1], "<U11") for p in parts])
    val = np.concatenate([p[2] for p in parts]).astype(np.float64)
    lim = np.concatenate([p[3] for p in parts]).astype(np.float64)
    order = np.lexsort((qty, t[rows]))
    rows, qty, val, lim = rows[order], qty[order], val[order], lim[order]
    excess = np.where(qty == "approach_mm", lim - val, val - lim)
    return {"rows": rows, "quantity": qty, "value": val, "limit": lim, "excess": excess,
            "bin": b[rows]}


# ------------------------------------------------------------------ files
def _toml_float(x: float) -> str:
    return "nan" if not math.isfinite(x) else repr(float(x))


def _toml_str(s: str) -> str:
    return '"' + str(s).replace("\\", "\\\\").replace('"', '\\"') + '"'


def save_limits(path, limits: ForceLimits) -> Path:
    """Write ``limits`` as a TOML file (readable and diffable; NaN for a bin
    without a limit); returns the path. Written to a temporary file first, so a
    failed write never leaves half a file."""
    path = Path(path)
    lines = [f"format = {_toml_str(LIMITS_FORMAT)}",
             f"structure = {_toml_str(limits.structure)}",
             f"force = {_toml_str(limits.force)}",
             f"case = {_toml_str(limits.case)}",
             f"percentile = {_toml_float(limits.percentile)}",
             f"max_distance_mm = {_toml_float(limits.max_distance_mm)}",
             "edges_mm = [" + ", ".join(_toml_float(x) for x in limits.edges_mm) + "]",
             "force_n = [" + ", ".join(_toml_float(x) for x in limits.force_n) + "]",
             "speed_rpm = [" + ", ".join(_toml_float(x) for x in limits.speed_rpm) + "]",
             "n = [" + ", ".join(str(int(x)) for x in limits.n) + "]",
             "source = [" + ", ".join(_toml_str(s) for s in limits.source) + "]",
             f"closest_mm = {'inf' if math.isinf(limits.closest_mm) else repr(limits.closest_mm)}"]
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("# per-bin force and speed limits near a structure, learned from "
                   "expert runs\n" + "\n".join(lines) + "\n")
    tmp.replace(path)
    return path


def load_limits(path) -> ForceLimits:
    """Read a limits file written by :func:`save_limits`.

    Raises
    ------
    bonesim.errors.BonesimError
        Naming the file and the field that is missing or wrong.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise BonesimError(f"cannot read the force limits ({exc.strerror or exc})", path) \
            from None
    doc = parse_toml_bytes(raw, path)
    if doc.get("format") != LIMITS_FORMAT:
        raise BonesimError(f"{path}: format must be {LIMITS_FORMAT!r}, got "
                           f"{doc.get('format')!r}")
    need = ("structure", "force", "percentile", "max_distance_mm", "edges_mm", "force_n",
            "speed_rpm", "n")
    for k in need:
        if k not in doc:
            raise BonesimError(f"{path}: field {k!r} is missing")
    try:
        return ForceLimits(doc["edges_mm"], doc["force_n"], doc["speed_rpm"], doc["n"],
                           float(doc["percentile"]), str(doc["structure"]),
                           str(doc["force"]), float(doc["max_distance_mm"]),
                           str(doc.get("case", "")), tuple(doc.get("source", ())),
                           float(doc.get("closest_mm", math.inf)))
    except (TypeError, ValueError) as exc:
        field, _, text = str(exc).partition(": ")
        if not text or " " in field:
            field, text = None, str(exc)
        raise BonesimError(text, path, field) from None


# ------------------------------------------------------------------ live
@dataclass(frozen=True)
class LimitWarning:
    """One moment the live run went above a limit (the largest excess of a step).

    Attributes
    ----------
    t_s : float
        Step time [s].
    quantity : str
        ``"force_n"``, ``"speed_rpm"`` or ``"approach_mm"`` (:func:`judge`).
    value, limit : float
        Applied and allowed, in the quantity's unit (:data:`UNITS`); for
        ``"approach_mm"`` the distance and the experts' closest approach.
    distance_mm : float
        The removed voxel's distance to the structure [mm].
    """

    t_s: float
    quantity: str
    value: float
    limit: float
    distance_mm: float


class ForceWatch:
    """Checks a live run's removals against force limits as they happen.

    Feed it the haptic loop's tissue events and samples in order, in any
    batches (:meth:`feed` says how); each removal near the structure is
    measured and checked by :func:`judge`, the rule
    :func:`metrics.forces.exceedances` applies to a recorded run, with the
    same limits (the experts' closest approach included).

    Parameters
    ----------
    model : bonesim.engine.model.Model
        The running case (structures, grid origin and spacing, clearance).
    limits : ForceLimits
        Their structure must be one of the case's.

    Attributes
    ----------
    count : dict of str -> int
        Steps above the limit so far, per quantity (:data:`UNITS`' keys).
    last : LimitWarning or None
        The latest.
    """

    def __init__(self, model, limits: ForceLimits):
        if not isinstance(limits, ForceLimits):
            raise ValueError(f"limits must be a ForceLimits, got {type(limits).__name__}")
        self.limits = limits
        self.label = structure_label(model.structures, limits.structure, model.name)
        cl = model.clearance
        if cl is None or self.label not in cl.structures:
            from bonesim.physics.clearance import Clearance

            _, lab = model.grid.to_dense()
            cl = Clearance(lab, model.grid.spacing_mm, model.grid.origin_mm, [self.label])
        self.clearance = cl
        self.origin_mm = np.asarray(model.grid.origin_mm, np.float64)
        self.voxel_mm = float(model.grid.spacing_mm)
        self.count = {q: 0 for q in UNITS}
        self.last: LimitWarning | None = None
        self._held = events.empty_events()
        self._t = np.zeros(0)
        self._force = np.zeros(0)
        self._speed = np.zeros(0)

    def feed(self, tissue: dict | None = None, samples: dict | None = None) -> list:
        """Take new tissue events and samples; returns the new :class:`LimitWarning`
        list (time order).

        Drain the tissue ring before the samples ring, as the loop publishes a
        step's removals before its sample: then every removal of a step is in
        by the feed after the one that brought the step's sample. A removal is
        checked at that feed (one feed late: each step's removals are judged
        together, once), and older samples are let go.
        """
        delivered = self._t[-1] if len(self._t) else -math.inf
        if samples is not None and len(samples["t_s"]):
            self._t = np.concatenate((self._t, samples["t_s"]))
            self._force = np.concatenate((self._force,
                                          force_magnitude(samples, self.limits.force)))
            self._speed = np.concatenate((self._speed, samples["speed_rpm"]))
        if tissue is not None and len(tissue["t_s"]):
            self._held = events.concat([self._held, events.select(tissue, events.REMOVED)])
        rem = self._held
        done = rem["t_s"] <= delivered
        self._held = {k: v[~done] for k, v in rem.items()}
        out = self._check({k: v[done] for k, v in rem.items()})
        k = int(np.searchsorted(self._t, delivered, side="right"))
        self._t, self._force, self._speed = self._t[k:], self._force[k:], self._speed[k:]
        return out

    def _check(self, rem: dict) -> list:
        if not len(rem["t_s"]):
            return []
        idx = np.clip(np.searchsorted(self._t, rem["t_s"]), 0, len(self._t) - 1)
        found = self._t[idx] == rem["t_s"]           # a removal always has its step's sample
        centre = self.origin_mm + self.voxel_mm * np.asarray(rem["ijk"], np.float64)
        dist = np.where(found, self.clearance.distance(centre, [self.label]), np.nan)
        got = judge(rem["t_s"], dist, {"force_n": self._force[idx],
                                       "speed_rpm": self._speed[idx]}, self.limits)
        warn = [LimitWarning(float(rem["t_s"][r]), str(q), float(v), float(lim), float(dist[r]))
                for r, q, v, lim in zip(got["rows"], got["quantity"], got["value"],
                                        got["limit"])]
        for w in warn:
            self.count[w.quantity] += 1
        if warn:
            self.last = warn[-1]
        return warn
