"""Event rings: how the haptic step publishes what happened to its consumers.

The haptic step never waits for anybody. It appends fixed-size records to
single-producer ring buffers (plain numpy arrays plus a monotonically growing
write counter); each consumer (surface, dust, sound, recorder, tutor, metrics)
keeps its own read counter and drains at its own pace. A consumer that falls
more than ``capacity`` records behind has lost records, which
:meth:`Ring.read` reports as an overflow instead of returning garbage.

One tissue-event stream
-----------------------
Every change of the tissue travels as one versioned record
(:data:`TISSUE_EVENT_VERSION`) in the ``tissue`` ring: the haptic loop's
shared memory, the session file's ``tissue`` table, the tutoring packets and
the trainee's ring all carry exactly these columns, and nothing else carries
tissue changes. A record is

``kind`` (uint8)
    :data:`REMOVED`, :data:`CONTACT`, :data:`INJURY`, :data:`RESET`,
    :data:`BURR`, :data:`SPLIT`, :data:`POSE`, :data:`CUT` or :data:`PLATE` (names in
    :data:`KIND_NAMES`);
``body`` (uint8)
    the body it concerns (see :mod:`bonesim.engine.bodies`);
``label`` (uint8)
    structure label (removal, contact, injury);
``t_s`` (float64) [s]
    step time;
``ijk`` (int32, 3)
    voxel index in the body's own frame (removal);
``n`` (int32)
    a count or index: voxels lost this step (injury), voxels of the new body
    (split), the burr index (burr change), the epoch (reset);
``value`` (float64, 7)
    the tool centre in the case frame [mm] in the first three (contact,
    injury), or the body's pose ``(tx, ty, tz [mm], qw, qx, qy, qz)`` (pose;
    body-to-case rigid transform, unit quaternion).

A ``touched`` ring beside it carries shading hints only (voxels that lost
density but stayed): the density itself is shared state, so the hint is not
a tissue change and is never recorded.

Rings that live outside a state (:data:`OTHER_RINGS`): the haptic loop's
per-step ``samples``, the window's ``camera`` and ``ui`` streams, the
``commands`` into the loop, and the trainee's ``changes`` (tissue events
again: those its source applied, for the trainee's window).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TISSUE_EVENT_VERSION", "REMOVED", "CONTACT", "INJURY", "RESET", "BURR",
           "SPLIT", "POSE", "PLATE", "KIND_NAMES", "N_VALUE", "INJURY_CONTACT", "INJURY_REMOVAL",
           "INJURY_KINDS", "RingOverflow", "Ring", "Cursor", "RINGS", "COMMAND_ARGS",
           "OTHER_RINGS", "TISSUE_FIELDS", "ring_arrays_spec", "ring_from_arrays",
           "tissue_ring", "push_event", "empty_events", "removals", "injuries", "select",
           "concat", "CUT"]

#: Version of the tissue-event record (session schema 2 stores it as is).
TISSUE_EVENT_VERSION = 2
# tissue-event kinds
REMOVED, CONTACT, INJURY, RESET, BURR, SPLIT, POSE = range(7)
KIND_NAMES = ("removed", "contact", "injury", "reset", "burr", "split", "pose")
# a cut-plane stroke (bonesim.engine.cut_plane): ``ijk`` its width, height and
# depth [um], ``n`` the voxels it removed, ``value`` its pose; after its removals.
# A stroke done in slices (large): before its removals, ``n`` = -(rays per step)
CUT = 7
KIND_NAMES = KIND_NAMES + ("cut",)
#: A plate's or distractor's pose (:mod:`bonesim.engine.rigid`): ``body`` the
#: plate's slot, ``n`` its index in the plate catalogue, ``label`` the body it
#: is affixed to plus one (0: free), ``ijk`` (second body of a distractor plus
#: one, slot mode, 0), ``value`` its mesh-to-case pose. No replica's tissue
#: changes; replay applies them as recorded.
#: (Kind 7 is the cut plane's ``CUT``, issue 13; the names are padded so
#: that ``KIND_NAMES[PLATE]`` holds whichever lands first.)
PLATE = 8
KIND_NAMES = KIND_NAMES + ("",) * (PLATE - len(KIND_NAMES)) + ("plate",)
#: Floats in a record's ``value`` column.
N_VALUE = 7

# injury kinds as :func:`injuries` reports them (0 contact onset, 1 removal)
INJURY_CONTACT = 0
INJURY_REMOVAL = 1
INJURY_KINDS = ("contact", "removal")


class RingOverflow(RuntimeError):
    """A consumer read records that were already overwritten."""


@dataclass
class Ring:
    """A single-producer ring of records stored column-wise.

    Attributes
    ----------
    fields : dict of str -> ndarray
        Column arrays, each with first dimension ``capacity``.
    head : (1,) int64
        Total number of records ever written (the producer's counter). Kept in
        an array so numba kernels can advance it in place.
    """

    fields: dict
    head: np.ndarray

    @classmethod
    def create(cls, capacity: int, **spec) -> "Ring":
        """Allocate a ring; ``spec`` maps field name -> ``(dtype, trailing shape)``."""
        if capacity <= 0 or capacity & (capacity - 1):
            raise ValueError("ring capacity must be a positive power of two")
        fields = {name: np.zeros((capacity,) + tuple(shape), dtype=dtype)
                  for name, (dtype, shape) in spec.items()}
        return cls(fields, np.zeros(1, dtype=np.int64))

    @property
    def capacity(self) -> int:
        return next(iter(self.fields.values())).shape[0]

    @property
    def count(self) -> int:
        """Records written so far."""
        return int(self.head[0])

    def read(self, start: int, stop: int | None = None) -> dict:
        """Copy records ``start .. stop-1`` (absolute counters) out of the ring.

        Raises
        ------
        RingOverflow
            If some of those records were already overwritten.
        """
        stop = self.count if stop is None else stop
        cap = self.capacity
        if stop - start > cap or start < self.count - cap:
            raise RingOverflow(f"consumer fell {self.count - start} records behind a ring "
                               f"of {cap}")
        idx = np.arange(start, stop) & (cap - 1)
        return {name: arr[idx] for name, arr in self.fields.items()}

    def append(self, **cols) -> None:
        """Write records (first axis of each column) from Python; the head
        moves after the data, so a reader in another process never sees a
        half-written record."""
        n = len(next(iter(cols.values())))
        if n == 0:
            return
        idx = (self.count + np.arange(n)) & (self.capacity - 1)
        for name, v in cols.items():
            self.fields[name][idx] = v
        self.head[0] += n

    def reset(self) -> None:
        self.head[0] = 0


class Cursor:
    """A consumer's position in a :class:`Ring`."""

    def __init__(self, ring: Ring, start: int | None = None):
        self.ring = ring
        self.pos = ring.count if start is None else start

    def drain(self) -> dict:
        """Everything written since the last drain."""
        stop = self.ring.count
        out = self.ring.read(self.pos, stop)
        self.pos = stop
        return out


#: Columns of one tissue event: name -> (dtype, trailing shape).
TISSUE_FIELDS = {"kind": (np.uint8, ()), "body": (np.uint8, ()), "label": (np.uint8, ()),
                 "t_s": (np.float64, ()), "ijk": (np.int32, (3,)), "n": (np.int32, ()),
                 "value": (np.float64, (N_VALUE,))}

#: Ring name -> (capacity, {field: (dtype, trailing shape)}): the rings that
#: live in a :class:`~bonesim.engine.model.State`.
RINGS = {
    "tissue": (1 << 20, TISSUE_FIELDS),
    "touched": (1 << 18, {"ijk": (np.int32, (3,))}),
}


#: Arguments of one command record (a body id and a 4x4 pose fit, with room).
COMMAND_ARGS = 24

#: Rings that live beside a :class:`~bonesim.engine.model.State` but are not part of
#: it: the haptic loop's per-step ``samples`` (what the device read, what was
#: stepped and what force went back: the recorder's and the tutor's input),
#: the window's ``camera`` and ``ui`` streams (see :mod:`bonesim.runtime.record`), the
#: tissue events the trainee servo applied, ``changes`` (tissue-event records,
#: for the trainee's window: :mod:`bonesim.tutoring.trainee`) and the
#: ``commands`` into the haptic loop (see :mod:`bonesim.runtime.commands`).
OTHER_RINGS = {
    "samples": (1 << 16, {
        "t_s": (np.float64, ()),            # loop time [s]
        "pos_mm": (np.float64, (3,)),       # tool centre handed to step [mm]
        "axis": (np.float64, (3,)),         # unit drill axis handed to step
        "hand_mm": (np.float64, (3,)),      # what the device read [mm]
        "drill": (np.uint8, ()),
        "speed_rpm": (np.float64, ()),
        "direction": (np.int8, ()),
        "burr": (np.uint8, ()),             # index into the session's burrs
        "epoch": (np.int32, ()),            # case resets so far
        "buttons": (np.uint32, ()),
        "force_n": (np.float64, (3,)),      # sent to the device, vibration included [N]
        "tangential_n": (np.float64, (3,)),  # drag part of the bone force [N]
        "vibration_n": (np.float64, (3,)),  # synthesized vibration [N]
        "mag_n": (np.float64, ()),          # multi-gain normal magnitude [N]
        "volume_mm3": (np.float64, ()),     # immersed volume [mm^3]
    }),
    "camera": (1 << 12, {"t_s": (np.float64, ()), "eye_mm": (np.float64, (3,)),
                         "focal_mm": (np.float64, (3,)), "up": (np.float64, (3,))}),
    "ui": (1 << 10, {"t_s": (np.float64, ()), "name": ("S16", ()), "value": ("S64", ())}),
    # the tissue events a trainee's source applied, in order (bonesim.tutoring.trainee)
    "changes": (1 << 19, TISSUE_FIELDS),
    # window -> haptic loop (bonesim.runtime.commands): kind, producer's sequence number, arguments
    "commands": (1 << 8, {"kind": (np.uint16, ()), "seq": (np.int64, ()),
                          "args": (np.float64, (COMMAND_ARGS,))}),
}

__all__ += ["HANDLE_CHANNELS"]
#: Channels an instrumented handle's record holds (unused ones NaN).
HANDLE_CHANNELS = 4
# an instrumented handle's readings (bonesim.runtime.handle_stream): loop time
# [s], calibrated angles [deg] (NaN without a calibration) and raw counts
OTHER_RINGS["handle"] = (1 << 12, {"t_s": (np.float64, ()),
                                   "angles_deg": (np.float64, (HANDLE_CHANNELS,)),
                                   "counts": (np.float64, (HANDLE_CHANNELS,))})


def _ring_spec(name: str) -> tuple:
    return RINGS[name] if name in RINGS else OTHER_RINGS[name]


def ring_arrays_spec(name: str, capacity: int | None = None) -> list:
    """``(array name, shape, dtype)`` of a ring's columns and head, for shared memory."""
    cap, fields = _ring_spec(name)
    cap = cap if capacity is None else capacity
    out = [(f"{name}.{f}", (cap,) + tuple(shape), dt) for f, (dt, shape) in fields.items()]
    out.append((f"{name}.head", (1,), np.int64))
    return out


def ring_from_arrays(name: str, arrays: dict) -> Ring:
    """A :class:`Ring` over existing column arrays (e.g. in shared memory)."""
    fields = {f: arrays[f"{name}.{f}"] for f in _ring_spec(name)[1]}
    return Ring(fields, arrays[f"{name}.head"])


def tissue_ring(capacity: int = RINGS["tissue"][0]) -> Ring:
    """A private tissue-event ring (tests, single-process tools)."""
    return Ring.create(capacity, **TISSUE_FIELDS)


def push_event(ring: Ring, kind: int, t_s: float, *, body: int = 0, label: int = 0,
               ijk=(0, 0, 0), n: int = 0, value=()) -> None:
    """Append one tissue event from Python (commands, resets, burr changes);
    ``value`` fills the first floats of the record's ``value``, the rest is 0."""
    v = np.zeros(N_VALUE)
    v[:len(value)] = value
    ring.append(kind=[kind], body=[body], label=[label], t_s=[t_s], ijk=[ijk], n=[n],
                value=[v])


def empty_events(n: int = 0) -> dict:
    """``n`` zeroed tissue-event records, column-wise."""
    return {f: np.zeros((n,) + tuple(shape), dtype=dt)
            for f, (dt, shape) in TISSUE_FIELDS.items()}


def select(ev: dict, *kinds: int) -> dict:
    """The records of ``ev`` whose kind is one of ``kinds``, in order."""
    k = ev["kind"]
    m = k == kinds[0] if len(kinds) == 1 else np.isin(k, kinds)
    return {f: a[m] for f, a in ev.items()}


def concat(parts) -> dict:
    """Tissue-event batches joined in order."""
    parts = list(parts)
    if not parts:
        return empty_events()
    return {f: np.concatenate([p[f] for p in parts]) for f in TISSUE_FIELDS}


def removals(ev: dict) -> dict:
    """Removed voxels of a tissue-event batch: ``ijk`` (n, 3) int32 (body
    frame), ``label`` (n,) uint8, ``body`` (n,) uint8, ``t_s`` (n,) [s],
    ``shed`` (n,) bool (a speck shed as dust, not drilled: :data:`REMOVED_SHED`)."""
    r = select(ev, REMOVED)
    return {"ijk": r["ijk"], "label": r["label"], "body": r["body"], "t_s": r["t_s"],
            "shed": r["n"] == REMOVED_SHED}


def injuries(ev: dict) -> dict:
    """Contact onsets and removals of injury-emitting structures: ``label``,
    ``kind`` (:data:`INJURY_CONTACT` or :data:`INJURY_REMOVAL`), ``t_s`` [s],
    ``pos_mm`` (n, 3) tool centre [mm], ``voxels`` lost that step, ``body``."""
    r = select(ev, CONTACT, INJURY)
    kind = np.where(r["kind"] == CONTACT, INJURY_CONTACT, INJURY_REMOVAL).astype(np.uint8)
    return {"label": r["label"], "kind": kind, "t_s": r["t_s"],
            "pos_mm": np.ascontiguousarray(r["value"][:, :3]), "voxels": r["n"],
            "body": r["body"]}


#: A ``REMOVED`` record's ``n`` says why the voxel went: 0 (``REMOVED_DRILLED``)
#: for the tool's removals, :data:`REMOVED_SHED` for a speck of bone cut off
#: and shed as dust (:mod:`bonesim.engine.fragments`): a removal for dust,
#: replicas and surfaces, but not drilled volume for the metrics.
REMOVED_DRILLED = 0
REMOVED_SHED = 1
__all__ += ["REMOVED_DRILLED", "REMOVED_SHED", "drilled"]


def drilled(ev: dict) -> np.ndarray:
    """(n,) bool: the records of a tissue-event batch that are drilled
    removals (``REMOVED`` and not :data:`REMOVED_SHED`)."""
    return (np.asarray(ev["kind"]) == REMOVED) & (np.asarray(ev["n"]) != REMOVED_SHED)
