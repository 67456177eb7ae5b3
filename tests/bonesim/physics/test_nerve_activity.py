"""The nerve's activity law and its spike trains (bonesim.physics.nerve_activity)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.physics.nerve_activity import (ActivityParams, activity, default_params_path,
                                            load_activity_params, poisson_spikes)

P = load_activity_params()


def test_shipped_parameters_are_the_documented_defaults():
    assert P == ActivityParams()


def test_activity_is_monotone_in_distance_and_lower_without_force_or_drill():
    d = np.linspace(-2.0, 15.0, 3401)
    for force in (0.0, 0.5, 2.0, 5.0):
        for drill in (True, False):
            r = activity(d, force, drill, P)
            assert np.all(np.diff(r) <= 0.0)              # never rises moving away
            assert r[-1] == pytest.approx(P.baseline_hz, abs=1e-6)
            assert np.all((r >= P.baseline_hz) & (r <= P.max_hz))
    for dd in (0.0, 0.5, 1.0, 2.0):
        assert activity(dd, 0.0, True, P) < activity(dd, 1.0, True, P)
        assert activity(dd, 1.0, False, P) < activity(dd, 1.0, True, P)
        # force saturates
        assert activity(dd, P.force_sat_n, True, P) == activity(dd, 10 * P.force_sat_n,
                                                                True, P)
    # the law by hand: at 1 mm, 1 N, drill on
    h = P.force_floor + (1 - P.force_floor) * 1.0 / P.force_sat_n
    assert activity(1.0, 1.0, True, P) == pytest.approx(
        P.baseline_hz + h * P.near_gain_hz * math.exp(-1.0 / P.length_mm))
    # a steep rise in the last 2 mm, a burst on contact, the ceiling holds
    assert activity(2.0, 2.0, True, P) < 3 * P.baseline_hz
    assert activity(0.5, 2.0, True, P) > 10 * P.baseline_hz
    assert activity(P.contact_mm, 2.0, True, P) \
        - activity(P.contact_mm + 1e-9, 2.0, True, P) == pytest.approx(P.contact_hz, rel=1e-6)
    loud = dataclasses.replace(P, contact_hz=1e4)
    assert activity(0.0, 2.0, True, loud) == loud.max_hz
    # NaN force counts as none; arrays broadcast
    assert activity(0.5, math.nan, True, P) == activity(0.5, 0.0, True, P)
    assert activity(np.zeros((4, 2)), np.ones((4, 1)), True, P).shape == (4, 2)


BAD_PARAMS = [
    ("near_gain_hz = 150.0", "", "missing required key(s) 'near_gain_hz'"),
    ("max_hz = 400.0", "max_hz = 400.0\nmin_hz = 1.0", "unknown key(s) 'min_hz'"),
    ("drill_off = 0.1", "drill_off = 1.5", "'drill_off' must be <= 1.0"),
    ("length_mm = 0.66", "length_mm = 0.0", "'length_mm' must be a finite number > 0"),
    ("baseline_hz = 4.0", "baseline_hz = 500.0", "'baseline_hz' (500.0) exceeds"),
    ("contact_hz = 200.0", 'contact_hz = "a lot"', "'contact_hz' must be a number"),
]


@pytest.mark.parametrize("old,new,fragment", BAD_PARAMS)
def test_bad_parameter_files_name_file_and_key(tmp_path, old, new, fragment):
    text = default_params_path().read_text()
    assert old in text
    path = tmp_path / "monitor.toml"
    path.write_text(text.replace(old, new))
    with pytest.raises(BonesimError) as e:
        load_activity_params(path)
    assert fragment in str(e.value) and str(path) in str(e.value)
    assert e.value.field == "activity"


def test_poisson_spikes_counts_times_and_seed():
    edges = np.linspace(0.0, 20.0, 4001)                      # 5 ms intervals
    rates = np.zeros((4000, 3))
    rates[:, 0] = 5.0
    rates[:2000, 1] = 100.0                                   # first 10 s only
    t, which = poisson_spikes(np.random.default_rng(1), edges, rates)
    assert np.all(np.diff(t) >= 0) and t.min() >= 0.0 and t.max() <= 20.0
    n0, n1, n2 = (np.count_nonzero(which == c) for c in range(3))
    assert n2 == 0
    assert abs(n0 - 100) < 5 * math.sqrt(100) and abs(n1 - 1000) < 5 * math.sqrt(1000)
    assert t[which == 1].max() <= 10.0
    # a Poisson process: exponential intervals (coefficient of variation ~ 1)
    isi = np.diff(t[which == 1])
    assert 0.85 < isi.std() / isi.mean() < 1.15
    t2, w2 = poisson_spikes(np.random.default_rng(1), edges, rates)
    assert np.array_equal(t, t2) and np.array_equal(which, w2)
    t3, _ = poisson_spikes(np.random.default_rng(2), edges, rates)
    assert not np.array_equal(t, t3)
    e, w = poisson_spikes(np.random.default_rng(1), [0.0, 1.0], [[0.0]])
    assert len(e) == 0 and w.dtype == np.uint8
