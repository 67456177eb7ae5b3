"""The fixed-budget haptic step (bonesim.engine.haptics_budget): where it
takes over, its sampled force against the exact voxel sum within the
documented bound, removal that reaches every covered voxel and carries what
exceeds the budget to later steps without losing any, and a native-resolution
run that replays bit for bit."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs
from scipy import ndimage

from bonesim.engine import events
from bonesim.engine.haptics import O_MAG, O_N_REMOVED, O_VOLUME, multi_gain
from bonesim.engine.haptics_budget import LAT_TABLE, lat_table, load_budget_settings
from bonesim.engine.model import Sample, make_model, make_state, step

from tests.bonesim.engine.test_haptics import ref_step
from tests.bonesim.fakes import BONE, MATERIALS, NERVE, FakeBurr

MIN_H = load_budget_settings().min_spacing_mm


def _model(labels, voxel, burr, oversample=2):
    m = make_model(labels, voxel, [BONE, NERVE], burr, materials=MATERIALS,
                   oversample=oversample)
    return m, make_state(m)


def _run(m, s, pos, axis, drill=False, t=0.0, speed=60000.0):
    return step(m, s, Sample(t, np.asarray(pos, float), np.asarray(axis, float), drill,
                             speed, 1))


# ------------------------------------------------------------ where it binds
def test_budget_binds_only_below_the_finest_lattice():
    labels = np.ones((8, 8, 8), np.uint8)
    burr = FakeBurr(radius_mm=1.0)
    m, _ = _model(labels, 0.5, burr)                 # 0.5 / 2 = the finest spacing
    assert not m.budget.binding
    assert m.stencil.spacing_mm == 0.5 / 2            # the very float of before
    m, _ = _model(labels, 0.19, burr)
    assert m.budget.binding and m.stencil.spacing_mm == MIN_H
    assert m.budget.cell == 2                         # 2 x 0.19 mm >= 0.25 mm
    m, _ = _model(labels, 0.1, burr)
    assert m.budget.binding and m.budget.cell == 4
    m4, _ = _model(labels, 0.5, burr, oversample=4)   # 0.125 mm: the budget
    assert m4.budget.binding and m4.stencil.spacing_mm == MIN_H and m4.budget.cell == 1
    # the sample count is set by the burr, not the voxel
    n = {v: _model(labels, v, burr)[0].stencil.n for v in (0.19, 0.13, 0.1)}
    assert len(set(n.values())) == 1


@settings(max_examples=30, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1), radius=hs.sampled_from([0.6, 1.5, 2.5]),
       moves=hs.lists(hs.sampled_from(["same", "small", "brick", "bricks", "far"]),
                      min_size=1, max_size=25))
def test_brick_table_kept_between_passes_is_the_table_filled_afresh(seed, radius, moves):
    """The budget step's brick table, moved with the burr from pass to pass,
    against :func:`bonesim.engine.haptics.block_bricks` filled afresh."""
    from bonesim.engine.grid import BRICK, Grid
    from bonesim.engine.haptics import block_bricks, block_size
    from bonesim.engine.haptics_budget import _brick_table

    rng = np.random.default_rng(seed)
    labels = (rng.random((70, 60, 50)) < 0.3).astype(np.uint8)
    labels[rng.random(labels.shape) < 0.5] = 0        # brick-sized holes come and go
    labels[:, :, 30:] = 0                               # whole bricks absent
    v = 0.1
    g = Grid.from_dense(labels, spacing_mm=v, origin_mm=(-1.0, 2.0, 0.5))
    nb = block_size(radius, v)[1]
    kept = np.zeros((nb, nb, nb), np.int32)
    key = np.zeros(5, np.int64)
    fresh = np.zeros_like(kept)
    pos = g.origin_mm + v * np.array([35.0, 30.0, 25.0])
    step_mm = {"same": 0.01, "small": 0.2, "brick": BRICK * v, "bricks": 3 * BRICK * v,
               "far": 30.0}
    for mv in moves:
        pos = pos + rng.choice([-1.0, 0.0, 1.0], 3) * step_mm[mv] * rng.random(3)
        got = _brick_table(g.keys, g.vals, pos, radius, g.origin_mm, v, kept, key)
        want = block_bricks(g.keys, g.vals, pos, radius, g.origin_mm, v, fresh)
        assert got == want
        np.testing.assert_array_equal(kept, fresh)


def test_lat_table_matches_the_removal_law():
    t = lat_table(4.0, 2.0)
    u = np.linspace(0, 1, 1001)
    exact = np.maximum(0, 4.0 - 2.0 * np.abs(np.pi / 2 - np.arccos(u)))
    x = u * (LAT_TABLE - 1)
    q = np.minimum(x.astype(int), LAT_TABLE - 2)
    interp = t[q] + (x - q) * (t[q + 1] - t[q])
    assert np.max(np.abs(interp - exact)) < 2e-3 * 2.0


# ------------------------------------------------------------- force bound
def _lattice_bound(m, dens, pos, axis, r, h, v):
    """``h^3 N_h + v^3 N_v`` (module notes): the lattice cells the sphere or
    a bone face cuts, and the bone voxels the sphere cuts. Conservative: a
    cell counts as cut by a bone face when bone and empty voxels both lie
    within ``h sqrt(3)/2 + v sqrt(3)`` of its sample's voxel centre."""
    from tests.bonesim.engine.test_haptics import ref_frame

    R = ref_frame(axis)
    mm = int(math.ceil(r / h)) + 2
    ax = (np.arange(-mm, mm) + 0.5) * h
    g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    rad = np.linalg.norm(g, axis=1)
    n_shell = int((np.abs(rad - r) <= h * math.sqrt(3) / 2).sum())
    inside = g[rad <= r] @ R.T + pos
    occ = dens > 0
    rho = (h * math.sqrt(3) / 2 + v * math.sqrt(3)) / v
    k = int(math.ceil(rho))
    z = np.mgrid[-k:k + 1, -k:k + 1, -k:k + 1]
    foot = (z ** 2).sum(0) <= rho ** 2
    pad = k + 2
    occp = np.pad(occ, pad)
    mixed = ndimage.maximum_filter(occp, footprint=foot) != \
        ndimage.minimum_filter(occp, footprint=foot)
    idx = np.floor((inside - m.grid.origin_mm) / v + 0.5).astype(int) + pad
    n_mixed = int(mixed[idx[:, 0], idx[:, 1], idx[:, 2]].sum())
    ijk = np.argwhere(occ)
    d = np.linalg.norm(m.grid.origin_mm + ijk * v - pos, axis=1)
    n_vox = int((np.abs(d - r) <= v * math.sqrt(3) / 2).sum())
    return h ** 3 * (n_shell + n_mixed) + v ** 3 * n_vox


@settings(max_examples=30, deadline=None)
@given(voxel=hs.sampled_from([0.1, 0.13, 0.19, 0.22]),
       radius=hs.floats(0.6, 1.6),
       seed=hs.integers(0, 2**31 - 1),
       frac=hs.tuples(*[hs.floats(0.3, 0.7)] * 3),
       axis=hs.tuples(*[hs.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.2),
       normal=hs.tuples(*[hs.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.2))
def test_sampled_force_is_within_the_bound_of_the_exact_voxel_sum(voxel, radius, seed, frac,
                                                                  axis, normal):
    """Bone: a half-space with random blobs cut out, at a random pose."""
    rng = np.random.default_rng(seed)
    n = int(math.ceil(5.0 / voxel))
    g = np.stack(np.mgrid[0:n, 0:n, 0:n], -1) * voxel
    nrm = np.asarray(normal) / np.linalg.norm(normal)
    bone = (g - 2.5) @ nrm < 0.0
    for _ in range(4):                                 # air cells
        c = rng.random(3) * 5.0
        bone &= np.linalg.norm(g - c, axis=-1) > rng.uniform(0.2, 0.8)
    labels = bone.astype(np.uint8)
    burr = FakeBurr(radius_mm=radius, k_low=0.5, k_high=2.0, max_force_n=1e6)
    m, s = _model(labels, voxel, burr)
    assert m.budget.binding
    pos = 1.5 + np.asarray(frac) * 2.0
    _run(m, s, pos, axis)
    dens, _ = m.grid.to_dense()
    # the step reads the samples it says it does: the per-sample reference,
    # up to samples within rounding of a voxel face (the kernel steps along
    # the lattice's rows in voxel units, the reference adds each float32
    # offset in mm: either side may win)
    ref = ref_step(m, dens, labels, pos, np.asarray(axis), False)
    from tests.bonesim.engine.test_haptics import ref_frame

    x = (pos + m.stencil.offsets @ ref_frame(axis).T - m.grid.origin_mm) / voxel + 0.5
    n_amb = int(np.any(np.abs(x - np.rint(x)) < 1e-5, axis=1).sum())
    h3 = m.stencil.spacing_mm ** 3
    assert abs(s.out[O_VOLUME] - ref[3]) <= n_amb * h3 + 1e-12
    if n_amb == 0:
        np.testing.assert_allclose(s.force_n, ref[0], rtol=1e-9, atol=1e-9)
    # against the exact voxel sum, within the documented bound
    ijk = np.argwhere(dens > 0)
    exact = voxel ** 3 * int((np.linalg.norm(m.grid.origin_mm + ijk * voxel - pos, axis=1)
                              <= radius).sum())
    bound = _lattice_bound(m, dens, pos, np.asarray(axis), radius, m.stencil.spacing_mm,
                           voxel)
    assert abs(s.out[O_VOLUME] - exact) <= bound + 1e-12
    p = m.params
    want = multi_gain(exact, p[0], p[1], p[2])
    assert abs(s.out[O_MAG] - want) <= p[1] * bound + 1e-9


# ----------------------------------------------------------------- removal
def _plunge(m, s, pos, axis, n, t0=0.0, drill=True):
    for q in range(n):
        _run(m, s, pos, axis, drill, t=t0 + q * 1e-3)


def test_removal_reaches_every_covered_voxel():
    """Samples 2.5 voxels apart (0.1 mm bone): every voxel whose removal
    cell's centre the burr covers goes, and no other."""
    v = 0.1
    labels = np.zeros((40, 40, 40), np.uint8)
    labels[:, :, :25] = 1
    burr = FakeBurr(radius_mm=1.0, k_low=2.0, k_high=8.0, max_force_n=4.0, r_max=40.0)
    m, s = _model(labels, v, burr)
    assert m.stencil.spacing_mm > 2 * v
    pos = np.array([2.0, 2.0, 2.4])
    _plunge(m, s, pos, (0.0, 0.0, -1.0), 400)
    _plunge(m, s, pos, (0.0, 0.0, -1.0), 50, t0=1.0, drill=False)   # drain the queue
    assert s._budget.pending == 0
    dens, _ = s.grid.to_dense()
    ijk = np.argwhere(labels > 0)
    left = dens[tuple(ijk.T)] > 0
    c = m.budget.cell
    centre = (ijk // c) * c + (c - 1) / 2          # its removal cell's centre [voxels]
    d = np.linalg.norm(centre * v - pos, axis=1)
    assert not left[d <= 1.0 - 1e-9].any(), "an uncut island inside the burr"
    assert left[d > 1.0 + 1e-9].all(), "removed outside the burr's cells"


def _drill_path(m, s, n, t0=0.0):
    out = 0
    for q in range(n):
        pos = np.array([1.5 + 0.004 * q, 2.0, 2.45])
        _run(m, s, pos, (0.2, 0.0, -1.0), True, t=t0 + q * 1e-3)
        out += int(s.out[O_N_REMOVED])
    return out


def _effective(m, s):
    """(n_bricks, 512): each voxel's density less its cell's pending dose
    times its removal factor (0 where empty)."""
    off = np.arange(512)
    cs = m.budget.cell.bit_length() - 1
    n = 8 >> cs
    cq = ((((off >> 6) & 7) >> cs) * n + (((off >> 3) & 7) >> cs)) * n + ((off & 7) >> cs)
    dose = s._budget.dose[:, cq]
    d = s.grid.density.astype(np.float64)
    return np.where(d > 0, d - dose * m.removal[s.grid.label], 0.0)


def test_removal_budget_carries_over_without_losing_a_voxel():
    v = 0.1
    labels = np.zeros((40, 40, 40), np.uint8)
    labels[:, :, :25] = 1
    labels[15:20, 15:25, 18:25] = 2                    # a nerve: injuries too
    burr = FakeBurr(radius_mm=1.0, k_low=2.0, k_high=8.0, max_force_n=4.0, r_max=40.0)
    m, _ = _model(labels, v, burr)
    one = replace(m, budget=replace(m.budget, removal_voxels=(10 ** 9,)))
    tight = replace(m, budget=replace(m.budget, removal_voxels=(1,)))   # one cell a step
    s1, s2 = make_state(one), make_state(tight)
    r1 = _drill_path(one, s1, 300)
    r2 = _drill_path(tight, s2, 300)
    assert s1._budget.pending == 0 and r1 > 0
    assert s2._budget.pending > 0 and r2 < r1           # the budget held removal back
    peak = 0
    q = 0
    while s2._budget.pending:                           # drill off, away from the bone
        _run(tight, s2, (2.0, 2.0, 9.0), (0.0, 0.0, -1.0), False, t=1.0 + q * 1e-3)
        r2 += int(s2.out[O_N_REMOVED])
        peak = max(peak, int(s2.out[O_N_REMOVED]))
        q += 1
    assert peak <= m.budget.cell ** 3                   # one cell per step
    assert r1 == r2 == s1.n_removed == s2.n_removed
    np.testing.assert_array_equal(s1.grid.density > 0, s2.grid.density > 0)
    np.testing.assert_array_equal(s1.removed_by_label, s2.removed_by_label)
    # and the rest agrees too: density less the dose not applied yet
    np.testing.assert_allclose(_effective(m, s1), _effective(m, s2), rtol=0, atol=1e-5)
    for st in (s1, s2):
        ev = st.tissue.read(0)
        assert int((ev["kind"] == events.REMOVED).sum()) == st.n_removed
        assert int(ev["n"][ev["kind"] == events.INJURY].sum()) == st.removed_by_label[2] > 0


def test_budget_step_is_deterministic_and_resets():
    labels = np.zeros((30, 30, 30), np.uint8)
    labels[:, :, :18] = 1
    labels[10:14, :, 12:18] = 2
    burr = FakeBurr(radius_mm=0.8, k_low=2.0, k_high=8.0, max_force_n=4.0, r_max=40.0)
    m, a = _model(labels, 0.13, burr)
    b = make_state(m)
    assert _drill_path(m, a, 200) == _drill_path(m, b, 200) > 0
    np.testing.assert_array_equal(a.grid.density, b.grid.density)
    ea, eb = a.tissue.read(0), b.tissue.read(0)
    for k in ea:
        np.testing.assert_array_equal(ea[k], eb[k])
    assert any(ea["kind"] == events.CONTACT)
    from bonesim.engine.model import reset_state

    reset_state(m, a)
    assert a._budget.pending == 0 and not a._budget.dose.any()
    np.testing.assert_array_equal(a.grid.density, m.grid.density)
    np.testing.assert_array_equal(a._budget.occ, m.budget.occ0)


# ------------------------------------------------ native resolution, replayed
@pytest.mark.slow
def test_a_native_resolution_run_replays_bit_for_bit(tmp_path):
    """The phantom at 0.19 mm, a stretch of the demo path where it drills,
    recorded and replayed."""
    from bonesim.io.burrs import DEFAULT_BURR
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.runtime.simulate import run_trajectory
    from bonesim.session.reader import read_session
    from bonesim.session.replay import verify

    model = load_model("phantom", DEFAULT_BURR, voxel_mm=0.19)
    assert model.budget.binding
    traj = demo_trajectory(load_case("phantom"), DEFAULT_BURR)
    start = int(np.flatnonzero(traj.drill)[0])
    traj = traj.at_times(traj.t_s[start:start + 600])
    path = tmp_path / "native.h5"
    summary = run_trajectory(model, traj, surface=False, record=path)
    assert summary["voxels_removed"] > 0
    report = verify(read_session(path))
    assert report["ok"] and report["identical"], report
    assert report["removals_recorded"] == report["removals_replayed"] \
        == summary["voxels_removed"]


def test_doses_stay_with_the_body_whose_pass_gave_them():
    """A block split at a face through removal cells, the new body moved
    10 mm along x: drilling either removes only that body's voxels (the
    cells on the split face hold both), and steps out of every body's reach
    still flush what is carried."""
    from bonesim.engine.bodies import set_pose, split_body

    v = 0.1
    labels = np.zeros((40, 40, 40), np.uint8)
    labels[:, :, :25] = 1
    burr = FakeBurr(radius_mm=0.8, k_low=2.0, k_high=8.0, max_force_n=4.0, r_max=40.0)
    m, s = _model(labels, v, burr)
    g = np.stack(np.mgrid[0:40, 0:40, 0:25], -1).reshape(-1, 3)
    split_body(s, 0, g[g[:, 0] >= 18].astype(np.int32), 1)     # cells 16..19 hold both
    set_pose(s, 1, (10.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0))
    for q in range(150):                                      # body 0, up to its face
        _run(m, s, (1.5, 2.0, 2.45), (0.0, 0.0, -1.0), True, t=q * 1e-3)
    for q in range(150):                                      # body 1, in the case frame
        _run(m, s, (13.0, 2.0, 2.45), (0.0, 0.0, -1.0), True, t=0.2 + q * 1e-3)
    q = 0
    while s._budget.pending:                                  # nothing within reach
        _run(m, s, (-20.0, -20.0, 20.0), (0.0, 0.0, -1.0), False, t=1.0 + q * 1e-3)
        q += 1
    dens, _ = s.grid.to_dense()
    gone = np.argwhere((labels > 0) & (dens == 0))
    assert len(gone) > 0
    d0 = np.linalg.norm(gone * v - (1.5, 2.0, 2.45), axis=1)
    d1 = np.linalg.norm(gone * v - (3.0, 2.0, 2.45), axis=1)
    tol = m.budget.cell * v * math.sqrt(3)
    of_1 = gone[:, 0] >= 18                                   # the split's body 1
    assert (d0[~of_1] <= 0.8 + tol).all() and (~of_1).sum() > 0   # each body's voxels
    assert (d1[of_1] <= 0.8 + tol).all() and of_1.sum() > 0       # went by its own pass
    assert s.n_removed == len(gone)
    # the voxels of body 1 on the face next to the first hole are still there
    face = np.argwhere((labels > 0) & (np.arange(40)[:, None, None] == 18))
    near = face[np.linalg.norm(face * v - (1.5, 2.0, 2.45), axis=1) < 0.75]
    assert len(near) and (dens[tuple(near.T)] > 0).all()
