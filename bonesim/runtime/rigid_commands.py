"""Fragments and plates in the haptic loop: the ring commands that drive them.

The rigid bodies' state is the run's (``state.rigid``, a
:class:`~bonesim.engine.rigid_set.RigidSet` made by
:func:`~bonesim.engine.model.make_state`), and the rigid step is part of
the world step (:func:`bonesim.engine.world.world_step`): with the drill
stopped the tool pushes the fragments it touches, grabbed rigids follow
the tool, everything that moves falls along the case's gravity and rests on
the bone (:mod:`bonesim.engine.rigid`). Every pose change is a tissue event
(``POSE`` for a body, ``PLATE`` for a plate) at the time of the step that
follows, so a recording replays bit for bit (:mod:`bonesim.session.replay`
applies them as recorded, like commands) and playback and tutoring see
them. Body 0 never moves by itself. The commands here decode into the world
commands of :mod:`bonesim.engine.world_commands` (a plate of the
catalogue, :mod:`bonesim.io.plates`, into its geometry).

Commands (kinds 40-44):

:class:`GrabBody` (``"grab_body"``)
    a fragment (or, with ``body=-1``, whatever the tool touches: a fragment,
    else a plate) follows the tool;
:class:`ReleaseBody` (``"release_body"``)
    every grabbed rigid moves freely again (and falls);
:class:`PlacePlate` (``"place_plate"``)
    a plate or distractor of the catalogue (:mod:`bonesim.io.plates`) at a
    pose, by default at the tool with its bottom facing along gravity; it
    falls and rests on the bone;
:class:`AffixPlate` (``"affix_plate"``)
    fixes a plate to the body it touches (a distractor to two bodies);
:class:`Distract` (``"distract"``)
    sets an affixed distractor's length: its second body moves along the
    distractor's axis.
"""
from __future__ import annotations

import math

import numpy as np

from bonesim.engine import world_commands as wc
from bonesim.engine.rigid_set import RigidSet, publish_plate
from bonesim.runtime.commands import Command, LoopContext

__all__ = ["warmup_rigid", "GrabBody", "ReleaseBody", "PlacePlate", "AffixPlate",
           "Distract"]


def _plates():
    from bonesim.io.plates import default_plates

    return default_plates()


class GrabBody(Command):
    """Fragment ``body`` follows the tool; ``body=-1``: the fragment the tool
    touches, else the nearest free plate within reach."""

    kind, name = 40, "grab_body"

    @classmethod
    def encode(cls, body: int = -1) -> np.ndarray:
        if int(body) != body or body < -1 or body == 0:
            raise ValueError(f"grab: body must be -1 (what the tool touches) or a fragment "
                             f"id >= 1 (body 0 never moves), got {body!r}")
        return cls.pack(body)

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.Grab:
        return wc.Grab(int(args[0]))


class ReleaseBody(Command):
    """Let go of every grabbed fragment and plate (they fall and rest)."""

    kind, name = 41, "release_body"

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.Release:
        return wc.Release()


class PlacePlate(Command):
    """Put catalogue plate ``plate`` (index or name) at ``pose``
    (mesh-to-case; default: at the tool, bottom along gravity)."""

    kind, name = 42, "place_plate"

    @classmethod
    def encode(cls, plate=0, pose=None) -> np.ndarray:
        cat = _plates()
        if isinstance(plate, str):
            names = [p.name for p in cat]
            if plate not in names:
                raise ValueError(f"place plate: unknown plate {plate!r} (known: "
                                 f"{', '.join(names)})")
            plate = names.index(plate)
        if int(plate) != plate or not 0 <= plate < len(cat):
            raise ValueError(f"place plate: index {plate!r} out of range 0..{len(cat) - 1}")
        if pose is None:
            return cls.pack(plate, 0.0)
        p = np.asarray(pose, np.float64)
        if p.shape != (7,) or not np.isfinite(p).all() or not np.linalg.norm(p[3:]) > 0:
            raise ValueError(f"place plate: pose must be (tx, ty, tz, qw, qx, qy, qz), got "
                             f"{p.tolist()}")
        return cls.pack(plate, 1.0, p)

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.PlacePlate:
        i = int(args[0])
        spec = _plates()[i]                # the catalogue's geometry into the command
        return wc.PlacePlate(i, spec.pos, spec.nrm, spec.offset_mm, spec.mass_kg,
                             spec.stiffness_n_mm, axis=spec.axis, samples=spec.samples,
                             pose=args[2:9].copy() if args[1] else None)


class AffixPlate(Command):
    """Fix plate ``slot`` (-1: the one placed last) to the body it touches."""

    kind, name = 43, "affix_plate"

    @classmethod
    def encode(cls, slot: int = -1) -> np.ndarray:
        if int(slot) != slot or slot < -1:
            raise ValueError(f"affix: slot must be -1 or a slot index, got {slot!r}")
        return cls.pack(slot)

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.AffixPlate:
        return wc.AffixPlate(int(args[0]) if args[0] >= 0 else -1)


class Distract(Command):
    """Set affixed distractor ``slot``'s (-1: the one placed last) extension
    to ``length_mm`` (from where it was affixed): its second body moves."""

    kind, name = 44, "distract"

    @classmethod
    def encode(cls, length_mm: float, slot: int = -1) -> np.ndarray:
        if not math.isfinite(length_mm) or abs(length_mm) > 50.0:
            raise ValueError(f"distract: length must be within +-50 mm, got {length_mm!r}")
        return cls.pack(length_mm, slot)

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.Distract:
        return wc.Distract(float(args[0]), int(args[1]) if args[1] >= 0 else -1)


def warmup_rigid() -> None:
    """Compile the rigid kernels (cached on disk after the first run) on a
    small slab: a fragment pushed, grabbed and dropped, a plate placed and
    affixed. The loop calls it before its timed part."""
    from bonesim.engine.bodies import split_body
    from bonesim.engine.model import make_state
    from bonesim.io.loading import warmup_model

    m = warmup_model()
    st = make_state(m)
    split_body(st, 0, np.argwhere(np.ones((4, 4, 2), bool)) + [4, 4, 4])
    rs = RigidSet(m.max_bodies, 4, 1000.0)
    tool = np.array([3.0, 3.0, 4.0])
    rs.advance(st, 0.0, tool, False, 2.0, 1.0)            # the tool's push wakes it
    s = rs.wake_body(st, 1)
    rs.grab(st, s, tool)
    rs.advance(st, 0.001, tool, False, 2.0, 1.0)
    rs.release()
    pos = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    nrm = np.tile([0.0, 0.0, -1.0], (4, 1))
    p = rs.add_plate(pos, nrm, 0.1, 1e-4, 1e-3, [2.0, 2.0, 3.2, 1.0, 0.0, 0.0, 0.0])
    rs.advance(st, 0.002, tool, True, 2.0, 1.0)
    try:
        rs.affix(st, p)
    except ValueError:                                     # not touching yet: fine
        pass
    rs.advance(st, 0.003, tool, True, 2.0, 1.0)
    publish_plate(st, rs, p, 0.003)
    from bonesim.engine.rigid_measure import MeasureJob      # a large fragment's slices

    MeasureJob(st, 1).advance(st, 4, 8)
