"""Fragments: the parts a burst of removals cuts off, found by the local pass,
checked against a from-scratch labelling (scipy.ndimage.label) and the global
pass; carried out by the split commands' kernels."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.ndimage as ndi
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as hs

from bonesim.engine import events
from bonesim.engine.bodies import body_voxel_counts
from bonesim.engine.fragments import (DEFAULT_SPECK_VOXELS, body_mask, component_voxels,
                                      find_parts, find_parts_global, label_parts,
                                      publish_part, shed_voxels)
from bonesim.engine.model import make_model, make_state, reset_state
from bonesim.io.burrs import load_burr

BONE = SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200))
#: The test grid [voxels]; every voxel has a brick, so any pattern can be set.
SHAPE = (24, 16, 16)
FULL = np.ones((3, 3, 3), bool)


@pytest.fixture(scope="module")
def model():
    return make_model(np.ones(SHAPE, np.uint8), 0.5, [BONE], load_burr("cutting-1mm"))


def _index(grid):
    """(brick, offset) of every voxel of the grid, arrays of the grid's shape."""
    br = np.full(grid.shape, -1, np.int64)
    off = np.zeros(grid.shape, np.int64)
    o = np.arange(512)
    li, lj, lk = o >> 6, (o >> 3) & 7, o & 7
    for b, (bi, bj, bk) in enumerate(grid.bricks.tolist()):
        i, j, k = bi * 8 + li, bj * 8 + lj, bk * 8 + lk
        ok = (i < grid.shape[0]) & (j < grid.shape[1]) & (k < grid.shape[2])
        br[i[ok], j[ok], k[ok]] = b
        off[i[ok], j[ok], k[ok]] = o[ok]
    return br, off


def _set(state, solid):
    """Material where ``solid`` (density 1), none elsewhere; one body."""
    br, off = _index(state.grid)
    state.grid.density[br, off] = solid.astype(np.float32)


def _dense(state, what):
    br, off = _index(state.grid)
    return what[br, off]


def _cut(state, ijk):
    """Remove voxels (density 0) as drilling would; returns them and their bodies."""
    ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
    br, off = _index(state.grid)
    b, o = br[tuple(ijk.T)], off[tuple(ijk.T)]
    keep = state.grid.density[b, o] > 0
    state.grid.density[b[keep], o[keep]] = 0.0
    return ijk[keep], state.body[b[keep], o[keep]].astype(np.int64)


def _reference(state, body, removed, speck=DEFAULT_SPECK_VOXELS):
    """The parts, by the module docstring's rule, from a scipy labelling of the
    whole grid: ``[(seed, n, shed, voxel set)]`` in seed order."""
    solid = (_dense(state, state.body) == body) & (_dense(state, state.grid.density) > 0)
    lab, n = ndi.label(solid, FULL)
    near = np.zeros(solid.shape, bool)
    near[tuple(np.asarray(removed).T)] = True
    near = ndi.binary_dilation(near, FULL)
    cand = sorted(set(np.unique(lab[near]).tolist()) - {0})
    if len(cand) <= 1:
        return []
    edge = np.ones(solid.shape, bool)
    edge[1:-1, 1:-1, 1:-1] = False
    info = []
    for c in cand:
        vox = np.argwhere(lab == c)               # (i, j, k) order
        info.append((not bool(edge[lab == c].any()), -len(vox), tuple(vox[0].tolist()), c,
                     vox))
    keeper = min(info)[3]
    return sorted((s, -m, -m < speck, {tuple(v) for v in vox.tolist()})
                  for _, m, s, c, vox in info if c != keeper)


def _apply(state, parts, t=0.0):
    return [publish_part(state, p.body, p.seed, p.lo, p.hi, p.n, t, shed=p.shed)
            for p in parts]


def _bar(model):
    """A 2x2 bar along x from the grid's face x = 0 to x = 19, cut through at
    x = 6 and x = 13."""
    st = make_state(model)
    solid = np.zeros(SHAPE, bool)
    solid[0:20, 6:8, 6:8] = True
    _set(st, solid)
    cut = np.argwhere(np.isin(np.arange(SHAPE[0])[:, None, None], (6, 13)) & solid)
    return st, solid, _cut(st, cut)


def test_bar_cut_twice_leaves_three_bodies_as_a_fresh_labelling(model):
    st, solid, (ijk, bod) = _bar(model)
    before = int((st.grid.density > 0).sum())
    parts = find_parts(st, ijk, bod)
    assert [p.n for p in parts] == [24, 24] and not any(p.shed for p in parts)
    assert parts == find_parts_global(st, 0, ijk)
    done = _apply(st, parts)
    assert [d for d, _ in done] == [1, 2] and [n for _, n in done] == [24, 24]
    assert st.n_bodies == 3
    # each body's voxels are one component of a from-scratch labelling
    left = solid.copy()
    left[[6, 13]] = False
    lab, n = ndi.label(left, FULL)
    assert n == 3
    body = _dense(st, st.body)
    comps = {frozenset(map(tuple, np.argwhere(lab == c).tolist())) for c in range(1, 4)}
    got = {frozenset(map(tuple, np.argwhere(left & (body == b)).tolist())) for b in range(3)}
    assert comps == got
    # the piece on the case boundary (x = 0) kept body 0
    assert body[0, 6, 6] == 0 and body[10, 6, 6] == 1 and body[17, 6, 6] == 2
    # splitting conserves voxels: none lost, each in exactly one body
    counts = body_voxel_counts(st)
    assert int((st.grid.density > 0).sum()) == before == counts.sum()
    assert counts[:3].tolist() == [24, 24, 24]
    # the records: one block per new body, in (i, j, k) order, n = its size
    ev = st.tissue.read(0)
    sp = ev["kind"] == events.SPLIT
    assert sp.sum() == 48 and (ev["n"][sp] == 24).all()
    assert (ev["value"][sp, 0] == 0).all()
    for b in (1, 2):
        v = ev["ijk"][sp & (ev["body"] == b)]
        assert (np.lexsort(v.T[::-1]) == np.arange(len(v))).all()
    # nothing more to find
    assert find_parts(st, ijk, bod) == []


def test_a_fragment_splits_again(model):
    st, solid, (ijk, bod) = _bar(model)
    _apply(st, find_parts(st, ijk, bod))
    # cut the middle fragment (body 1, x = 7..12) at x = 9
    cut = np.argwhere(solid & (np.arange(SHAPE[0])[:, None, None] == 9))
    ijk2, bod2 = _cut(st, cut)
    assert set(bod2.tolist()) == {1}
    parts = find_parts(st, ijk2, bod2)
    ref = _reference(st, 1, ijk2)
    assert [(tuple(p.seed.tolist()), p.n, p.shed) for p in parts] == \
        [r[:3] for r in ref]
    assert len(parts) == 1 and parts[0].body == 1
    # the larger piece (x = 10..12, 12 voxels vs x = 7..8, 8) keeps body 1
    assert parts[0].n == 8 and parts[0].seed.tolist() == [7, 6, 6]
    (dst, n), = _apply(st, parts)
    assert (dst, n) == (3, 8)
    assert st.n_bodies == 4
    body = _dense(st, st.body)
    assert body[7, 6, 6] == 3 and body[11, 6, 6] == 1


def test_specks_become_dust_not_bodies(model):
    st = make_state(model)
    solid = np.zeros(SHAPE, bool)
    solid[0:12, 6:10, 6:10] = True
    solid[12:14, 7:9, 7] = True           # a 4-voxel nub on the bar's end...
    _set(st, solid)
    n_ev = st.tissue.count
    ijk, bod = _cut(st, np.argwhere(solid & (np.arange(SHAPE[0])[:, None, None] == 11)))
    parts = find_parts(st, ijk, bod)      # ...cut off with the bar's last slice
    assert len(parts) == 1 and parts[0].shed and parts[0].n == 4
    assert parts[0] == find_parts_global(st, 0, ijk)[0]
    removed_before = st.n_removed
    (dst, n), = _apply(st, parts, t=1.5)
    assert (dst, n) == (-1, 4) and st.n_bodies == 1
    assert not (_dense(st, st.grid.density)[12:14] > 0).any()
    ev = st.tissue.read(n_ev)
    assert (ev["kind"] == events.REMOVED).all() and len(ev["kind"]) == 4
    assert (ev["n"] == events.REMOVED_SHED).all() and (ev["label"] == 1).all()
    assert (ev["t_s"] == 1.5).all()
    # a removal for replicas and the totals, but not drilled
    assert st.n_removed == removed_before + 4
    assert not events.drilled(ev).any() and events.removals(ev)["shed"].all()


def test_speck_size_is_a_parameter(model):
    st, solid, (ijk, bod) = _bar(model)
    parts = find_parts(st, ijk, bod, speck_voxels=25)
    assert [p.shed for p in parts] == [True, True]
    with pytest.raises(ValueError, match="speck_voxels"):
        find_parts(st, ijk, bod, speck_voxels=0)


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=hs.integers(0, 2 ** 31 - 1), fill=hs.floats(0.35, 0.65),
       n_cuts=hs.integers(1, 6), margin=hs.integers(1, 4))
def test_local_pass_equals_global_pass_and_a_fresh_labelling(model, seed, fill, n_cuts,
                                                             margin):
    rng = np.random.default_rng(seed)
    st = make_state(model)
    # blobby random bone: smoothed noise, thresholded
    solid = ndi.uniform_filter(rng.random(SHAPE), 3) < fill
    _set(st, solid)
    # random cuts: thin slabs, small boxes, or the shell of a box (which
    # frees what it encloses)
    cut = []
    for _ in range(n_cuts):
        lo = rng.integers(0, np.array(SHAPE) - 2)
        if rng.random() < 0.3:
            size = rng.integers(3, 9, 3)
            inner = np.zeros(size, bool)
            inner[1:-1, 1:-1, 1:-1] = True
            box = np.argwhere(~inner) + lo
        else:
            size = rng.integers(1, 4, 3)
            size[rng.integers(0, 3)] = rng.integers(4, 14)
            box = np.argwhere(np.ones(size, bool)) + lo
        cut.append(box[(box < np.array(SHAPE)).all(axis=1)])
    ijk, bod = _cut(st, np.concatenate(cut))
    if len(ijk) == 0:
        return
    _check_round(st, ijk, bod, margin)
    # a second round of cuts, across the bodies the first one made
    cut = []
    for _ in range(n_cuts):
        lo = rng.integers(0, np.array(SHAPE) - 2)
        size = rng.integers(1, 4, 3)
        size[rng.integers(0, 3)] = rng.integers(4, 14)
        box = np.argwhere(np.ones(size, bool)) + lo
        cut.append(box[(box < np.array(SHAPE)).all(axis=1)])
    ijk, bod = _cut(st, np.concatenate(cut))
    if len(ijk):
        _check_round(st, ijk, bod, margin)


def _check_round(st, ijk, bod, margin):
    """One burst: the local pass equals the global pass and the reference,
    body by body; the flood fill takes exactly each part's voxels; carrying
    the parts out conserves voxels (less the shed specks)."""
    local = find_parts(st, ijk, bod, margin=margin)
    bodies = np.unique(bod)
    glob = [p for b in bodies for p in find_parts_global(st, int(b), ijk[bod == b])]
    assert local == glob
    ref = [r for b in bodies for r in _reference(st, int(b), ijk[bod == b])]
    assert [(p.body, tuple(p.seed.tolist()), p.n, p.shed) for p in local] == \
        [(int(b), *r[:3]) for b in bodies for r in _reference(st, int(b), ijk[bod == b])]
    # the flood fill moves exactly the labelled voxels of each part
    for p, r in zip(local, ref):
        vox = component_voxels(st, p.body, p.seed, p.lo, p.hi, p.n)
        assert {tuple(v) for v in vox.tolist()} == r[3]
        assert vox.min(axis=0).tolist() == p.lo.tolist()
        assert vox.max(axis=0).tolist() == p.hi.tolist()
    total = int((st.grid.density > 0).sum())
    _apply(st, local)
    shed = sum(p.n for p in local if p.shed)
    assert int((st.grid.density > 0).sum()) == total - shed
    assert body_voxel_counts(st).sum() == total - shed


def test_labelling_matches_scipy():
    rng = np.random.default_rng(3)
    mask = ndi.uniform_filter(rng.random((30, 20, 25)), 3) < 0.45
    lab, n = label_parts(mask)
    ref, m = ndi.label(mask, FULL)
    assert n == m
    # the same partition (labels may be numbered differently)
    pairs = np.unique(np.stack([lab[mask], ref[mask]]), axis=1)
    assert pairs.shape[1] == n


def test_a_part_larger_than_found_is_refused(model):
    st, solid, (ijk, bod) = _bar(model)
    p = find_parts(st, ijk, bod)[0]
    with pytest.raises(ValueError, match="more than 23 voxels"):
        component_voxels(st, p.body, p.seed, p.lo, p.hi, p.n - 1)
    # a seed without material moves nothing
    assert publish_part(st, 0, (0, 0, 0), (0, 0, 0), (1, 1, 1), 5, 0.0) == (-1, 0)


def test_body_mask_and_shed_checks(model):
    st = make_state(model)
    reset_state(model, st)
    m = body_mask(st, 0, (0, 0, 0), (3, 2, 1))
    assert m.shape == (4, 3, 2) and m.all()
    with pytest.raises(ValueError, match="not inside the grid"):
        body_mask(st, 0, (0, 0, 0), SHAPE)
    # shedding skips voxels of other bodies or without material, and repeats
    assert shed_voxels(st, 0, [(1, 1, 1), (1, 1, 1), (2, 2, 2)], 0.0) == 2
    assert shed_voxels(st, 0, [(1, 1, 1)], 0.0) == 0
    assert shed_voxels(st, 1, [(3, 3, 3)], 0.0) == 0


def test_a_part_publishes_what_publish_split_of_its_voxels_does(model):
    """Replay re-applies a recorded split with publish_split: the loop's
    records for a part must be exactly those."""
    from bonesim.engine.bodies import publish_split

    a, _, (ijk, bod) = _bar(model)
    b, _, _ = _bar(model)
    n_a, n_b = a.tissue.count, b.tissue.count
    for p in find_parts(a, ijk, bod):
        publish_part(a, p.body, p.seed, p.lo, p.hi, p.n, 0.25)
    ev = a.tissue.read(n_a)
    for dst in np.unique(ev["body"]):
        m = ev["body"] == dst
        publish_split(b, int(ev["value"][m][0, 0]), ev["ijk"][m][::-1], 0.25)
    got = b.tissue.read(n_b)
    for f in events.TISSUE_FIELDS:
        np.testing.assert_array_equal(ev[f], got[f], err_msg=f)
    for name in ("body", "alive", "bounds", "pose"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


@pytest.mark.parametrize("layout", ["large_closed", "closed_on_boundary"])
def test_local_pass_grows_when_the_box_cannot_tell_the_keeper(model, layout):
    """A closed part the box holds whole and an open part that leaves the box:
    the box alone cannot say which keeps the body, the grown box can."""
    st = make_state(model)
    solid = np.zeros(SHAPE, bool)
    if layout == "large_closed":
        # a 5^3 blob (125 voxels) and a bar of 9 beyond the cut: the blob keeps
        solid[8:13, 5:10, 5:10] = True
        solid[13:23, 7, 7] = True
        cut_x, margin, keeper = 13, 6, (10, 7, 7)
    else:
        # a 2x2x2 blob on the grid's face x = 0 and a longer bar (20), more
        # of it in the first box than the blob has: the blob touches the case
        # boundary and keeps, though it is smaller
        solid[0:2, 6:8, 6:8] = True
        solid[2:23, 7, 7] = True
        cut_x, margin, keeper = 2, 9, (1, 7, 7)
    _set(st, solid)
    ijk, bod = _cut(st, np.argwhere(solid & (np.arange(SHAPE[0])[:, None, None] == cut_x)))
    stats = {}
    parts = find_parts(st, ijk, bod, margin=margin, stats=stats)
    assert stats["boxes"] > 1                       # the first box could not decide
    assert parts == find_parts_global(st, 0, ijk)
    ref = _reference(st, 0, ijk)
    assert [(tuple(p.seed.tolist()), p.n, p.shed) for p in parts] == [r[:3] for r in ref]
    assert len(parts) == 1 and tuple(parts[0].seed.tolist()) != keeper
    _apply(st, parts)
    assert _dense(st, st.body)[keeper] == 0
