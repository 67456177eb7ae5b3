"""Tests of the full-tessellation kernels on occupancy bit rows
(bonesim.engine.surface_build) and the full shading's box gather.

The whole build is checked against the slow numpy reference of the
definition in test_surface.py; here: the bit rows against plain dense
arrays (occupancy words, surface voxels, per-brick counts), the row-copy
gather of the shading against a voxel-by-voxel one, and that a build gives
the same arrays, bit for bit, whatever the number of threads.
"""
from __future__ import annotations

import functools
import itertools
import math

import numba
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bonesim.engine.grid import BRICK, Grid
from bonesim.engine.shading_full import _HALO, _LB, _gather_plane
from bonesim.engine.surface import Surface
from bonesim.engine.surface_build import (_KEY_CORNERS, _gather_rows, _gather_slots, build_count,
                                          build_prepare, occupancy_bits)
from bonesim.engine.work_items import new_counter
from bonesim.engine.surface_tables import (CORNER_OFFSETS, TRIPLE_CORNERS, TRIPLE_FACE,
                                           brick_neighbours, qualifying_triples)

COLORS = np.array([[0, 0, 0], [230, 220, 190], [200, 60, 50], [40, 90, 210]], dtype=np.uint8)


def _volume(seed, shape=(21, 19, 26), p_occ=0.6):
    rng = np.random.default_rng(seed)
    lab = (rng.random(shape) < p_occ).astype(np.uint8) \
        * rng.integers(1, 4, size=shape).astype(np.uint8)
    # a solid block too, so that some bricks are all bone
    lab[2:19, 2:17, 3:22] = 1
    lab[6:10, 6:10, 6:10] = 0
    dens = rng.uniform(0.05, 1.0, size=shape).astype(np.float32)
    return dens, lab


@functools.lru_cache(maxsize=256)
def _triples(code):
    """:func:`qualifying_triples` of a cell code, once per code (256)."""
    return tuple(qualifying_triples(code))


def _dense_occ(grid):
    lo = grid.bricks.min(axis=0) * BRICK - BRICK
    hi = (grid.bricks.max(axis=0) + 2) * BRICK
    dens, _ = grid.to_dense(lo=lo, shape=hi - lo)
    return dens > 0, lo


def _ref_counts(grid):
    """Per brick: surface voxels (occupied, an empty 26-neighbour), their
    bits (bit z of ``[b, 8 x + y]``) and owned triangles, from dense arrays,
    cell by cell (plain loops)."""
    occ, lo = _dense_occ(grid)
    nv = np.zeros(grid.n_bricks, np.int64)
    nt = np.zeros(grid.n_bricks, np.int64)
    bits = np.zeros((grid.n_bricks, BRICK * BRICK), np.uint8)
    for b, (bi, bj, bk) in enumerate(grid.bricks):
        o = np.array([bi, bj, bk]) * BRICK - lo
        for x in range(BRICK):
            for y in range(BRICK):
                for z in range(BRICK):
                    p = o + (x, y, z)
                    if occ[tuple(p)] and not occ[p[0] - 1:p[0] + 2, p[1] - 1:p[1] + 2,
                                                 p[2] - 1:p[2] + 2].all():
                        nv[b] += 1
                        bits[b, x * BRICK + y] |= 1 << z
                    cell = occ[p[0]:p[0] + 2, p[1]:p[1] + 2, p[2]:p[2] + 2]
                    code = sum(int(cell[c >> 2, (c >> 1) & 1, c & 1]) << c for c in range(8))
                    for tid, _ in _triples(code):
                        f = int(TRIPLE_FACE[tid])
                        if 0 <= f < 3:
                            below = p.copy()
                            below[f] -= 1
                            sl = [slice(below[a], below[a] + 2) for a in range(3)]
                            sl[f] = slice(below[f], below[f] + 1)
                            if not occ[tuple(sl)].any():
                                continue           # owned by the cell below
                        nt[b] += 1
    return nv, nt, bits


@pytest.mark.parametrize("seed", [0, 1])
def test_occupancy_bits_are_the_occupied_voxels(seed):
    dens, lab = _volume(seed)
    grid = Grid.from_dense(lab, dens)
    om = np.empty((grid.n_bricks, BRICK), np.int64)
    occupancy_bits(grid.density, om)
    want = (grid.density > 0).reshape(grid.n_bricks, BRICK, 64)
    got = (om.view(np.uint64)[:, :, None] >> np.arange(64, dtype=np.uint64)) & np.uint64(1)
    assert np.array_equal(got.astype(bool), want)


@pytest.mark.parametrize("seed,n_workers", [(0, 1), (1, 3)])
def test_prepare_gives_neighbours_and_occupancy(seed, n_workers):
    dens, lab = _volume(seed, shape=(40, 30, 50))
    grid = Grid.from_dense(lab, dens)
    index = {tuple(int(c) for c in b): n for n, b in enumerate(grid.bricks)}
    want_nbr = np.array([[index.get((bi + di, bj + dj, bk + dk), -1)
                          for di in (-1, 0, 1) for dj in (-1, 0, 1) for dk in (-1, 0, 1)]
                         for bi, bj, bk in grid.bricks.tolist()], np.int32)
    want_om = np.empty((grid.n_bricks, BRICK), np.int64)
    occupancy_bits(grid.density, want_om)
    nbr = np.full((grid.n_bricks, 27), -7, np.int32)
    om = np.full((grid.n_bricks, BRICK), -7, np.int64)
    build_prepare(grid.keys, grid.vals, grid.bricks, grid.density_ro, nbr, om, new_counter(),
                  n_workers)
    assert np.array_equal(nbr, want_nbr)
    assert np.array_equal(nbr, brick_neighbours(grid.keys, grid.vals, grid.bricks))
    assert np.array_equal(om, want_om)


@pytest.mark.parametrize("seed,p_occ", [(0, 0.6), (3, 0.3), (4, 0.9)])
def test_counts_match_dense_reference(seed, p_occ):
    dens, lab = _volume(seed, p_occ=p_occ)
    grid = Grid.from_dense(lab, dens)
    nbr = brick_neighbours(grid.keys, grid.vals, grid.bricks)
    om = np.empty((grid.n_bricks, BRICK), np.int64)
    occupancy_bits(grid.density, om)
    nv = np.full(grid.n_bricks, -1, np.int64)
    nt = np.full(grid.n_bricks, -1, np.int64)
    srf = np.full((grid.n_bricks, BRICK * BRICK), 0xAA, np.uint8)
    build_count(om, nbr, nv, nt, srf, new_counter(), 2)
    want_v, want_t, want_bits = _ref_counts(grid)
    assert np.array_equal(nv, want_v)
    assert np.array_equal(nt, want_t)
    assert np.array_equal(srf, want_bits)
    assert nv.sum() > 0 and nt.sum() > 0


@pytest.mark.parametrize("seed,p_occ", [(0, 0.6), (2, 0.1)])
def test_row_gather_equals_voxel_by_voxel(seed, p_occ):
    dens, lab = _volume(seed, p_occ=p_occ)
    grid = Grid.from_dense(lab, dens)
    nbr = brick_neighbours(grid.keys, grid.vals, grid.bricks)
    om = np.empty((grid.n_bricks, BRICK), np.int64)
    occupancy_bits(grid.density, om)
    rows = np.empty((BRICK + 2, BRICK + 2), np.int64)
    for b, (bi, bj, bk) in enumerate(grid.bricks):
        up, full = _gather_rows(om, nbr, b, rows)
        occ = np.array([[[grid.density_at(bi * BRICK + lx - 1, bj * BRICK + ly - 1,
                                          bk * BRICK + lz - 1) > 0
                          for lz in range(BRICK + 2)] for ly in range(BRICK + 2)]
                        for lx in range(BRICK + 2)])
        want = (occ * (1 << np.arange(BRICK + 2))).sum(axis=2)
        assert np.array_equal(rows, want), b
        assert up == bool(occ[1:, 1:, 1:].any())
        assert full == bool(occ.all())


@pytest.mark.parametrize("seed", [0, 5])
def test_slot_gather_equals_voxel_by_voxel(seed):
    dens, lab = _volume(seed, p_occ=0.4)
    grid = Grid.from_dense(lab, dens)
    surf = Surface.build(grid, COLORS)
    loc = np.empty((BRICK + 1) ** 3, np.int32)
    for b, (bi, bj, bk) in enumerate(grid.bricks):
        _gather_slots(surf.vmap, surf._nbr, b, loc)
        want = np.array([[[surf.vertex_at(bi * BRICK + x, bj * BRICK + y, bk * BRICK + z)
                           for z in range(BRICK + 1)] for y in range(BRICK + 1)]
                         for x in range(BRICK + 1)], np.int32)
        assert np.array_equal(loc.reshape(want.shape), want), b


def test_key_corner_offsets_follow_the_winding():
    for key in range(2 * TRIPLE_CORNERS.shape[0]):
        cs = TRIPLE_CORNERS[key >> 1]
        order = (cs[0], cs[2], cs[1]) if key & 1 else tuple(cs)
        for s, cn in enumerate(order):
            dx, dy, dz = CORNER_OFFSETS[cn]
            assert _KEY_CORNERS[key, s] == (dx * (BRICK + 1) + dy) * (BRICK + 1) + dz


def test_shading_gather_equals_voxel_by_voxel():
    dens, lab = _volume(7)
    grid = Grid.from_dense(lab, dens)
    nbr = brick_neighbours(grid.keys, grid.vals, grid.bricks)
    out = np.full(_LB * _LB + 5, -1, np.float32)
    for b, (bi, bj, bk) in enumerate(grid.bricks):
        for x in range(-_HALO, BRICK + _HALO):
            _gather_plane(grid.density_ro, nbr, b, x, out, 5)
            want = np.zeros((_LB, _LB), np.float32)
            for ly in range(_LB):
                for lz in range(_LB):
                    want[ly, lz] = grid.density_at(bi * BRICK + x, bj * BRICK + ly - _HALO,
                                                   bk * BRICK + lz - _HALO)
            assert np.array_equal(out[5:].reshape(_LB, _LB), want), (b, x)
            assert (out[:5] == -1).all()


def _raw(surf):
    return {"pos": surf.pos, "nrm": surf.nrm, "shift": surf.shift, "col": surf.col,
            "ijk": surf.ijk, "alive": surf.alive, "vmap": surf.vmap, "tflip": surf.tflip,
            "trec": surf._trec, "vrec": surf._vrec}


def test_build_is_bit_identical_in_any_thread_count_and_schedule(monkeypatch):
    import bonesim.engine.shading as shading_mod
    import bonesim.engine.surface as surface_mod

    dens, lab = _volume(11, shape=(70, 45, 60), p_occ=0.5)
    grid = Grid.from_dense(lab, dens, spacing_mm=0.3)
    n0 = numba.get_num_threads()
    n_max = numba.config.NUMBA_NUM_THREADS
    builds = []
    try:
        # workers: one per thread, or more (a thread then runs several in turn)
        for threads, n_workers in ((1, 1), (n_max, n_max), (n_max, 3), (1, 5)):
            numba.set_num_threads(threads)
            for mod in (surface_mod, shading_mod):
                monkeypatch.setattr(mod, "workers", lambda n=n_workers: n)
            builds.append(_raw(Surface.build(grid, COLORS, bone=[0, 1, 0, 0])))
    finally:
        numba.set_num_threads(n0)
    one = builds[0]
    for other in builds[1:]:
        for name in one:
            assert one[name].shape == other[name].shape, name
            assert np.array_equal(one[name].view(np.uint8), other[name].view(np.uint8)), name


def test_take_item_hands_out_every_item_once():
    from numba import njit, prange

    from bonesim.engine.work_items import new_counter, take_item

    @njit(parallel=True)
    def run(n_items, owner, counter, n_workers):
        for w in prange(n_workers):
            while True:
                it = take_item(counter)
                if it >= n_items:
                    break
                owner[it] += w + 1

    for n_workers in (1, 2, 7):
        owner = np.zeros(10_000, np.int64)
        counter = new_counter()
        run(owner.size, owner, counter, n_workers)
        assert ((owner >= 1) & (owner <= n_workers)).all()
        assert counter[0] == owner.size + n_workers      # each worker's last take overshoots once


@pytest.mark.parametrize("x0", [0, 1, 5, 6, 7])
def test_zero_gradient_takes_the_fallback_normal(x0):
    """A surface voxel whose one empty neighbour (+x) is balanced by a
    lighter voxel two to -x has no gradient (|g| below GRAD_EPS): its normal
    is the offset toward its empty neighbours, +x, and it is not moved;
    wherever it lies in its brick (the 3x3x3 neighbours across bricks)."""
    from bonesim.engine.normals import stencil_weights
    from bonesim.engine.shading import load_shading

    w = stencil_weights(load_shading().sigma_voxels)
    c = (8 + x0, 10, 10)
    lab = np.zeros((29, 21, 21), np.uint8)
    lab[c[0] - 8:c[0] + 9, 2:19, 2:19] = 1
    dens = np.ones(lab.shape, np.float32)
    lab[c[0] + 1, c[1], c[2]] = 0
    dens[c[0] + 1, c[1], c[2]] = 0
    dens[c[0] - 2, c[1], c[2]] = np.float32(1 - float(w[4]) / float(w[5]))
    surf = Surface.build(Grid.from_dense(lab, dens), COLORS)
    v = surf.vertex_at(*c)
    assert v >= 0
    assert surf.nrm[v].tolist() == [1.0, 0.0, 0.0]
    assert surf.shift[v] == 0.0


def test_flat_passes_equal_the_plane_passes_bit_for_bit():
    """kj_flat (the full shading's k and j passes over a brick's plane as one
    row) gives kj_plane's values, bit for bit, where they are read (z < 8),
    and those are the separable Gaussian sums (float64 reference)."""
    from bonesim.engine.normals import (FLAT_EDGE, FLAT_PLANE, kj_flat, kj_plane,
                                        normal_weights, stencil_weights)

    rng = np.random.default_rng(3)
    e = FLAT_EDGE
    w = stencil_weights(2.0)
    s, d = normal_weights(2.0)
    for trial in range(20):
        box = rng.uniform(0, 1, (3, e, e)).astype(np.float32)
        box[rng.random(box.shape) < 0.4] = 0.0
        if trial % 4 == 0:
            box[1] = 0.0                      # an empty plane
        flat = box.ravel()
        rs, rd = np.zeros(e * e, np.float32), np.zeros(e * e, np.float32)
        ring_f = np.zeros(21 * FLAT_PLANE, np.float32)
        rs_p, rd_p = np.zeros(e * 8, np.float32), np.zeros(e * 8, np.float32)
        ring_p = np.zeros(21 * 64, np.float32)
        for x in range(3):
            slot = (x + trial) % 7
            kj_flat(flat, x, w, rs, rd, ring_f, slot)
            kj_plane(flat, x, e, e, w, rs_p, rd_p, ring_p, slot)
            got = ring_f[3 * slot * FLAT_PLANE:3 * (slot + 1) * FLAT_PLANE]
            got = got.reshape(3, 8, e)[:, :, :8]
            want = ring_p[3 * slot * 64:3 * (slot + 1) * 64].reshape(3, 8, 8)
            assert np.array_equal(got.view(np.uint32), want.view(np.uint32))
            # tx, ty, tz: S_j S_k, D_j S_k, S_j D_k of the plane
            pl = box[x].astype(np.float64)
            for y in range(8):
                for z in range(8):
                    win = pl[y:y + 7, z:z + 7]
                    ref = (s @ win @ s, d @ win @ s, s @ win @ d)
                    assert np.allclose(got[:, y, z], ref, atol=1e-5)


# ---------------------------------------------------------------------------
# the shaded vertices, bit for bit, against the float32 operations of the
# definition written out in numpy (one vertex at a time, no planes or rings)
# ---------------------------------------------------------------------------
def _s_pass(a, w):
    """S-pass over the last axis (7 values): s0 v3 + s1 (v2 + v4) + ..."""
    return (w[0] * a[..., 3] + w[1] * (a[..., 2] + a[..., 4]) + w[2] * (a[..., 1] + a[..., 5])
            + w[3] * (a[..., 0] + a[..., 6]))


def _d_pass(a, w):
    """D-pass over the last axis: d1 (v4 - v2) + d2 (v5 - v1) + d3 (v6 - v0)."""
    return (w[4] * (a[..., 4] - a[..., 2]) + w[5] * (a[..., 5] - a[..., 1])
            + w[6] * (a[..., 6] - a[..., 0]))


def _ref_shading(grid, surf, colors):
    """Normals, shifts, positions and colours of every live vertex (no tint),
    from the definition in bonesim.engine.normals: passes along k, then j,
    then i, in float32, over the 7x7x7 densities around each vertex."""
    from bonesim.engine.normals import GRAD_EPS, stencil_weights
    from bonesim.engine.shading import load_shading

    p = load_shading()
    w = stencil_weights(p.sigma_voxels)
    lo = grid.bricks.min(axis=0) * BRICK - 8
    hi = (grid.bricks.max(axis=0) + 2) * BRICK + 8
    dens, lab = grid.to_dense(lo=lo, shape=hi - lo)
    vs = surf.vertex_slots
    ijk = surf.ijk[vs].astype(np.int64)
    c = ijk - lo
    off = np.arange(-3, 4)
    box = dens[c[:, 0, None, None, None] + off[:, None, None],
               c[:, 1, None, None, None] + off[None, :, None],
               c[:, 2, None, None, None] + off[None, None, :]]          # (n, 7, 7, 7) float32
    rs, rd = _s_pass(box, w), _d_pass(box, w)                          # along k: (n, 7, 7)
    tx, ty, tz = _s_pass(rs, w), _d_pass(rs, w), _s_pass(rd, w)        # along j: (n, 7)
    gx, gy, gz, f = _d_pass(tx, w), _s_pass(ty, w), _s_pass(tz, w), _s_pass(tx, w)
    assert gx.dtype == np.float32 and f.dtype == np.float32
    nrm = np.empty((vs.size, 3))
    shift = np.zeros(vs.size)
    for q in range(vs.size):
        g = [float(gx[q]), float(gy[q]), float(gz[q])]
        norm = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
        if norm > GRAD_EPS:
            nrm[q] = [-g[0] / norm, -g[1] / norm, -g[2] / norm]
            shift[q] = min(max((float(f[q]) - p.iso_density) / norm, -p.max_in_voxels),
                           p.max_out_voxels)
        else:
            s = np.zeros(3, np.int64)
            for d in itertools.product((-1, 0, 1), repeat=3):
                if d != (0, 0, 0) and not box[q, 3 + d[0], 3 + d[1], 3 + d[2]] > 0:
                    s += d
            sn = math.sqrt(float(s @ s))
            nrm[q] = s / sn if sn > 0 else (0.0, 0.0, 1.0)
    pos = np.array([[grid.origin_mm[a] + grid.spacing_mm * (ijk[q, a] + shift[q] * nrm[q, a])
                     for a in range(3)] for q in range(vs.size)]).reshape(-1, 3)
    col = np.concatenate([colors[lab[c[:, 0], c[:, 1], c[:, 2]]],
                          np.full((vs.size, 1), 255, np.uint8)], axis=1)
    return nrm.astype(np.float32), shift.astype(np.float32), pos.astype(np.float32), col


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2 ** 32 - 1), p_occ=st.sampled_from([0.1, 0.5, 0.9]),
       graded=st.booleans(), shape=st.tuples(st.integers(1, 30), st.integers(1, 30),
                                             st.integers(1, 30)))
def test_shaded_vertices_are_the_definition_bit_for_bit(seed, p_occ, graded, shape):
    rng = np.random.default_rng(seed)
    lab = ((rng.random(shape) < p_occ) * rng.integers(1, 4, size=shape)).astype(np.uint8)
    dens = rng.uniform(0.05, 1.0, size=shape).astype(np.float32) if graded else None
    grid = Grid.from_dense(lab, dens, spacing_mm=0.19, origin_mm=(-3.0, 1.5, 0.25))
    surf = Surface.build(grid, COLORS)
    if surf.n_vertices == 0:
        return
    nrm, shift, pos, col = _ref_shading(grid, surf, COLORS)
    vs = surf.vertex_slots
    assert np.array_equal(surf.nrm[vs].view(np.uint32), nrm.view(np.uint32))
    assert np.array_equal(surf.shift[vs].view(np.uint32), shift.view(np.uint32))
    assert np.array_equal(surf.pos[vs].view(np.uint32), pos.view(np.uint32))
    assert np.array_equal(surf.col[vs], col)


def test_owned_tables_drop_the_faces_below():
    """The keys a cell owns by code and low mask are QUAL_KEY's, in order,
    less those in a minimum face whose four voxels below are empty; their
    number is QUAL_N less QUAL_NMIN of those faces."""
    from bonesim.engine.surface_build import _OWN_KEY, _OWN_N
    from bonesim.engine.surface_tables import QUAL_KEY, QUAL_N, QUAL_NMIN

    for code in range(256):
        for low in range(8):
            want = [int(k) for k in QUAL_KEY[code, :QUAL_N[code]]
                    if not (0 <= TRIPLE_FACE[k >> 1] < 3 and (low >> TRIPLE_FACE[k >> 1]) & 1)]
            n = int(_OWN_N[code, low])
            assert _OWN_KEY[code, low, :n].tolist() == want
            assert (_OWN_KEY[code, low, n:] == -1).all()
            assert n == QUAL_N[code] - sum(int(QUAL_NMIN[code, a]) for a in range(3)
                                           if (low >> a) & 1)
