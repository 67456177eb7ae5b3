"""Large splits in bounded slices (bonesim.engine.split_jobs): the sliced
split moves exactly the voxels of the one-shot split and of a slow labelling,
each slice within the budget, no voxel lost, through the world step."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage

from bonesim.engine import events
from bonesim.engine.bodies import body_voxel_counts
from bonesim.engine.fragments import publish_part, shed_voxels
from bonesim.engine.model import Sample, make_model, make_state
from bonesim.engine.replica import TissueReplica
from bonesim.engine.slicing import voxels_per_step
from bonesim.engine.split_jobs import advance_splits, filling, queue_split, run_split
from bonesim.engine.world import world_step
from bonesim.engine.world_commands import Reset, SplitPart
from bonesim.io.burrs import load_burr

BONE = SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200))
EDGE = 20


def _porous(seed: int, fill: float) -> np.ndarray:
    """A 20^3 volume of bone blobs (several parts, tunnels and bridges)."""
    rng = np.random.default_rng(seed)
    solid = ndimage.uniform_filter(rng.random((EDGE,) * 3), 3) < fill
    return solid.astype(np.uint8)


def _model(lab):
    return make_model(lab, 0.5, [BONE], load_burr("cutting-1mm"))


def _dense_body(state, b):
    """(body == b) & material as a dense volume (slow, obviously right)."""
    g = state.grid
    out = np.zeros(g.shape, bool)
    for q, (bi, bj, bk) in enumerate(g.bricks.tolist()):
        blk = (state.body[q] == b) & (g.density[q] > 0)
        sl = np.s_[bi * 8:bi * 8 + 8, bj * 8:bj * 8 + 8, bk * 8:bk * 8 + 8]
        tgt = out[sl]
        tgt[...] = blk.reshape(8, 8, 8)[:tgt.shape[0], :tgt.shape[1], :tgt.shape[2]]
    return out


def _reference(state, src, seed, lo, hi):
    """The part of ``src`` holding ``seed`` inside the box, by scipy's
    26-connected labelling of the dense volume: sorted (n, 3) voxels."""
    mask = _dense_body(state, src)
    box = np.zeros_like(mask)
    box[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1] = True
    lab, _ = ndimage.label(mask & box, np.ones((3, 3, 3), bool))
    c = lab[tuple(seed)]
    return np.argwhere(lab == c) if c else np.zeros((0, 3), np.int64)


def _sorted(ijk):
    ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
    return ijk[np.lexsort(ijk.T[::-1])]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), fill=st.floats(0.45, 0.6),
       budget=st.sampled_from([1, 2, 7, 50, 100_000]),
       box=st.sampled_from(["whole", "half"]))
def test_a_sliced_split_moves_exactly_the_one_shot_split_and_the_labelling(seed, fill,
                                                                           budget, box):
    lab = _porous(seed, fill)
    if not lab.any():
        return
    m = _model(lab)
    one, sliced = make_state(m), make_state(m)
    pts = np.argwhere(lab > 0)
    s = pts[np.random.default_rng(seed).integers(len(pts))]
    lo = np.zeros(3, np.int64)
    hi = np.full(3, EDGE - 1) if box == "whole" else np.array([EDGE - 1, EDGE // 2, EDGE - 1])
    if s[1] > hi[1]:
        s = s.copy()
        s[1] = hi[1]
        if lab[tuple(s)] == 0:
            return
    ref = _reference(one, 0, s, lo, hi)
    n = len(ref)
    d1, n1 = publish_part(one, 0, s, lo, hi, n, 0.5)
    job = queue_split(sliced, 0, s, lo, hi, n)
    per_slice = []
    while sliced.split_jobs:                       # one slice per "step", at its own time
        per_slice.append(advance_splits(sliced, 0.5 + len(per_slice), budget))
    d2, n2 = job.dst, job.moved
    assert n1 == n2 == n and d1 == d2 == 1 and sum(per_slice) == n
    # the same bodies, voxel for voxel, and the same box of the new body
    np.testing.assert_array_equal(sliced.body, one.body)
    np.testing.assert_array_equal(_sorted(np.argwhere(_dense_body(sliced, 1))), _sorted(ref))
    for name in ("alive", "bounds", "pose", "pose_m"):
        np.testing.assert_array_equal(getattr(sliced, name), getattr(one, name), err_msg=name)
    np.testing.assert_array_equal(sliced.grid.density, one.grid.density)
    # the records: the same voxels, each once, in blocks each within the budget
    ev = sliced.tissue.read(0)
    assert (ev["kind"] == events.SPLIT).all() and (ev["body"] == 1).all()
    assert (ev["value"][:, 0] == 0).all() and (ev["value"][:, 1:] == 0).all()
    np.testing.assert_array_equal(_sorted(ev["ijk"]), _sorted(ref))
    t, sizes = np.unique(ev["t_s"], return_counts=True)
    np.testing.assert_array_equal(t, 0.5 + np.flatnonzero(per_slice))
    np.testing.assert_array_equal(sizes, np.asarray(per_slice)[np.asarray(per_slice) > 0])
    assert (sizes <= budget + 26).all()
    for tt, m in zip(t, sizes):                    # each block's records carry its count
        assert (ev["n"][ev["t_s"] == tt] == m).all()


def test_run_split_runs_a_split_to_its_end():
    m, corner, edge = _cube_case(edge=8)
    a, b = make_state(m), make_state(m)
    lo, hi = np.asarray(corner) - 1, np.asarray(corner) + edge
    dst, n, slices = run_split(a, 0, corner, lo, hi, edge ** 3, 0.0, budget=10)
    # each slice expands 10 voxels or moves at least 10: at most n / 10 of each
    assert (dst, n) == (1, edge ** 3) and n / 36 <= slices <= 2 * n / 10 + 1
    publish_part(b, 0, corner, lo, hi, edge ** 3, 0.0)
    np.testing.assert_array_equal(a.body, b.body)
    # a part larger than its n_max stops there (the job ends; what moved stays moved)
    c = make_state(m)
    assert run_split(c, 0, corner, lo, hi, 100, 0.0, budget=10)[1] == 100


def test_the_budget_comes_from_the_data_file():
    assert voxels_per_step() >= 1
    from bonesim.resources import data_path
    from bonesim.tomlfile import read_toml

    assert voxels_per_step() == read_toml(data_path("slicing.toml"))["split"]["voxels_per_step"]


def _cube_case(edge=24, gap=4):
    """A floor slab and, above it, a cube of bone apart from it."""
    lab = np.zeros((edge + 8, edge + 8, edge + 8 + gap + 6), np.uint8)
    lab[:, :, :6] = 1
    lab[4:4 + edge, 4:4 + edge, 6 + gap:6 + gap + edge] = 1
    return _model(lab), (4, 4, 6 + gap), edge


def test_split_part_queues_a_large_part_and_the_world_step_slices_it():
    m, corner, edge = _cube_case()
    st_ = make_state(m)
    ref = make_state(m)
    lo, hi = np.asarray(corner) - 1, np.asarray(corner) + edge
    publish_part(ref, 0, corner, lo, hi, edge ** 3, 0.0)
    rep = TissueReplica(m, st_, snapshot=False)
    budget = voxels_per_step()
    assert edge ** 3 > budget            # the case needs slices
    away = Sample(0.0, np.array([-20.0, -20.0, 40.0]), np.array([0.0, 0.0, -1.0]), False,
                  0.0, 1)
    cmd = SplitPart(0, corner, tuple(lo), tuple(hi), edge ** 3, 0)
    world_step(m, st_, away, (cmd,))
    assert len(st_.split_jobs) == 1 and st_.n_bodies == 2
    assert filling(st_, 1) and not filling(st_, 0)
    with pytest.raises(ValueError, match="still being split"):
        st_.rigid.wake_body(st_, 1)
    q = 1
    while st_.split_jobs:
        world_step(m, st_, away._replace(t_s=q * 1e-3))
        q += 1
        rep.drain()
        np.testing.assert_array_equal(rep.state.body, st_.body)
    assert q == -(-edge ** 3 // budget) or q == -(-edge ** 3 // budget) + 1
    np.testing.assert_array_equal(st_.body, ref.body)
    np.testing.assert_array_equal(st_.bounds, ref.bounds)
    ev = st_.tissue.read(0)
    split = ev["kind"] == events.SPLIT
    # one block per step, each at its step's time
    assert len(np.unique(ev["t_s"][split])) == q
    assert not filling(st_, 1)
    # a small part after it splits at once, as before slicing
    small = SplitPart(0, (0, 0, 0), (0, 0, 0), (1, 1, 1), 8, 0)
    world_step(m, st_, away._replace(t_s=1.0), (small,))
    assert not st_.split_jobs and st_.n_bodies == 3


def test_a_reset_drops_the_queued_split():
    m, corner, edge = _cube_case()
    st_ = make_state(m)
    away = Sample(0.0, np.array([-20.0, -20.0, 40.0]), np.array([0.0, 0.0, -1.0]), False,
                  0.0, 1)
    lo, hi = np.asarray(corner) - 1, np.asarray(corner) + edge
    world_step(m, st_, away, (SplitPart(0, corner, tuple(lo), tuple(hi), edge ** 3, 0),))
    assert st_.split_jobs
    world_step(m, st_, away._replace(t_s=0.001), (Reset(),))
    assert not st_.split_jobs and st_.n_bodies == 1 and (st_.body == 0).all()


def test_removal_across_a_part_while_it_splits_loses_no_voxel():
    """A layer through the cube is removed (as dust, from both bodies) while
    the cube is split in slices of 16: the split-off body ends as exactly the
    half that holds the seed, the other half stays with body 0, every voxel of
    the case is in a living body or removed, and every removal is published."""
    m, corner, edge = _cube_case(edge=16)
    st_ = make_state(m)
    dens0 = int((st_.grid.density > 0).sum())
    corner = np.asarray(corner)
    lo, hi = corner - 1, corner + edge
    queue_split(st_, 0, corner, lo, hi, edge ** 3)
    cut = corner[2] + edge // 2
    layer = np.argwhere(np.ones((edge, edge, 1), bool)) + (corner[0], corner[1], cut)
    q = 0
    while st_.split_jobs:
        advance_splits(st_, q * 1e-3, budget=16)
        if q == 3:                                   # the fill is still near the seed
            assert 0 < (st_.body == 1).sum() < edge ** 3 // 4
            shed_voxels(st_, 0, layer, q * 1e-3)
            shed_voxels(st_, 1, layer, q * 1e-3)
        q += 1
        assert q < 10_000
    counts = body_voxel_counts(st_)
    assert st_.n_removed == edge * edge
    assert counts.sum() == dens0 - st_.n_removed            # no voxel lost
    new = _sorted(np.argwhere(_dense_body(st_, 1)))
    half = _sorted(np.argwhere(np.ones((edge, edge, edge // 2), bool)) + corner)
    np.testing.assert_array_equal(new, half)
    assert counts[0] == dens0 - st_.n_removed - len(half)
    ev = st_.tissue.read(0)
    assert (ev["kind"] == events.SPLIT).sum() == len(half)
    assert len(events.removals(ev)["ijk"]) == st_.n_removed


def test_queued_specks_are_shed_in_turn_and_one_larger_than_found_is_left():
    m, corner, edge = _cube_case(edge=8)
    st_ = make_state(m)
    lo, hi = np.asarray(corner) - 1, np.asarray(corner) + edge
    queue_split(st_, 0, corner, lo, hi, edge ** 3)            # the cube, in slices
    queue_split(st_, 0, (0, 0, 0), (0, 0, 0), (1, 1, 1), 8, shed=True)      # 8 voxels
    queue_split(st_, 0, (2, 2, 0), (2, 2, 0), (3, 3, 1), 3, shed=True)      # 8 > 3
    n0 = body_voxel_counts(st_).sum()
    q = 0
    while st_.split_jobs:
        advance_splits(st_, q * 1e-3, budget=64)
        q += 1
    assert st_.n_removed == 8 and body_voxel_counts(st_).sum() == n0 - 8
    assert body_voxel_counts(st_)[1] == edge ** 3
    rem = events.removals(st_.tissue.read(0))
    assert rem["shed"].all() and len(rem["ijk"]) == 8
