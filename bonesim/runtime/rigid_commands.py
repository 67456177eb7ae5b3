"""Fragments and plates in the haptic loop: the rigid step and its commands.

The loop holds one :class:`~bonesim.engine.rigid_set.RigidSet` (made by
:func:`attach_rigid`, kept as ``ctx.rigid``) and calls :func:`rigid_step`
between the commands and the haptic step of each period: with the drill
stopped the tool pushes the fragments it touches, grabbed rigids follow
the tool, everything that moves falls along the case's gravity and rests on
the bone (:mod:`bonesim.engine.rigid`). Every pose change is a tissue event
(``POSE`` for a body, ``PLATE`` for a plate) at the time of the step that
follows, so a recording replays bit for bit (:mod:`bonesim.session.replay`
applies them as recorded, like commands) and playback and tutoring see
them. Body 0 never moves by itself.

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

from bonesim.engine.bodies import publish_pose
from bonesim.engine.haptics import P_K_LOW, P_RADIUS
from bonesim.engine.rigid import AFFIXED, KIND_PLATE, gravity_direction, tool_push
from bonesim.engine.rigid_set import RigidSet, publish_plate
from bonesim.runtime.commands import Command, LoopContext

__all__ = ["RIGID_SLOTS", "GRAB_REACH_MM", "attach_rigid", "rigid_step", "warmup_rigid", "GrabBody",
           "ReleaseBody", "PlacePlate", "AffixPlate", "Distract"]

#: Rigid slots of a loop (fragments in motion and plates together).
RIGID_SLOTS = 16
#: How far beyond the burr's surface a grab reaches [mm].
GRAB_REACH_MM = 1.0


def attach_rigid(ctx: LoopContext, model, rate_hz: float) -> RigidSet:
    """Make the loop's rigid set (gravity from the model's case) as ``ctx.rigid``."""
    ctx.rigid = RigidSet(model.max_bodies, RIGID_SLOTS, rate_hz, gravity_direction(model))
    ctx.rigid_epoch = ctx.epoch
    return ctx.rigid


def rigid_step(ctx: LoopContext, t_s: float, pos_mm, drill: bool, burr: int) -> int:
    """One period of rigid motion, after the commands and before the haptic
    step of time ``t_s`` (tool at ``pos_mm``, the burr ``burr`` of the
    model's table). A reset forgets every rigid. Returns the poses published."""
    rs = ctx.rigid
    if ctx.rigid_epoch != ctx.epoch:
        rs.clear()
        ctx.rigid_epoch = ctx.epoch
    p = ctx.model.burr_params[burr]
    return rs.advance(ctx.state, t_s, pos_mm, drill, p[P_RADIUS], p[P_K_LOW])


def _rigid(ctx) -> RigidSet:
    rs = getattr(ctx, "rigid", None)
    if rs is None:
        raise RuntimeError("this loop has no rigid set (attach_rigid)")
    return rs


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
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        rs, st = _rigid(ctx), ctx.state
        tool = st.pos_mm
        b = int(args[0])
        if b < 0:
            p = ctx.model.burr_params[ctx.burr]
            push = tool_push(st, tool, p[P_RADIUS] + GRAB_REACH_MM, 1.0)
            if push[:, 6].max() > 0.0:
                b = int(np.argmax(push[:, 6]))
        if b >= 1:
            rs.grab(st, rs.wake_body(st, b), tool)
            return
        reach = ctx.model.burr_params[ctx.burr][P_RADIUS] + GRAB_REACH_MM
        best, best_d = -1, math.inf
        for s in np.flatnonzero((rs.kind == KIND_PLATE) & (rs.mode != 0)
                                & (rs.mode != AFFIXED)):
            pts, _ = rs.samples_case(st, int(s))
            d = float(np.linalg.norm(pts - tool, axis=1).min())
            if d < best_d:
                best, best_d = int(s), d
        if best < 0 or best_d > reach:
            raise ValueError("grab: the tool touches no fragment and no free plate")
        rs.grab(st, best, tool)


class ReleaseBody(Command):
    """Let go of every grabbed fragment and plate (they fall and rest)."""

    kind, name = 41, "release_body"

    @classmethod
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        _rigid(ctx).release()


def _down_pose(pos, gravity) -> np.ndarray:
    """A pose at ``pos`` turning the mesh's -z onto ``gravity``."""
    g = np.asarray(gravity, float)
    z = np.array([0.0, 0.0, -1.0])
    axis = np.cross(z, g)
    s, c = float(np.linalg.norm(axis)), float(z @ g)
    if s < 1e-12:
        q = [1.0, 0.0, 0.0, 0.0] if c > 0 else [0.0, 1.0, 0.0, 0.0]
    else:
        half = math.atan2(s, c) / 2
        q = [math.cos(half), *(math.sin(half) * axis / s)]
    return np.r_[np.asarray(pos, float), q]


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
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        rs = _rigid(ctx)
        i = int(args[0])
        spec = _plates()[i]
        pose = args[2:9].copy() if args[1] else _down_pose(ctx.state.pos_mm, rs.gvec /
                                                          np.linalg.norm(rs.gvec))
        s = rs.add_plate(spec.pos, spec.nrm, spec.offset_mm, spec.mass_kg,
                         spec.stiffness_n_mm, pose, catalog=i, axis=spec.axis,
                         samples=spec.samples)
        publish_plate(ctx.state, rs, s, ctx.t_s)


class AffixPlate(Command):
    """Fix plate ``slot`` (-1: the one placed last) to the body it touches."""

    kind, name = 43, "affix_plate"

    @classmethod
    def encode(cls, slot: int = -1) -> np.ndarray:
        if int(slot) != slot or slot < -1:
            raise ValueError(f"affix: slot must be -1 or a slot index, got {slot!r}")
        return cls.pack(slot)

    @classmethod
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        rs = _rigid(ctx)
        s = int(args[0]) if args[0] >= 0 else rs.last_plate
        if s < 0:
            raise ValueError("affix: no plate has been placed")
        rs.affix(ctx.state, s)
        publish_plate(ctx.state, rs, s, ctx.t_s)


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
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        rs = _rigid(ctx)
        s = int(args[1]) if args[1] >= 0 else rs.last_plate
        pose = rs.distract(ctx.state, s, float(args[0]))
        publish_pose(ctx.state, int(rs.tag[s]), pose, ctx.t_s)


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
