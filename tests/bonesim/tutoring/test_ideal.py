"""The ideal follower (bonesim/tutoring/ideal.py): its kernel against an
obviously-correct loop, the law's target, the damping criterion, the
property that a handicap (input delay, join ramp) never makes a follower of
the law better than the ideal, and :func:`compare` scoring the same instants."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bonesim.errors import BonesimError
from bonesim.tutoring.ideal import (IdealParams, InstructorLog, TickLog, best_ideal, compare,
                                    error_summary, ideal_follow, ideal_params, law_target,
                                    tracking_vs_ideal)


def _lin(t, v, q):
    """Obviously-correct linear interpolation, held past the ends."""
    if q <= t[0]:
        return v[0].copy()
    if q >= t[-1]:
        return v[-1].copy()
    i = max(j for j in range(len(t)) if t[j] <= q)
    w = (q - t[i]) / (t[i + 1] - t[i])
    return (1 - w) * v[i] + w * v[i + 1]


def _reference(t, p, f, kp, fmax, prm, at, ticks, delay=0.0, ramp=0.0, k=0.0):
    """Obviously-correct follower: plain loops, numpy force law, the force
    held from tick to tick, positions taken at the report instants."""
    x = _lin(t, p, ticks[0] - delay)
    rest, v = x.copy(), np.zeros(3)
    out, j, now = [], 0, ticks[0]

    def move(dt):
        nonlocal x, v
        if dt <= 0:
            return
        n = int(math.ceil(dt / prm.max_substep_s))
        h = dt / n
        for _ in range(n):
            v = v + h * (1000.0 / prm.mass_kg) * (F - prm.damping_ns_per_mm * v - k * (x - rest))
            x = x + h * v

    for i, tk in enumerate(ticks):
        g = 1.0 if ramp == 0 else min(1.0, (tk - ticks[0]) / ramp)
        F = g * (kp * (_lin(t, p, tk - delay) - x) + _lin(t, f, tk - delay))
        if np.linalg.norm(F) > fmax:
            F = F * fmax / np.linalg.norm(F)
        end = ticks[i + 1] if i + 1 < len(ticks) else math.inf
        while j < len(at) and at[j] < end:
            move(at[j] - now)
            now = at[j]
            out.append(x.copy())
            j += 1
        if j == len(at):
            break
        move(end - now)
        now = end
    return np.array(out)


def _motion(seed, seconds=1.0):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.0005, 0.003, int(seconds / 0.0017)))
    p = np.cumsum(rng.normal(0, 0.3, (len(t), 3)), axis=0)
    f = rng.normal(0, 1.0, (len(t), 3))
    return t, p, f


def test_ideal_follower_matches_the_reference():
    t, p, f = _motion(1, 0.3)
    prm = IdealParams(0.15, 0.004, 0.0005)
    ticks = t[0] + np.arange(int((t[-1] - t[0]) * 1000) + 1) / 1000.0
    got = ideal_follow(t, p, f, 0.2, 1.5, prm)
    np.testing.assert_allclose(got, _reference(t, p, f, 0.2, 1.5, prm, ticks, ticks),
                               atol=1e-9)
    # report instants between ticks, the servo's own ticks, every handicap
    rng = np.random.default_rng(2)
    at = np.sort(rng.uniform(t[0] + 0.01, t[-1], 80))
    own = at[0] - 0.0003 + np.cumsum(rng.uniform(0.0005, 0.004, 150))
    own = np.r_[at[0] - 0.0003, own]
    got = ideal_follow(t, p, f, 0.2, 1.5, prm, at_s=at, delay_s=0.01, ticks_s=own,
                       ramp_s=0.05, stiffness_n_per_mm=0.02)
    want = _reference(t, p, f, 0.2, 1.5, prm, at, own, delay=0.01, ramp=0.05, k=0.02)
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_a_still_instructor_pressing_holds_the_follower_on_the_laws_target():
    prm = IdealParams(0.15, 0.004, 0.0005)
    t = np.arange(0, 3.0, 0.001)
    p = np.zeros((len(t), 3))
    f = np.tile([0.5, 0.0, 0.0], (len(t), 1))
    x = ideal_follow(t, p, f, 0.2, 3.3, prm)
    assert np.linalg.norm(x[-1] - p[-1]) == pytest.approx(0.5 / 0.2, rel=1e-3)
    target = law_target(t, p, f, t[-1:], 0.2)
    np.testing.assert_allclose(target, [[2.5, 0.0, 0.0]])
    assert np.linalg.norm(x[-1] - target[0]) < 1e-3


def test_inputs_are_checked():
    with pytest.raises(ValueError, match="non-decreasing"):
        ideal_follow([1.0, 0.0], np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        ideal_follow([0.0], np.zeros(3), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="ticks"):
        ideal_follow([0.0, 1.0], np.zeros((2, 3)), np.zeros((2, 3)), at_s=[0.5],
                     ticks_s=[0.6, 0.7])
    with pytest.raises(ValueError, match="delay"):
        ideal_follow([0.0, 1.0], np.zeros((2, 3)), np.zeros((2, 3)), delay_s=-1.0)
    assert ideal_follow([], np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 3)


def test_best_ideal_is_the_least_mean_distance_to_the_laws_target():
    prm = IdealParams(0.15, 0.0, 0.0005, (0.0, 0.004, 0.02))
    t = np.arange(0, 2.0, 0.001)
    p = np.stack([30.0 * np.sin(2 * np.pi * 0.5 * t), 0 * t, 0 * t], axis=1)
    f = np.zeros_like(p)
    f[500:900, 2] = 2.0                                     # a contact
    x, b = best_ideal(t, p, f, t, params=prm)
    target = law_target(t, p, f, t)
    each = [np.linalg.norm(target - ideal_follow(t, p, f, params=IdealParams(0.15, d, 0.0005),
                                                 at_s=t), axis=1).mean()
            for d in prm.dampings_ns_per_mm]
    assert np.linalg.norm(target - x, axis=1).mean() == min(each)
    assert b == prm.dampings_ns_per_mm[int(np.argmin(each))]
    assert best_ideal(t, p, f, [], params=prm)[0].shape == (0, 3)


def _contact_motion(seed):
    """Smooth motion with a few contacts (forces held for a while)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, 2.0, 0.001)
    p = np.zeros((len(t), 3))
    f = np.zeros((len(t), 3))
    for a in range(3):
        for _ in range(3):
            p[:, a] += rng.uniform(0, 20) * np.sin(2 * np.pi * rng.uniform(0.1, 2) * t
                                                   + rng.uniform(0, 6))
    for _ in range(3):
        s = int(rng.integers(0, len(t) - 500))
        f[s:s + int(rng.integers(100, 500))] = rng.normal(0, 1.5, 3)
    return t, p, f


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), delay_ms=st.sampled_from([2.0, 10.0, 30.0]),
       offset=st.floats(0.0, 0.001))
def test_no_follower_of_the_law_with_a_delay_beats_the_ideal_and_a_ramp_barely(
        seed, delay_ms, offset):
    """A link delay never beats the ideal. The join ramp can, a little: it
    lowers the force while the follower starts, which on some motions
    overshoots less. Over 400 of these motions (seeds 0, 25, ..., 9975) and
    every damping, the ramp was at most 1.4 % better (seed 1450, 0.0028 N s/mm)
    and a 2 ms delay at least 5 % worse: the ideal is the best the law
    allows to within that, not a strict bound."""
    t, p, f = _contact_motion(seed)
    at = t[5:-5] + offset
    prm = ideal_params()
    x, b = best_ideal(t, p, f, at, 0.2, 3.3, prm)
    target = law_target(t, p, f, at, 0.2)
    ideal = np.linalg.norm(target - x, axis=1).mean()
    for d in prm.dampings_ns_per_mm:                        # any damping the ideal may take
        one = IdealParams(prm.mass_kg, d, prm.max_substep_s)
        y = ideal_follow(t, p, f, 0.2, 3.3, one, at_s=at, delay_s=delay_ms / 1e3)
        assert np.linalg.norm(target - y, axis=1).mean() >= ideal, (d, delay_ms)
        y = ideal_follow(t, p, f, 0.2, 3.3, one, at_s=at, ramp_s=0.2)
        assert np.linalg.norm(target - y, axis=1).mean() >= 0.97 * ideal, (d, "ramp")


def test_the_ramp_can_beat_the_ideal_a_little():
    """The counterexample the property search found, kept: the ideal is not
    a strict lower bound (the README and the bench say so)."""
    t, p, f = _contact_motion(1450)
    at = t[5:-5]
    prm = ideal_params()
    x, _ = best_ideal(t, p, f, at, 0.2, 3.3, prm)
    target = law_target(t, p, f, at, 0.2)
    ideal = np.linalg.norm(target - x, axis=1).mean()
    y = ideal_follow(t, p, f, 0.2, 3.3, IdealParams(prm.mass_kg, 0.0028, prm.max_substep_s),
                     at_s=at, ramp_s=0.2)
    r = np.linalg.norm(target - y, axis=1).mean() / ideal
    assert 0.97 <= r < 1.0


def test_compare_scores_both_followers_at_the_same_instants():
    t, p, f = _contact_motion(7)
    clock = 1000.0                                          # the trainee's clock: shifted
    link = 0.004 + 0.002 * (np.arange(len(t)) % 3)          # 4 to 8 ms on the way
    seen = t + clock + link
    ticks = clock + 0.004 + np.arange(1900) / 1000.0
    scored = np.ones(len(ticks), bool)
    scored[:50] = False                                     # before the join
    scored[700:760] = False                                 # a link loss
    prm = ideal_params()
    # a session that is the ideal follower itself scores 1
    local = t + clock + 0.004
    at = ticks[scored]
    x, b = best_ideal(local, p, f, at, 0.2, 3.3, prm)
    dev = np.zeros((len(ticks), 3))
    dev[scored] = x
    r = compare(ticks, dev, scored, t, p, f, seen, 0.2, 3.3, params=prm)
    assert r["value"] == 1.0 and r["damping_ns_per_mm"] == b
    assert r["law_target"]["session"]["n"] == r["law_target"]["ideal"]["n"] == scored.sum()
    assert r["span_s"] == [round(at[0], 4), round(at[-1], 4)]
    assert r["delay_ms"]["p50"] == pytest.approx(2.0, abs=1e-6)
    # a session with the link's delay, the join ramp and a hand: worse, and said why
    y = ideal_follow(local, p, f, 0.2, 3.3, IdealParams(0.15, 0.008, 0.0005), at_s=at,
                     delay_s=0.006, ramp_s=0.2, stiffness_n_per_mm=0.02)
    dev[scored] = y
    r = compare(ticks, dev, scored, t, p, f, seen, 0.2, 3.3, params=prm,
                hand=(0.15, 0.008, 0.02))
    assert r["value"] > 1.0
    assert set(r["handicaps"]) == {"link_delay", "servo_ticks", "join_ramp", "hand"}
    assert r["limited_by"] in r["handicaps"]
    assert r["handicaps"][r["limited_by"]] > r["law_target"]["ideal"]["mean"]
    # nothing scored: no figures
    none = compare(ticks, dev, np.zeros(len(ticks), bool), t, p, f, seen)
    assert none["value"] is None and none["law_target"]["session"]["n"] == 0


def test_summaries_and_ratios():
    assert error_summary([]) == {"mean": None, "p50": None, "p95": None, "n": 0}
    v = tracking_vs_ideal([2.0, 2.0, 5.0], [1.0, 1.0, 1.0])
    assert v["ratio_p50"] == 2.0 and v["ratio_mean"] == 3.0
    assert v["session"]["p95"] == pytest.approx(4.7)
    assert tracking_vs_ideal([1.0], [0.0])["ratio_p50"] is None


def test_ideal_params_and_a_bad_file_in_one_line(tmp_path):
    prm = ideal_params()
    assert prm.mass_kg > 0 and len(prm.dampings_ns_per_mm) > 1
    bad = tmp_path / "t.toml"
    bad.write_text("[ideal_follower]\nmass_kg = -1\ndampings_ns_per_mm = [0.0]\n"
                   "max_substep_s = 0.001\n")
    with pytest.raises(BonesimError, match="mass_kg") as e:
        ideal_params(bad)
    assert str(bad) in str(e.value)


def test_logs_keep_each_sample_once_in_time_order():
    log = InstructorLog(4)
    for t in (0.0, 0.0, 1.0, 3.0, 2.0, 4.0, 5.0):     # a repeat and a reordered packet
        log.add(t, [t, 0, 0], [0, 0, t], 10.0 + t)
    t, p, f, seen = log.arrays(seen=True)
    np.testing.assert_array_equal(t, [2.0, 3.0, 4.0, 5.0])  # the last four, sorted
    np.testing.assert_array_equal(p[:, 0], t)
    np.testing.assert_array_equal(f[:, 2], t)
    np.testing.assert_array_equal(seen, 10.0 + t)
    ticks = TickLog(4)
    for i in range(6):
        ticks.add(float(i), [i, 0, 0], i % 2 == 0)
    tt, pos, sc = ticks.arrays()
    np.testing.assert_array_equal(tt, [2.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(sc, [True, False, True, False])


def test_compare_puts_a_playback_at_another_speed_on_the_trainees_clock():
    t, p, f = _contact_motion(3)
    speed, clock = 2.0, 50.0                     # two recorded seconds per trainee second
    local = t / speed + clock
    seen = local + 0.001 * (np.arange(len(t)) % 2)   # held at the tick after, or at once
    ticks = clock + np.arange(900) / 1000.0
    scored = np.ones(len(ticks), bool)
    prm = IdealParams(0.15, 0.004, 0.0005, (0.002, 0.004))
    x, _ = best_ideal(local, p, f, ticks, 0.2, 3.3, prm)
    r = compare(ticks, x, scored, t, p, f, seen, 0.2, 3.3, speed=speed, params=prm)
    assert r["value"] == 1.0 and 0.0 <= r["delay_ms"]["p50"] <= 1.0
    with pytest.raises(ValueError, match="speed"):
        compare(ticks, x, scored, t, p, f, seen, speed=0.0)
