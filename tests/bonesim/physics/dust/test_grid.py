"""Eulerian bone dust: each rule against a dense numpy reference, plus the
physical behaviour (settling, piling, tool push, suction) and exact mass
conservation."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from bonesim.engine import events
from bonesim.physics.dust.grid import Q, DustGrid, DustParams, warmup
from bonesim.engine.grid import Grid, voxel_offset

H = 0.5                                 # cell edge [mm]
ORIGIN = np.array([-3.0, 1.5, 2.0])     # [mm]
W_ONE = 1 << 16
ROOM_SHARE = W_ONE // 5


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    warmup()


# ------------------------------------------------------------------ reference
# Dense int64 arrays over the domain box; ``wall`` is bone (everything
# outside the box is a wall too). Same integer formulas as documented in
# bonesim.physics.dust.grid, written the obvious way.
def _pairs(shape, a, s):
    """Slices (S, D) with D = S + s e_a."""
    n = shape[a]
    src, dst = [slice(None)] * 3, [slice(None)] * 3
    if s > 0:
        src[a], dst[a] = slice(0, n - 1), slice(1, n)
    else:
        src[a], dst[a] = slice(1, n), slice(0, n - 1)
    return tuple(src), tuple(dst)


def gravity_axes(g, split=True):
    g = np.asarray(g, float) / np.linalg.norm(g)
    dom = int(np.argmax(np.abs(g)))
    axes = [a for a in range(3) if abs(g[a]) > 1e-6] if split else [dom]
    tot = sum(abs(g[a]) for a in axes)
    return [(a, 1 if g[a] > 0 else -1,
             W_ONE if len(axes) == 1 else int(math.floor(abs(g[a]) / tot * W_ONE)))
            for a in axes]


def ref_gravity(d, wall, g, rate_q, split=True):
    out = d.copy()
    for a, s, w in gravity_axes(g, split):
        S, D = _pairs(d.shape, a, s)
        m = np.minimum(np.minimum(d[S], rate_q), Q - d[D])
        f = (w * m) >> 16
        f = np.where((f > 0) & ~wall[S] & ~wall[D], f, 0)
        out[S] -= f
        out[D] += f
    return out


def ref_spill(d, wall, g, kq, repose_q):
    g = np.asarray(g, float)
    dom = int(np.argmax(np.abs(g)))
    dsgn = 1 if g[dom] > 0 else -1
    lat = [a for a in range(3) if a != dom]
    supported = np.ones(d.shape, bool)                  # the box edge is a wall
    S, D = _pairs(d.shape, dom, dsgn)
    supported[S] = wall[D] | (d[D] >= Q)
    elig = ~wall & ((d > Q) | ((d > repose_q) & supported))
    out = d.copy()
    for a, s, lateral in [(lat[0], -1, True), (lat[0], 1, True), (lat[1], -1, True),
                          (lat[1], 1, True), (dom, -dsgn, False)]:
        S, D = _pairs(d.shape, a, s)
        excess = d[S] - d[D] - repose_q if lateral else d[S] - Q
        f = np.minimum((excess * kq) >> 16, ((Q - d[D]) * ROOM_SHARE) >> 16)
        f = np.where((f > 0) & elig[S] & ~wall[D], f, 0)
        out[S] -= f
        out[D] += f
    return out


def ref_tool(d, wall, lo, p, rad, search, up):
    out = d.copy()
    r2 = rad * rad
    for idx in np.argwhere(d > 0):
        ci, cj, ck = (int(v) for v in idx + lo)
        dx = (ORIGIN[0] + H * ci) - p[0]
        dy = (ORIGIN[1] + H * cj) - p[1]
        dz = (ORIGIN[2] + H * ck) - p[2]
        if dx * dx + dy * dy + dz * dz >= r2:
            continue
        r = math.sqrt(dx * dx + dy * dy + dz * dz)
        u = (dx / r, dy / r, dz / r) if r > 0 else tuple(up)
        for t in range(search):
            dist = rad + (t + 0.5) * H
            tgt = [int(math.floor((p[a] + u[a] * dist - ORIGIN[a]) / H + 0.5))
                   for a in range(3)]
            e = [(ORIGIN[a] + H * tgt[a]) - p[a] for a in range(3)]
            if e[0] * e[0] + e[1] * e[1] + e[2] * e[2] < r2:
                continue
            loc = tuple(tgt[a] - lo[a] for a in range(3))
            if not all(0 <= loc[a] < d.shape[a] for a in range(3)) or wall[loc]:
                continue
            out[loc] += d[tuple(idx)]
            out[tuple(idx)] -= d[tuple(idx)]
            break
    return out


def ref_suction(d, lo, p, rad, rate_q):
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in d.shape], indexing="ij"), -1) + lo
    c = ORIGIN + H * idx
    dx, dy, dz = (c[..., a] - p[a] for a in range(3))
    near = dx * dx + dy * dy + dz * dz <= rad * rad
    f = np.where(near, np.minimum(d, rate_q), 0)
    return d - f, int(f.sum())


def rates(p: DustParams, dt):
    return dict(rate_q=int(round(p.settle_rate * dt * Q)),
                kq=int(math.floor(min(p.spill_rate * dt, 0.2) * W_ONE)),
                repose_q=int(round(p.repose * Q)),
                srate_q=int(round(p.suction_rate * dt * Q)))


# ------------------------------------------------------------------ helpers
def make_case(shape, seed, bone_p=0.1, dust_max=1.0, floor=2, packed=False):
    """Bone grid (a floor plus scattered voxels) and random dust in free cells;
    ``packed``: also a bone-free block of exactly full cells (whole bricks)."""
    rng = np.random.default_rng(seed)
    lab = (rng.random(shape) < bone_p).astype(np.uint8)
    lab[:, :, :floor] = 1
    block = (slice(0, 16), slice(0, 16), slice(8, 24))
    if packed:
        lab[block] = 0
    bone = Grid.from_dense(lab, spacing_mm=H, origin_mm=ORIGIN)
    dust_q = np.where(lab == 0, rng.integers(0, int(dust_max * Q), size=shape), 0)
    dust_q[rng.random(shape) < 0.3] = 0
    if packed:
        dust_q[block] = Q
    return bone, lab > 0, dust_q.astype(np.int64)


def load(dust: DustGrid, dust_q, lo=(0, 0, 0)):
    ijk = np.argwhere(dust_q > 0)
    order = np.random.default_rng(len(ijk)).permutation(len(ijk))   # any order
    ijk = ijk[order]
    dust.add_removed(ijk + np.asarray(lo), dust_q[tuple(ijk.T)] / Q)


def dense_q(dust: DustGrid) -> np.ndarray:
    return np.round(dust.to_dense() * Q).astype(np.int64)


def check_mass(dust: DustGrid):
    total, added, sucked = dust.totals_q()
    assert total == added - sucked
    assert dust.recount_q() == total
    assert int(dense_q(dust).sum()) == total


SHAPES = [(13, 11, 17), (20, 17, 24), (9, 26, 16), (25, 18, 27)]
GRAVITIES = [(0, 0, -1), (1, 0, 0), (0, -1, 0), (0.3, -0.5, -1.0), (-1, 0.4, 0.2)]


# --------------------------------------------------------------- rule tests
@pytest.mark.parametrize("g", GRAVITIES)
@pytest.mark.parametrize("split", [True, False])
def test_gravity_matches_reference(g, split):
    for n, shape in enumerate(SHAPES):
        bone, wall, d = make_case(shape, seed=n, packed=n == 3)
        prm = DustParams(spill_rate=0.0, settle_rate=300.0, split_gravity=split,
                         initial_bricks=4)
        dust = DustGrid.for_grid(bone, g, prm)
        load(dust, d)
        dt = 1e-3
        r = rates(prm, dt)
        for _ in range(6):
            dust.step(bone, dt)
            d = ref_gravity(d, wall, g, r["rate_q"], split)
            np.testing.assert_array_equal(dense_q(dust), d)
        check_mass(dust)


@pytest.mark.parametrize("g", GRAVITIES)
def test_spill_matches_reference(g):
    for n, shape in enumerate(SHAPES):
        bone, wall, d = make_case(shape, seed=10 + n, dust_max=2.5, packed=n == 3)
        prm = DustParams(settle_rate=0.0, spill_rate=150.0, repose=0.3, initial_bricks=4)
        dust = DustGrid.for_grid(bone, g, prm)
        load(dust, d)
        dt = 1e-3
        r = rates(prm, dt)
        for _ in range(6):
            dust.step(bone, dt)
            d = ref_spill(d, wall, g, r["kq"], r["repose_q"])
            np.testing.assert_array_equal(dense_q(dust), d)
        check_mass(dust)


def test_tool_push_and_suction_match_reference():
    shape = (24, 22, 26)
    bone, wall, d = make_case(shape, seed=5, bone_p=0.05, dust_max=1.0)
    prm = DustParams(settle_rate=0.0, spill_rate=0.0, suction_rate=150.0, push_search=3)
    g = (0.0, 0.0, -1.0)
    dust = DustGrid.for_grid(bone, g, prm)
    load(dust, d)
    rng = np.random.default_rng(3)
    dt = 2e-3
    r = rates(prm, dt)
    for _ in range(8):
        tool = ORIGIN + rng.uniform(2, 9, 3)
        rad = float(rng.uniform(0.6, 2.5))
        suck = ORIGIN + rng.uniform(2, 9, 3)
        srad = float(rng.uniform(0.4, 2.0))
        got = dust.step(bone, dt, tool, rad, suck, srad)
        d = ref_tool(d, wall, np.zeros(3, int), tool, rad, prm.push_search, (0.0, 0.0, 1.0))
        d, sucked = ref_suction(d, np.zeros(3, int), suck, srad, r["srate_q"])
        np.testing.assert_array_equal(dense_q(dust), d)
        assert got == sucked / Q
    check_mass(dust)
    assert dust.suctioned_cells > 0


def steps_match_reference(bone, wall, d, g, seed, bodies=None):
    """Ten full steps (gravity, spill, tool push, suction) against the
    references, ``wall`` the cells the references treat as walls."""
    prm = DustParams(settle_rate=120.0, spill_rate=120.0, repose=0.4, suction_rate=90.0)
    dust = DustGrid.for_grid(bone, g, prm)
    load(dust, d)
    dt = 1.5e-3
    r = rates(prm, dt)
    gn = np.asarray(g, float) / np.linalg.norm(g)
    rng = np.random.default_rng(seed)
    for _ in range(10):
        tool = ORIGIN + rng.uniform(2, 8, 3)
        suck = ORIGIN + rng.uniform(2, 8, 3)
        dust.step(bone, dt, tool, 1.3, suck, 1.1, bodies=bodies)
        d = ref_gravity(d, wall, g, r["rate_q"])
        d = ref_spill(d, wall, g, r["kq"], r["repose_q"])
        d = ref_tool(d, wall, np.zeros(3, int), tool, 1.3, prm.push_search, tuple(-gn))
        d, _ = ref_suction(d, np.zeros(3, int), suck, 1.1, r["srate_q"])
        np.testing.assert_array_equal(dense_q(dust), d)
    check_mass(dust)


@pytest.mark.parametrize("g", [(0, 0, -1), (0.2, 0.3, -1.0)])
def test_full_step_matches_reference(g):
    bone, wall, d = make_case((21, 19, 23), seed=7, dust_max=1.8)
    steps_match_reference(bone, wall, d, g, seed=1)


# ------------------------------------------------------------ conservation
@settings(max_examples=25, deadline=None)
@given(seed=hs.integers(0, 2 ** 31), n_ops=hs.integers(1, 25),
       gx=hs.floats(-1, 1), gy=hs.floats(-1, 1), gz=hs.floats(-1, -0.05))
def test_mass_is_conserved_exactly(seed, n_ops, gx, gy, gz):
    rng = np.random.default_rng(seed)
    shape = (18, 16, 20)
    lab = (rng.random(shape) < 0.15).astype(np.uint8)
    lab[:, :, :3] = 1
    bone = Grid.from_dense(lab, spacing_mm=H, origin_mm=ORIGIN)
    prm = DustParams(settle_rate=float(rng.uniform(0, 500)),
                     spill_rate=float(rng.uniform(0, 400)),
                     repose=float(rng.uniform(0, 0.9)), initial_bricks=1)
    dust = DustGrid.for_grid(bone, (gx, gy, gz), prm)
    for _ in range(n_ops):
        if rng.random() < 0.4:
            n = int(rng.integers(1, 60))
            ijk = rng.integers(0, shape, size=(n, 3))
            dust.add_removed(ijk, rng.uniform(0, 3, n))
        tool = ORIGIN + rng.uniform(0, 10, 3) if rng.random() < 0.5 else None
        suck = ORIGIN + rng.uniform(0, 10, 3) if rng.random() < 0.3 else None
        dust.step(bone, float(rng.uniform(0, 0.02)), tool, float(rng.uniform(0, 2)),
                  suck, float(rng.uniform(0, 2)))
        total, added, sucked = dust.totals_q()
        assert total == added - sucked
    check_mass(dust)
    d = dust.to_dense()
    assert (d >= 0).all()
    assert math.isclose(dust.total_cells, dust.added_cells - dust.suctioned_cells,
                        rel_tol=0, abs_tol=1e-9)


# ---------------------------------------------------------------- behaviour
def _floor_case(shape=(24, 24, 30), floor=4, gravity=(0, 0, -1), **kw):
    lab = np.zeros(shape, np.uint8)
    lab[:, :, :floor] = 1
    bone = Grid.from_dense(lab, spacing_mm=H, origin_mm=ORIGIN)
    return bone, DustGrid.for_grid(bone, gravity, DustParams(**kw))


def test_dust_settles_on_the_floor():
    bone, dust = _floor_case(settle_rate=200.0)
    ijk = np.stack(np.meshgrid(np.arange(8, 14), np.arange(9, 15), np.arange(18, 24),
                               indexing="ij"), -1).reshape(-1, 3)
    dust.add_removed(ijk, 0.1)                          # 21.6 cells over 36 columns
    for _ in range(400):
        dust.step(bone, 2e-3)
    d = dust.to_dense()
    assert d[:, :, :4].sum() == 0                       # none inside the bone
    assert d[:, :, 5:].sum() == 0                       # none floating
    assert d[:, :, 4].sum() == dust.added_cells         # ~21.6 (amounts are in 1/Q)
    check_mass(dust)


def test_a_tall_heap_rests_on_full_cells():
    bone, dust = _floor_case(settle_rate=200.0, spill_rate=100.0, repose=0.5)
    ijk = np.stack(np.meshgrid(np.arange(10, 14), np.arange(10, 14), np.arange(10, 26),
                               indexing="ij"), -1).reshape(-1, 3)
    dust.add_removed(ijk, 0.9)                          # 230 cells: several layers
    for _ in range(1500):
        dust.step(bone, 2e-3)
    d = dust.to_dense()
    assert d[:, :, :4].sum() == 0
    assert d.max() <= 1.0 + 1e-9
    # every dusty cell above the first layer sits on a full cell
    above = d[:, :, 5:] > 0
    assert (d[:, :, 4:-1][above] >= 1.0).all()
    assert (d[:, :, 5] > 0).any()                       # it did pile up
    check_mass(dust)


def test_an_overfull_cell_piles_and_spills_sideways():
    bone, dust = _floor_case(settle_rate=200.0, spill_rate=150.0, repose=0.5)
    dust.add_removed(np.array([[12, 12, 4]]), 12.0)     # twelve cells' worth in one
    for _ in range(2000):
        dust.step(bone, 2e-3)
    d = dust.to_dense()
    # shed its excess (down to a few 1/Q units that a neighbour 5 units short
    # of full cannot take: its room share rounds to zero)
    assert np.maximum(d - 1.0, 0.0).sum() < 1e-3
    assert np.count_nonzero(d > 0.01) >= 12             # spread over the floor
    assert d[:, :, 5].sum() > 0.5                       # and piled up in the middle
    cols = d.sum(axis=2)
    assert cols[12, 12] >= cols[12, 17] and cols[12, 12] > 1.0
    spread = np.argwhere(d > 0.01)
    assert np.ptp(spread[:, 0]) >= 3 and np.ptp(spread[:, 1]) >= 3
    check_mass(dust)


def test_repose_zero_levels_the_dust():
    bone, dust = _floor_case(settle_rate=200.0, spill_rate=150.0, repose=0.0)
    dust.add_removed(np.array([[12, 12, 4]]), 0.9)
    for _ in range(3000):
        dust.step(bone, 2e-3)
    d = dust.to_dense()[:, :, 4]
    assert d.max() < 0.2
    assert np.count_nonzero(d > 0) > 9


def test_tool_pushes_dust_out_of_its_sphere():
    bone, dust = _floor_case(settle_rate=0.0, spill_rate=0.0)
    ijk = np.stack(np.meshgrid(*[np.arange(6, 18)] * 2, np.arange(10, 22),
                               indexing="ij"), -1).reshape(-1, 3)
    dust.add_removed(ijk, 0.5)
    c = np.array([12, 12, 16])
    tool = ORIGIN + H * c + 0.1
    rad = 2.2
    before = dust.to_dense()
    dust.step(bone, 1e-3, tool_pos_mm=tool, tool_radius_mm=rad)
    d = dust.to_dense()
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in d.shape], indexing="ij"), -1)
    r = np.linalg.norm(ORIGIN + H * idx - tool, axis=-1)
    assert d[r < rad].sum() == 0
    assert before[r < rad].sum() > 10
    assert dust.last_pushed_cells == before[r < rad].sum()
    shell = (r >= rad) & (r < rad + 1.5 * H)
    assert d[shell].sum() > before[shell].sum() + 0.9 * before[r < rad].sum()
    check_mass(dust)


def test_tool_buried_in_bone_leaves_dust():
    lab = np.ones((16, 16, 16), np.uint8)
    lab[8, 8, 8] = 0
    bone = Grid.from_dense(lab, spacing_mm=H, origin_mm=ORIGIN)
    dust = DustGrid.for_grid(bone, (0, 0, -1), DustParams(push_search=2))
    dust.add_removed(np.array([[8, 8, 8]]), 1.0)
    dust.step(bone, 1e-3, ORIGIN + H * 8 + 0.05, 1.0)
    assert dust.to_dense()[8, 8, 8] == 1.0


def test_suction_clears_its_reach_and_counts():
    bone, dust = _floor_case(settle_rate=0.0, spill_rate=0.0, suction_rate=100.0)
    ijk = np.stack(np.meshgrid(*[np.arange(6, 18)] * 2, np.arange(10, 22),
                               indexing="ij"), -1).reshape(-1, 3)
    dust.add_removed(ijk, 0.7)
    tip = ORIGIN + H * np.array([12, 12, 16])
    rad = 1.6
    d0 = dust.to_dense()
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in d0.shape], indexing="ij"), -1)
    near = np.linalg.norm(ORIGIN + H * idx - tip, axis=-1) <= rad
    in_reach = d0[near].sum()
    got = sum(dust.step(bone, 1e-3, suction_pos_mm=tip, suction_radius_mm=rad)
              for _ in range(10))
    d = dust.to_dense()
    assert d[near].sum() == 0
    np.testing.assert_array_equal(d[~near], d0[~near])
    assert math.isclose(got, in_reach, abs_tol=1e-9)
    assert math.isclose(dust.suctioned_cells, in_reach, abs_tol=1e-9)
    check_mass(dust)


@pytest.mark.parametrize("g, axis, end", [((1, 0, 0), 0, -1), ((0, 0, -1), 2, 0),
                                          ((0, 0, 1), 2, -1), ((0, -1, 0), 1, 0)])
def test_gravity_direction_is_configurable(g, axis, end):
    shape = (16, 17, 18)
    dust = DustGrid(H, ORIGIN, g, DustParams(settle_rate=300.0),
                    bounds_vox=((0, 0, 0), shape))
    dust.add_removed(np.array([[8, 8, 9], [5, 10, 4]]), 0.8)
    for _ in range(300):
        dust.step(None, 2e-3)
    d = dust.to_dense()
    layer = np.take(d, end, axis=axis)
    assert layer.sum() == dust.added_cells              # all against that wall


def test_tilted_gravity_moves_along_both_axes():
    shape = (30, 12, 30)
    dust = DustGrid(H, ORIGIN, (1.0, 0.0, -1.0), DustParams(settle_rate=50.0),
                    bounds_vox=((0, 0, 0), shape))
    dust.add_removed(np.array([[5, 6, 25]]), 1.0)
    for _ in range(20):
        dust.step(None, 5e-3)
    com = (np.argwhere(np.ones(shape, bool)) * dust.to_dense().reshape(-1, 1)).sum(0)
    assert com[0] > 6 and com[2] < 24


# ------------------------------------------------------------------- grid
def test_only_dusty_bricks_and_their_halo_are_allocated():
    dust = DustGrid(H, ORIGIN, (0, 0, -1), bounds_vox=((0, 0, 0), (1024, 1024, 1024)))
    dust.add_removed(np.array([[500, 500, 500]]), 1.0)
    dust.step(None, 1e-3)
    assert dust.n_bricks <= 7                            # the brick and its 6 faces
    assert dust.n_active_bricks == 1


def test_bricks_left_behind_are_recycled():
    shape = (8, 8, 400)
    dust = DustGrid(H, ORIGIN, (0, 0, -1), DustParams(settle_rate=1000.0, initial_bricks=8),
                    bounds_vox=((0, 0, 0), shape))
    dust.add_removed(np.array([[3, 3, 395]]), 1.0)
    for _ in range(500):
        dust.step(None, 5e-3)
    d = dust.to_dense()
    assert d[:, :, 0].sum() == 1.0                      # fell 395 cells through 50 bricks
    assert dust.pool_size <= 32                         # ... without keeping them
    check_mass(dust)


def test_result_does_not_depend_on_insertion_order_or_table_size():
    bone, wall, d = make_case((20, 18, 22), seed=9, dust_max=1.5)
    ijk = np.argwhere(d > 0)
    out = []
    for order_seed, pool in ((0, 1), (1, 4), (2, 300)):
        dust = DustGrid.for_grid(bone, (0.2, -0.1, -1.0), DustParams(initial_bricks=pool))
        perm = np.random.default_rng(order_seed).permutation(len(ijk))
        dust.add_removed(ijk[perm], d[tuple(ijk[perm].T)] / Q)
        for s in range(15):
            dust.step(bone, 2e-3, ORIGIN + 4.0, 1.2, ORIGIN + 3.0 + 0.1 * s, 1.0)
        out.append(dense_q(dust))
    np.testing.assert_array_equal(out[0], out[1])
    np.testing.assert_array_equal(out[0], out[2])


def test_dust_resting_on_removed_bone_falls():
    lab = np.zeros((16, 16, 20), np.uint8)
    lab[:, :, :10] = 1
    bone = Grid.from_dense(lab, spacing_mm=H, origin_mm=ORIGIN)
    dust = DustGrid.for_grid(bone, (0, 0, -1), DustParams(settle_rate=500.0))
    dust.add_removed(np.array([[8, 8, 10]]), 0.5)
    dust.step(bone, 2e-3)
    assert dust.to_dense()[8, 8, 10] == 0.5
    for z in range(3, 10):                               # drill a shaft
        bone.density[bone.brick_index(8, 8, z), voxel_offset(8, 8, z)] = 0.0
    for _ in range(100):
        dust.step(bone, 2e-3)
    assert dust.to_dense()[8, 8, 3] == 0.5


# ------------------------------------------------------------------ output
def test_sprites_list_dusty_cells():
    bone, wall, d = make_case((17, 15, 19), seed=4)
    dust = DustGrid.for_grid(bone, (0, 0, -1))
    load(dust, d)
    pos, val, cell_mm, age, wet = dust.sprites(threshold=0.25, top_only=False, jitter=0.0)
    assert pos.dtype == np.float32 and val.dtype == np.float32 and cell_mm == H
    dense = dust.to_dense()
    want = np.argwhere(dense > 0.25)
    assert len(pos) == len(want) == len(age) == len(wet)
    got = np.round((pos - ORIGIN) / H).astype(int)
    order = np.lexsort(got.T[::-1])
    np.testing.assert_array_equal(got[order], want)
    np.testing.assert_allclose(val[order], dense[tuple(want.T)], rtol=1e-6)
    assert not wet.any()


def ref_top_layer(dense, g, thr, cover):
    """Cells above ``thr`` whose neighbour against gravity's dominant axis
    (outside the box: none) holds less than ``cover``."""
    g = np.asarray(g, float)
    dom = int(np.argmax(np.abs(g)))
    up = -1 if g[dom] > 0 else 1
    above = np.zeros_like(dense)
    S, D = _pairs(dense.shape, dom, -up)         # D = S - up e_dom: S is above D
    above[D] = dense[S]
    return np.argwhere((dense > thr) & (above < cover))


@pytest.mark.parametrize("g", [(0, 0, -1), (1, 0, 0), (0, -1, 0.3), (0, 0.2, 1)])
def test_sprites_show_the_top_layer_only(g):
    bone, wall, d = make_case((20, 17, 22), seed=8, dust_max=1.0, packed=True)
    dust = DustGrid.for_grid(bone, g)
    load(dust, d)
    prm = dust.params
    pos, val, _, _, _ = dust.sprites(jitter=0.0)
    want = ref_top_layer(dust.to_dense(), g, prm.sprite_threshold, prm.sprite_cover)
    got = np.round((pos - ORIGIN) / H).astype(int)
    assert len(got) == len(want)
    np.testing.assert_array_equal(got[np.lexsort(got.T[::-1])],
                                  want[np.lexsort(want.T[::-1])])
    # a packed block is covered: only its top face shows
    assert len(want) < np.count_nonzero(dust.to_dense() > prm.sprite_threshold)


def test_sprites_are_jittered_inside_their_cells_the_same_every_frame():
    from bonesim.physics.dust.sprites import cell_jitter

    bone, dust = _floor_case()
    ijk = np.stack(np.meshgrid(np.arange(4, 16), np.arange(4, 16), [4],
                               indexing="ij"), -1).reshape(-1, 3)
    dust.add_removed(ijk, 0.8)
    pos0, *_ = dust.sprites(jitter=0.0)
    pos, *_ = dust.sprites()
    again, *_ = dust.sprites()
    np.testing.assert_array_equal(pos, again)
    cells = np.round((pos0 - ORIGIN) / H).astype(int)
    off = (pos - pos0) / H
    jit = dust.params.sprite_jitter
    assert np.abs(off).max() <= jit + 1e-5
    np.testing.assert_allclose(off, cell_jitter(cells) * jit, atol=1e-5)
    # no regular pattern: offsets spread over the range, neighbours differ
    assert off[:, 0].std() > 0.4 * jit and off[:, 1].std() > 0.4 * jit
    assert len(np.unique(np.round(off, 3), axis=0)) == len(off)


def test_sprites_carry_the_age_of_their_dust():
    bone, dust = _floor_case(settle_rate=0.0, spill_rate=0.0)
    dust.add_removed(np.array([[5, 5, 4]]), 0.6)
    dust.sprites()                                  # arrival seen at t = 0
    for _ in range(10):
        dust.step(bone, 0.05)
    dust.add_removed(np.array([[9, 9, 4]]), 0.6)    # arrives at t = 0.5
    dust.sprites()                                  # (seen by the next frame's call)
    for _ in range(4):
        dust.step(bone, 0.05)
    pos, _, _, age, _ = dust.sprites(jitter=0.0)
    cells = [tuple(c) for c in np.round((pos - ORIGIN) / H).astype(int)]
    ages = dict(zip(cells, age))
    assert ages[(5, 5, 4)] == pytest.approx(0.7, abs=1e-6)
    assert ages[(9, 9, 4)] == pytest.approx(0.2, abs=1e-6)
    # a cell emptied by suction and filled again is young again
    dust.step(bone, 0.05, suction_pos_mm=ORIGIN + H * np.array([5, 5, 4]),
              suction_radius_mm=0.3, suction_rate=1e3)
    dust.sprites()
    dust.add_removed(np.array([[5, 5, 4]]), 0.6)
    dust.sprites()
    dust.step(bone, 0.05)
    pos, _, _, age, _ = dust.sprites(jitter=0.0)
    cells = [tuple(c) for c in np.round((pos - ORIGIN) / H).astype(int)]
    assert dict(zip(cells, age))[(5, 5, 4)] == pytest.approx(0.05, abs=1e-6)


# -------------------------------------------------------------- irrigation
def test_wetting_matches_reference():
    shape = (22, 20, 24)
    bone, wall, d = make_case(shape, seed=21, dust_max=1.5)
    prm = DustParams(settle_rate=0.0, spill_rate=0.0, wet_settle_rate=0.0,
                     wet_spill_rate=0.0, wetting_rate=30.0,
                     water_flow_mm3_s=0.0)        # the spray's wetting alone, no water poured
    dust = DustGrid.for_grid(bone, (0, 0, -1), prm)
    load(dust, d)
    dt = 4e-3
    rate_q = int(round(prm.wetting_rate * dt * Q))
    rng = np.random.default_rng(2)
    wet = np.zeros_like(d)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    centres = ORIGIN + H * idx
    for _ in range(6):
        tip = ORIGIN + rng.uniform(2, 9, 3)
        rad = float(rng.uniform(0.5, 3.0))
        dust.step(bone, dt, irrigation_pos_mm=tip, irrigation_radius_mm=rad)
        near = ((centres - tip) ** 2).sum(-1) <= rad * rad
        f = np.where(near, np.minimum(d, rate_q), 0)
        d, wet = d - f, wet + f
        np.testing.assert_array_equal(np.round(dust.to_dense(species="dry") * Q), d)
        np.testing.assert_array_equal(np.round(dust.to_dense(species="wet") * Q), wet)
        assert int(wet.sum()) == int(round(dust.wetted_cells * Q))
    # wet + dry is the original dust, cell by cell
    check_mass(dust)
    assert dust.wet_cells > 0


def test_wetting_moves_dry_dust_to_wet_in_the_same_cell():
    bone, dust = _floor_case(settle_rate=0.0, spill_rate=0.0, wet_settle_rate=0.0,
                             wet_spill_rate=0.0, wetting_rate=1e4,
                             water_flow_mm3_s=0.0)   # the spray's wetting alone
    dust.add_removed(np.array([[6, 6, 4], [6, 7, 4], [15, 15, 4]]), 0.7)
    before = dust.to_dense()
    dust.step(bone, 0.01, irrigation_pos_mm=ORIGIN + H * np.array([6, 6.5, 4]),
              irrigation_radius_mm=0.6)
    np.testing.assert_array_equal(dust.to_dense(), before)        # no cell changed
    wet = dust.to_dense(species="wet")
    assert wet[6, 6, 4] == pytest.approx(0.7) and wet[6, 7, 4] == pytest.approx(0.7)
    assert wet[15, 15, 4] == 0 and dust.to_dense(species="dry")[15, 15, 4] == \
        pytest.approx(0.7)
    _, _, _, _, flag = dust.sprites(top_only=False)
    assert sorted(flag.tolist()) == [0, 1, 1]


def test_wet_dust_drains_downhill_and_spreads_flat():
    """A heap on a tilted floor: dry dust keeps its angle of repose; wetted,
    it runs down the slope and spreads into a thin layer."""
    shape = (30, 12, 20)
    lab = np.zeros(shape, np.uint8)
    lab[:, :, :3] = 1
    bone = Grid.from_dense(lab, spacing_mm=H, origin_mm=ORIGIN)
    g = (0.35, 0.0, -1.0)                       # downhill is +x
    heap = np.stack(np.meshgrid(np.arange(4, 8), np.arange(4, 8), np.arange(3, 9),
                                indexing="ij"), -1).reshape(-1, 3)
    runs = {}
    for wet in (False, True):
        dust = DustGrid.for_grid(bone, g, DustParams(repose=0.5))
        dust.add_removed(heap, 1.0)
        for _ in range(200):
            w = ORIGIN + H * np.array([6.0, 6.0, 5.0]) if wet else None
            dust.step(bone, 5e-3, irrigation_pos_mm=w, irrigation_radius_mm=6.0)
        d = dust.to_dense()
        x = np.arange(shape[0])
        runs[wet] = (float((d.sum(axis=(1, 2)) * x).sum() / d.sum()),
                     float(d.max()), dust.totals_q())
        check_mass(dust)
    assert runs[True][0] > runs[False][0] + 3.0          # the paste ran downhill
    assert runs[True][1] < runs[False][1]                # and spread thinner
    assert runs[True][2][0] == runs[False][2][0]         # nothing lost


def test_suction_takes_wet_and_dry_dust():
    bone, dust = _floor_case(wetting_rate=1e4)
    ijk = np.stack(np.meshgrid(np.arange(4, 12), np.arange(4, 12), [4], indexing="ij"),
                   -1).reshape(-1, 3)
    dust.add_removed(ijk, 0.5)
    dust.step(bone, 0.01, irrigation_pos_mm=ORIGIN + H * np.array([6, 8, 4]),
              irrigation_radius_mm=1.5)
    assert dust.wet_cells > 0 and dust.to_dense(species="dry").sum() > 0
    tip = ORIGIN + H * np.array([8, 8, 4])
    got = 0.0
    for _ in range(40):
        got += dust.step(bone, 0.01, suction_pos_mm=tip, suction_radius_mm=6.0)
    assert dust.total_cells == pytest.approx(0.0, abs=1e-9)
    assert got == pytest.approx(dust.added_cells, abs=1e-6)
    check_mass(dust)


@settings(max_examples=20, deadline=None)
@given(seed=hs.integers(0, 2 ** 31), n_ops=hs.integers(1, 25))
def test_mass_is_conserved_exactly_with_irrigation(seed, n_ops):
    rng = np.random.default_rng(seed)
    shape = (18, 16, 20)
    lab = (rng.random(shape) < 0.15).astype(np.uint8)
    lab[:, :, :3] = 1
    bone = Grid.from_dense(lab, spacing_mm=H, origin_mm=ORIGIN)
    prm = DustParams(wetting_rate=float(rng.uniform(0, 500)), initial_bricks=1)
    g = rng.uniform(-1, 1, 3)
    g[2] = -abs(g[2]) - 0.05
    dust = DustGrid.for_grid(bone, g, prm)
    for _ in range(n_ops):
        if rng.random() < 0.4:
            n = int(rng.integers(1, 60))
            dust.add_removed(rng.integers(0, shape, size=(n, 3)), rng.uniform(0, 3, n))
        tool = ORIGIN + rng.uniform(0, 10, 3) if rng.random() < 0.5 else None
        suck = ORIGIN + rng.uniform(0, 10, 3) if rng.random() < 0.3 else None
        wet = ORIGIN + rng.uniform(0, 10, 3) if rng.random() < 0.5 else None
        dust.step(bone, float(rng.uniform(0, 0.02)), tool, float(rng.uniform(0, 2)),
                  suck, float(rng.uniform(0, 2)), irrigation_pos_mm=wet,
                  irrigation_radius_mm=float(rng.uniform(0, 4)))
        total, added, sucked = dust.totals_q()
        assert total == added - sucked
        if rng.random() < 0.2:
            dust.recycle()
    check_mass(dust)
    assert (dust.to_dense(species="wet") >= 0).all()
    assert (dust.to_dense(species="dry") >= 0).all()


def test_drain_turns_removed_voxels_into_bulked_dust():
    ring = events.tissue_ring(64)
    cur = events.Cursor(ring)
    n = 5
    ring.fields["ijk"][:n + 1] = [[4, 4, 6], [5, 4, 6], [4, 4, 6], [0, 0, 0], [6, 6, 6], [7, 7, 7]]
    ring.fields["kind"][3] = events.CONTACT          # not a removal: no dust
    ring.head[0] = n + 1
    bone, dust = _floor_case(bulking=1.6)
    assert dust.drain(cur) == n
    assert math.isclose(dust.added_cells, 1.6 * n, abs_tol=1e-5)
    assert math.isclose(dust.to_dense()[4, 4, 6], 3.2, abs_tol=1e-5)
    assert dust.drain(cur) == 0


# -------------------------------------------------------------- validation
def test_inputs_are_validated():
    with pytest.raises(ValueError):
        DustGrid(H, ORIGIN, (0, 0, 0))
    with pytest.raises(ValueError):
        DustGrid(0.0, ORIGIN, (0, 0, -1))
    with pytest.raises(ValueError):
        DustParams(repose=1.0)
    with pytest.raises(ValueError):
        DustParams(settle_rate=-1.0)
    bone, dust = _floor_case()
    with pytest.raises(ValueError):
        dust.add_removed(np.zeros((3, 2), np.int32))
    with pytest.raises(ValueError):
        dust.add_removed(np.array([[0.5, 1, 2]]))
    with pytest.raises(ValueError):
        dust.add_removed(np.array([[100, 1, 2]]))            # outside the domain
    with pytest.raises(ValueError):
        dust.add_removed(np.array([[1, 1, 2]]), -1.0)
    with pytest.raises(ValueError):
        dust.step(bone, -1e-3)
    with pytest.raises(ValueError):
        dust.step(bone, 1e-3, tool_pos_mm=(0, 0))
    other = Grid.from_dense(np.ones((4, 4, 4), np.uint8), spacing_mm=0.4)
    with pytest.raises(ValueError):
        dust.step(other, 1e-3)


# ------------------------------------------------------------------ bodies
def _bodies(bone, body_dense, poses):
    """Body arrays for ``bone``: ``body_dense`` (shape of the grid) laid out
    like its density, ``poses`` one per body."""
    from bonesim.engine.bodies import Bodies, pose_matrix

    body = np.zeros(bone.density.shape, np.uint8)
    for i, j, k in np.argwhere(body_dense > 0):
        b = bone.brick_index(i, j, k)
        if b >= 0:
            body[b, voxel_offset(i, j, k)] = body_dense[i, j, k]
    pose = np.array(poses, dtype=np.float64)
    pose_m = np.stack([pose_matrix(p) for p in pose])
    bounds = np.zeros((len(pose), 6), np.int32)
    bounds[:, 3:] = np.asarray(bone.shape) - 1
    return Bodies(body, pose, pose_m, np.ones(len(pose), np.uint8), bounds)


IDENT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
#: a quarter turn about z (x -> y, y -> -x) and a shift
TURN = (6.0, 4.0, 1.0, math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))


@pytest.mark.parametrize("g", [(0, 0, -1), (0.2, 0.3, -1.0)])
def test_only_bodies_at_the_identity_are_dust_walls(g):
    shape = (21, 19, 23)
    bone, wall, d = make_case(shape, seed=8, dust_max=1.8)
    # bone split into three bodies by a random pattern; body 1 moved away
    body_dense = np.random.default_rng(2).integers(0, 3, shape).astype(np.uint8)
    bodies = _bodies(bone, body_dense, [IDENT, TURN, IDENT])
    steps_match_reference(bone, wall & (body_dense != 1), d, g, seed=4, bodies=bodies)


def test_bodies_at_the_identity_step_exactly_as_one_body():
    shape = (21, 19, 23)
    out = []
    for split in (None, "ident", "none"):
        bone, _, d = make_case(shape, seed=9, dust_max=1.8)
        body_dense = np.random.default_rng(2).integers(0, 3, shape).astype(np.uint8)
        bodies = None if split is None else _bodies(bone, body_dense, [IDENT] * 3)
        dust = DustGrid.for_grid(bone, (0.2, 0.3, -1.0),
                                 DustParams(settle_rate=120.0, spill_rate=120.0))
        load(dust, d)
        for q in range(8):
            dust.step(bone, 1.5e-3, ORIGIN + 4.0 + 0.3 * q, 1.3, ORIGIN + 6.0, 1.1,
                      irrigation_pos_mm=ORIGIN + 5.0, irrigation_radius_mm=2.0,
                      bodies=bodies)
        out.append(dense_q(dust))
    for o in out[1:]:
        np.testing.assert_array_equal(o, out[0])


def test_dust_falls_through_where_a_moved_body_was_cut():
    lab = np.zeros((16, 16, 20), np.uint8)
    lab[:, :, :10] = 1
    bone = Grid.from_dense(lab, spacing_mm=H, origin_mm=ORIGIN)
    body_dense = np.zeros(lab.shape, np.uint8)
    body_dense[6:11, 6:11, 3:10] = 1                      # a plug cut out of the slab
    prm = DustParams(settle_rate=500.0)
    got = []
    for pose in (IDENT, (0.0, 0.0, 30.0, 1.0, 0.0, 0.0, 0.0)):   # in place, lifted away
        bodies = _bodies(bone, body_dense, [IDENT, pose])
        dust = DustGrid.for_grid(bone, (0, 0, -1), prm)
        dust.add_removed(np.array([[8, 8, 10]]), 0.5)
        for _ in range(100):
            dust.step(bone, 2e-3, bodies=bodies)
        got.append(dust.to_dense())
    assert got[0][8, 8, 10] == 0.5                          # rests on the plug
    assert got[1][8, 8, 3] == 0.5 and got[1][8, 8, 10] == 0  # the plug is gone


def test_removals_of_a_moved_body_land_in_their_case_frame_cell():
    bone, dust = _floor_case(bulking=1.0)
    lab = np.ones(bone.shape, np.uint8)
    bodies = _bodies(bone, lab * 0, [IDENT, TURN])
    ijk = np.array([[4, 4, 6], [5, 7, 9], [6, 6, 6], [4, 4, 6]])
    body = np.array([0, 1, 1, 1])
    dust.add_removed(ijk, body=body, bodies=bodies)
    # reference: the centre of each voxel of body 1 through R c + t, by hand
    want = np.zeros(bone.shape)
    want[4, 4, 6] += 1.0                                    # body 0: its own cell
    for i, j, k in ijk[1:]:
        x, y, z = ORIGIN + H * np.array([i, j, k])
        c = np.array([-y + 6.0, x + 4.0, z + 1.0])          # quarter turn about z, shift
        cell = np.floor((c - ORIGIN) / H + 0.5).astype(int)
        assert (cell >= 0).all() and (cell < bone.shape).all()
        want[tuple(cell)] += 1.0
    assert want.sum() == 4 and want[4, 4, 6] == 1.0
    np.testing.assert_allclose(dust.to_dense(), want, atol=1e-6)
    # through the tissue stream: the events name the body
    ring = events.tissue_ring(16)
    cur = events.Cursor(ring)
    ring.fields["ijk"][:2] = [[5, 7, 9], [4, 4, 6]]
    ring.fields["body"][:2] = [1, 0]
    ring.head[0] = 2
    bone, dust2 = _floor_case(bulking=1.0)
    assert dust2.drain(cur, bodies=bodies) == 2
    w2 = np.zeros(bone.shape)
    w2[4, 4, 6] = 1.0
    x, y, z = ORIGIN + H * np.array([5, 7, 9])
    w2[tuple(np.floor((np.array([-y + 6.0, x + 4.0, z + 1.0]) - ORIGIN) / H + 0.5)
             .astype(int))] += 1.0
    np.testing.assert_allclose(dust2.to_dense(), w2, atol=1e-6)
    # a removal carried out of the domain is dropped; at the identity nothing moves
    far = bodies._replace(pose=np.array([IDENT, (90.0, 0, 0, 1, 0, 0, 0)], float))
    far.pose_m[1, 0, 3] = 90.0
    before = dust2.added_cells
    dust2.add_removed(np.array([[5, 7, 9]]), body=[1], bodies=far)
    assert dust2.added_cells == before
    bone, d3 = _floor_case(bulking=1.0)
    bone, d4 = _floor_case(bulking=1.0)
    d3.add_removed(ijk)
    d4.add_removed(ijk, body=body, bodies=_bodies(bone, lab * 0, [IDENT, IDENT]))
    np.testing.assert_array_equal(d3.to_dense(), d4.to_dense())
