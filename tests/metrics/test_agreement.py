"""ICC, Bland-Altman and ROC (metrics.agreement) against published worked
examples and the Mann-Whitney U."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from metrics.agreement import bland_altman, icc, roc_auc

#: Shrout & Fleiss (1979), table 2: 6 targets rated by 4 judges.
SHROUT_FLEISS = [[9, 2, 5, 8], [6, 1, 3, 2], [8, 4, 6, 8], [7, 1, 2, 6], [10, 5, 6, 9],
                 [6, 2, 4, 7]]
#: Bland & Altman (1986), PEFR [l/min], first readings: Wright and mini Wright meters.
WRIGHT = [494, 395, 516, 434, 476, 557, 413, 442, 650, 433, 417, 656, 267, 478, 178, 423, 427]
MINI = [512, 430, 520, 428, 500, 600, 364, 380, 658, 445, 432, 626, 260, 477, 259, 350, 451]


def test_icc_matches_shrout_and_fleiss():
    r = icc(SHROUT_FLEISS)
    # published: ICC(1,1) .17, ICC(2,1) .29, ICC(3,1) .71; F = 11.03 on 5 and 15 df
    assert round(r["icc1_1"], 2) == 0.17
    assert round(r["icc2_1"], 2) == 0.29
    assert round(r["icc3_1"], 2) == 0.71
    assert r["f"] == pytest.approx(11.03, abs=0.005) and r["df"] == [5, 15]
    # the interval of ICC(2,1) as R's psych::ICC reports it for these data
    lo, hi = r["icc2_1_ci"]
    assert lo == pytest.approx(0.019, abs=0.001) and hi == pytest.approx(0.76, abs=0.005)


def test_icc_of_identical_raters_is_one_and_checks_its_table():
    x = np.arange(10.0).reshape(5, 2)[:, :1] * np.ones((1, 3))
    assert icc(x)["icc2_1"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="n targets, k raters"):
        icc([1, 2, 3])
    with pytest.raises(ValueError, match="finite"):
        icc([[1, 2], [np.nan, 3]])


def test_bland_altman_matches_the_pefr_example():
    r = bland_altman(WRIGHT, MINI)
    # published: mean difference -2.1 l/min, sd of the differences 38.8
    assert round(r["bias"], 1) == -2.1 and round(r["sd"], 1) == 38.8
    assert r["loa"] == pytest.approx([r["bias"] - 1.959964 * r["sd"],
                                      r["bias"] + 1.959964 * r["sd"]], rel=1e-6)
    lo, hi = r["bias_ci"]
    assert lo < r["bias"] < hi and r["lower_ci"][0] < r["loa"][0] < r["lower_ci"][1]
    assert len(r["mean"]) == len(r["diff"]) == 17
    with pytest.raises(ValueError, match="pair at least 3"):
        bland_altman([1, 2], [1, 2])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_auc_is_the_mann_whitney_u_and_the_area_under_its_curve(seed):
    rng = np.random.default_rng(seed)
    s = np.round(rng.normal(size=30), 1)                    # ties on purpose
    y = rng.random(30) < 0.4
    r = roc_auc(s, y)
    u = stats.mannwhitneyu(s[y], s[~y]).statistic
    assert r["auc"] == pytest.approx(u / (y.sum() * (~y).sum()), rel=1e-12)
    assert np.trapezoid(r["tpr"], r["fpr"]) == pytest.approx(r["auc"], rel=1e-12)
    lo, hi = r["auc_ci"]
    assert 0.0 <= lo < r["auc"] < hi <= 1.0 and r["se"] > 0


def test_perfect_separation_keeps_an_interval():
    r = roc_auc(np.arange(16.0), [False] * 8 + [True] * 8)
    assert r["auc"] == 1.0 and r["note"] == "perfect separation"
    lo, hi = r["auc_ci"]
    assert 0.6 < lo < 0.95 and hi == 1.0           # Newcombe's interval is not the point
    assert roc_auc(-np.arange(16.0), [False] * 8 + [True] * 8)["auc_ci"][1] < 0.4
    with pytest.raises(ValueError, match="both classes"):
        roc_auc([1, 2], [True, True])
