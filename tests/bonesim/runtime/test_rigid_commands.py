"""Fragments and plates through the loop's commands (bonesim.runtime.rigid_commands)
and the world step's rigid step: the loop body run in-process on a bone
block."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.bodies import pose_matrix, split_body
from bonesim.engine.model import Sample
from bonesim.engine.world import world_step
from bonesim.engine.rigid import AFFIXED, ASLEEP, GRABBED
from bonesim.runtime.commands import LoopContext, Reset
from bonesim.runtime.rigid_commands import (AffixPlate, Distract, GrabBody, PlacePlate,
                                            ReleaseBody)

from tests.bonesim.fakes import FakeBurr, block_model

SP = 0.5
TOP = 19 * SP + SP / 2            # the block's top face [mm]
AXIS = np.array([0.0, 0.0, -1.0])


class Loop:
    """The haptic loop's body without its process: commands decoded and
    applied as the loop does, then one world step (rigid and haptic) per
    period of 1 ms."""

    def __init__(self, model, state):
        self.model, self.state = model, state
        self.status = np.zeros((), dtype=[("commands_applied", np.int64),
                                          ("commands_rejected", np.int64),
                                          ("command_error", "S160"), ("epoch", np.int64),
                                          ("tool", np.int32)])
        self.ctx = LoopContext(model, state, None, None, self.status)
        self.t = 0.0
        self.pos = np.array([1e3, 1e3, 1e3])

    def send(self, cls, **kw):
        self.ctx.t_s = self.t
        cls.apply(self.ctx, cls.encode(**kw))

    def run(self, n, to=None, drill=False):
        start = self.pos.copy()
        for q in range(n):
            self.t += 1e-3
            if to is not None:
                self.pos = start + (np.asarray(to) - start) * min(1.0, (q + 1) / (0.8 * n))
            world_step(self.model, self.state, Sample(self.t, self.pos, AXIS, drill, 60000.0,
                                                      1))


def _fragment_model(edge=8, lo=(12, 16, 20)):
    labels = np.zeros((48, 40, 40), np.uint8)
    labels[:, :, :20] = 1
    i, j, k = lo
    labels[i:i + edge, j:j + edge, k:k + edge] = 1
    m, s = block_model(labels=labels, burr=FakeBurr(radius_mm=1.5))
    split_body(s, 0, np.argwhere(np.ones((edge,) * 3, bool)) + np.asarray(lo))
    return m, s


def _case_xyz(state, b, ijk):
    c = state.grid.origin_mm + SP * np.asarray(ijk, float)
    m = pose_matrix(state.pose[b])
    return c @ m[:, :3].T + m[:, 3]


def test_a_grabbed_fragment_moved_by_the_tool_is_drilled_where_it_stands():
    m, s = _fragment_model()
    loop = Loop(m, s)
    top = (20 + 8) * SP - SP / 2                   # the fragment's top face [mm]
    centre = np.array([(12 + 3.5) * SP, (16 + 3.5) * SP])
    loop.pos = np.r_[centre, top + 1.2]            # the burr just in its top
    loop.run(50)
    loop.send(GrabBody)
    assert s.rigid.mode[s.rigid.slot_of(1)] == GRABBED
    # lift it 4 mm, carry it 8 mm along +x, put it down and let go
    loop.run(400, to=loop.pos + [0.0, 0.0, 4.0])
    loop.run(600, to=loop.pos + [8.0, 0.0, 0.0])
    loop.run(400, to=loop.pos + [0.0, 0.0, -3.5])
    loop.send(ReleaseBody)
    loop.pos = loop.pos + [0.0, 0.0, 6.0]          # the tool away, above it
    loop.run(1500)
    slot = s.rigid.slot_of(1)
    assert s.rigid.mode[slot] == ASLEEP     # resting where it was put
    moved = s.pose[1, :3].copy()
    assert moved[0] == pytest.approx(8.0, abs=0.3) and abs(moved[2]) < 0.3
    # drill straight down onto its new place
    n0 = s.tissue.count
    down = np.r_[centre + [8.0, 0.0], top + 1.2]
    loop.pos = down + [0.0, 0.0, 2.0]
    loop.run(1500, to=down - [0.0, 0.0, 1.0], drill=True)
    rem = events.removals(s.tissue.read(n0))
    assert len(rem["ijk"]) > 20
    assert (rem["body"] == 1).all()                # the fragment's bone, not the block's
    # each removed voxel was within the burr where it stood, not where it came from
    ev = s.tissue.read(n0)
    at = ev["kind"] == events.REMOVED
    xyz = _case_xyz(s, 1, rem["ijk"])
    tool_x = centre[0] + 8.0
    assert np.abs(xyz[:, 0] - tool_x).max() < 1.5 + SP
    orig = s.grid.origin_mm + SP * rem["ijk"].astype(float)
    assert np.abs(orig[:, 0] - tool_x).min() > 6.0
    assert at.sum() == len(xyz)
    # the fragment never moved while the drill ran (no push while drilling)
    poses = events.select(s.tissue.read(n0), events.POSE)
    assert len(poses["t_s"]) == 0 or np.abs(poses["value"][:, :3] - moved).max() < 0.05


def test_the_stopped_tool_pushes_a_fragment_across_the_bone():
    m, s = _fragment_model()
    loop = Loop(m, s)
    y = (16 + 3.5) * SP
    z = 21 * SP
    loop.pos = np.array([4.0, y, z])               # beside its -x face
    loop.run(100)
    x0 = s.pose[1, 0]
    loop.run(1000, to=[12.0, y, z])                # sweep through where it was
    assert s.pose[1, 0] > x0 + 3.0                 # pushed along +x
    assert s.pose[1, 2] > -0.3                     # never into the block
    poses = events.select(s.tissue.read(0), events.POSE)
    assert (poses["body"] == 1).all() and len(poses["t_s"]) > 100
    assert events.removals(s.tissue.read(0))["ijk"].size == 0


def test_a_plate_placed_rests_and_affixed_follows_its_fragment_and_a_reset_clears():
    m, s = _fragment_model(edge=16, lo=(8, 8, 20))
    loop = Loop(m, s)
    top = (20 + 16) * SP - SP / 2
    loop.pos = np.array([8.0, 8.0, top + 3.0])
    loop.send(PlacePlate, plate="straight-4", pose=[8.0, 8.0, top + 2.0, 1, 0, 0, 0])
    rs = s.rigid
    slot = rs.last_plate
    loop.run(2500)
    assert rs.mode[slot] == ASLEEP
    loop.send(AffixPlate)
    assert rs.mode[slot] == AFFIXED and rs.host[slot] == 1
    plate_ev = events.select(s.tissue.read(0), events.PLATE)
    assert plate_ev["label"][-1] == 2 and plate_ev["n"][-1] == 0
    # grab the fragment, lift it: the plate goes along
    before = rs.rpose[slot].copy()
    loop.pos = np.array([8.0, 8.0, top - 2.0])     # in the fragment beside the plate
    loop.run(1)                                    # the command reads the stepped tool
    loop.send(GrabBody, body=1)
    loop.run(500, to=loop.pos + [0.0, 0.0, 5.0])
    assert rs.rpose[slot, 2] - before[2] == pytest.approx(s.pose[1, 2], abs=0.05)
    assert rs.rpose[slot, 2] - before[2] > 4.0
    loop.send(Reset)
    loop.run(1)
    assert not rs.active and rs.last_plate == -1


def test_a_distractor_sets_the_distance_of_two_bodies():
    labels = np.zeros((64, 32, 32), np.uint8)
    labels[:, :, :16] = 1
    m, s = block_model(labels=labels, burr=FakeBurr(radius_mm=1.5))
    split_body(s, 0, np.argwhere(np.ones((32, 32, 16), bool)) + [32, 0, 0])
    loop = Loop(m, s)
    top = 15 * SP + SP / 2
    loop.send(PlacePlate, plate="distractor", pose=[16.0, 8.0, top + 1.0, 1, 0, 0, 0])
    loop.run(2500)
    loop.send(AffixPlate)
    rs = s.rigid
    assert (rs.host[rs.last_plate], rs.tag[rs.last_plate]) == (0, 1)
    x1 = s.pose[1, 0]
    loop.send(Distract, length_mm=2.5)
    assert s.pose[1, 0] - x1 == pytest.approx(2.5, abs=1e-3)
    assert s.pose[0, 0] == 0.0                     # body 0 never moves
    last = events.select(s.tissue.read(0), events.POSE)
    assert last["body"][-1] == 1


def test_bad_rigid_commands_are_refused_where_sent():
    with pytest.raises(ValueError, match="body 0 never moves"):
        GrabBody.encode(body=0)
    with pytest.raises(ValueError, match="unknown plate"):
        PlacePlate.encode(plate="screw")
    with pytest.raises(ValueError, match="50 mm"):
        Distract.encode(length_mm=80.0)
