"""Validity statistics (metrics.validity) against their textbook formulas."""
from __future__ import annotations

import math
from itertools import product

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from metrics import validity as V

_VALS = st.lists(st.floats(-100, 100, allow_nan=False), min_size=2, max_size=12)


@settings(max_examples=60, deadline=None)
@given(a=_VALS, b=_VALS)
def test_group_comparison_matches_the_formulas(a, b):
    a, b = np.array(a), np.array(b)
    sp2 = ((len(a) - 1) * a.var(ddof=1) + (len(b) - 1) * b.var(ddof=1)) / (len(a) + len(b) - 2)
    if sp2 < 1e-12:
        return                                     # no spread: t and d undefined
    r = V.compare_groups(a, b)
    t = (a.mean() - b.mean()) / math.sqrt(sp2 * (1 / len(a) + 1 / len(b)))
    assert r["t"] == pytest.approx(t, rel=1e-6, abs=1e-9)
    # U by counting pairs (ties count one half)
    u = sum(1.0 if x > y else 0.5 if x == y else 0.0 for x, y in product(a, b))
    assert r["u"] == pytest.approx(u)
    assert r["rank_biserial"] == pytest.approx(1 - 2 * u / (len(a) * len(b)))
    flat = [g for g, v in (("expert", a), ("novice", b)) if np.ptp(v) == 0]
    if flat:                                       # a group without spread: d undefined
        assert math.isnan(r["d"]) and all(math.isnan(x) for x in r["d_ci"])
        assert r["d_note"].startswith("undefined: no variance within the")
        assert all(g in r["d_note"] for g in flat)
        return
    d = (a.mean() - b.mean()) / math.sqrt(sp2)
    assert r["d"] == pytest.approx(d, rel=1e-9, abs=1e-12) and r["d_note"] == ""
    assert r["d_ci"][0] <= r["d"] <= r["d_ci"][1]


def test_exact_u_is_used_without_ties_and_d_ci_covers_as_it_should():
    r = V.compare_groups([1.0, 2.0, 3.5], [4.0, 5.0, 6.0])
    assert r["u_method"] == "exact" and r["u"] == 0.0
    assert r["p_u"] == pytest.approx(2 / math.comb(6, 3))   # the most extreme of 20
    tie = V.compare_groups([1.0, 2.0, 4.0], [4.0, 5.0, 6.0])
    assert tie["u_method"].startswith("normal")
    # the noncentral-t interval: at its bounds the observed t sits at the
    # 97.5th / 2.5th percentile
    n1, n2, d = 8, 9, 1.2
    lo, hi = V.cohens_d_ci(d, n1, n2)
    k = math.sqrt(n1 * n2 / (n1 + n2))
    assert stats.nct.cdf(d * k, n1 + n2 - 2, lo * k) == pytest.approx(0.975, abs=1e-6)
    assert stats.nct.cdf(d * k, n1 + n2 - 2, hi * k) == pytest.approx(0.025, abs=1e-6)
    # coverage by simulation: about 95 % of intervals hold the true d
    rng = np.random.default_rng(0)
    hits = 0
    for _ in range(300):
        a, b = rng.normal(0.8, 1, n1), rng.normal(0, 1, n2)
        lo, hi = V.compare_groups(a, b)["d_ci"]
        hits += lo <= 0.8 <= hi
    assert 0.90 <= hits / 300 <= 0.99


def test_correlation_matches_ranks_and_fisher():
    rng = np.random.default_rng(1)
    x = rng.normal(size=20)
    y = x + rng.normal(size=20)
    r = V.correlate(x, y)
    rx, ry = stats.rankdata(x), stats.rankdata(y)
    assert r["rho"] == pytest.approx(np.corrcoef(rx, ry)[0, 1])
    assert r["r"] == pytest.approx(np.corrcoef(x, y)[0, 1])
    z, h = math.atanh(r["r"]), 1.959963984540054 / math.sqrt(17)
    assert r["r_ci"] == pytest.approx([math.tanh(z - h), math.tanh(z + h)])
    assert r["rho_ci"][0] < r["rho"] < r["rho_ci"][1]


def test_bad_input_names_the_problem():
    with pytest.raises(ValueError, match="at least 2 values"):
        V.compare_groups([1.0], [2.0, 3.0])
    with pytest.raises(ValueError, match="finite"):
        V.compare_groups([1.0, np.nan], [2.0, 3.0])
    with pytest.raises(ValueError, match="pair at least 3"):
        V.correlate([1, 2, 3], [1, 2])
    with pytest.raises(ValueError, match="confidence"):
        V.correlate([1, 2, 3, 4], [1, 3, 2, 4], confidence=1.0)


@pytest.mark.slow
def test_a_synthetic_cohort_of_six_and_six_separates_on_three_metrics(tmp_path):
    """The issue's check: visibility, the Naive Bayes score (leave one
    participant out) and the force near a structure each tell the groups apart
    (two-tailed t-test, p < 0.05) on 6 + 6 synthetic runs."""
    import csv

    from bonesim.session.reader import read_session
    from metrics.forces import force_vs_distance
    from metrics.regions import loo_scores, region_run
    from metrics.synth import PARTICIPANTS_CSV, synth_cohort
    from metrics.visibility import visible_fraction

    paths = synth_cohort(tmp_path, 6, 6, seed=0, duration_s=30.0)
    groups = {r["id"]: r["group"] for r in csv.DictReader(open(tmp_path / PARTICIPANTS_CSV))}
    sessions = [read_session(p) for p in paths]
    model = sessions[0].burr_models()[0]
    g = np.array([groups[s.header["participant"]] for s in sessions])
    vis = np.array([visible_fraction(s) for s in sessions])
    loo = loo_scores([region_run(s, group=groups[s.header["participant"]]) for s in sessions])
    nb = np.asarray(loo.scores)
    force = np.array([force_vs_distance(s, model=model).force_n.mean() for s in sessions])
    for name, v in (("visibility", vis), ("naive bayes", nb), ("force", -force)):
        r = V.compare_groups(v[g == "expert"], v[g == "novice"])
        assert r["p_t"] < 0.05 and r["t"] > 0, (name, r)
