"""The volume-sampled haptic step against a numpy reference and analytic truths."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from bonesim.engine import events
from bonesim.engine.device_caps import DeviceCaps
from bonesim.engine.haptics import (O_MAG, O_N_IMMERSED, O_TX, O_TZ, O_VOLUME, make_stencil,
                                    multi_gain)
from bonesim.engine.model import Sample, make_model, make_state, step

from tests.bonesim.fakes import BONE, MATERIALS, NERVE, FakeBurr, block_model


# ---------------------------------------------------------------- reference
def ref_frame(axis):
    """Tool-to-case rotation, written independently of the kernel."""
    d = np.asarray(axis, float) / np.linalg.norm(axis)
    e = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(e, d)
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    return np.column_stack([u, v, d])


def ref_step(model, density, labels, pos, axis, drill, direction=1, speed_factor=1.0,
             dt=1e-3):
    """Slow, obvious numpy version of one step on dense arrays.

    Returns the force, tangential force, magnitude, immersed volume and the
    new density array.
    """
    st, p = model.stencil, model.params
    R = ref_frame(axis)
    world = pos + st.offsets @ R.T
    idx = np.floor((world - model.grid.origin_mm) / model.spacing_mm + 0.5).astype(int)
    inb = np.all((idx >= 0) & (idx < np.array(density.shape)), axis=1)
    imm = np.zeros(len(idx), bool)
    ii = idx[inb]
    imm[inb] = density[ii[:, 0], ii[:, 1], ii[:, 2]] > 0
    lab = np.zeros(len(idx), int)
    lab[imm] = labels[idx[imm, 0], idx[imm, 1], idx[imm, 2]]
    w = model.stiff[lab] * imm
    volume = w.sum() * st.sample_volume_mm3
    k_low, k_high, v_t = p[0], p[1], p[2]
    mag = k_low * volume if volume <= v_t else k_low * v_t + k_high * (volume - v_t)
    mag = min(mag, model.max_force_n)
    direction_sum = -(R @ (w[:, None] * st.unit).sum(axis=0))
    n = np.linalg.norm(direction_sum)
    f = direction_sum / n * mag if n > 1e-9 * (imm.sum() + 1) else np.zeros(3)
    tan = np.zeros(3)
    if drill:
        tan = p[3] * st.sample_volume_mm3 * direction * speed_factor * (
            R @ (w[:, None] * st.tang).sum(axis=0))
    total = f + tan
    if np.linalg.norm(total) > model.max_force_n:
        total *= model.max_force_n / np.linalg.norm(total)
    new = density.astype(np.float64).copy()
    if drill:
        rate = st.lat * model.removal[lab] * imm
        amount = np.zeros(density.shape)
        for s in np.flatnonzero(rate > 0):
            amount[tuple(idx[s])] += rate[s]
        amount *= mag * speed_factor * dt * st.sample_volume_mm3 / model.spacing_mm ** 3
        new = new - amount
        new[new <= 0] = 0.0
    return total, tan, mag, volume, new.astype(np.float32)


def run(model, state, pos, axis, drill=True, direction=1, t=None, speed=None):
    t = state.n_steps * 1e-3 if t is None else t
    speed = model.burr.default_speed_rpm if speed is None else speed
    return step(model, state, Sample(t, np.asarray(pos, float), np.asarray(axis, float),
                                     drill, speed, direction)).copy()


# ------------------------------------------------------------------ tests
@settings(max_examples=25, deadline=None)
@given(seed=hs.integers(0, 2**31 - 1),
       pos=hs.tuples(*[hs.floats(2.0, 8.0)] * 3),
       axis=hs.tuples(*[hs.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.2),
       drill=hs.booleans(), direction=hs.sampled_from([-1, 1]))
def test_kernel_matches_numpy_reference(seed, pos, axis, drill, direction):
    rng = np.random.default_rng(seed)
    labels = (rng.random((20, 20, 20)) < 0.6).astype(np.uint8)
    labels[rng.random(labels.shape) < 0.1] = 2
    burr = FakeBurr(radius_mm=1.5, k_low=0.5, k_high=2.0, max_force_n=50.0)
    m = make_model(labels, 0.5, [BONE, NERVE], burr, materials=MATERIALS)
    s = make_state(m)
    dens0, _ = m.grid.to_dense()
    total, tan, mag, vol, new = ref_step(m, dens0, labels, np.array(pos), np.array(axis),
                                         drill, direction)
    got = run(m, s, pos, axis, drill, direction)
    assert s.out[O_VOLUME] == pytest.approx(vol, rel=1e-12, abs=1e-12)
    assert s.out[O_MAG] == pytest.approx(mag, rel=1e-9, abs=1e-12)
    np.testing.assert_allclose(got, total, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(s.out[O_TX:O_TZ + 1], tan, rtol=1e-9, atol=1e-12)
    dens1, _ = s.grid.to_dense()
    np.testing.assert_allclose(dens1, new, rtol=0, atol=2e-7)
    assert s.n_removed == int(((dens0 > 0) & (new == 0)).sum())


def test_total_force_matches_reference_with_tangential():
    m, s = block_model(burr=FakeBurr(k_tan=0.5))
    dens, labels = m.grid.to_dense()
    total, tan, *_ = ref_step(m, dens, labels, np.array([10.0, 10.0, 10.0]),
                              np.array([1.0, 0, 0]), True)
    got = run(m, s, (10.0, 10.0, 10.0), (1.0, 0, 0))
    np.testing.assert_allclose(got, total, rtol=1e-9, atol=1e-12)
    assert np.linalg.norm(tan) > 0


def test_sphere_plunge_removes_ball_volume():
    """Held inside solid bone, the burr carves out its own ball, voxelized."""
    r, h = 2.0, 0.5
    burr = FakeBurr(radius_mm=r, k_low=1e4, k_high=1e4, max_force_n=4.0)
    labels = np.ones((24, 24, 24), np.uint8)
    m = make_model(labels, h, [BONE], burr, materials=MATERIALS)
    s = make_state(m)
    centre = np.array([6.1, 5.9, 6.05])
    for n in range(4000):
        run(m, s, centre, (0.3, 0.2, 0.9), t=n * 1e-3)
        if n > 50 and s.out[O_N_IMMERSED] == 0:
            break
    assert s.out[O_N_IMMERSED] == 0, "burr should have cleared its whole volume"
    removed = events.removals(s.tissue.read(0))["ijk"]
    # exact discrete truth: the voxels holding at least one sample
    world = centre + m.stencil.offsets @ ref_frame((0.3, 0.2, 0.9)).T
    expect = np.unique(np.floor(world / h + 0.5).astype(int), axis=0)
    assert sorted(map(tuple, removed)) == sorted(map(tuple, expect))
    # analytic truth: 4/3 pi r^3 within the voxelization tolerance (half a
    # voxel diagonal either way)
    vol = len(removed) * h ** 3
    slack = math.sqrt(3) / 2 * h
    assert 4 / 3 * math.pi * (r - slack) ** 3 < vol < 4 / 3 * math.pi * (r + slack) ** 3
    assert vol == pytest.approx(4 / 3 * math.pi * r ** 3, rel=0.4)


def test_equator_removes_more_than_pole():
    """Side contact (equator) removes more bone per step than tip contact (pole)."""
    burr = FakeBurr(radius_mm=1.5, r_max=4.0, falloff=2.0)
    results = {}
    for name, axis in (("equator", (1.0, 0, 0)), ("pole", (0, 0, -1.0))):
        m, s = block_model(burr=burr)
        top = 20 * 0.5 - 0.25                       # top face of the block [mm]
        pos = np.array([10.0, 10.0, top + 1.0])      # 0.5 mm deep
        before = s.grid.density.sum(dtype=np.float64)
        run(m, s, pos, axis)
        results[name] = (before - s.grid.density.sum(dtype=np.float64), s.out[O_MAG])
        # the same amount follows from the falloff law over the immersed samples
        R = ref_frame(axis)
        world = pos + m.stencil.offsets @ R.T
        imm = np.floor(world[:, 2] / 0.5 + 0.5) < 20
        expect = (m.stencil.lat[imm].sum() * s.out[O_MAG] * 1e-3
                  * m.stencil.sample_volume_mm3 / 0.5 ** 3)
        assert results[name][0] == pytest.approx(expect, rel=1e-5)
    assert results["equator"][1] == pytest.approx(results["pole"][1])
    assert results["equator"][0] > 1.5 * results["pole"][0]


def test_falloff_zero_removes_evenly():
    burr = FakeBurr(radius_mm=1.5, r_max=3.0, falloff=0.0)
    st = make_stencil(1.5, 0.25, burr.r_max, burr.falloff)
    assert np.all(st.lat == 3.0)


def test_force_points_out_of_bone_and_follows_multi_gain():
    burr = FakeBurr(radius_mm=1.5, k_low=0.5, k_high=3.0, n_t_fraction=0.15,
                    max_force_n=1e3)
    m, _ = block_model(burr=burr)
    top = 20 * 0.5 - 0.25
    v_t = m.params[2]
    vols, mags = [], []
    for depth in np.linspace(0.2, 1.5, 27):
        s = make_state(m)
        f = run(m, s, (10.0, 10.0, top + 1.5 - depth), (0, 0, -1.0), drill=False)
        vol = s.out[O_VOLUME]
        expect = 0.5 * vol if vol <= v_t else 0.5 * v_t + 3.0 * (vol - v_t)
        assert np.linalg.norm(f) == pytest.approx(expect, rel=1e-9)
        assert f[2] / np.linalg.norm(f) > 0.999          # straight out of the top face
        vols.append(vol)
        mags.append(np.linalg.norm(f))
    assert np.all(np.diff(vols) >= 0) and vols[0] < v_t < vols[-1]
    # slope below the threshold is K_low, above it K_high
    pts = dict(zip(vols, mags))                           # one point per distinct volume
    lo = sorted((v, f) for v, f in pts.items() if 0 < v < v_t)
    hi = sorted((v, f) for v, f in pts.items() if v > v_t)
    assert len(lo) >= 2 and len(hi) >= 2
    assert (lo[-1][1] - lo[0][1]) / (lo[-1][0] - lo[0][0]) == pytest.approx(0.5)
    assert (hi[-1][1] - hi[0][1]) / (hi[-1][0] - hi[0][0]) == pytest.approx(3.0)
    assert multi_gain(v_t, 0.5, 3.0, v_t) == pytest.approx(0.5 * v_t)


def test_force_direction_side_wall():
    """Pressing into a wall facing +x pushes the tool toward +x."""
    labels = np.zeros((40, 40, 40), np.uint8)
    labels[:20] = 1
    m, s = block_model(labels=labels)
    f = run(m, s, (9.75 + 1.0, 10.0, 10.0), (0, 0, -1.0), drill=False)
    assert f[0] / np.linalg.norm(f) > 0.999


def test_force_clamped_to_device_and_burr_limits():
    burr = FakeBurr(k_low=100.0, k_high=100.0, max_force_n=4.0)
    m, s = block_model(burr=burr, device=DeviceCaps("weak", 1.2, (100, 100, 100), 1.0))
    f = run(m, s, (10.0, 10.0, 9.75), (0, 0, -1.0), drill=False)
    assert np.linalg.norm(f) == pytest.approx(1.2)
    m2, s2 = block_model(burr=burr)
    assert np.linalg.norm(run(m2, s2, (10.0, 10.0, 9.75), (0, 0, -1.0), drill=True)) \
        == pytest.approx(4.0)


def test_tangential_force_flips_with_direction_and_needs_drill():
    burr = FakeBurr(k_tan=0.3)
    tans = {}
    for d in (1, -1):
        m, s = block_model(burr=burr)
        run(m, s, (10.0, 10.0, 10.5), (1.0, 0, 0), direction=d)
        tans[d] = s.out[O_TX:O_TZ + 1].copy()
    assert np.linalg.norm(tans[1]) > 1e-3
    np.testing.assert_allclose(tans[1], -tans[-1], rtol=1e-12)
    assert abs(np.dot(tans[1], (1.0, 0, 0))) < 1e-9 * np.linalg.norm(tans[1])  # ⟂ axis
    m, s = block_model(burr=burr)
    run(m, s, (10.0, 10.0, 10.5), (1.0, 0, 0), drill=False)
    assert np.all(s.out[O_TX:O_TZ + 1] == 0)


def test_removal_scales_with_speed_and_stops_when_drill_off():
    m, s = block_model()
    run(m, s, (10.0, 10.0, 10.5), (1.0, 0, 0), drill=False)
    assert s.grid.density.sum() == m.grid.density.sum()
    lost = {}
    for speed in (30000.0, 60000.0):
        m, s = block_model()
        before = float(s.grid.density.sum(dtype=np.float64))
        run(m, s, (10.0, 10.0, 10.5), (1.0, 0, 0), speed=speed)
        lost[speed] = before - float(s.grid.density.sum(dtype=np.float64))
    assert lost[60000.0] == pytest.approx(2 * lost[30000.0], rel=1e-4)


def test_deterministic_bit_identical():
    def go():
        m, s = block_model(burr=FakeBurr(k_low=50, k_high=50))
        rng = np.random.default_rng(7)
        for n in range(300):
            pos = np.array([10.0, 10.0, 10.0]) + rng.normal(0, 0.3, 3)
            run(m, s, pos, (0.1, 0.2, -1.0), t=n * 1e-3)
        return s
    a, b = go(), go()
    assert a.n_removed > 0
    assert a.grid.density.tobytes() == b.grid.density.tobytes()
    ra, rb = events.removals(a.tissue.read(0)), events.removals(b.tissue.read(0))
    assert all(np.array_equal(ra[k], rb[k]) for k in ra)


def test_injury_events_on_contact_and_removal():
    labels = np.zeros((40, 40, 40), np.uint8)
    labels[:, :, :20] = 1
    labels[:, :, 17:20] = 2                              # nerve sheet at the top
    burr = FakeBurr(k_low=1e3, k_high=1e3)
    m, s = block_model(labels=labels, structures=[BONE, NERVE], burr=burr)
    run(m, s, (10.0, 10.0, 10.5), (0, 0, -1.0), drill=False)
    assert len(events.injuries(s.tissue.read(0))["t_s"]) == 0                         # no drill, no injury
    for n in range(1, 400):
        run(m, s, (10.0, 10.0, 10.4), (0, 0, -1.0), t=n * 1e-3)
    inj = events.injuries(s.tissue.read(0))
    assert inj["kind"][0] == 0 and inj["label"][0] == 2 and inj["voxels"][0] == 0
    assert (inj["kind"] == 0).sum() == 1                 # one contact onset
    lost = inj["voxels"][inj["kind"] == 1].sum()
    assert lost > 0 and lost == s.removed_by_label[2]
    assert s.removed_by_label[1] == 0


def test_removed_ring_records_time_and_label():
    m, s = block_model(burr=FakeBurr(k_low=1e3, k_high=1e3))
    for n in range(200):
        run(m, s, (10.0, 10.0, 10.0), (0, 0, -1.0), t=0.5 + n * 1e-3)
    rec = events.removals(s.tissue.read(0))
    assert len(rec["t_s"]) == s.n_removed > 0
    assert np.all(np.diff(rec["t_s"]) >= 0) and rec["t_s"][0] >= 0.5
    assert np.all(rec["label"] == 1)
    dens, _ = s.grid.to_dense()
    assert np.all(dens[tuple(rec["ijk"].T)] == 0)


def test_time_must_not_go_backwards():
    m, s = block_model()
    run(m, s, (10.0, 10.0, 12.0), (0, 0, -1.0), t=1.0)
    with pytest.raises(ValueError, match="precedes"):
        run(m, s, (10.0, 10.0, 12.0), (0, 0, -1.0), t=0.5)
    with pytest.raises(ValueError, match="axis"):
        run(m, s, (10.0, 10.0, 12.0), (0, 0, 0.0), t=2.0)
