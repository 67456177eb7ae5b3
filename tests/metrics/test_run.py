"""Every metric of one run (metrics.run) on recorded synthetic runs."""
from __future__ import annotations

import json

import pytest

from bonesim.session.reader import read_session
from metrics.run import _clean, run_metrics
from metrics.synth import synth_cohort


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return synth_cohort(tmp_path_factory.mktemp("runs"), 2, 1, seed=4, duration_s=8.0)


def test_every_metric_of_a_run_is_json_and_consistent(runs):
    e1, e2, n1 = runs
    res = run_metrics(n1, experts=[e1, e2], force_profile=e1)
    text = json.dumps(res)
    assert "NaN" not in text
    s = read_session(n1)
    assert res["run"]["participant"] == "N01" and res["run"]["case"] == "phantom"
    assert res["run"]["removed_voxels"] == res["visibility"]["removals"] > 0
    assert res["visibility"]["live_mismatches"] == 0
    assert res["forces"]["structure"] == "chorda_tympani" and res["forces"]["rows"] > 0
    assert sum(b["rows"] for b in res["forces"]["bins"]) == res["forces"]["rows"]
    assert set(res["exposure"]) <= {st.name for st in s.burr_models()[0].structures}
    assert len(res["final_product"]["per_expert"]) == 2
    # exceedances against limits learned from the two experts: as the
    # functions give them, the largest first
    from metrics.forces import exceedances, force_vs_distance, learn_limits

    model = s.burr_models()[0]
    ex = exceedances(force_vs_distance(s, model=model),
                     learn_limits([force_vs_distance(read_session(e), model=model)
                                   for e in (e1, e2)]))
    got = res["exceedances"]
    assert sum(got["count"].values()) == len(ex)
    assert [w["excess"] for w in got["worst"]] == sorted(ex.excess, reverse=True)[:5]
    assert res["alignment"]["rms_n"] <= res["alignment"]["unaligned_rms_n"] + 1e-9
    # an expert against itself: a perfect final product
    same = run_metrics(e1, experts=[e1])
    assert same["final_product"]["mean"]["dice"] == 1.0
    assert same["final_product"]["mean"]["mean_mm"] == 0.0


def test_a_structure_the_case_lacks_is_skipped_and_said(runs):
    res = run_metrics(runs[0], structure="stapedius")
    assert "no structure 'stapedius'" in res["forces"]["skipped"]


def test_clean_turns_nan_and_numpy_into_json():
    import numpy as np

    assert _clean({"a": np.float32(np.nan), "b": [np.int64(3), (1.5,)],
                   "c": np.arange(2)}) == {"a": None, "b": [3, [1.5]], "c": [0, 1]}
