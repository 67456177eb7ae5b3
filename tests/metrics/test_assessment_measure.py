"""The assessment's measurement kernels on small synthetic blocks, against
slow obviously-correct references."""
from __future__ import annotations

import math

import numpy as np
import pytest

from metrics import assessment_measure as M

PARAMS = {"occluder_depth_voxels": 1, "step_voxels": 0.5, "min_area_mm2": 1.0}


def _box(present, tissue0=None, h=0.5, bone0=None):
    tissue0 = np.ones(present.shape, bool) if tissue0 is None else tissue0
    present = present & tissue0
    return M.Box(lo=np.zeros(3, int), h=h, origin_mm=np.zeros(3),
                 labels=tissue0.astype(np.uint8), tissue0=tissue0, present=present,
                 removed=tissue0 & ~present, bone0=tissue0 if bone0 is None else bone0)


def _clear_slow(occ, start, eye_v, step):
    """One sight line, a sample at a time."""
    p = np.asarray(start, float)
    d = np.asarray(eye_v, float) - p
    dist = math.sqrt(float(d @ d))
    d /= dist
    k = 1
    while True:
        t = step * k
        if t >= dist:
            return True
        q = np.rint(p + t * d).astype(int)
        if np.any(q < 0) or np.any(q >= occ.shape):
            return True
        if occ[tuple(q)]:
            return False
        k += 1


def test_clear_to_eye_equals_the_slow_march():
    rng = np.random.default_rng(3)
    occ = rng.random((14, 12, 10)) < 0.08
    box = _box(np.ones(occ.shape, bool))
    ijk = np.argwhere(rng.random(occ.shape) < 0.05)
    for eye in ([40.0, 3.0, 2.5], [-20.0, -15.0, 30.0], [2.0, 2.0, 50.0]):
        fast = M.clear_to_eye(box, ijk, eye, occ, 0.5)
        eye_v = np.asarray(eye) / box.h
        slow = [_clear_slow(occ, v, eye_v, 0.5) for v in ijk]
        assert fast.tolist() == slow
        assert 0 < fast.sum() < len(fast)


def test_cover_equals_the_kd_tree_reference():
    from metrics.exposure import cover_mm

    rng = np.random.default_rng(5)
    shape = (16, 14, 12)
    present = rng.random(shape) > 0.15
    box = _box(present)
    box.cavity = box.removed
    surface = rng.random(shape) < 0.1
    q = M.cover_quantities(box, surface, PARAMS, 1.0)
    ref = cover_mm(np.argwhere(surface), np.argwhere(box.removed), box.h)
    assert np.allclose(np.sort(q["_cover"]), np.sort(ref))
    k = int(math.ceil(PARAMS["min_area_mm2"] / box.h ** 2))
    assert q["thinnest_mm"] == pytest.approx(np.sort(ref)[k - 1])
    assert M.thinnest(np.array([0.3]), 0.5, 1.0) == math.inf


def _block(n=24, top=16):
    """A block of bone (z below ``top``) under air; the eye far above."""
    present = np.zeros((n, n, n), bool)
    present[:, :, :top] = True
    return present


def test_an_open_pit_hides_nothing_and_a_lidded_one_does():
    eye = np.array([6.0, 6.0, 500.0])                 # straight above [mm]
    pit = _block()
    pit[6:18, 6:18, 8:16] = False                      # a pit, walls along the view
    tissue0 = _block()
    box = _box(pit, tissue0)
    q = M.sightlines(box, eye, PARAMS)
    assert q["overhang_mm3"] == 0.0 and q["hidden_wall_share"] == 0.0
    # undercut: the pit widened under an intact rim 2 voxels thick
    under = pit.copy()
    under[3:21, 3:21, 8:14] = False
    q = M.sightlines(_box(under, tissue0), eye, PARAMS)
    rim = np.zeros_like(under)
    rim[3:21, 3:21, 14:16] = True
    rim[6:18, 6:18, 14:16] = False                     # the opening
    assert q["hidden_wall_share"] > 0.3
    # the overhang is the rim over the undercut, within a voxel's growth
    assert 0.8 * rim.sum() * 0.125 <= q["overhang_mm3"] <= 1.6 * rim.sum() * 0.125


def test_opened_air_is_the_air_joined_to_the_cavity_and_seen():
    eye = np.array([6.0, 6.0, 500.0])
    tissue0 = _block()
    tissue0[10:14, 10:14, 4:7] = False                 # a cell under the pit's floor
    tissue0[1:4, 1:4, 4:7] = False                     # a cell far from it
    present = tissue0.copy()
    present[8:16, 8:16, 7:16] = False                  # the pit, down onto the cell
    box = _box(present, tissue0)
    box.occluder = M.occluder(box, PARAMS)
    air = M.opened_air(box, hull_mm=6.0, reach_mm=6.0, eye_mm=eye)
    assert air[10:14, 10:14, 4:7].all()
    assert not air[1:4, 1:4, 4:7].any()
    assert not air[:, :, 16:].any()                    # the outside is not opened air


def test_antrum_angle_tip_and_injury_quantities():
    tissue0 = _block()
    present = tissue0.copy()
    present[8:16, 8:16, 10:16] = False
    box = _box(present, tissue0)
    box.cavity = box.removed
    region = np.zeros_like(present)
    region[10:14, 10:14, 6:9] = True                   # an "antrum" 1 voxel below
    q = M.antrum_quantities(box, region)
    assert q["gap_mm"] == pytest.approx(0.5) and q["opening_mm2"] == 0.0
    region[10:14, 10:14, 9] = True                     # touching the floor
    q = M.antrum_quantities(box, region)
    assert q["gap_mm"] == 0.0 and q["opening_mm2"] == pytest.approx(16 * 0.25)
    assert M.tip_gap(box, 2.0)["gap_mm"] == pytest.approx(10 * 0.5 - 2.0)
    nerve = np.zeros_like(present)
    nerve[12, 12, 8:10] = True
    q = M.injury_quantities(box, nerve)
    assert q["removed_mm3"] == 0.0 and q["exposed_mm2"] == pytest.approx(0.25)
    q = M.injury_quantities(box, nerve | (np.arange(24)[None, None, :] == 10)
                            & (np.arange(24)[:, None, None] == 12)
                            & (np.arange(24)[None, :, None] == 12))
    assert q["removed_mm3"] == pytest.approx(0.125)
    box.groups = {"sinus": np.zeros_like(present), "tegmen": np.zeros_like(present)}
    box.groups["sinus"][8:16, 17:19, 12:14] = True     # 2 voxels beyond the pit's side
    box.groups["tegmen"][8:16, 8:16, 8] = True         # 2 voxels below its floor
    g = M.angle_gap(box)
    assert g["gap_mm"] == pytest.approx(math.hypot(1.0, 1.0) - 0.5, abs=0.3)
