"""Per-body surfaces of a replica against a naive reference: each body's
surface is ``Surface.build`` of the replica grid with every other body's
voxels emptied."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.bodies import publish_pose, publish_split, publish_split_box, voxel_bodies
from bonesim.engine.body_surfaces import BodySurfaces, margin_bricks
from bonesim.engine.grid import BRICK
from bonesim.engine.model import Sample, reset_state, step
from bonesim.engine.replica import TissueReplica
from bonesim.engine.surface import Surface

from tests.bonesim.fakes import BONE, NERVE, block_model

AXIS = np.array([0.0, 0.0, -1.0])
TURN = (0.0, 0.0, 4.0, np.cos(np.pi / 12), 0.0, 0.0, np.sin(np.pi / 12))   # 30 deg about z


def _model():
    labels = np.zeros((40, 40, 30), np.uint8)
    labels[:, :, :20] = 1
    labels[12:20, 12:20, 14:18] = 2
    return block_model(labels=labels, structures=[BONE, NERVE])


def _reference(model, state, b):
    """Surface.build of the replica grid holding only body ``b``'s voxels."""
    g = state.grid.copy()
    g.density[state.body != b] = 0.0
    return Surface.of_model(model, g)


def _check(model, rep):
    """Every body's surface equals its reference; the bodies' voxels are
    the replica's, each once."""
    st = rep.state
    surfs, grids = rep.body_surfaces, rep.body_grids
    assert sorted(surfs) == np.flatnonzero(st.alive).tolist()
    assert rep.surface is surfs[0]
    total = 0
    for b, s in surfs.items():
        diff = _reference(model, st, b).canonical().differences(s.canonical())
        assert not diff, (b, diff)
        total += grids[b].occupied_count()
        g = grids[b]
        assert g.spacing_mm == rep.grid.spacing_mm
        np.testing.assert_array_equal(g.origin_mm, rep.grid.origin_mm)
        # a body grid holds exactly that body's voxels of the replica
        occ = np.argwhere(g.density > 0)
        ijk = (g.bricks[occ[:, 0]].astype(np.int64) << 3) + np.stack(
            [(occ[:, 1] >> 6) & 7, (occ[:, 1] >> 3) & 7, occ[:, 1] & 7], axis=1)
        assert (voxel_bodies(st.grid, st.body, ijk) == b).all()
    assert total == rep.grid.occupied_count()


def _feed(rep, st, pos=0):
    ev = st.tissue.read(pos)
    ch = rep.apply(ev)
    return st.tissue.count, ch


def test_one_body_keeps_the_single_surface_and_poses_only_move_it():
    m, st = _model()
    rep = TissueReplica(m, surface=True)
    surf = rep.surface
    t = 0.0
    for q in range(100):
        t += 1e-3
        step(m, st, Sample(t, np.array([5.0 + 0.05 * q, 10.0, 9.3]), AXIS, True, 6e4, 1))
    publish_pose(st, 0, TURN, t)
    pos, ch = _feed(rep, st)
    assert rep.surface is surf and rep.body_surfaces == {0: surf}
    assert rep.body_grids[0] is rep.grid and ch.bodies == (0,) and len(ch.split) == 0
    m4 = rep.body_matrix(0)
    assert m4.shape == (4, 4) and np.allclose(m4[:3], st.pose_m[0])
    assert np.allclose(m4[3], (0, 0, 0, 1))
    fresh = Surface.of_model(m, rep.grid)
    assert not fresh.canonical().differences(surf.canonical())


def test_split_move_drill_and_reset_against_the_reference():
    m, st = _model()
    rep = TissueReplica(m, surface=True)
    main = rep.surface
    t, pos = 0.0, 0
    for q in range(600):                                 # drill body 0 first
        t += 1e-3
        step(m, st, Sample(t, np.array([4.0 + 0.012 * q, 6.0, 9.3]), AXIS, True, 6e4, 1))
    pos, _ = _feed(rep, st, pos)
    # a box crossing the drilled groove and the nerve, not brick-aligned
    b1, n1 = publish_split_box(st, 0, (10, 3, 5), (22, 21, 19), t)
    assert b1 == 1 and n1 > 0
    pos, ch = _feed(rep, st, pos)
    assert rep.surface is main                           # body 0 took it over
    assert ch.bodies == (1,) and len(ch.split) == n1 and len(ch.changed) == n1
    _check(m, rep)
    # move the fragment: geometry unchanged, only its matrix
    rev = rep.body_revisions
    publish_pose(st, 1, TURN, t)
    pos, ch = _feed(rep, st, pos)
    assert ch.bodies == (1,) and rep.body_revisions == rev
    assert np.allclose(rep.body_matrix(1)[:3], st.pose_m[1])
    # drill both bodies (the tool in each body's frame is the haptic step's job)
    for q in range(900):
        t += 1e-3
        step(m, st, Sample(t, np.array([3.0 + 0.015 * q, 12.0, 9.4 + 0.004 * q]), AXIS,
                           True, 6e4, 1))
        if q % 100 == 99:
            pos, _ = _feed(rep, st, pos)
    pos, _ = _feed(rep, st, pos)
    rem = st.tissue.read(0)
    drilled = set(rem["body"][rem["kind"] == events.REMOVED].tolist())
    assert drilled == {0, 1}
    _check(m, rep)
    # split the fragment again, and a second piece off body 0, in one batch
    b2, n2 = publish_split_box(st, 1, (10, 3, 5), (14, 9, 12), t)
    b3, n3 = publish_split_box(st, 0, (30, 30, 0), (37, 37, 7), t)
    assert (b2, b3) == (2, 3) and n2 > 0 and n3 > 0
    pos, ch = _feed(rep, st, pos)
    assert ch.bodies == (2, 3)
    _check(m, rep)
    # a fragment's grid covers its box plus the margin, not the whole case
    assert rep.body_grids[3].n_bricks < rep.grid.n_bricks // 4
    # reset: one surface over the whole grid again
    reset_state(m, st, rings=False)
    events.push_event(st.tissue, events.RESET, t, n=1)
    pos, ch = _feed(rep, st, pos)
    assert ch.reset and list(rep.body_surfaces) == [0] and rep.body_grids[0] is rep.grid
    assert not Surface.of_model(m, rep.grid).canonical().differences(rep.surface.canonical())


@pytest.mark.parametrize("lo,hi", [((8, 8, 0), (15, 15, 7)),        # exactly one brick
                                   ((8, 8, 8), (16, 16, 16)),       # one voxel past it
                                   ((0, 0, 0), (7, 39, 19))])       # at the grid's edge
def test_split_on_brick_boundaries(lo, hi):
    m, st = _model()
    rep = TissueReplica(m, surface=True)
    b, n = publish_split_box(st, 0, lo, hi, 0.0)
    assert n > 0
    _feed(rep, st)
    _check(m, rep)
    g = rep.body_grids[b]
    k = margin_bricks(m.grid.spacing_mm)
    want_lo = [max(-1, x // BRICK - k) for x in lo]
    want_hi = [x // BRICK + k for x in hi]
    assert (g.bricks.min(axis=0) == want_lo).all() and (g.bricks.max(axis=0) <= want_hi).all()


def test_split_read_in_two_chunks_grows_the_body_and_late_replicas_build_all():
    m, st = _model()
    rep = TissueReplica(m, surface=True)
    publish_split(st, 0, np.mgrid[5:12, 5:12, 10:19].reshape(3, -1).T, 0.0)
    publish_split_box(st, 0, (20, 20, 0), (35, 30, 19), 0.0)
    ev = st.tissue.read(0)
    cut = len(ev["kind"]) - 700                    # inside the second split's block
    assert ev["kind"][cut - 1] == ev["kind"][cut] == events.SPLIT
    assert ev["body"][cut - 1] == ev["body"][cut] == 2
    rep.apply({f: a[:cut] for f, a in ev.items()})
    ch = rep.apply({f: a[cut:] for f, a in ev.items()})
    assert ch.bodies == (2,) and len(ch.split) == 700
    _check(m, rep)
    # a replica joining a split state builds every body from scratch
    late = TissueReplica(m, st, surface=True)
    assert sorted(late.body_surfaces) == [0, 1, 2]
    _check(m, late)


def test_body_surfaces_build_equals_take_over():
    m, st = _model()
    rep = TissueReplica(m, surface=True)
    publish_split_box(st, 0, (3, 3, 3), (20, 20, 12), 0.0)
    _feed(rep, st)
    fresh = BodySurfaces.build(m, rep.state)
    for b, s in rep.body_surfaces.items():
        assert not fresh.surfaces[b].canonical().differences(s.canonical())
    with pytest.raises(ValueError, match="does not exist"):
        rep.body_matrix(5)
