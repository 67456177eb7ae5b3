"""The world's commands: state transitions applied between two steps.

A command is a small immutable record whose :meth:`WorldCommand.apply`
changes a :class:`~bonesim.engine.model.State` (and nothing else) at the
time ``t_s`` of the step it precedes; every change to the tissue is
published as tissue events (:mod:`bonesim.engine.events`) of that time, so
that recorders, replicas and replay see it. :func:`bonesim.engine.world.world_step`
applies the commands handed to it, in order, before the rigid step and the
haptic step. The same records serve every run:

* the haptic loop decodes its ring's records (:mod:`bonesim.runtime.commands`,
  :mod:`bonesim.runtime.rigid_commands`) into them;
* ``simulate`` (:func:`bonesim.runtime.simulate.run_trajectory`) takes them
  with their times, and turns the trajectory's burr column into
  :class:`SetBurr`;
* replay (:mod:`bonesim.session.replay`) rebuilds them from a recording's
  epochs, burrs and body records.

Shipped:

=====================  =================================================
:class:`Reset`         the case's initial tissue back, a new epoch
:class:`SetBurr`       the burr the next steps use
:class:`SetTool`       the tool (:data:`TOOLS`)
:class:`SplitBox`      the voxels of a body in a box become a new body
:class:`SplitPart`     the fragment finder's split (or, ``shed``, a speck)
:class:`SplitVoxels`   listed voxels of a body become a new body (replay)
:class:`ShedVoxels`    listed voxels removed as dust (replay)
:class:`MoveBody`      a body placed at a rigid pose
:class:`CutStroke`     one stroke of the cut plane
:class:`PlateRecord`   a recorded plate pose published again (replay)
:class:`Grab`          a fragment or plate follows the tool
:class:`Release`       every grabbed rigid moves freely again
:class:`PlacePlate`    a plate or distractor (its geometry given) placed
:class:`AffixPlate`    a plate fixed to the body it touches
:class:`Distract`      an affixed distractor's length set
=====================  =================================================

The rigid commands (grab, release, place, affix, distract) need the
state's :class:`~bonesim.engine.rigid_set.RigidSet` (``state.rigid``) and
raise ``ValueError`` without one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bonesim.engine import events
from bonesim.engine.bodies import publish_pose, publish_split, publish_split_box
from bonesim.engine.cut_plane import (SIZE_QUANTUM_MM, publish_cut_record, queue_cut,
                                       rays_per_step, stroke_rays)
from bonesim.engine.fragments import publish_part, shed_voxels
from bonesim.engine.haptics import P_RADIUS
from bonesim.engine.model import reset_state
from bonesim.engine.rigid import AFFIXED, KIND_PLATE, tool_push
from bonesim.engine.rigid_set import publish_plate
from bonesim.engine.slicing import voxels_per_step
from bonesim.engine.split_jobs import queue_split

__all__ = ["TOOLS", "GRAB_REACH_MM", "WorldCommand", "Reset", "SetBurr", "SetTool",
           "SplitBox", "SplitPart", "SplitVoxels", "ShedVoxels", "MoveBody", "CutStroke",
           "PlateRecord", "Grab", "Release", "PlacePlate", "AffixPlate", "Distract",
           "down_pose"]

#: The tools a run knows (:class:`SetTool`): the drill, and the cut plane
#: (:class:`CutStroke`; the tool's pose is the plane's, a key applies a stroke).
TOOLS = ("drill", "cutplane")
#: How far beyond the burr's surface a grab reaches [mm].
GRAB_REACH_MM = 1.0


class WorldCommand:
    """Base of the world's commands (see the module docstring)."""

    __slots__ = ()

    def apply(self, model, state, t_s: float) -> None:
        """Change ``state`` (in place) before the step of time ``t_s`` [s].

        Raises
        ------
        ValueError, IndexError
            The command does not fit the state (nothing of it is applied).
        """
        raise NotImplementedError(f"{type(self).__name__} has no apply()")


def _rigid(state):
    rs = state.rigid
    if rs is None:
        raise ValueError("this run has no rigid motion (state.rigid is None)")
    return rs


@dataclass(frozen=True, eq=False)
class Reset(WorldCommand):
    """The case's initial tissue back (:func:`~bonesim.engine.model.reset_state`,
    rings kept counting so that consumers miss nothing), every rigid
    forgotten; a new epoch, published as a ``RESET`` event.

    Attributes
    ----------
    epoch : int or None
        The new epoch (None: the state's plus one).
    """

    epoch: int | None = None

    def apply(self, model, state, t_s: float) -> None:
        reset_state(model, state, rings=False)
        state.epoch = state.epoch + 1 if self.epoch is None else int(self.epoch)
        events.push_event(state.tissue, events.RESET, t_s, n=state.epoch)


@dataclass(frozen=True, eq=False)
class SetBurr(WorldCommand):
    """The burr the next steps use, ``index`` into the model's burr table; a
    change is published as a ``BURR`` event."""

    index: int

    def apply(self, model, state, t_s: float) -> None:
        b, n = int(self.index), len(model.burrs)
        if not 0 <= b < n:
            raise IndexError(f"burr index {b} out of range 0..{n - 1}")
        if b != state.burr:
            state.burr = b
            events.push_event(state.tissue, events.BURR, t_s, n=b)


@dataclass(frozen=True, eq=False)
class SetTool(WorldCommand):
    """The tool, an index into :data:`TOOLS`."""

    tool: int

    def apply(self, model, state, t_s: float) -> None:
        t = int(self.tool)
        if not 0 <= t < len(TOOLS):
            raise IndexError(f"tool index {t} out of range 0..{len(TOOLS) - 1}")
        state.tool = t


@dataclass(frozen=True, eq=False)
class SplitBox(WorldCommand):
    """The voxels of body ``body`` inside the box ``lo .. hi`` (its own frame,
    voxel indices, inclusive) become a new body at its parent's pose
    (:func:`~bonesim.engine.bodies.publish_split_box`, ``SPLIT`` events)."""

    body: int
    lo: tuple
    hi: tuple

    def apply(self, model, state, t_s: float) -> None:
        publish_split_box(state, int(self.body), np.asarray(self.lo, np.int64),
                          np.asarray(self.hi, np.int64), t_s)


@dataclass(frozen=True, eq=False)
class SplitPart(WorldCommand):
    """The fragment finder's split (:func:`~bonesim.engine.fragments.publish_part`):
    the 26-connected part of body ``body`` holding voxel ``seed``, inside
    ``lo .. hi``, at most ``n`` voxels, becomes a new body, or with ``shed``
    is removed as dust. A command of another epoch than the state's (found
    before a reset) does nothing. A part of more voxels than a world step's
    split budget, and any part while split jobs are queued, is queued as a
    split job and done in slices by the next world steps
    (:mod:`bonesim.engine.split_jobs`)."""

    body: int
    seed: tuple
    lo: tuple
    hi: tuple
    n: int
    epoch: int
    shed: bool = False

    def apply(self, model, state, t_s: float) -> None:
        if int(self.epoch) != state.epoch:
            return                          # found before a reset: nothing of it is left
        if state.split_jobs or (not self.shed and int(self.n) > voxels_per_step()):
            # a large part (or any behind one): in slices, one per world step
            queue_split(state, int(self.body), self.seed, self.lo, self.hi, int(self.n),
                        shed=bool(self.shed))
            return
        publish_part(state, int(self.body), np.asarray(self.seed, np.int64),
                     np.asarray(self.lo, np.int64), np.asarray(self.hi, np.int64),
                     int(self.n), t_s, shed=bool(self.shed))


@dataclass(frozen=True, eq=False)
class SplitVoxels(WorldCommand):
    """Voxels ``ijk`` (n, 3) of body ``src`` become body ``body``
    (:func:`~bonesim.engine.bodies.publish_split`; a recorded split). With
    ``ordered`` the records keep the order of ``ijk`` (replay: a sliced
    split's block as recorded); a ``body`` that exists already grows (the
    later blocks of a sliced split, :mod:`bonesim.engine.split_jobs`)."""

    src: int
    ijk: np.ndarray
    body: int | None = None
    ordered: bool = False

    def apply(self, model, state, t_s: float) -> None:
        publish_split(state, int(self.src), self.ijk, t_s, self.body, ordered=self.ordered)


@dataclass(frozen=True, eq=False)
class ShedVoxels(WorldCommand):
    """Voxels ``ijk`` (n, 3) of body ``body`` removed as dust
    (:func:`~bonesim.engine.fragments.shed_voxels`; a recorded speck)."""

    body: int
    ijk: np.ndarray

    def apply(self, model, state, t_s: float) -> None:
        shed_voxels(state, int(self.body), self.ijk, t_s)


@dataclass(frozen=True, eq=False)
class MoveBody(WorldCommand):
    """Body ``body`` placed at ``pose`` ``(tx, ty, tz [mm], qw, qx, qy, qz)``,
    its body-to-case transform (a ``POSE`` event). A fragment in the state's
    rigid set stays where it was put (asleep) until touched or grabbed."""

    body: int
    pose: np.ndarray

    def apply(self, model, state, t_s: float) -> None:
        publish_pose(state, int(self.body), self.pose, t_s)
        if state.rigid is not None:
            state.rigid.hold(int(self.body))


@dataclass(frozen=True, eq=False)
class CutStroke(WorldCommand):
    """One stroke of the cut plane (:mod:`bonesim.engine.cut_plane`): the
    rectangle at ``pose`` (case frame), ``size_um`` = (width, height, depth)
    [um], removing every voxel its rays pass (removals and a ``CUT`` record).
    ``rays_per_step``: None (live) walks a stroke larger than a step's budget,
    or any stroke while one is under way, in slices over the next world steps
    (:func:`~bonesim.engine.cut_plane.queue_cut`); 0 at once; ``k`` > 0 in
    slices of ``k`` rays (replay, from the ``CUT`` record's ``n = -k``)."""

    pose: np.ndarray
    size_um: np.ndarray
    rays_per_step: int | None = None

    def apply(self, model, state, t_s: float) -> None:
        um = np.asarray(self.size_um, np.int64)
        rays = self.rays_per_step
        if rays is None:                   # live: in slices if large, or behind one
            per = rays_per_step(float(um[2]) * SIZE_QUANTUM_MM, model.spacing_mm)
            rays = per if state.cut_jobs or stroke_rays(um, model.spacing_mm) > per else 0
        if rays:
            queue_cut(state, model.injury, um, np.asarray(self.pose, np.float64), t_s, rays)
        else:
            publish_cut_record(state, model.injury, um, np.asarray(self.pose, np.float64), t_s)


@dataclass(frozen=True, eq=False)
class PlateRecord(WorldCommand):
    """A recorded ``PLATE`` event published again as it was (a plate's pose
    touches no tissue). ``record``: one row of every tissue field, as
    arrays of length 1."""

    record: dict

    def apply(self, model, state, t_s: float) -> None:
        state.tissue.append(**self.record)


@dataclass(frozen=True, eq=False)
class Grab(WorldCommand):
    """Fragment ``body`` follows the tool; ``body=-1``: the fragment the tool
    (at its last stepped position) touches, else the nearest free plate
    within :data:`GRAB_REACH_MM` of the burr's surface. A large fragment not
    yet measured follows from the step its measurement completes
    (:mod:`bonesim.engine.rigid_measure`)."""

    body: int = -1

    def apply(self, model, state, t_s: float) -> None:
        rs = _rigid(state)
        tool = state.pos_mm
        b = int(self.body)
        reach = model.burr_params[state.burr][P_RADIUS] + GRAB_REACH_MM
        if b < 0:
            push = tool_push(state, tool, reach, 1.0)
            if push[:, 6].max() > 0.0:
                b = int(np.argmax(push[:, 6]))
        if b >= 1:
            rs.grab_body(state, b, tool)        # a large fragment: once measured
            return
        best, best_d = -1, math.inf
        for s in np.flatnonzero((rs.kind == KIND_PLATE) & (rs.mode != 0)
                                & (rs.mode != AFFIXED)):
            pts, _ = rs.samples_case(state, int(s))
            d = float(np.linalg.norm(pts - tool, axis=1).min())
            if d < best_d:
                best, best_d = int(s), d
        if best < 0 or best_d > reach:
            raise ValueError("grab: the tool touches no fragment and no free plate")
        rs.grab(state, best, tool)


@dataclass(frozen=True, eq=False)
class Release(WorldCommand):
    """Every grabbed fragment and plate moves freely again (falls and rests)."""

    def apply(self, model, state, t_s: float) -> None:
        _rigid(state).release()


def down_pose(pos, gravity) -> np.ndarray:
    """A pose ``(7,)`` at ``pos`` [mm] turning a mesh's -z onto the unit
    direction ``gravity``."""
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


@dataclass(frozen=True, eq=False)
class PlacePlate(WorldCommand):
    """A plate or distractor mesh placed, free to fall and rest on the bone
    (a ``PLATE`` event).

    Attributes
    ----------
    catalog : int
        Its index in the plate catalogue (recorded with its poses).
    pos, nrm : (n, 3) float
        Vertices [mm] and unit normals, mesh frame.
    offset_mm, mass_kg, stiffness_n_mm : float
        Sample offset [mm], mass [kg], contact stiffness per sample [N/mm].
    axis : (3,) float
        A distractor's axis, mesh frame.
    samples : int or None
        Contact samples kept.
    pose : (7,) float or None
        Mesh-to-case pose; None: at the tool's last stepped position, bottom
        (mesh -z) along gravity.
    """

    catalog: int
    pos: np.ndarray
    nrm: np.ndarray
    offset_mm: float
    mass_kg: float
    stiffness_n_mm: float
    axis: tuple = (1.0, 0.0, 0.0)
    samples: int | None = None
    pose: np.ndarray | None = None

    def apply(self, model, state, t_s: float) -> None:
        rs = _rigid(state)
        pose = down_pose(state.pos_mm, rs.gvec / np.linalg.norm(rs.gvec)) \
            if self.pose is None else np.array(self.pose, np.float64)
        s = rs.add_plate(self.pos, self.nrm, self.offset_mm, self.mass_kg,
                         self.stiffness_n_mm, pose, catalog=int(self.catalog),
                         axis=self.axis, samples=self.samples)
        publish_plate(state, rs, s, t_s)


@dataclass(frozen=True, eq=False)
class AffixPlate(WorldCommand):
    """Plate ``slot`` (-1: the one placed last) fixed to the body it touches
    (a distractor across two; a ``PLATE`` event)."""

    slot: int = -1

    def apply(self, model, state, t_s: float) -> None:
        rs = _rigid(state)
        s = int(self.slot) if self.slot >= 0 else rs.last_plate
        if s < 0:
            raise ValueError("affix: no plate has been placed")
        rs.affix(state, s)
        publish_plate(state, rs, s, t_s)


@dataclass(frozen=True, eq=False)
class Distract(WorldCommand):
    """Affixed distractor ``slot`` (-1: the one placed last) set to
    ``length_mm`` [mm] from where it was affixed: its second body moves
    along the distractor's axis (a ``POSE`` event)."""

    length_mm: float
    slot: int = -1

    def apply(self, model, state, t_s: float) -> None:
        rs = _rigid(state)
        s = int(self.slot) if self.slot >= 0 else rs.last_plate
        pose = rs.distract(state, s, float(self.length_mm))
        publish_pose(state, int(rs.tag[s]), pose, t_s)
