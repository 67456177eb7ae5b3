"""Safe forces: the table, the per-group bins, the expert limits and the
exceedances, each against a plain loop; an analytic check of the interval;
and the table of a recorded run."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from bonesim.physics.clearance import Clearance
from metrics.forces import (AT_LIMIT_RTOL, BIN_MM, MAX_DISTANCE_MM, ForceTable, bin_edges,
                            bin_index, exceedances, force_vs_distance, group_bins, learn_limits)


def _table(d, f, v=None, t=None, group="expert", structure="chorda_tympani"):
    n = len(d)
    t = np.arange(n) * 1e-3 if t is None else t
    v = np.full(n, 80000.0) if v is None else v
    pos = np.column_stack([t, t, t])
    return ForceTable(t, pos + 1.0, pos, d, f, v, np.zeros(n), structure, MAX_DISTANCE_MM,
                      group=group)


def _naive_bin(d, w=BIN_MM, dmax=MAX_DISTANCE_MM):
    nb = math.ceil(dmax / w)
    if not 0 <= d <= dmax:
        return -1
    return min(int(d // w), nb - 1)


rows = st.lists(st.tuples(st.floats(0, 32), st.floats(0, 3), st.floats(0, 1e5)),
                min_size=0, max_size=40)


# ------------------------------------------------------------------ bins
def test_bin_edges_and_index():
    e = bin_edges()
    assert e[0] == 0 and e[-1] == 30.0 and len(e) == 16
    assert bin_index([0.0, 1.99, 2.0, 29.9, 30.0, 30.1, -1, np.nan], e).tolist() == \
        [0, 0, 1, 14, 14, -1, -1, -1]
    assert bin_edges(3.0, 10.0).tolist() == [0, 3, 6, 9, 12]
    with pytest.raises(ValueError, match="bin_mm"):
        bin_edges(0.0)


@settings(max_examples=50, deadline=None)
@given(st.lists(rows, min_size=1, max_size=4), st.lists(st.sampled_from(["expert", "novice"]),
                                                        min_size=4, max_size=4))
def test_group_bins_match_a_loop(tables, groups):
    tbs = [_table([r[0] for r in rs], [r[1] for r in rs], [r[2] for r in rs]) for rs in tables]
    groups = groups[:len(tbs)]
    got = group_bins(tbs, groups)
    for gi, g in enumerate(got.groups):
        per_bin = {}
        for rs, gg in zip(tables, groups):
            if gg != g:
                continue
            for d, f, v in rs:
                b = _naive_bin(d)
                if b >= 0:
                    per_bin.setdefault(b, []).append((f, v))
        for b in range(len(got.edges_mm) - 1):
            vals = per_bin.get(b, [])
            assert got.n[gi, b] == len(vals)
            for k, col in ((0, "force"), (1, "speed")):
                x = [r[k] for r in vals]
                mean = getattr(got, f"{col}_mean")[gi, b]
                if not x:
                    assert np.isnan(mean)
                    continue
                assert mean == pytest.approx(sum(x) / len(x), rel=1e-9, abs=1e-9)
                lo, hi = getattr(got, f"{col}_lo")[gi, b], getattr(got, f"{col}_hi")[gi, b]
                if len(x) < 2:
                    assert np.isnan(lo) and np.isnan(hi)
                    continue
                m = sum(x) / len(x)
                sd = math.sqrt(sum((xi - m) ** 2 for xi in x) / (len(x) - 1))
                half = stats.t.ppf(0.975, len(x) - 1) * sd / math.sqrt(len(x))
                assert lo == pytest.approx(m - half, rel=1e-7, abs=1e-7)
                assert hi == pytest.approx(m + half, rel=1e-7, abs=1e-7)


def test_constant_force_has_that_mean_and_no_spread():
    d = np.linspace(0, 30, 301)
    got = group_bins([_table(d, np.full(301, 0.25)), _table(d, np.full(301, 0.25))])
    assert got.groups == ("expert",)
    np.testing.assert_allclose(got.force_mean[0], 0.25)
    np.testing.assert_allclose(got.force_lo[0], 0.25)
    np.testing.assert_allclose(got.force_hi[0], 0.25)
    assert got.n[0].sum() == 602


def test_interval_equals_scipys():
    rng = np.random.default_rng(3)
    f = rng.gamma(2.0, 0.1, 50)
    got = group_bins([_table(np.full(50, 5.0), f)], confidence=0.9)
    lo, hi = stats.t.interval(0.9, 49, loc=f.mean(), scale=stats.sem(f))
    assert got.force_lo[0, 2] == pytest.approx(lo) and got.force_hi[0, 2] == pytest.approx(hi)
    assert got.n[0, 2] == 50 and got.n[0].sum() == 50


# ------------------------------------------------------------------ limits
@settings(max_examples=50, deadline=None)
@given(st.lists(rows, min_size=1, max_size=3), st.sampled_from([50.0, 95.0, 100.0]),
       st.integers(1, 4))
def test_limits_are_the_expert_percentile_per_bin(tables, pct, min_n):
    tbs = [_table([r[0] for r in rs], [r[1] for r in rs], [r[2] for r in rs]) for rs in tables]
    lim = learn_limits(tbs, percentile=pct, min_samples=min_n)
    pooled = [r for rs in tables for r in rs]
    for b in range(15):
        f = [r[1] for r in pooled if _naive_bin(r[0]) == b]
        v = [r[2] for r in pooled if _naive_bin(r[0]) == b]
        assert lim.n[b] == len(f)
        if len(f) < min_n:
            assert np.isnan(lim.force_n[b]) and np.isnan(lim.speed_rpm[b])
        else:
            assert lim.force_n[b] == pytest.approx(np.percentile(f, pct))
            assert lim.speed_rpm[b] == pytest.approx(np.percentile(v, pct))


def test_limits_refuse_a_novice_table_and_bad_arguments():
    with pytest.raises(ValueError, match="expert_tables: .*'novice' run"):
        learn_limits([_table([1.0], [1.0], group="novice")])
    with pytest.raises(ValueError, match="percentile"):
        learn_limits([_table([1.0], [1.0])], percentile=0)
    with pytest.raises(ValueError, match="different structures"):
        learn_limits([_table([1.0], [1.0]), _table([1.0], [1.0], structure="facial_nerve")])


# ------------------------------------------------------------------ exceedances
def naive_exceedances(tb, lim):
    best = {}
    for q in range(len(tb)):
        b = _naive_bin(tb.distance_mm[q])
        if b < 0:
            continue
        for name, vals, limits in (("force_n", tb.force_n, lim.force_n),
                                   ("speed_rpm", tb.speed_rpm, lim.speed_rpm)):
            if not np.isnan(limits[b]) and vals[q] > limits[b] * (1 + AT_LIMIT_RTOL):
                key = (tb.t_s[q], name)
                exc = vals[q] - limits[b]
                if key not in best or exc > best[key][0]:
                    best[key] = (exc, q, b)
        # no force limit in the bin: closer than the closest expert is over
        if np.isnan(lim.force_n[b]) and np.isfinite(lim.closest_mm) and \
                tb.distance_mm[q] < lim.closest_mm:
            key = (tb.t_s[q], "approach_mm")
            exc = lim.closest_mm - tb.distance_mm[q]
            if key not in best or exc > best[key][0]:
                best[key] = (exc, q, b)
    return [(t, name, q, b, exc) for (t, name), (exc, q, b) in sorted(best.items())]


@settings(max_examples=50, deadline=None)
@given(rows, rows, st.integers(1, 3))
def test_exceedances_match_a_loop(expert, trainee, per_step):
    lim = learn_limits([_table([r[0] for r in expert], [r[1] for r in expert],
                               [r[2] for r in expert])], percentile=90.0, min_samples=2)
    t = np.arange(len(trainee)) // per_step * 1e-3      # several voxels per step
    tb = _table([r[0] for r in trainee], [r[1] for r in trainee], [r[2] for r in trainee], t,
                group="novice")
    got = exceedances(tb, lim)
    want = naive_exceedances(tb, lim)
    assert len(got) == len(want)
    for k, (t_s, name, q, b, exc) in enumerate(want):
        assert got.t_s[k] == t_s and got.quantity[k] == name and got.bin[k] == b
        assert got.excess[k] == pytest.approx(exc) and got.excess[k] > 0
        np.testing.assert_array_equal(got.pos_mm[k], tb.pos_mm[q])
        assert abs(got.value[k] - got.limit[k]) == pytest.approx(got.excess[k])


def test_a_force_at_the_limit_up_to_rounding_is_not_above_it():
    """A clamped force equals the experts' clamped force up to the last bits."""
    lim = learn_limits([_table(np.full(10, 5.0), np.full(10, 3.3))], percentile=95.0,
                       min_samples=1)
    at = _table([5.0, 5.0, 5.0], [3.3 * (1 + 1e-12), 3.3 * (1 + 1e-6), 3.3], group="novice")
    ex = exceedances(at, lim)
    assert len(ex) == 1 and ex.value[0] == 3.3 * (1 + 1e-6)


def test_an_expert_run_under_its_own_maximum_exceeds_nothing():
    rng = np.random.default_rng(0)
    tb = _table(rng.uniform(0, 30, 500), rng.uniform(0, 1, 500))
    assert len(exceedances(tb, learn_limits([tb], percentile=100.0, min_samples=1))) == 0


# ------------------------------------------------------------------ the table
def _toy_session():
    """A 10x6x6 grid of 1 mm voxels; structure 2 ("nerve") is the column
    i = 9; ten removals of bone along i in three steps."""
    labels = np.ones((10, 6, 6), np.uint8)
    labels[9] = 2
    ijk = np.array([[i, 2, 3] for i in range(10)], np.int32)
    t_samples = np.array([0.0, 0.001, 0.002, 0.003])
    t_rem = np.array([0.001] * 4 + [0.002] * 3 + [0.003] * 3)
    force = np.array([[0, 0, 0.0], [0.3, 0.4, 0.0], [1.0, 0, 0], [0, 2.0, 0]])
    vib = np.array([[0, 0, 0.0], [0.0, 0.0, 0.0], [0.5, 0, 0], [0, 0.0, 0]])
    header = {"structures": [{"label": 1, "name": "bone", "kind": "bone"},
                             {"label": 2, "name": "nerve", "kind": "critical"}],
              "voxel_mm": 1.0, "origin_mm": [-2.0, 0.0, 0.0], "case": {"name": "toy"},
              "group": "Expert", "participant": "p1"}
    sess = SimpleNamespace(
        header=header, path="toy.h5",
        removals={"ijk": ijk, "t_s": t_rem, "epoch": np.zeros(10, np.int32),
                  "label": labels[ijk[:, 0], ijk[:, 1], ijk[:, 2]]},
        samples={"t_s": t_samples, "pos_mm": np.arange(12.0).reshape(4, 3),
                 "force_n": force, "vibration_n": vib, "mag_n": np.array([0, 1, 2, 3.0]),
                 "speed_rpm": np.array([0, 1e4, 2e4, 3e4]), "epoch": np.zeros(4, np.int32)})
    return sess, Clearance(labels, 1.0, (-2.0, 0.0, 0.0), [2])


def test_table_of_a_hand_made_session_matches_a_loop():
    sess, clear = _toy_session()
    tb = force_vs_distance(sess, "nerve", max_distance_mm=5.0, clearance=clear)
    # the nerve's boxes span x in [6.5, 7.5] (voxel 9 at -2 + 9); a voxel
    # i < 9 at x = i - 2 is 8.5 - i from it
    want = []
    for q, (i, _, _) in enumerate(sess.removals["ijk"]):
        d = max(0.0, 8.5 - i) if i < 9 else 0.0
        if d <= 5.0:
            s = int(round(sess.removals["t_s"][q] * 1000))
            f = math.dist(sess.samples["force_n"][s], sess.samples["vibration_n"][s])
            want.append((d, f, sess.samples["speed_rpm"][s], sess.samples["pos_mm"][s]))
    assert len(tb) == len(want) == 6
    for q, (d, f, v, p) in enumerate(want):
        assert tb.distance_mm[q] == pytest.approx(d)
        assert tb.force_n[q] == pytest.approx(f) and tb.speed_rpm[q] == v
        np.testing.assert_array_equal(tb.pos_mm[q], p)
    assert tb.group == "expert" and tb.case == "toy" and tb.structure == "nerve"
    dev = force_vs_distance(sess, "nerve", max_distance_mm=5.0, clearance=clear, force="device")
    assert dev.force_n[-1] == pytest.approx(2.0) and dev.force_n[-4] == pytest.approx(1.0)


def test_unknown_structure_names_the_case_structures():
    sess, clear = _toy_session()
    with pytest.raises(ValueError, match=r"'chorda_tympani' is not a structure of case 'toy' "
                                         r"\(it has bone, nerve\)"):
        force_vs_distance(sess, clearance=clear)
    with pytest.raises(ValueError, match="force must be"):
        force_vs_distance(sess, "nerve", clearance=clear, force="peak")


# ------------------------------------------------------------------ a recorded run
def _record_demo(folder, steps: int):
    """``steps`` points of the planned demo from its first drilling sample,
    recorded: ``(session, model)``."""
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.session.header import make_header
    from bonesim.runtime.simulate import run_trajectory
    from bonesim.session.reader import read_session

    model = load_model("phantom", "cutting-5mm")
    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    path = folder / "run.h5"
    run_trajectory(model, t.at_times(t.t_s[start:start + steps]), surface=False, record=path,
                   header=make_header(model, participant="p1", group="novice"))
    return read_session(path), model


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """3 s of the planned demo from its first drilling sample, recorded."""
    return _record_demo(tmp_path_factory.mktemp("forces"), 300)


def test_table_of_a_recorded_run(recorded):
    sess, model = recorded
    tb = force_vs_distance(sess, model=model)
    rem, s = sess.removals, sess.samples
    assert 0 < len(tb) <= len(rem["t_s"]) and tb.group == "novice"
    label = next(st["label"] for st in sess.header["structures"]
                 if st["name"] == "chorda_tympani")
    centres = model.grid.voxel_centers(rem["ijk"])
    d = model.clearance.distance(centres, [label])
    keep = d <= MAX_DISTANCE_MM
    np.testing.assert_allclose(tb.distance_mm, d[keep])
    for q, t in zip(np.flatnonzero(keep)[:50], tb.t_s[:50]):
        k = int(np.flatnonzero(s["t_s"] == rem["t_s"][q])[0])
        assert t == s["t_s"][k]
        f = np.linalg.norm(s["force_n"][k] - s["vibration_n"][k])
        assert tb.force_n[list(tb.t_s).index(t)] == pytest.approx(f)
    # a structure the clearance does not hold (bone): from the grid's labels;
    # every removed voxel was bone, at distance 0
    bone = force_vs_distance(sess, "bone", model=model)
    assert len(bone) == len(rem["t_s"]) and np.all(bone.distance_mm == 0)


@pytest.fixture(scope="module")
def recorded_40s(tmp_path_factory):
    """40 s of the planned demo from its first drilling sample (about 9,600
    removals within 30 mm of the chorda, over 9 distance bins), recorded."""
    return _record_demo(tmp_path_factory.mktemp("forces4"), 4000)


def test_the_live_watch_warns_exactly_where_the_recording_exceeds(recorded_40s, tmp_path):
    """The window's ForceWatch, fed the recorded streams as the window drains
    them (tissue before samples, in frame-sized batches), warns at the same
    steps, with the same values, as the offline exceedances: forces over the
    bins' limits and, in a bin without one, approaches closer than the
    experts' closest (both from one rule, force_limits.judge)."""
    from bonesim.physics.force_limits import ForceWatch

    sess, model = recorded_40s
    tb = force_vs_distance(sess, model=model)
    assert len(tb) > 1000 and len(np.unique(bin_index(tb.distance_mm, bin_edges()))) > 3
    # this run's forces sit mostly at the device's 3.3 N clamp: limits just
    # under its own median leave the clamped steps above, the others not
    from dataclasses import replace

    lim = learn_limits([replace(tb, group="expert")], percentile=50.0, min_samples=1)
    # the closest bin reached as if the experts had left it empty: there the
    # rule is the experts' closest approach (half way into the bin's rows)
    b = bin_index(tb.distance_mm, lim.edges_mm)
    near = int(b.min())
    f = 0.99 * lim.force_n
    f[near] = np.nan
    lim = replace(lim, force_n=f, closest_mm=float(np.median(tb.distance_mm[b == near])))
    want = exceedances(sess, lim, model=model)
    assert 0 < len(want) < len(np.unique(tb.t_s)) * 3
    assert {"force_n", "approach_mm"} <= set(want.quantity.tolist())
    # the window reads the limits from the file bonesim metrics limits writes
    from bonesim.physics.force_limits import load_limits, save_limits

    watch = ForceWatch(model, load_limits(save_limits(tmp_path / "limits.toml", lim)))
    assert watch.limits.closest_mm == lim.closest_mm
    got = []
    tis, s = sess.tissue, sess.samples
    edges = np.arange(0.0, s["t_s"][-1] + 2 / 30, 1 / 30)          # 30 frames a second
    for a, b in zip(edges[:-1], edges[1:]):
        ti = (tis["t_s"] >= a) & (tis["t_s"] < b)
        si = (s["t_s"] >= a) & (s["t_s"] < b)
        got += watch.feed({k: v[ti] for k, v in tis.items()},
                          {k: v[si] for k, v in s.items()})
    got += watch.feed()
    assert [w.t_s for w in got] == want.t_s.tolist()
    assert [w.quantity for w in got] == want.quantity.tolist()
    np.testing.assert_array_equal([w.value for w in got], want.value)
    np.testing.assert_array_equal([w.limit for w in got], want.limit)
    np.testing.assert_array_equal([w.distance_mm for w in got], want.distance_mm)


def test_a_bin_without_expert_rows_flags_approaches_closer_than_any_expert():
    """Experts never came under 5 mm: the bins there have no force limit, and a
    trainee's rows closer than the closest expert row are flagged, one per
    step (the closest), however light the force."""
    from metrics.forces import closest_approach, exceedances, learn_limits

    rng = np.random.default_rng(0)
    d = rng.uniform(5.0, 20.0, 300)
    ex = _table(d, rng.uniform(0.5, 1.0, 300))
    lim = learn_limits([ex])
    closest = closest_approach([ex])
    assert closest == pytest.approx(d.min()) and lim.closest_mm == closest   # kept in the limits
    assert np.isnan(lim.force_n[:2]).all()               # 0-2 and 2-4 mm: no limit
    tr = _table(np.array([0.8, 0.9, 3.5, 4.9, 12.0]), np.array([0.1, 0.1, 0.1, 0.1, 0.1]),
                t=np.array([1.0, 1.0, 2.0, 3.0, 4.0]), group="novice")
    none = exceedances(tr, lim, closest_mm=math.inf)     # without the rule: nothing
    assert len(none) == 0
    got = exceedances(tr, lim)                           # the limits' own closest approach
    # 4.9 mm lies in the 4-6 mm bin, which has expert rows (a force limit): not flagged
    assert list(got.quantity) == ["approach_mm"] * 2
    np.testing.assert_allclose(got.value, [0.8, 3.5])         # the closest row of t = 1 s
    np.testing.assert_allclose(got.excess, closest - got.value)
    assert (got.limit == closest).all() and (got.excess > 0).all()


def test_tool_speed_is_the_burr_centres_speed():
    from metrics.forces import tool_speed

    t = np.arange(0.0, 1.0, 0.001)
    pos = np.stack([3.0 * t, 4.0 * t, 0 * t], axis=1)        # 5 mm/s
    np.testing.assert_allclose(tool_speed({"t_s": t, "pos_mm": pos}), 5.0, rtol=1e-9)
    tt = np.repeat(t[:10], 2)                                # repeated times
    v = tool_speed({"t_s": tt, "pos_mm": np.repeat(pos[:10], 2, axis=0)})
    np.testing.assert_allclose(v, 5.0, rtol=1e-9)
    assert tool_speed({"t_s": np.zeros(1), "pos_mm": np.zeros((1, 3))}).tolist() == [0.0]
