"""Haptic-rate drill vibration, checked by the spectrum of scripted runs."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.io.burrs import load_burr
from bonesim.physics.vibration import (NYQUIST_FRACTION, RAMP_S, Vibration, free_components,
                                       vibration_signal)

RATE = 1000.0
SECONDS = 2.0
N = int(RATE * SECONDS)
T = np.arange(N) / RATE
CUTTING = load_burr("cutting-5mm")
DIAMOND = load_burr("diamond-3mm")


def spectrum(x, rate=RATE):
    """Magnitude spectrum of one force component (Hann window)."""
    mag = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return np.fft.rfftfreq(len(x), 1.0 / rate), mag


def peaks(x, count, rate=RATE):
    """The ``count`` strongest local maxima [Hz], strongest first."""
    f, m = spectrum(x, rate)
    is_peak = np.r_[False, (m[1:-1] > m[:-2]) & (m[1:-1] >= m[2:]), False]
    idx = np.flatnonzero(is_peak)
    idx = idx[np.argsort(m[idx])[::-1]][:count]
    return f[idx]


def run(burr, contact, force=1.0, drill=True, speed=None, rate=RATE, n=N, axis=(0, 0, 1)):
    speed = burr.default_speed_rpm if speed is None else speed
    return vibration_signal(burr, np.arange(n) / rate, contact, force, drill, speed,
                            rate, axis=axis)


def near(found, expected, tol):
    return all(np.min(np.abs(np.asarray(found) - e)) <= tol for e in expected)


BIN = 1.0 / SECONDS      # FFT bin width [Hz]


@pytest.mark.parametrize("burr", [CUTTING, DIAMOND], ids=["cutting", "diamond"])
def test_contact_moves_peaks_to_contact_subharmonics(burr):
    limit = NYQUIST_FRACTION * RATE / 2
    contact = [f for f, _ in burr.vib_harmonics if f < limit]
    free = [f for f, _ in free_components(burr) if f < limit]
    # free running: subharmonics of the free peak (1/3, 1/4; 1/2 is above Nyquist)
    assert near(free, [burr.vib_free_hz / 3, burr.vib_free_hz / 4], 1e-9)
    got_free = peaks(run(burr, False)[:, 0], len(free))
    got_contact = peaks(run(burr, True)[:, 0], len(contact))
    assert near(got_free, free, BIN) and near(free, got_free, BIN)
    assert near(got_contact, contact, BIN) and near(contact, got_contact, BIN)
    # the strongest contact peak is the 1/2 subharmonic of the contact peak
    assert abs(got_contact[0] - burr.vib_contact_hz / 2) <= BIN
    # and none of the free peaks survive in contact
    assert not near(got_contact[:1], free, 2 * BIN)


def test_cutting_and_diamond_differ():
    for contact in (False, True):
        a = peaks(run(CUTTING, contact)[:, 0], 1)[0]
        b = peaks(run(DIAMOND, contact)[:, 0], 1)[0]
        assert abs(a - b) > 10 * BIN
    # diamond runs smoother than cutting at the same force
    assert np.std(run(DIAMOND, True)) < np.std(run(CUTTING, True))


@pytest.mark.parametrize("burr", [CUTTING, DIAMOND], ids=["cutting", "diamond"])
def test_amplitude_grows_with_force(burr):
    rms = [np.sqrt(np.mean(np.sum(run(burr, True, force=f)[100:] ** 2, axis=1)))
           for f in (0.0, 1.0, 3.0)]
    assert rms[0] > 0 and rms[0] < rms[1] < rms[2]
    # linear law: A = vib_amp_n + vib_amp_per_n * |F|
    expect = [(burr.vib_amp_n + burr.vib_amp_per_n * f) for f in (0.0, 1.0, 3.0)]
    assert np.allclose(np.array(rms) / rms[0], np.array(expect) / expect[0], rtol=1e-6)
    # force sign does not matter
    assert np.array_equal(run(burr, True, force=-2.0), run(burr, True, force=2.0))


@pytest.mark.parametrize("burr", [CUTTING, DIAMOND], ids=["cutting", "diamond"])
@pytest.mark.parametrize("speed_factor", [1.0, 4.0 / 3.0])
def test_no_content_above_nyquist_and_no_aliased_peaks(burr, speed_factor):
    speed = burr.default_speed_rpm * speed_factor
    limit = NYQUIST_FRACTION * RATE / 2
    for contact, main in ((False, burr.vib_free_hz), (True, burr.vib_contact_hz)):
        x = run(burr, contact, force=2.0, speed=speed)[:, 0]
        f, m = spectrum(x)
        comps = [c * speed_factor for c, _ in
                 (burr.vib_harmonics if contact else free_components(burr))]
        rendered = [c for c in comps if c < limit]
        assert rendered, "something must be rendered"
        # all energy sits at the rendered components (within a few bins) ...
        mask = np.zeros_like(m, bool)
        for c in rendered:
            mask |= np.abs(f - c) <= 3 * BIN
        energy = m ** 2
        assert energy[~mask].sum() < 1e-3 * energy.sum()
        # ... so nothing at the alias of the main peak, nor of any skipped one
        aliases = [abs(main * speed_factor - RATE * round(main * speed_factor / RATE))]
        aliases += [abs(c - RATE * round(c / RATE)) for c in comps if c >= limit]
        for a in aliases:
            if all(abs(a - c) > 5 * BIN for c in rendered):
                near_a = np.abs(f - a) <= 2 * BIN
                assert energy[near_a].sum() < 1e-4 * energy.sum()


def test_half_subharmonic_rendered_at_a_faster_loop():
    v = Vibration(CUTTING, 1500.0)
    assert (CUTTING.vib_free_hz / 2, 0.5) in [(round(f, 6), a) for f, a in v.free]
    assert not v.skipped
    assert Vibration(CUTTING, 1000.0).skipped == [("free", 515.0, 0.5)]


def test_zero_with_drill_off_or_stopped():
    assert not run(CUTTING, True, force=3.0, drill=False).any()
    assert not run(CUTTING, False, drill=False).any()
    assert not run(DIAMOND, True, speed=0.0).any()
    # switching off: silent once the envelope has ramped down
    drill = T < 1.0
    x = vibration_signal(CUTTING, T, True, 1.0, drill, CUTTING.default_speed_rpm, RATE)
    off = int(1.0 * RATE + RAMP_S * RATE) + 1
    assert np.abs(x[:1000]).max() > 0 and not x[off:].any()


def test_switching_sets_ramps_without_a_jolt():
    contact = (T >= 0.5) & (T < 1.5)
    x = vibration_signal(CUTTING, T, contact, 1.0, True, CUTTING.default_speed_rpm, RATE)
    amp = CUTTING.vib_amp_n + CUTTING.vib_amp_per_n
    # the largest sample-to-sample change bounded by the fastest component's slope
    fmax = max(f for f, _ in CUTTING.vib_harmonics)
    total = sum(a for _, a in CUTTING.vib_harmonics)
    bound = amp * total * (2 * np.pi * fmax / RATE + 1.0 / (RAMP_S * RATE))
    assert np.linalg.norm(np.diff(x, axis=0), axis=1).max() <= bound


def test_perpendicular_to_the_axis_and_deterministic():
    rng = np.random.default_rng(3)
    for _ in range(5):
        axis = rng.normal(size=3)
        x = run(CUTTING, True, axis=axis, n=500)
        assert np.abs(x @ (axis / np.linalg.norm(axis))).max() < 1e-12
        assert np.abs(x).max() > 0
    a = vibration_signal(DIAMOND, T, True, 1.0, True, 40000.0, RATE, seed=7)
    b = vibration_signal(DIAMOND, T, True, 1.0, True, 40000.0, RATE, seed=7)
    c = vibration_signal(DIAMOND, T, True, 1.0, True, 40000.0, RATE, seed=8)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_sample_matches_series_and_reset():
    rng = np.random.default_rng(0)
    n = 400
    t = np.arange(n) / RATE
    contact = rng.random(n) < 0.5
    force = rng.random(n) * 3
    drill = rng.random(n) < 0.9
    speed = rng.uniform(0, 80000, n)
    axis = np.array([0.2, -0.5, 1.0])
    ref = vibration_signal(CUTTING, t, contact, force, drill, speed, RATE, axis=axis)
    v = Vibration(CUTTING, RATE)
    for _ in range(2):
        got = np.array([v.sample(t[q], axis, drill[q], contact[q], force[q], speed[q]).copy()
                        for q in range(n)])
        assert np.array_equal(got, ref)
        v.reset()


def test_bad_inputs():
    with pytest.raises(ValueError):
        Vibration(CUTTING, 0.0)
    with pytest.raises(ValueError):
        Vibration(CUTTING).sample(0.0, (0, 0, 0), True, True, 1.0, 60000.0)
    with pytest.raises(ValueError):
        vibration_signal(CUTTING, T[:3], True, [1.0, np.nan, 1.0], True, 60000.0)


def test_free_components_derivation():
    from types import SimpleNamespace

    # subharmonics (as rounded in a file) snap to the free peak's; others scale
    b = SimpleNamespace(vib_free_hz=1000.0, vib_contact_hz=900.0,
                        vib_harmonics=((450.0, 0.5), (300.1, 0.3), (170.0, 0.2)))
    got = free_components(b)
    assert got[0] == (500.0, 0.5) and got[1] == (1000.0 / 3, 0.3)
    assert got[2] == pytest.approx((170.0 * 1000.0 / 900.0, 0.2))
