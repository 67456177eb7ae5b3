"""Exposure: surface voxels and bone cover against brute-force loops."""
from __future__ import annotations

import itertools
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from metrics.exposure import cover_mm, exposure, structure_surface

SHAPE = (6, 5, 4)


def naive_surface(labels, label, bone):
    out = []
    nx, ny, nz = labels.shape
    for i, j, k in itertools.product(range(nx), range(ny), range(nz)):
        if labels[i, j, k] != label:
            continue
        for di, dj, dk in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)):
            a, b, c = i + di, j + dj, k + dk
            if 0 <= a < nx and 0 <= b < ny and 0 <= c < nz and labels[a, b, c] in bone:
                out.append((i, j, k))
                break
    return out


def naive_cover(surface, drilled, h):
    return [max(0.0, min((math.dist(s, d) * h for d in drilled), default=math.inf) - h)
            for s in surface]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 3), min_size=120, max_size=120),
       st.lists(st.integers(0, 119), max_size=15), st.sampled_from([0.5, 1.0]))
def test_surface_and_cover_match_loops(flat_labels, drilled_flat, h):
    labels = np.array(flat_labels, np.uint8).reshape(SHAPE)
    surf = structure_surface(labels, 2, [1, 3])
    want = naive_surface(labels, 2, {1, 3})
    assert sorted(map(tuple, surf.tolist())) == sorted(want)
    drilled = [np.unravel_index(f, SHAPE) for f in sorted(set(drilled_flat))]
    got = cover_mm(surf, np.array(drilled).reshape(-1, 3), h)
    np.testing.assert_allclose(got, naive_cover(surf.tolist(), drilled, h), atol=1e-12)


def test_exposure_of_a_plate_thinned_to_one_voxel():
    """A 'sinus' layer at z = 0 under bone z = 1..3 (0.5 mm voxels); the run
    drills z = 2..3 over half of it, and an earlier epoch's removals (reset
    since) went all the way down: only the last epoch counts."""
    labels = np.ones((4, 4, 4), np.uint8)
    labels[:, :, 0] = 2
    drilled = [(i, j, k) for i in range(2) for j in range(4) for k in (2, 3)]
    old = [(i, j, 1) for i in range(4) for j in range(4)]
    ijk = np.array(old + drilled, np.int32)
    epoch = np.array([0] * len(old) + [1] * len(drilled))
    sess = SimpleNamespace(
        header={"structures": [{"label": 1, "name": "bone", "kind": "bone"},
                               {"label": 2, "name": "sinus", "kind": "soft"}],
                "shape": [4, 4, 4], "voxel_mm": 0.5, "case": {"name": "plate"}},
        removals={"ijk": ijk, "epoch": epoch}, samples={"epoch": np.array([0, 1])})
    got = exposure(sess, ["sinus"], labels=labels)["sinus"]
    assert got.surface == 16
    # under the drilled half one voxel (0.5 mm) of bone is left; the other
    # half is >= 0.5 mm diagonally from the cavity
    want = naive_cover(naive_surface(labels, 2, {1}), drilled, 0.5)
    np.testing.assert_allclose(np.sort(got.cover_mm), np.sort(want))
    assert got.count == (sum(c < 1.0 for c in want), sum(c < 0.5 for c in want))
    assert got.count[1] == 0 and got.fraction[0] == pytest.approx(got.count[0] / 16)
    with pytest.raises(ValueError, match="'tegmen' is not a structure of case 'plate'"):
        exposure(sess, ["tegmen"], labels=labels)
    with pytest.raises(ValueError, match="thresholds_mm"):
        exposure(sess, ["sinus"], labels=labels, thresholds_mm=(0.0,))
