"""How a run was drilled (metrics.conduct) against slow obvious references
and hand-made runs."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from metrics import conduct as C


def _samples(n, rng, drill=None, vol=None, burr=None):
    return {"t_s": np.arange(n) * 1e-3, "pos_mm": np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0),
            "drill": np.ones(n, np.uint8) if drill is None else drill,
            "volume_mm3": np.ones(n) if vol is None else vol,
            "force_n": rng.uniform(0, 3.3, (n, 3)) / np.sqrt(3), "vibration_n": np.zeros((n, 3)),
            "burr": np.zeros(n, np.uint8) if burr is None else burr,
            "epoch": np.zeros(n, np.int32)}


def _runs_naive(mask):
    out, start = [], None
    for q, m in enumerate(list(mask) + [False]):
        if m and start is None:
            start = q
        elif not m and start is not None:
            out.append((start, q))
            start = None
    return out


@settings(max_examples=60, deadline=None)
@given(bits=st.lists(st.booleans(), max_size=200))
def test_runs_match_a_loop(bits):
    a, b = C._runs(np.array(bits, bool))
    assert list(zip(a.tolist(), b.tolist())) == _runs_naive(bits)


def test_a_straight_sweep_and_a_plunge():
    view = np.array([0.0, 0.0, 1.0])
    n = 200
    sweep = np.stack([np.linspace(0, 4, n), np.zeros(n), np.zeros(n)], 1)
    plunge = np.stack([np.zeros(n), np.zeros(n), np.linspace(0, 3, n)], 1)
    pos = np.concatenate([sweep, np.tile(sweep[-1] + 10, (n, 1)), plunge + 20])
    drill = np.concatenate([np.ones(n), np.zeros(n), np.ones(n)]).astype(np.uint8)
    smp = {"t_s": np.arange(3 * n) * 1e-3, "pos_mm": pos, "drill": drill,
           "volume_mm3": np.ones(3 * n)}
    s = C.strokes(smp, view)
    assert len(s["path_mm"]) == 2
    np.testing.assert_allclose(s["path_mm"], [4.0, 3.0])
    np.testing.assert_allclose(s["straightness"], [1.0, 1.0])
    np.testing.assert_allclose(s["plunge"], [0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(s["start_s"], [0.0, 2 * n * 1e-3])
    summ = C.stroke_summary(s)
    assert summ["strokes"] == 2 and summ["mean_plunge"] == pytest.approx(0.5)
    assert summ["consistency_cv"] == pytest.approx(np.std([4, 3]) / 3.5)
    # a stroke shorter than MIN_STROKE_S does not count
    short = {k: v[:20] for k, v in smp.items()}
    assert len(C.strokes(short, view)["path_mm"]) == 0
    assert np.isnan(C.stroke_summary(C.strokes(short, view))["mean_path_mm"])
    with pytest.raises(ValueError, match="view"):
        C.strokes(smp, (0, 0, 0))


def test_excessive_force_events_against_a_loop():
    rng = np.random.default_rng(0)
    smp = _samples(3000, rng)
    lim = np.where(np.arange(3000) < 1500, 3.3, 2.0)
    ev = C.excessive_force_events(smp, lim, share=0.9, min_s=0.002)
    f = np.linalg.norm(smp["force_n"] - smp["vibration_n"], axis=1)
    want = [(i, j) for i, j in _runs_naive(f >= 0.9 * lim)
            if smp["t_s"][j - 1] - smp["t_s"][i] >= 0.002]
    assert len(ev["start_s"]) == len(want) > 0
    for q, (i, j) in enumerate(want):
        assert ev["start_s"][q] == smp["t_s"][i]
        assert ev["peak_n"][q] == f[i:j].max()
    with pytest.raises(ValueError, match="share"):
        C.excessive_force_events(smp, 3.3, share=0.0)
    with pytest.raises(ValueError, match="max_force_n"):
        C.excessive_force_events(smp, np.inf)


def test_time_near_volumes_and_stages_against_loops():
    rng = np.random.default_rng(1)
    n = 600
    drill = (rng.random(n) < 0.8).astype(np.uint8)
    smp = _samples(n, rng, drill=drill, vol=rng.uniform(0, 1, n) * (rng.random(n) < 0.9),
                   burr=(np.arange(n) >= 400).astype(np.uint8))
    gaps = rng.uniform(-0.5, 4.0, (n, 2))
    got = C.time_near(smp, gaps, (1.0, 2.0))
    dt = np.diff(smp["t_s"], append=smp["t_s"][-1])
    m = C.drilling_mask(smp)
    for s in range(2):
        for c, thr in enumerate((1.0, 2.0)):
            want = sum(dt[q] for q in range(n) if m[q] and gaps[q, s] < thr)
            assert got[s, c] == pytest.approx(want)
    rem = {"label": rng.integers(0, 4, 50)}
    dist = rng.uniform(0, 12, (50, 2))
    vol = C.drilled_volume(rem, 3, 0.5, dist, (2.0, 5.0))
    assert vol["by_label"].tolist() == [0.125 * list(rem["label"]).count(k) for k in range(4)]
    for s in range(2):
        for q, (lo, hi) in enumerate([(0, 2), (2, 5), (5, np.inf)]):
            want = 0.125 * sum(1 for d in dist[:, s] if lo <= d < hi)
            assert vol["by_band"][s, q] == pytest.approx(want)
    st_ = C.burr_stages(smp, ["big", "small"], gaps.min(axis=1), [5.0, 2.0], n_stages=3)
    assert st_["stages"][0] == {"big": 1.0}          # the first 400 samples: burr 0
    assert set(st_["stages"][2]) <= {"big", "small"} and "small" in st_["stages"][2]
    for stage in st_["stages"]:
        assert sum(stage.values()) == pytest.approx(1.0)
    near = m & (gaps.min(axis=1) < C.NEAR_BURR_MM)
    d = np.where(smp["burr"] == 0, 5.0, 2.0)
    assert st_["diameter_near_mm"] == pytest.approx((d[near] * dt[near]).sum() / dt[near].sum())


def test_conduct_of_recorded_runs_is_json_and_tells_a_plunge_from_a_sweep(tmp_path):
    import json

    from bonesim.session.reader import read_session
    from metrics.synth import synth_cohort

    e, n = synth_cohort(tmp_path, 1, 1, seed=2, duration_s=12.0)
    ce, cn = (C.conduct(read_session(p)) for p in (e, n))
    json.dumps(ce)
    json.dumps(cn)
    assert ce["strokes"]["strokes"] > 0 and cn["strokes"]["strokes"] > 0
    assert cn["strokes"]["mean_plunge"] > ce["strokes"]["mean_plunge"] + 0.2
    assert ce["drilled_mm3"]["total"] == pytest.approx(
        sum(ce["drilled_mm3"]["by_structure"].values()))
    assert ce["burr"]["stages"][0] == {"cutting-5mm": 1.0}
    assert set(ce["contacts"]) == set(ce["drilled_mm3"]["by_structure"])
