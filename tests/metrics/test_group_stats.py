"""Participants as the unit, the mixed model, corrections and exclusions
(metrics.group_stats) and the sessions of the participants table
(metrics.participants)."""
from __future__ import annotations

import math
import warnings
from unittest import mock

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st_hyp
from statsmodels.stats.multitest import multipletests

from bonesim.errors import BonesimError
from metrics.group_stats import (Design, correct, group_statistics, load_design,
                                 mixed_model, participant_means)
from metrics.participants import assign_sessions, read_participants


def _cohort(n=8, sessions=3, seed=0, group_effect=2.0, session_effect=0.5, p_sd=1.0,
            noise=0.5, copies=1):
    """A table of ``n`` experts and ``n`` novices with known effects."""
    rng = np.random.default_rng(seed)
    rows = []
    for g in ("expert", "novice"):
        for q in range(n):
            pid = f"{g[0].upper()}{q:02d}"
            b = rng.normal(0, p_sd)
            for s in range(1, sessions + 1):
                y = (group_effect if g == "novice" else 0.0) + session_effect * s + b \
                    + rng.normal(0, noise)
                for _ in range(copies):
                    rows.append({"participant": pid, "group": g, "session": float(s),
                                 "instructor_score": 4.0 if g == "expert" else 2.0, "y": y,
                                 "const": 7.0, "flat_e": (1.0 if g == "expert" else y),
                                 "y_copy": 3.0 * y + 1.0})
    return pd.DataFrame(rows)


def test_the_mixed_model_recovers_known_effects():
    df = _cohort(n=20, sessions=4, seed=1)
    r = mixed_model(df, "y")
    assert r["converged"] and r["runs"] == 160 and r["participants"] == 40
    assert abs(r["group_effect"] - 2.0) < 3 * r["group_se"] and r["group_se"] < 0.5
    assert abs(r["session_effect"] - 0.5) < 3 * r["session_se"] and r["session_se"] < 0.1
    assert r["p_group"] < 1e-4 and r["p_session"] < 1e-4
    assert r["participant_sd"] == pytest.approx(1.0, abs=0.4)
    assert r["residual_sd"] == pytest.approx(0.5, abs=0.1)
    null = mixed_model(_cohort(n=20, sessions=4, seed=2, group_effect=0.0), "y")
    assert abs(null["group_effect"]) < 3 * null["group_se"]


@pytest.mark.parametrize("seed, noise", [(9, 0.3), (11, 0.05), (24, 0.3)])
def test_no_participant_variance_still_converges_and_says_so(seed, noise):
    """Participants who differ only by session noise (the synthetic cohort's
    case): the participant variance lies at its bound of 0, where the default
    optimizer stalls for these seeds; the refit converges, recovers the
    effects, agrees with OLS of the same terms (what a zero participant
    variance reduces to) and the note says both."""
    import statsmodels.formula.api as smf
    from statsmodels.regression.mixed_linear_model import MixedLM

    df = _cohort(n=8, sessions=3, seed=seed, p_sd=0.0, noise=noise)
    z = df.assign(novice=(df["group"] == "novice").astype(float))
    std = z.assign(y=(z["y"] - z["y"].mean()) / z["y"].std(ddof=1))   # as mixed_model fits
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = MixedLM.from_formula("y ~ novice + session", std,
                                     groups=std["participant"]).fit(reml=True)
    assert not plain.converged                  # the default stalls here
    r = mixed_model(df, "y")
    assert r["converged"] and "refitted with Powell" in r["note"] and "boundary" in r["note"]
    assert abs(r["group_effect"] - 2.0) < 4 * r["group_se"]
    assert r["participant_sd"] < 1e-3 * r["residual_sd"]
    ols = smf.ols("y ~ novice + session", z).fit()
    assert r["group_effect"] == pytest.approx(ols.params["novice"], rel=1e-3)
    assert r["session_effect"] == pytest.approx(ols.params["session"], rel=1e-3)


def test_repeated_runs_do_not_count_as_people():
    one = _cohort(seed=3)
    two = _cohort(seed=3, copies=2)                  # every run recorded twice
    d = Design(primary=("y",))
    a, _ = group_statistics(one, {"y": ("", 1)}, d)
    b, _ = group_statistics(two, {"y": ("", 1)}, d)
    assert a.loc[0, "expert_n"] == b.loc[0, "expert_n"] == 8
    assert a.loc[0, "p_t"] == pytest.approx(b.loc[0, "p_t"], rel=1e-9)
    runs, _ = group_statistics(two, {"y": ("", 1)}, Design(unit="run", primary=("y",)))
    assert runs.loc[0, "expert_n"] == 48 and runs.loc[0, "p_t"] < b.loc[0, "p_t"]
    pm = participant_means(one, "y")
    assert len(pm) == 16 and (pm["runs"] == 3).all()


def test_corrections_match_statsmodels_and_a_plain_holm_and_bh():
    rng = np.random.default_rng(4)
    p = rng.uniform(0, 0.2, 9)
    p[3] = np.nan
    for method in ("holm", "fdr_bh"):
        got = correct(p, method)
        ok = np.isfinite(p)
        np.testing.assert_allclose(got[ok], multipletests(p[ok], method=method)[1])
        assert np.isnan(got[3])
    q = p[np.isfinite(p)]
    m = len(q)
    order = np.argsort(q)
    holm = np.maximum.accumulate(np.minimum(1, (m - np.arange(m)) * q[order]))
    bh = np.minimum.accumulate((q[order] * m / np.arange(1, m + 1))[::-1])[::-1]
    np.testing.assert_allclose(correct(q, "holm")[order], holm)
    np.testing.assert_allclose(correct(q, "fdr_bh")[order], np.minimum(bh, 1))


def test_families_exclusions_and_undefined_effect_sizes():
    df = _cohort(seed=5)
    rng = np.random.default_rng(6)
    for k in range(4):
        df[f"noise{k}"] = rng.normal(size=len(df))
    cols = {"y": ("", -1), "const": ("", 0), "flat_e": ("", 0), "y_copy": ("", 0),
            "skip": ("s", 0), **{f"noise{k}": ("", 0) for k in range(4)}}
    df["skip"] = rng.normal(size=len(df))
    d = Design(primary=("y", "flat_e"), excluded={"skip": "fixed by design"})
    st, ex = group_statistics(df, cols, d)
    assert ex["skip"] == "fixed by design"
    assert ex["const"].startswith("constant")
    assert ex["y_copy"] == "a monotone copy of y (Spearman rho +1)"
    st = st.set_index("metric")
    assert set(st.index) == {"y", "flat_e", "noise0", "noise1", "noise2", "noise3"}
    assert list(st.loc[["y", "flat_e"], "family"]) == ["primary", "primary"]
    prim = st.loc[["y", "flat_e"], "p_t"].to_numpy()
    np.testing.assert_allclose(st.loc[["y", "flat_e"], "p_t_adj"],
                               multipletests(prim, method="holm")[1])
    sec = st.loc[[f"noise{k}" for k in range(4)], "p_t"].to_numpy()
    np.testing.assert_allclose(st.loc[[f"noise{k}" for k in range(4)], "p_t_adj"],
                               multipletests(sec, method="fdr_bh")[1])
    assert math.isnan(st.loc["flat_e", "d"])
    assert st.loc["flat_e", "d_note"] == "undefined: no variance within the expert group"
    assert st.loc["y", "d_note"] == "" and st.loc["y", "d"] < 0
    assert bool(st.loc["y", "significant"]) and bool(st.loc["y", "mixed_significant"])
    # lower is better for y and novices are higher: experts are told apart
    assert st.loc["y", "auc"] > 0.9 and st.loc["y", "auc_lo"] < st.loc["y", "auc"]


def test_the_default_design_and_bad_designs(tmp_path):
    d = load_design()
    assert d.unit == "participant" and "visible_fraction" in d.primary
    assert {"duration_s", "drilled_mm3"} <= set(d.excluded)
    bad = tmp_path / "d.toml"
    bad.write_text('unit = "person"\n')
    with pytest.raises(BonesimError, match=r"d\.toml: field 'unit': 'person'"):
        load_design(bad)
    bad.write_text('alpha = 2\n')
    with pytest.raises(BonesimError, match="field 'alpha'"):
        load_design(bad)
    bad.write_text('primary_correction = "magic"\n')
    with pytest.raises(BonesimError, match="field 'primary_correction'"):
        load_design(bad)


def test_participants_with_sessions_and_files(tmp_path):
    p = tmp_path / "p.csv"
    p.write_text("id,group,instructor_score,session,file\n"
                 "A,expert,4,2026-03-02,a2.h5\nA,expert,5,2026-01-05,a1.h5\n"
                 "B,novice,2,1,b1.h5\nB,novice,3,2,b2.h5\n")
    out = read_participants(p)
    assert [s["session"] for s in out["A"]["sessions"]] == [1.0, 2.0]     # by date
    assert out["A"]["sessions"][0]["file"] == "a1.h5" and out["A"]["instructor_score"] == 4.5
    runs = [{"file": "/x/a2.h5", "participant": "A"}, {"file": "/x/a1.h5", "participant": "A"},
            {"file": "/x/b1.h5", "participant": "B"}, {"file": "/x/b9.h5", "participant": "B"}]
    where, errors = assign_sessions(out, runs)
    assert where["/x/a2.h5"] == {"session": 2.0, "instructor_score": 4.0}
    assert where["/x/b1.h5"]["session"] == 1.0 and math.isnan(where["/x/b9.h5"]["session"])
    assert len(errors) == 1 and "b9.h5" in errors[0]
    # one row per participant: their runs are sessions 1, 2 ... by start time
    q = tmp_path / "q.csv"
    q.write_text("id,group,instructor_score\nA,expert,4\n")
    runs = [{"file": "/y/2.h5", "participant": "A", "start_time": "2026-01-02"},
            {"file": "/y/1.h5", "participant": "A", "start_time": "2026-01-01"}]
    where, errors = assign_sessions(read_participants(q), runs)
    assert where["/y/1.h5"]["session"] == 1.0 and where["/y/2.h5"]["session"] == 2.0
    assert errors == []
    for text, msg in (("A,expert,4,1\nA,novice,3,2\n", "is 'novice' here but 'expert'"),
                      ("A,expert,4,1\nA,expert,3,1\n", "listed twice session '1'"),
                      ("A,expert,4,soon\n", "column 'session': 'soon'")):
        p.write_text("id,group,instructor_score,session\n" + text)
        with pytest.raises(BonesimError, match=msg):
            read_participants(p)


@settings(max_examples=200, deadline=None)
@given(st_hyp.lists(st_hyp.sampled_from([0.0, 1e-4, 0.01, 0.02, 0.04, 0.3, 0.5, 0.99, 1.0])
                    | st_hyp.floats(0.0, 1.0), min_size=1, max_size=30))
def test_holm_is_statsmodels_holm_with_ties_and_large_values(values):
    """Our Holm (statsmodels' Holm collects garbage on every call) gives
    statsmodels' adjusted values, ties and values near 1 included."""
    p = np.asarray(values, float)
    with mock.patch("gc.collect", lambda *a: 0):
        want = multipletests(p, method="holm")[1]      # (its values, without the collection)
    np.testing.assert_allclose(correct(p, "holm"), want, rtol=0, atol=1e-15)
