"""Event rings: how the haptic step publishes what happened to its consumers.

The haptic step never waits for anybody. It appends fixed-size records to
single-producer ring buffers (plain numpy arrays plus a monotonically growing
write counter); each consumer (surface, dust, sound, recorder, metrics) keeps
its own read counter and drains at its own pace. A consumer that falls more
than ``capacity`` records behind has lost records, which :meth:`Ring.read`
reports as an overflow instead of returning garbage.

Three rings exist per :class:`~bonesim.model.State`:

``removed``
    one record per voxel whose density reached 0:
    ``ijk`` (int32, 3), ``label`` (uint8), ``t_s`` (float64 [s]).
``touched``
    voxels whose density dropped but stayed positive (vertex shading only);
    a voxel is pushed once until a consumer clears its flag.
``injuries``
    contact with or removal of a structure whose material emits injuries:
    ``label`` (uint8), ``kind`` (0 contact onset, 1 voxels removed),
    ``t_s`` [s], ``pos_mm`` (3) tool centre [mm], ``voxels`` lost this step.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["INJURY_CONTACT", "INJURY_REMOVAL", "INJURY_KINDS", "RingOverflow", "Ring",
           "Cursor", "RINGS", "COMMAND_ARGS", "OTHER_RINGS", "ring_arrays_spec", "ring_from_arrays",
           "removal_ring"]

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


#: Ring name -> (capacity, {field: (dtype, trailing shape)}).
RINGS = {
    "removed": (1 << 20, {"ijk": (np.int32, (3,)), "label": (np.uint8, ()),
                          "t_s": (np.float64, ())}),
    "touched": (1 << 18, {"ijk": (np.int32, (3,))}),
    "injuries": (1 << 14, {"label": (np.uint8, ()), "kind": (np.uint8, ()),
                           "t_s": (np.float64, ()), "pos_mm": (np.float64, (3,)),
                           "voxels": (np.int32, ())}),
}


#: Arguments of one command record (a body id and a 4x4 pose fit, with room).
COMMAND_ARGS = 24

#: Rings that live beside a :class:`~bonesim.model.State` but are not part of
#: it: the haptic loop's per-step ``samples`` (what the device read, what was
#: stepped and what force went back: the recorder's and the tutor's input),
#: the window's ``camera`` and ``ui`` streams (see :mod:`bonesim.record`), the
#: trainee servo's replica ``changes`` (:mod:`bonesim.trainee`) and the
#: ``commands`` into the haptic loop (see :mod:`bonesim.commands`).
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
    # the trainee's replica changes (bonesim.trainee): emptied voxels, RESET_IJK rows
    "changes": (1 << 20, {"ijk": (np.int32, (3,))}),
    # window -> haptic loop (bonesim.commands): kind, producer's sequence number, arguments
    "commands": (1 << 8, {"kind": (np.uint16, ()), "seq": (np.int64, ()),
                          "args": (np.float64, (COMMAND_ARGS,))}),
}


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


def removal_ring(capacity: int = RINGS["removed"][0]) -> Ring:
    """A private removal ring (tests, single-process tools)."""
    return Ring.create(capacity, **RINGS["removed"][1])
