"""Force-trajectory alignment (metrics.alignment): the DP kernel against a
naive reference, known warps recovered, identical curves, input checks, and
two recorded runs aligned."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from metrics.alignment import (MOVE_DIAGONAL, MOVE_HORIZONTAL, MOVE_VERTICAL, align,
                               align_sessions, band_limits, box_filter, dp_align, resample,
                               slope)
from metrics.studies.alignment_sensitivity import make_trial


# ------------------------------------------------------------- references
def naive_dp(fa, fb, sa, sb, w_force, w_slope, penalty, band=None):
    """The DP written out over the whole table: ``D[i][j]`` is the cheapest
    path from (0, 0) to (i, j); cells outside the band cost infinity. Ties:
    diagonal, then vertical, then horizontal (the documented order)."""
    n, m = len(fa), len(fb)
    lo, hi = band_limits(n, m, band)
    inside = [[lo[i] <= j <= hi[i] for j in range(m)] for i in range(n)]
    D = [[math.inf] * m for _ in range(n)]
    came = [[None] * m for _ in range(n)]
    for i in range(n):
        for j in range(m):
            if not inside[i][j]:
                continue
            df, ds = float(fa[i] - fb[j]), float(sa[i] - sb[j])
            c = w_force * (df * df) + w_slope * (ds * ds)
            if i == 0 and j == 0:
                D[i][j] = c + 0.0
                continue
            options = []
            if i > 0 and j > 0:
                options.append((D[i - 1][j - 1], MOVE_DIAGONAL))
            if i > 0:
                options.append((D[i - 1][j] + penalty, MOVE_VERTICAL))
            if j > 0:
                options.append((D[i][j - 1] + penalty, MOVE_HORIZONTAL))
            best, move = math.inf, None
            for d, mv in options:                 # first strictly smaller wins
                if d < best:
                    best, move = d, mv
            D[i][j] = c + best
            came[i][j] = move
    path = [(n - 1, m - 1)]
    i, j = n - 1, m - 1
    while (i, j) != (0, 0):
        mv = came[i][j]
        i, j = (i - 1, j - 1) if mv == MOVE_DIAGONAL else (i - 1, j) if mv == MOVE_VERTICAL \
            else (i, j - 1)
        path.append((i, j))
    return D[n - 1][m - 1], np.array(path[::-1], dtype=np.int64)


def naive_box(t, f, at, window_s, fine=20001):
    """Mean of the linear interpolant over the clipped window, by a dense
    trapezoid sum."""
    out = []
    for x in at:
        a, b = max(x - window_s / 2, t[0]), min(x + window_s / 2, t[-1])
        u = np.linspace(a, b, fine)
        v = np.interp(u, t, f)
        out.append(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(u)) / (b - a))
    return np.array(out)


# ------------------------------------------------------------------ the DP
@settings(max_examples=150, deadline=None)
@given(n=hs.integers(1, 9), m=hs.integers(1, 9), seed=hs.integers(0, 2**32 - 1),
       ties=hs.booleans(), w_force=hs.sampled_from([0.0, 0.5, 1.0]),
       w_slope=hs.sampled_from([0.0, 0.03, 1.0]), penalty=hs.sampled_from([0.0, 0.1, 2.0]),
       band=hs.one_of(hs.none(), hs.floats(0.0, 4.0)))
def test_kernel_equals_the_naive_dp(n, m, seed, ties, w_force, w_slope, penalty, band):
    rng = np.random.default_rng(seed)
    draw = (lambda k: rng.integers(0, 3, k).astype(float)) if ties else \
        (lambda k: rng.normal(0, 1, k))           # small integers: many ties
    fa, fb, sa, sb = draw(n), draw(m), draw(n), draw(m)
    want_cost, want_path = naive_dp(fa, fb, sa, sb, w_force, w_slope, penalty, band)
    cost, path = dp_align(fa, fb, sa, sb, w_force=w_force, w_slope=w_slope, penalty=penalty,
                          band=band)
    assert cost == want_cost                      # exactly: same sums in the same order
    np.testing.assert_array_equal(path, want_path)


def test_path_is_monotone_connected_and_within_its_band():
    rng = np.random.default_rng(3)
    fa, fb = rng.normal(size=80), rng.normal(size=60)
    for band in (None, 0.0, 2.5, 10.0):
        _, path = dp_align(fa, fb, fa, fb, band=band)
        assert tuple(path[0]) == (0, 0) and tuple(path[-1]) == (79, 59)
        steps = np.diff(path, axis=0)
        assert {tuple(s) for s in steps.tolist()} <= {(1, 1), (1, 0), (0, 1)}
        lo, hi = band_limits(80, 60, band)
        assert ((path[:, 1] >= lo[path[:, 0]]) & (path[:, 1] <= hi[path[:, 0]])).all()


def test_a_wide_band_is_no_band():
    rng = np.random.default_rng(4)
    fa, fb = rng.normal(size=50), rng.normal(size=70)
    assert dp_align(fa, fb, fa, fb, band=100.0)[0] == dp_align(fa, fb, fa, fb)[0]


# ------------------------------------------------------------ resampling
def test_box_filter_matches_a_dense_average_on_irregular_times():
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.0005, 0.003, 400))
    f = rng.uniform(0, 3.3, 400)
    at = np.linspace(t[0], t[-1], 37)
    np.testing.assert_allclose(box_filter(t, f, at, 0.1), naive_box(t, f, at, 0.1),
                               rtol=0, atol=1e-6)
    np.testing.assert_array_equal(box_filter(t, f, at, 0.0), np.interp(at, t, f))


def test_resample_and_slope():
    t = np.array([0.0, 0.3, 1.0])
    tb, fb = resample(t, 2 * t, rate_hz=10.0)
    np.testing.assert_allclose(tb, np.arange(11) / 10.0)
    np.testing.assert_allclose(fb, 2 * tb)
    np.testing.assert_allclose(slope(fb, 10.0), 2.0)


# --------------------------------------------------------------- alignment
def test_identical_curves_align_on_the_diagonal_with_no_residual():
    rng = np.random.default_rng(6)
    t = np.cumsum(rng.uniform(0.0005, 0.0015, 3000))
    f = np.clip(np.cumsum(rng.normal(0, 0.05, 3000)), 0, 3.3)
    for kw in (dict(filter_target=True), dict(window_s=0.0), dict(penalty=0.0,
                                                                  filter_target=True)):
        al = align(t, f, t, f, **kw)
        n = len(al.t_s)
        assert al.rms_n == 0.0 and al.unaligned_rms_n == 0.0 and al.cost == 0.0
        np.testing.assert_array_equal(al.path, np.repeat(np.arange(n)[:, None], 2, 1))
        assert al.distortion == 0.0 and not al.offset_s.any()
        np.testing.assert_array_equal(al.warped_n, al.target_n)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_a_known_warp_is_recovered(seed):
    trial = make_trial(np.random.default_rng(seed))
    al = align(trial["target_t"], trial["target_f"], trial["applied_t"], trial["applied_f"])
    assert al.rms_n < 0.25 * al.unaligned_rms_n
    err = al.offset_s - trial["true_offset"](al.t_s)
    ramp = trial["on_ramp"](al.t_s)
    true_shift = np.abs(trial["true_offset"](al.t_s)).max()
    assert true_shift > 0.2                       # the warp is real
    assert np.sqrt(np.mean(err[ramp] ** 2)) < 0.1  # [s]; the study's mean is ~0.03
    assert np.sqrt(np.mean(err ** 2)) < 0.25 * true_shift


def test_a_shifted_pulse_is_found_at_its_shift():
    """A pulse 0.5 s late on a flat line: the path pairs the ramps 0.5 s apart."""
    t = np.linspace(0, 6, 6001)
    pulse = lambda c: np.interp(t, [0, c - 0.6, c - 0.4, c + 0.4, c + 0.6, 6],  # noqa: E731
                                [0, 0, 2.5, 2.5, 0, 0])
    al = align(t, pulse(2.5), t, pulse(3.0), filter_target=True)
    on_rise = (al.t_s > 1.95) & (al.t_s < 2.05)
    np.testing.assert_allclose(al.offset_s[on_rise], 0.5, atol=0.021)
    assert al.rms_n < 0.05 < 0.5 < al.unaligned_rms_n


def test_band_limits_the_offset():
    trial = make_trial(np.random.default_rng(11))
    kw = dict(target_t=trial["target_t"], target_f=trial["target_f"],
              applied_t=trial["applied_t"], applied_f=trial["applied_f"])
    free = align(**kw)
    tight = align(**kw, band_s=0.05)
    stretch = (len(tight.applied_n) - 1) / (len(tight.t_s) - 1)
    drift = np.abs(tight.offset_s - tight.t_s * (stretch - 1.0))
    assert drift.max() <= 0.05 + 1e-9 + 1.0 / tight.rate_hz
    assert tight.rms_n >= free.rms_n


# ----------------------------------------------------------- input checks
GOOD = dict(target_t=np.linspace(0, 1, 50), target_f=np.ones(50),
            applied_t=np.linspace(0, 1, 60), applied_f=np.ones(60))


@pytest.mark.parametrize("change, name", [
    (dict(target_t=np.linspace(0, 1, 50)[::-1]), "target_t"),
    (dict(target_t=np.zeros((50, 1))), "target_t"),
    (dict(target_f=np.ones(49)), "target_f"),
    (dict(applied_f=np.r_[np.ones(59), np.nan]), "applied_f"),
    (dict(applied_t=np.r_[0.0, np.inf]), "applied_t"),
    (dict(applied_t=[0.0], applied_f=[1.0]), "applied_t"),
    (dict(rate_hz=0.0), "rate_hz"),
    (dict(rate_hz=0.5), "target_t"),
    (dict(window_s=-0.1), "window_s"),
    (dict(w_force=-1.0), "w_force"),
    (dict(w_slope=float("nan")), "w_slope"),
    (dict(penalty="much"), "penalty"),
    (dict(band_s=0.0), "band_s"),
    (dict(w_force=0.0, w_slope=0.0), "w_force"),
    (dict(rate_hz=1e5), "rate_hz"),
])
def test_bad_inputs_name_the_argument(change, name):
    with pytest.raises(ValueError, match=name):
        align(**{**GOOD, **change})


def test_dp_align_checks_its_arrays():
    a = np.zeros(5)
    with pytest.raises(ValueError, match="applied_slope"):
        dp_align(a, a, a, np.zeros(4))
    with pytest.raises(ValueError, match="target"):
        dp_align(np.zeros(0), a, np.zeros(0), a)
    with pytest.raises(ValueError, match="penalty"):
        dp_align(a, a, a, a, penalty=-1)


# ---------------------------------------------------------------- sessions
#: The recorded runs: the demo from its first drilling, this long [s] for
#: the expert; the trainee follows the same path on a warped clock.
EXPERT_S = 2.0
TRAINEE_S = 2.3
WARP_AMPLITUDE_S = 0.2


def _warp(u):
    """Trainee time -> expert time [s]: slower overall, late in the middle."""
    return u * (EXPERT_S / TRAINEE_S) + WARP_AMPLITUDE_S * np.sin(np.pi * u / TRAINEE_S)


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.io.trajectory import Trajectory
    from bonesim.session.header import make_header
    from bonesim.runtime.simulate import run_trajectory

    model = load_model("phantom", "cutting-5mm")
    demo = demo_trajectory(load_case("phantom"), "cutting-5mm")
    # 2 s of the planned outline 5 s after the burr first runs: strokes that
    # touch and leave the bone, so the force profile shows the warp (a stretch of
    # steady contact would not; the first touch alone shows little of it)
    t0 = demo.t_s[int(np.flatnonzero(demo.drill)[0])] + 5.0
    folder = tmp_path_factory.mktemp("align")
    paths = []
    for who, clock, length in (("expert", lambda u: u, EXPERT_S),
                               ("trainee", _warp, TRAINEE_S)):
        u = np.arange(0.0, length, 0.01)
        at = demo.at_times(t0 + np.clip(clock(u), 0.0, EXPERT_S))
        traj = Trajectory(t_s=u, pos_mm=at.pos_mm, axis=at.axis, drill=at.drill,
                          speed_rpm=at.speed_rpm, direction=at.direction)
        path = folder / f"{who}.h5"
        run_trajectory(model, traj, surface=False, record=path,
                       header=make_header(model, participant=who))
        paths.append(path)
    return tuple(paths)


def test_align_sessions_recovers_the_trainees_clock(two_runs):
    from bonesim.session.reader import read_session

    expert, trainee = (read_session(p) for p in two_runs)
    assert expert.samples["mag_n"].max() > 1.0          # the runs drill
    al = align_sessions(expert, trainee, trim=False)
    assert al.rms_n < 0.3 * al.unaligned_rms_n
    u = np.linspace(0, trainee.duration_s, 5001)
    true = np.interp(al.t_s, _warp(u), u) - al.t_s
    active = al.target_n > 0.5                          # where the warp shows
    assert np.sqrt(np.mean((al.offset_s - true)[active] ** 2)) < 0.08
    # paths work as well as sessions; the trimmed runs and force_n align too
    trimmed = align_sessions(*two_runs)
    assert trimmed.rms_n < 0.4 * trimmed.unaligned_rms_n
    assert len(trimmed.t_s) < len(al.t_s)
    norm = align_sessions(expert, trainee, column="force_n")
    assert norm.rms_n < 0.4 * norm.unaligned_rms_n
    same = align_sessions(expert, expert)
    assert same.rms_n == 0.0 and same.distortion == 0.0


def test_align_sessions_checks_its_inputs(two_runs):
    from types import SimpleNamespace

    with pytest.raises(ValueError, match="column"):
        align_sessions(*two_runs, column="speed_rpm")
    idle = SimpleNamespace(samples={"t_s": np.arange(10.0), "mag_n": np.zeros(10)})
    with pytest.raises(ValueError, match="trainee_session"):
        align_sessions(two_runs[0], idle)
    with pytest.raises(ValueError, match="expert_session"):
        align_sessions(SimpleNamespace(samples={}), two_runs[1])

