"""The final product against expert runs (metrics.final_product), against set
arithmetic and brute-force distances."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from metrics import final_product as F

SHAPE = (7, 6, 5)
_SETS = st.lists(st.integers(0, int(np.prod(SHAPE)) - 1), max_size=40)


@settings(max_examples=80, deadline=None)
@given(d=_SETS, e=_SETS)
def test_overlap_is_set_arithmetic(d, e):
    o = F.overlap(np.array(d, np.int64), np.array(e, np.int64))
    sd, se = set(d), set(e)
    assert o["both"] == len(sd & se)
    assert o["missed"] == len(se - sd) and o["extra"] == len(sd - se)
    if sd or se:
        assert o["dice"] == pytest.approx(2 * len(sd & se) / (len(sd) + len(se)))
        assert o["jaccard"] == pytest.approx(len(sd & se) / len(sd | se))
    else:
        assert o["dice"] == o["jaccard"] == 1.0


@settings(max_examples=60, deadline=None)
@given(d=_SETS.filter(len), e=_SETS.filter(len))
def test_cavity_distance_is_brute_force(d, e):
    got = F.cavity_distance(np.array(d), np.array(e), SHAPE, 0.5)
    pd = [np.array(np.unravel_index(v, SHAPE)) * 0.5 for v in sorted(set(d))]
    pe = [np.array(np.unravel_index(v, SHAPE)) * 0.5 for v in sorted(set(e))]
    de = [min(np.linalg.norm(a - b) for b in pe) for a in pd]
    ed = [min(np.linalg.norm(a - b) for b in pd) for a in pe]
    assert got["mean_mm"] == pytest.approx(0.5 * (np.mean(de) + np.mean(ed)))
    assert got["hausdorff_mm"] == pytest.approx(np.percentile(de + ed, 95))


def test_empty_sets_and_bad_input():
    assert np.isnan(F.cavity_distance(np.zeros(0, int), np.array([3]), SHAPE, 0.5)["mean_mm"])
    with pytest.raises(ValueError, match="flat voxel indices"):
        F.overlap(np.zeros((2, 3), int), np.zeros(0, int))
    with pytest.raises(ValueError, match="percentile"):
        F.cavity_distance(np.array([1]), np.array([2]), SHAPE, 0.5, percentile=101)


def _session(ijk, epochs, last, case="phantom", shape=SHAPE, who="X"):
    ijk = np.asarray(ijk, np.int32).reshape(-1, 3)
    return SimpleNamespace(
        header={"case": {"name": case}, "shape": list(shape), "voxel_mm": 0.5,
                "origin_mm": [0.0, 0.0, 0.0], "participant": who},
        samples={"epoch": np.array([last], np.int32)},
        removals={"ijk": ijk, "epoch": np.asarray(epochs, np.int32)})


def test_against_a_panel_only_the_last_epoch_counts():
    run = _session([[1, 1, 1], [2, 2, 2], [3, 3, 3]], [0, 1, 1], last=1)
    ex1 = _session([[2, 2, 2], [3, 3, 3]], [0, 0], last=0, who="E1")
    ex2 = _session([[2, 2, 2], [4, 4, 4]], [0, 0], last=0, who="E2")
    res = F.compare_to_experts(run, [ex1, ex2], regions=False)
    assert [p["expert"] for p in res["per_expert"]] == ["E1", "E2"]
    assert res["per_expert"][0]["dice"] == 1.0 and res["per_expert"][1]["dice"] == 0.5
    assert res["mean"]["dice"] == pytest.approx(0.75)
    assert res["per_expert"][1]["extra_mm3"] == 0.125
    with pytest.raises(ValueError, match="of case 'other'"):
        F.compare_to_experts(run, [_session([[1, 1, 1]], [0], 0, case="other")],
                             regions=False)
    with pytest.raises(ValueError, match="at least one expert"):
        F.compare_to_experts(run, [], regions=False)


def test_regions_split_the_overlap_by_distance_band():
    class Bands:                       # region: voxel index along x below 3 or not
        names = ["s"]
        bands = ["near", "far"]

        def __call__(self, flat):
            return (np.unravel_index(flat, SHAPE)[0] >= 3).astype(int)[:, None]

    d = np.ravel_multi_index(np.array([[1, 0, 0], [4, 0, 0]]).T, SHAPE)
    e = np.ravel_multi_index(np.array([[1, 0, 0], [5, 0, 0]]).T, SHAPE)
    res = F.compare(d, e, SHAPE, 0.5, regions=Bands())
    assert res["regions"]["s"]["near"]["dice"] == 1.0
    assert res["regions"]["s"]["far"]["dice"] == 0.0
    assert res["regions"]["s"]["far"]["missed_mm3"] == res["regions"]["s"]["far"]["extra_mm3"] \
        == 0.125
