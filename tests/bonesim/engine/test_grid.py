"""The hashed brick grid against a dense numpy reference."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs
from hypothesis.extra import numpy as hnp

from bonesim.engine.grid import BRICK, Grid, density_at, find_brick


@settings(max_examples=40, deadline=None)
@given(labels=hnp.arrays(np.uint8, hnp.array_shapes(min_dims=3, max_dims=3, min_side=1,
                                                     max_side=19),
                         elements=hs.integers(0, 3)),
       origin=hs.tuples(*[hs.floats(-50, 50)] * 3))
def test_dense_round_trip_and_lookups(labels, origin):
    g = Grid.from_dense(labels, spacing_mm=0.5, origin_mm=origin)
    dens, lab = g.to_dense()
    np.testing.assert_array_equal(lab, labels)
    np.testing.assert_array_equal(dens, (labels > 0).astype(np.float32))
    # point lookups, including the halo and far outside, agree with the array
    rng = np.random.default_rng(0)
    for ijk in rng.integers(-10, 30, size=(50, 3)):
        i, j, k = map(int, ijk)
        inside = all(0 <= c < s for c, s in zip((i, j, k), labels.shape))
        expect = labels[i, j, k] if inside else 0
        assert g.label_at(i, j, k) == expect
        assert density_at(g.keys, g.vals, g.density_ro, i, j, k) == (1.0 if expect else 0.0)


def test_halo_bricks_cover_every_neighbour_of_tissue():
    labels = np.zeros((16, 16, 16), np.uint8)
    labels[0, 0, 0] = labels[15, 8, 7] = 1
    g = Grid.from_dense(labels)
    for v in ((0, 0, 0), (15, 8, 7)):
        for d in np.ndindex(3, 3, 3):
            n = np.array(v) + np.array(d) - 1
            assert g.brick_index(*map(int, n)) >= 0


def test_memory_follows_tissue_not_volume():
    small = np.zeros((256, 256, 256), np.uint8)
    small[100:110, 100:110, 100:110] = 1
    g = Grid.from_dense(small)
    assert g.n_bricks <= 27                   # a 10^3 blob plus halo spans <= 3^3 bricks
    assert g.nbytes < small.nbytes / 100
    assert g.occupied_count() == 1000


def test_find_brick_matches_dict():
    labels = np.zeros((64, 40, 33), np.uint8)
    rng = np.random.default_rng(1)
    labels[rng.random(labels.shape) < 0.01] = 1
    g = Grid.from_dense(labels)
    table = {tuple(b): n for n, b in enumerate(g.bricks)}
    for bi in range(-2, 10):
        for bj in range(-2, 7):
            for bk in range(-2, 6):
                assert find_brick(g.keys, g.vals, bi, bj, bk) == table.get((bi, bj, bk), -1)


def test_density_values_and_copy_independent():
    labels = np.ones((9, 9, 9), np.uint8)
    dens = np.linspace(0.1, 1.0, 729, dtype=np.float32).reshape(9, 9, 9)
    g = Grid.from_dense(labels, dens, spacing_mm=0.25, origin_mm=(1, 2, 3))
    np.testing.assert_array_equal(g.to_dense()[0], dens)
    c = g.copy()
    c.density[:] = 0
    assert g.occupied_count() == 729
    np.testing.assert_allclose(g.voxel_centers([[0, 0, 0], [4, 0, 8]]),
                               [[1, 2, 3], [2, 2, 5]])
    assert BRICK == 8


@pytest.mark.parametrize("bad, msg", [
    (dict(label=np.zeros((3, 3))), "3-D"),
    (dict(label=np.full((3, 3, 3), 300)), r"\[0, 255\]"),
    (dict(label=np.ones((3, 3, 3)), spacing_mm=0.0), "positive"),
    (dict(label=np.ones((3, 3, 3)), density=np.ones((2, 3, 3))), "shape"),
    (dict(label=np.ones((3, 3, 3)), density=np.full((3, 3, 3), -1.0)), "non-negative"),
])
def test_bad_input(bad, msg):
    with pytest.raises(ValueError, match=msg):
        Grid.from_dense(**bad)


@settings(max_examples=30, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1))
def test_sync_replica_applies_exactly_the_published_events(seed):
    """Removed voxels empty, touched voxels take the live value unless the
    live value is already 0 (its removal is still in flight); nothing else
    changes."""
    from bonesim.engine.grid import sync_replica

    rng = np.random.default_rng(seed)
    labels = (rng.random((12, 10, 9)) < 0.7).astype(np.uint8)
    live = Grid.from_dense(labels)
    replica = live.copy()
    occ = np.argwhere(labels > 0).astype(np.int32)
    # the producer lowers some voxels, removes others, publishes only a part
    lowered = occ[rng.random(len(occ)) < 0.3]
    removed = occ[rng.random(len(occ)) < 0.2]
    for i, j, k in lowered:
        live.density[live.brick_index(i, j, k), (i & 7) << 6 | (j & 7) << 3 | (k & 7)] = 0.4
    for i, j, k in removed:
        live.density[live.brick_index(i, j, k), (i & 7) << 6 | (j & 7) << 3 | (k & 7)] = 0.0
    pub_rem = removed[rng.random(len(removed)) < 0.5]
    pub_tch = np.concatenate([lowered[rng.random(len(lowered)) < 0.5],
                              removed[rng.random(len(removed)) < 0.3]])
    before, _ = replica.to_dense()
    sync_replica(replica, live, pub_rem, pub_tch)
    # reference, one voxel at a time
    expect = before.copy()
    live_d, _ = live.to_dense()
    for i, j, k in pub_rem:
        expect[i, j, k] = 0.0
    for i, j, k in pub_tch:
        if live_d[i, j, k] > 0 and expect[i, j, k] > 0:
            expect[i, j, k] = live_d[i, j, k]
    np.testing.assert_array_equal(replica.to_dense()[0], expect)
    with pytest.raises(ValueError, match="share"):
        sync_replica(Grid.from_dense(labels), live, pub_rem, pub_tch)


def test_sub_grid_keeps_the_lattice_and_only_the_boxed_bricks():
    lab = np.zeros((30, 20, 20), np.uint8)
    lab[2:28, 3:17, 4:15] = 1
    g = Grid.from_dense(lab, spacing_mm=0.25, origin_mm=(1.0, -2.0, 3.0))
    s = g.sub_grid((1, 0, 0), (2, 1, 1))
    assert s.spacing_mm == g.spacing_mm and s.shape == g.shape
    np.testing.assert_array_equal(s.origin_mm, g.origin_mm)
    assert ((s.bricks >= (1, 0, 0)) & (s.bricks <= (2, 1, 1))).all() and s.n_bricks == 8
    for ijk in [(8, 5, 5), (23, 15, 14), (20, 10, 10), (7, 5, 5), (24, 5, 5)]:
        inside = 8 <= ijk[0] < 24 and ijk[1] < 16 and ijk[2] < 16
        assert s.density_at(*ijk) == (g.density_at(*ijk) if inside else 0.0)
        assert s.label_at(*ijk) == (g.label_at(*ijk) if inside else 0)
    s.density[:] = 0.0                              # its own copy
    assert g.density_at(10, 5, 5) == 1.0
