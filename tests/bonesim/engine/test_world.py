"""The world step (bonesim.engine.world) and its commands
(bonesim.engine.world_commands): without commands it is the haptic step bit
for bit; commands are state transitions, checked against slow plain-Python
references; a fragment let go falls and rests."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.bodies import split_body
from bonesim.engine.grid import voxel_offset
from bonesim.engine.model import Sample, make_state, step
from bonesim.engine.rigid import ASLEEP, DYNAMIC, GRABBED
from bonesim.engine.world import apply_commands, world_step
from bonesim.engine.world_commands import (Grab, MoveBody, Release, Reset, SetBurr, SetTool,
                                           SplitBox, SplitVoxels)
from tests.bonesim.fakes import FakeBurr, block_model

SP = 0.5
TOP = 20 * SP - SP / 2                 # the block's top face [mm]
AXIS = np.array([0.0, 0.0, -1.0])


def _models():
    m, _ = block_model(burr=FakeBurr(radius_mm=1.5))
    return m.with_burrs([FakeBurr(radius_mm=1.0)])


def _path(n=400):
    """Down into the block's top and along it, drilling: (t, pos) per step."""
    for q in range(n):
        u = q / n
        yield q * 1e-3, np.array([6.0 + 6.0 * u, 9.0, TOP + 1.0 - 2.5 * min(1.0, 2 * u)])


def _body_at(state, i, j, k):
    b = state.grid.brick_index(i, j, k)
    return -1 if b < 0 else int(state.body[b, voxel_offset(i, j, k)])


def _quat_matrix(p):
    """Reference rotation of a unit quaternion (w, x, y, z), by the textbook formula."""
    w, x, y, z = np.asarray(p[3:], float) / np.linalg.norm(p[3:])
    return np.array([[w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])


# --------------------------------------------------------- no commands
def test_without_commands_the_world_step_is_the_haptic_step_bit_for_bit():
    m = _models()
    a, b = make_state(m), make_state(m)
    for t, pos in _path():
        fa = step(m, a, Sample(t, pos, AXIS, True, 80000.0, 1, 0)).copy()
        fb = world_step(m, b, Sample(t, pos, AXIS, True, 80000.0, 1, 0)).copy()
        assert np.array_equal(fa, fb) and np.array_equal(a.out, b.out)
    assert a.n_removed > 50
    np.testing.assert_array_equal(a.grid.density, b.grid.density)
    ea, eb = a.tissue.read(0), b.tissue.read(0)
    for k in events.TISSUE_FIELDS:
        np.testing.assert_array_equal(ea[k], eb[k])


def test_the_step_uses_the_states_burr_which_only_set_burr_changes():
    m = _models()
    ref, st = make_state(m), make_state(m)
    t, pos = 0.0, np.array([8.0, 9.0, TOP + 1.2])     # burr 0 (r 1.5 mm) touches, 1 not
    f_ref = step(m, ref, Sample(t, pos, AXIS, False, 80000.0, 1, 1)).copy()
    # the sample's burr field is not what the world step reads
    f0 = world_step(m, st, Sample(t, pos, AXIS, False, 80000.0, 1, 1)).copy()
    assert st.burr == 0 and not np.array_equal(f0, f_ref)
    st2 = make_state(m)
    f1 = world_step(m, st2, Sample(t, pos, AXIS, False, 80000.0, 1, 0), (SetBurr(1),))
    assert st2.burr == 1 and np.array_equal(f1, f_ref)
    burrs = events.select(st2.tissue.read(0), events.BURR)
    assert burrs["n"].tolist() == [1] and burrs["t_s"].tolist() == [t]
    apply_commands(m, st2, (SetBurr(1),), 0.001)          # no change: no event
    assert len(events.select(st2.tissue.read(0), events.BURR)["n"]) == 1


# ------------------------------------------------------------ commands
def test_reset_puts_the_initial_tissue_back_and_counts_the_epoch():
    m = _models()
    st = make_state(m)
    world_step(m, st, Sample(0.0, np.zeros(3) + [8.0, 9.0, TOP], AXIS, False, 1.0, 1),
               (SetBurr(1), SetTool(1)))
    for t, pos in _path(200):
        world_step(m, st, Sample(0.001 + t, pos, AXIS, True, 80000.0, 1))
    split_body(st, 0, [(2, 2, 2), (2, 2, 3)])
    assert st.n_removed > 0 and st.n_bodies == 2
    n0 = st.tissue.count
    apply_commands(m, st, (Reset(),), 0.5)
    # reference: every array as a fresh state holds it
    fresh = make_state(m)
    np.testing.assert_array_equal(st.grid.density, fresh.grid.density)
    np.testing.assert_array_equal(st.body, fresh.body)
    np.testing.assert_array_equal(st.alive, fresh.alive)
    np.testing.assert_array_equal(st.pose, fresh.pose)
    assert st.n_removed == 0 and st.n_steps == 0 and math.isnan(st.t_s)
    assert st.epoch == 1 and st.burr == 1 and st.tool == 1     # burr and tool kept
    ev = st.tissue.read(n0)
    assert ev["kind"].tolist() == [events.RESET] and ev["n"].tolist() == [1]
    assert ev["t_s"].tolist() == [0.5]
    apply_commands(m, st, (Reset(7),), 0.6)                   # a replay's recorded epoch
    assert st.epoch == 7


def test_split_box_moves_exactly_the_boxes_voxels_of_the_body():
    m = _models()
    st = make_state(m)
    split_body(st, 0, [(5, 5, 5)])                              # body 1 elsewhere
    before = {(i, j, k): _body_at(st, i, j, k) for i in range(0, 16)
              for j in range(0, 16) for k in range(0, 12)}
    lo, hi = (3, 4, 2), (9, 7, 10)
    apply_commands(m, st, (SplitBox(0, lo, hi),), 0.25)
    new = 2
    for (i, j, k), b in before.items():
        inside = all(lo[a] <= (i, j, k)[a] <= hi[a] for a in range(3))
        solid = st.grid.density[st.grid.brick_index(i, j, k), voxel_offset(i, j, k)] > 0 \
            if st.grid.brick_index(i, j, k) >= 0 else False
        want = new if inside and b == 0 and solid else b
        assert _body_at(st, i, j, k) == want, (i, j, k)
    split = events.select(st.tissue.read(0), events.SPLIT)
    assert (split["body"] == new).all() and (split["t_s"] == 0.25).all()
    assert len(split["body"]) == sum(1 for (i, j, k), b in before.items()
                                     if b == 0 and all(lo[a] <= (i, j, k)[a] <= hi[a]
                                                       for a in range(3))
                                     and k < 20)


def test_move_body_sets_the_pose_and_a_failing_command_does_not_stop_the_rest():
    m = _models()
    st = make_state(m)
    pose = np.array([1.0, -2.0, 0.5, 0.9, 0.1, -0.3, 0.2])
    pose[3:] /= np.linalg.norm(pose[3:])
    failed = []
    cmds = (SplitVoxels(0, np.array([[3, 3, 3], [3, 3, 4]]), 1), MoveBody(5, pose),
            MoveBody(1, pose), SetBurr(9))
    n = apply_commands(m, st, cmds, 0.1, lambda i, exc: failed.append((i, str(exc))))
    assert n == 2 and [i for i, _ in failed] == [1, 3]
    assert "body 5 does not exist" in failed[0][1] and "out of range" in failed[1][1]
    np.testing.assert_array_equal(st.pose[1], pose)
    np.testing.assert_allclose(st.pose_m[1][:, :3], _quat_matrix(pose), atol=1e-12)
    np.testing.assert_array_equal(st.pose_m[1][:, 3], pose[:3])
    poses = events.select(st.tissue.read(0), events.POSE)
    assert poses["body"].tolist() == [1] and np.array_equal(poses["value"][0], st.pose[1])
    with pytest.raises(IndexError, match="burr index 9"):       # without on_error: raised
        world_step(m, st, Sample(0.2, np.zeros(3), AXIS, False, 1.0, 1), (SetBurr(9),))


def test_rigid_commands_need_the_states_rigid_set():
    m = _models()
    st = make_state(m, rigid=False)
    split_body(st, 0, [(3, 3, 3)])
    with pytest.raises(ValueError, match="no rigid motion"):
        apply_commands(m, st, (Grab(1),), 0.0)
    with pytest.raises(ValueError, match="no rigid motion"):
        apply_commands(m, st, (Release(),), 0.0)


# ---------------------------------------------------------- rigid step
def test_a_fragment_let_go_falls_and_rests_on_the_block():
    labels = np.zeros((40, 40, 40), np.uint8)
    labels[:, :, :20] = 1
    labels[12:20, 12:20, 24:30] = 1                 # a piece 2 mm above the block
    m, _ = block_model(labels=labels, burr=FakeBurr(radius_mm=1.5))
    st = make_state(m)
    away = np.array([-20.0, -20.0, 40.0])
    cmds = {0: (SplitBox(0, (12, 12, 24), (19, 19, 29)),), 2: (Grab(1),), 3: (Release(),)}
    z = []
    for q in range(1500):
        world_step(m, st, Sample(q * 1e-3, away, AXIS, False, 1.0, 1), cmds.get(q, ()))
        if q == 2:
            assert st.rigid.mode[st.rigid.slot_of(1)] == GRABBED
        if q == 3:
            assert st.rigid.mode[st.rigid.slot_of(1)] == DYNAMIC
        z.append(st.pose[1, 2])
    # it fell the 2 mm gap (less than a voxel of give) and came to rest
    assert z[-1] == pytest.approx(-(24 - 20) * SP, abs=0.3)
    assert st.rigid.mode[st.rigid.slot_of(1)] == ASLEEP
    poses = events.select(st.tissue.read(0), events.POSE)
    assert (poses["body"] == 1).all() and len(poses["t_s"]) > 50
    # a reset forgets it
    apply_commands(m, st, (Reset(),), 2.0)
    assert st.rigid.slot_of(1) == -1 and not st.rigid.active
