"""Vibration in the force signal of scripted runs through the real haptic step.

The tool is scripted from the air into a bone block with the drill running;
the device force (contact force + vibration, as the haptic loop sends it) is
recorded at 1 kHz and its spectrum compared free-running vs in contact, and
cutting vs diamond."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.io.burrs import load_burr
from bonesim.engine.haptics import O_MAG, O_N_IMMERSED
from bonesim.engine.model import Sample, make_model, make_state, step
from bonesim.physics.vibration import Vibration, contact_components, free_components

from tests.bonesim.fakes import BONE, MATERIALS

RATE = 1000.0
N = 2048                     # samples per phase (about 2 s)


def _run(burr_name):
    burr = load_burr(burr_name)
    labels = np.zeros((60, 60, 40), np.uint8)
    labels[:, :, :20] = 1
    model = make_model(labels, 0.5, [BONE], burr, materials=MATERIALS)
    state = make_state(model)
    vib = Vibration(burr, RATE)
    top = 20 * 0.5 - 0.25
    out, contact = [], []
    for q in range(2 * N):
        # first N samples hover 2 mm above the bone, then rest 0.3 mm into it,
        # sliding slowly so there is bone to drill
        depth = -2.0 if q < N else 0.3
        pos = np.array([8.0 + 0.004 * q, 15.0, top + burr.radius_mm - depth])
        f = step(model, state, Sample(q / RATE, pos, np.array([0.0, 0.0, -1.0]), True,
                                      burr.default_speed_rpm, 1)).copy()
        touching = state.out[O_N_IMMERSED] > 0
        f += vib.sample(q / RATE, state.axis, True, touching, state.out[O_MAG],
                        burr.default_speed_rpm)
        out.append(f)
        contact.append(touching)
    return burr, np.array(out), np.array(contact)


def _peak_hz(signal):
    """Frequency of the strongest spectral line of a (n, 3) force signal."""
    x = signal - signal.mean(axis=0)
    spec = np.abs(np.fft.rfft(x * np.hanning(len(x))[:, None], axis=0)).sum(axis=1)
    freqs = np.fft.rfftfreq(len(x), 1.0 / RATE)
    spec[freqs < 20.0] = 0.0                   # ignore the slow contact force itself
    return freqs[np.argmax(spec)], spec, freqs


def _strongest(components):
    rendered = [(f, a) for f, a in components if f < RATE / 2 * 0.95]
    return max(rendered, key=lambda c: c[1])[0]


@pytest.mark.parametrize("name", ["cutting-4mm", "diamond-4mm"])
def test_free_running_and_contact_spectra(name):
    burr, force, contact = _run(name)
    assert not contact[:N].any() and contact[N + 100:].mean() > 0.9
    free_peak, _, _ = _peak_hz(force[:N])
    contact_peak, spec, freqs = _peak_hz(force[N:])
    df = RATE / N * 2
    assert free_peak == pytest.approx(_strongest(free_components(burr)), abs=df)
    assert contact_peak == pytest.approx(_strongest(contact_components(burr)), abs=df)
    assert free_peak != pytest.approx(contact_peak, abs=df)
    # nothing at the aliases of the recorded kHz peaks
    for f in (burr.vib_contact_hz, burr.vib_free_hz):
        alias = abs(f - RATE * round(f / RATE))
        near = np.abs(freqs - alias) < df
        assert spec[near].max() < 0.05 * spec.max()


def test_cutting_and_diamond_feel_different():
    _, cut, _ = _run("cutting-4mm")
    _, dia, _ = _run("diamond-4mm")
    assert _peak_hz(cut[N:])[0] != pytest.approx(_peak_hz(dia[N:])[0], abs=RATE / N * 2)
