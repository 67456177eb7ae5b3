"""Naive Bayes drilled regions: the estimator against plain dict counting, the
score's invariants, and leave-one-participant-out never scoring in-sample."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from metrics.regions import (ALPHA, EXPERT, NOVICE, RegionRun, drilled_voxels, fit_regions,
                             loo_scores, region_run)

SHAPE = (4, 3, 5)
N = int(np.prod(SHAPE))


def _run(voxels, group, participant, name=""):
    return RegionRun(np.asarray(sorted(set(voxels)), np.int64), SHAPE, group, participant,
                     "toy", name)


# ------------------------------------------------------------ naive reference
def naive_score(train, scored, alpha=ALPHA):
    """Plain Python: count per voxel and group in dicts, then sum the logs."""
    n = {EXPERT: 0, NOVICE: 0}
    count = {EXPERT: {}, NOVICE: {}}
    for voxels, group in train:
        n[group] += 1
        for v in set(voxels):
            count[group][v] = count[group].get(v, 0) + 1
    total = 0.0
    for v in set(scored):
        pe = (count[EXPERT].get(v, 0) + alpha) / (n[EXPERT] + 2 * alpha)
        pn = (count[NOVICE].get(v, 0) + alpha) / (n[NOVICE] + 2 * alpha)
        total += math.log(pe) - math.log(pn)
    return total


def naive_loo(runs, alpha=ALPHA):
    out = []
    for voxels, group, who in runs:
        train = [(v, g) for v, g, p in runs if p != who]
        out.append(naive_score(train, voxels, alpha))
    return out


voxel_sets = st.lists(st.integers(0, N - 1), max_size=12)
labelled = st.lists(st.tuples(voxel_sets, st.sampled_from([EXPERT, NOVICE]),
                              st.sampled_from("abcde")), min_size=2, max_size=9)


def _usable(runs):
    """Every leave-one-out fold keeps both groups."""
    people = {p for _, _, p in runs}
    return len(people) >= 2 and all(
        {g for _, g, q in runs if q != p} == {EXPERT, NOVICE} for p in people)


@settings(max_examples=60, deadline=None)
@given(labelled, st.sampled_from([0.5, 1.0, 2.0]))
def test_loo_matches_the_naive_dict_counting(runs, alpha):
    assume(_usable(runs))
    rr = [_run(v, g, p) for v, g, p in runs]
    got = loo_scores(rr, alpha=alpha)
    np.testing.assert_allclose(got.scores, naive_loo(runs, alpha), rtol=1e-12, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(labelled, voxel_sets)
def test_swapping_the_groups_negates_the_score(runs, scored):
    assume({g for _, g, _ in runs} == {EXPERT, NOVICE})
    swap = {EXPERT: NOVICE, NOVICE: EXPERT}
    m = fit_regions([_run(v, g, p) for v, g, p in runs])
    ms = fit_regions([_run(v, swap[g], p) for v, g, p in runs])
    assert m.score(scored) == pytest.approx(-ms.score(scored), abs=1e-12)
    assert m.score(scored) == pytest.approx(naive_score([(v, g) for v, g, _ in runs], scored),
                                            abs=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 4), voxel_sets, st.lists(voxel_sets, min_size=8, max_size=8))
def test_a_voxel_everyone_removes_contributes_nothing_with_equal_groups(k, common, extra):
    runs = [_run(list(common) + extra[q], EXPERT if q < k else NOVICE, f"p{q}")
            for q in range(2 * k)]
    m = fit_regions(runs)
    if common:
        np.testing.assert_allclose(m.log_ratio(np.unique(common)), 0.0, atol=1e-12)
    # nor does a voxel nobody removed
    nobody = np.setdiff1d(np.arange(N), np.concatenate([r.voxels for r in runs]))
    np.testing.assert_allclose(m.log_ratio(nobody), 0.0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(labelled, st.sampled_from("abcde"))
def test_loo_never_uses_the_held_out_participant(runs, held):
    """The held-out participant's runs get voxels nobody else removes: were any
    of them in the training, its score would move off the never-seen value."""
    assume(_usable(runs) and held in {p for _, _, p in runs})
    unique = list(range(N, N + 5))                  # beyond every other run's voxels
    shape = (4, 3, 6)                               # room for them
    rr = [RegionRun(np.asarray(sorted(set(v) | (set(unique) if p == held else set()))),
                    shape, g, p) for v, g, p in runs]
    got = loo_scores(rr)
    for q, (v, g, p) in enumerate(runs):
        if p != held:
            continue
        assert all(runs[t][2] != held for t in got.trained_on[q])
        train = [(rr[t].voxels.tolist(), rr[t].group) for t in got.trained_on[q]]
        ne = sum(g == EXPERT for _, g in train)
        nn = len(train) - ne
        unseen = math.log((nn + 2) / (ne + 2))      # log P_E - log P_N at count 0
        seen = naive_score(train, [x for x in rr[q].voxels.tolist() if x not in unique])
        assert got.scores[q] == pytest.approx(seen + len(unique) * unseen, abs=1e-9)


def test_loo_records_the_training_runs_and_names_a_fold_without_a_group():
    rr = [_run([0, 1], EXPERT, "a"), _run([0, 1, 2], EXPERT, "a"),
          _run([5], NOVICE, "b"), _run([0], EXPERT, "c"), _run([5, 6], NOVICE, "d")]
    got = loo_scores(rr)
    assert [t.tolist() for t in got.trained_on] == [[2, 3, 4], [2, 3, 4], [0, 1, 3, 4],
                                                    [0, 1, 2, 4], [0, 1, 2, 3]]
    assert got.participants == ("a", "a", "b", "c", "d")
    with pytest.raises(ValueError, match="holding out 'b'.*no novice"):
        loo_scores(rr[:4])
    with pytest.raises(ValueError, match="participants has 2 entries"):
        loo_scores(rr, ["a", "b"])
    with pytest.raises(ValueError, match="two participants"):
        loo_scores(rr[:2])


def test_experts_region_scores_above_novices():
    ex = [_run(range(10), EXPERT, f"e{q}") for q in range(3)]
    nv = [_run(range(20, 30), NOVICE, f"n{q}") for q in range(3)]
    got = loo_scores(ex + nv)
    assert (got.scores[:3] > 0).all() and (got.scores[3:] < 0).all()


def test_invalid_arguments_are_named():
    with pytest.raises(ValueError, match="group must be"):
        _run([1], "surgeon", "a")
    with pytest.raises(ValueError, match="alpha"):
        fit_regions([_run([1], EXPERT, "a"), _run([1], NOVICE, "b")], alpha=0)
    with pytest.raises(ValueError, match="outside the grid"):
        RegionRun(np.array([N]), SHAPE, EXPERT, "a")
    with pytest.raises(ValueError, match="one case grid"):
        fit_regions([_run([1], EXPERT, "a"), RegionRun(np.array([1]), (9, 9, 9), NOVICE, "b")])
    with pytest.raises(ValueError, match="ijk: voxel"):
        drilled_voxels([[0, 0, 5]], 0, SHAPE)
    with pytest.raises(ValueError, match="epoch has"):
        drilled_voxels([[0, 0, 1]], [0, 0], SHAPE)


def test_the_drilled_region_is_the_last_epochs_removals():
    ijk = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, 1], [3, 2, 4]])
    epoch = np.array([0, 0, 1, 1, 1])
    want = sorted({np.ravel_multi_index(tuple(v), SHAPE) for v in ijk[2:]})
    assert drilled_voxels(ijk, epoch, SHAPE).tolist() == want
    # a session-like object: a reset after the last removal leaves nothing
    sess = SimpleNamespace(
        header={"shape": list(SHAPE), "group": " Expert", "participant": "p1",
                "case": {"name": "toy"}},
        removals={"ijk": ijk, "epoch": epoch}, samples={"epoch": np.array([0, 1, 1])},
        path="x.h5")
    r = region_run(sess)
    assert r.voxels.tolist() == want and r.group == EXPERT and r.participant == "p1"
    sess.samples["epoch"] = np.array([0, 1, 2])
    assert len(region_run(sess).voxels) == 0
