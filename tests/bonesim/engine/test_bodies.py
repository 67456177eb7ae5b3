"""Bone as bodies: splitting, moving, and the step against a placed reference."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.bodies import (IDENTITY_POSE, body_voxel_counts, is_identity, plan_passes,
                                   pose_matrix, publish_pose, publish_split, publish_split_box,
                                   split_body, validate_pose)
from bonesim.engine.haptics import O_MAG, O_N_IMMERSED
from bonesim.engine.model import Sample, make_state, reset_state, step

from tests.bonesim.fakes import BONE, MATERIALS, NERVE, block_model

AXIS = np.array([0.0, 0.0, -1.0])


def _sweep(n=900, z=9.2, x0=4.0, x1=16.0, y=10.03):
    """A drilling stroke along x, half a burr deep into the block top (z = 9.75 mm)."""
    xs = np.linspace(x0, x1, n)
    return [Sample(q * 1e-3, np.array([xs[q], y, z]), AXIS, True, 60000.0, 1)
            for q in range(n)]


def _voxels(shape, box):
    (i0, i1), (j0, j1), (k0, k1) = box
    g = np.mgrid[i0:i1, j0:j1, k0:k1].reshape(3, -1).T
    return g.astype(np.int32)


def _rm(ev):
    r = events.removals(ev)
    return r["ijk"], r["t_s"], r["label"]


# --------------------------------------------------------------- identity
@pytest.mark.parametrize("oversample", [2, 4])
def test_a_split_at_the_identity_steps_exactly_as_one_body(oversample):
    m, one = block_model(oversample=oversample)
    two = make_state(m)
    dst, n = publish_split(two, 0, _voxels(m.grid.shape, ((10, 40), (0, 40), (0, 20))), 0.0)
    assert dst == 1 and n == 30 * 40 * 20 and two.n_bodies == 2
    assert two.tissue.count == n                    # one SPLIT record per voxel
    for smp in _sweep():
        fa = step(m, one, smp).copy()
        fb = step(m, two, smp).copy()
        np.testing.assert_array_equal(fa, fb)
        np.testing.assert_array_equal(one.out, two.out)
    np.testing.assert_array_equal(one.grid.density, two.grid.density)
    ra = _rm(one.tissue.read(0))
    rb = _rm(two.tissue.read(n))
    for a, b in zip(ra, rb):
        np.testing.assert_array_equal(a, b)
    # the stroke crossed the split: both bodies lost voxels, each named its own
    bodies = events.removals(two.tissue.read(n))["body"]
    assert set(np.unique(bodies)) == {0, 1}
    ijk = events.removals(two.tissue.read(n))["ijk"]
    np.testing.assert_array_equal(bodies == 1, ijk[:, 0] >= 10)


def test_split_takes_only_live_voxels_of_the_source_and_conserves_them():
    m, st = block_model()
    before = body_voxel_counts(st).sum()
    box = _voxels(m.grid.shape, ((0, 5), (0, 5), (15, 25)))   # half of it is air
    dst, n = publish_split(st, 0, np.concatenate([box, box]), 0.5)  # listed twice
    assert n == 5 * 5 * 5
    counts = body_voxel_counts(st)
    assert counts[dst] == n and counts.sum() == before
    # split again from the new body; then a split of nothing publishes nothing
    d2, n2 = publish_split(st, dst, _voxels(m.grid.shape, ((0, 2), (0, 5), (15, 20))), 0.6)
    assert n2 == 2 * 5 * 5 and body_voxel_counts(st)[d2] == n2
    assert body_voxel_counts(st).sum() == before
    head = st.tissue.count
    assert publish_split(st, 0, box, 0.7) == (-1, 0) and st.tissue.count == head
    with pytest.raises(ValueError, match="body 9 does not exist"):
        publish_split(st, 9, box, 0.8)
    reset_state(m, st)
    assert st.n_bodies == 1 and body_voxel_counts(st)[0] == before


def test_a_box_split_walked_in_place_equals_the_split_of_its_voxel_list():
    m, a = block_model()
    b = make_state(m)
    drill = Sample(0.0, np.array([5.0, 5.0, 9.3]), AXIS, True, 60000.0, 1)
    for st in (a, b):                               # a hole, so the box is ragged
        for q in range(50):
            step(m, st, drill._replace(t_s=q * 1e-3))
    lo, hi = (6, 3, 10), (14, 20, 45)               # reaches past the grid's top
    box = np.mgrid[6:15, 3:21, 10:46].reshape(3, -1).T
    ha, hb = a.tissue.count, b.tissue.count
    assert publish_split(a, 0, box, 0.5) == publish_split_box(b, 0, lo, hi, 0.5)
    ra, rb = a.tissue.read(ha), b.tissue.read(hb)
    for f in events.TISSUE_FIELDS:
        np.testing.assert_array_equal(ra[f], rb[f], err_msg=f)
    for name in ("body", "pose", "pose_m", "alive", "bounds"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert publish_split_box(b, 0, (30, 30, 30), (35, 35, 35), 0.6) == (-1, 0)  # air
    with pytest.raises(ValueError, match="body 7 does not exist"):
        publish_split_box(b, 7, lo, hi, 0.7)


def test_poses_are_validated_and_matrices_are_exact_for_the_identity():
    assert is_identity(IDENTITY_POSE)
    np.testing.assert_array_equal(pose_matrix(IDENTITY_POSE), np.eye(3, 4))
    with pytest.raises(ValueError, match="not unit"):
        validate_pose((0, 0, 0, 1.0, 0.1, 0, 0))
    with pytest.raises(ValueError, match="shape"):
        validate_pose((0, 0, 0, 1.0))
    with pytest.raises(ValueError, match="not finite"):
        validate_pose((np.nan, 0, 0, 1.0, 0, 0, 0))
    q = np.array([0.3, -0.2, 0.5, 0.7])
    q /= np.linalg.norm(q)
    r = pose_matrix((1.0, 2.0, 3.0, *q))[:, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(r), 1.0)


# --------------------------------------------------------------- moved body
CUBE = ((4, 12), (4, 12), (2, 10))                  # voxels of the piece cut free
MOVE = np.array([6.0, 5.0, 0.0])                   # [mm], whole voxels (0.5 mm)
# 180 degrees about z (an exact matrix): x, y mirrored through the body origin
TURN = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def _placed_reference(m, pose):
    """A one-body model whose labels hold the cube where ``pose`` puts it."""
    from bonesim.engine.model import make_model

    lab = np.zeros(m.grid.shape, np.uint8)
    cube = _voxels(m.grid.shape, CUBE)
    p = m.grid.origin_mm + m.spacing_mm * cube
    mat = pose_matrix(pose)
    q = np.rint((p @ mat[:, :3].T + mat[:, 3] - m.grid.origin_mm) / m.spacing_mm).astype(int)
    lab[q[:, 0], q[:, 1], q[:, 2]] = 1
    ref = make_model(lab, m.spacing_mm, [BONE], m.burr, materials=MATERIALS,
                     origin_mm=m.grid.origin_mm, oversample=m.oversample)
    return _unbounded_removal(ref), cube, q


def _unbounded_removal(m):
    """``m`` whose fixed-budget step (4x on 0.5 mm voxels) flushes every
    queued cell at once: where the removal budget binds, a turned body's
    cells queue in another order and go in another order (the same voxels
    once flushed), so forces compare step by step only without it."""
    from dataclasses import replace

    if not m.budget.binding:
        return m
    return replace(m, budget=replace(m.budget, removal_voxels=(10 ** 9,)))


@pytest.mark.parametrize("oversample", [2, 4])
@pytest.mark.parametrize("turn", [False, True])
def test_a_moved_body_is_drilled_where_it_now_stands(turn, oversample):
    labels = np.zeros((48, 48, 24), np.uint8)
    labels[CUBE[0][0]:CUBE[0][1], CUBE[1][0]:CUBE[1][1], CUBE[2][0]:CUBE[2][1]] = 1
    m, st = block_model(labels=labels, oversample=oversample)
    m = _unbounded_removal(m)
    dst, n = publish_split(st, 0, _voxels(m.grid.shape, CUBE), 0.0)
    assert n == 8 * 8 * 8
    if turn:
        # about the cube's centre: translate the centre, then turn
        c = m.grid.origin_mm + m.spacing_mm * np.array([7.5, 7.5, 0.0])
        pose = np.array([2 * c[0] + MOVE[0], 2 * c[1] + MOVE[1], 0.0, *TURN[3:]])
    else:
        pose = np.array([*MOVE, *IDENTITY_POSE[3:]])
    publish_pose(st, dst, pose, 0.0)
    ref, cube, placed = _placed_reference(m, pose)
    rs = make_state(ref)
    centre = m.grid.origin_mm + m.spacing_mm * placed.mean(axis=0)
    top = m.grid.origin_mm[2] + m.spacing_mm * (placed[:, 2].max() + 0.5)
    y = centre[1] + 0.037
    path = _sweep(600, z=top - 0.6, x0=centre[0] - 1.7, x1=centre[0] + 1.3, y=y)
    for smp in path:
        f = step(m, st, smp).copy()
        g = step(ref, rs, smp).copy()
        np.testing.assert_allclose(f, g, rtol=1e-9, atol=1e-12)
    assert rs.out[O_N_IMMERSED] > 0 and st.out[O_MAG] > 0
    got = events.removals(st.tissue.read(0))
    want = events.removals(rs.tissue.read(0))
    assert len(got["ijk"]) == len(want["ijk"]) > 20
    assert (got["body"] == dst).all()
    # the body's removed voxels, taken to the case frame, are the reference's
    mat = pose_matrix(pose)
    p = m.grid.origin_mm + m.spacing_mm * got["ijk"]
    q = np.rint((p @ mat[:, :3].T + mat[:, 3] - m.grid.origin_mm) / m.spacing_mm)
    assert set(map(tuple, q.astype(int))) == set(map(tuple, want["ijk"]))
    # where the cube was, there is nothing left to drill
    st2 = make_state(m)
    publish_split(st2, 0, _voxels(m.grid.shape, CUBE), 0.0)
    publish_pose(st2, 1, pose, 0.0)
    old = m.grid.origin_mm + m.spacing_mm * np.array([7.6, 7.6, 9.0])
    step(m, st2, Sample(0.0, old, AXIS, True, 60000.0, 1))
    assert st2.out[O_N_IMMERSED] == 0


def test_passes_group_bodies_by_pose_and_skip_far_bodies():
    m, st = block_model()
    split_body(st, 0, _voxels(m.grid.shape, ((0, 10), (0, 40), (0, 20))))
    split_body(st, 0, _voxels(m.grid.shape, ((30, 40), (0, 40), (0, 20))))
    publish_pose(st, 2, (50.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0), 0.0)   # far away
    group = np.zeros(m.max_bodies, np.int32)
    rep = np.zeros(m.max_bodies, np.int32)
    ident = np.zeros(m.max_bodies, np.bool_)
    g = m.grid
    n = plan_passes(st.alive, st.pose, st.pose_m, st.bounds, np.array([5.0, 10.0, 9.5]),
                    1.5, g.origin_mm, g.spacing_mm, group, rep, ident)
    assert n == 1 and ident[0] and list(group[:3]) == [0, 0, -1]
    n = plan_passes(st.alive, st.pose, st.pose_m, st.bounds, np.array([67.0, 10.0, 9.5]),
                    1.5, g.origin_mm, g.spacing_mm, group, rep, ident)
    assert n == 1 and not ident[0] and list(group[:3]) == [-1, -1, 0]


def test_injuries_name_the_body_and_keep_the_case_frame_position():
    labels = np.zeros((40, 40, 30), np.uint8)
    labels[:, :, :20] = 1
    labels[15:25, 15:25, 16:20] = 2                  # a nerve under the top
    m, st = block_model(labels=labels, structures=[BONE, NERVE])
    publish_split(st, 0, _voxels(m.grid.shape, ((0, 40), (0, 40), (0, 30))), 0.0)
    pose = (0.0, 0.0, 3.0, 1.0, 0.0, 0.0, 0.0)
    publish_pose(st, 1, pose, 0.0)
    head = st.tissue.count
    pos = np.array([10.0, 10.0, 9.6 + 3.0])          # over the nerve, moved up 3 mm
    for q in range(40):
        step(m, st, Sample(q * 1e-3, pos, AXIS, True, 60000.0, 1))
    inj = events.injuries(st.tissue.read(head))
    assert len(inj["t_s"]) >= 1 and inj["kind"][0] == events.INJURY_CONTACT
    assert (inj["body"] == 1).all() and (inj["label"] == 2).all()
    np.testing.assert_array_equal(inj["pos_mm"][0], pos)


def test_frame_transforms_are_inverse_and_match_the_pose_matrix():
    from bonesim.engine.bodies import pose_matrix, to_body_frame, to_case_frame

    rng = np.random.default_rng(3)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    m = pose_matrix(np.r_[[4.0, -2.5, 7.0], q])
    pts = rng.normal(size=(20, 3)) * 10
    case = to_case_frame(m, pts)
    # naive: one point at a time, homogeneous coordinates
    for p, c in zip(pts, case):
        np.testing.assert_allclose(m @ np.r_[p, 1.0], c, atol=1e-12)
    np.testing.assert_allclose(to_body_frame(m, case), pts, atol=1e-12)
    np.testing.assert_allclose(to_body_frame(m, case[0]), pts[0], atol=1e-12)
