"""The planned demo mastoidectomy: drills bone, approaches danger, never enters it."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from bonesim.case import load_case
from bonesim.errors import BonesimError
from bonesim.model import load_model
from bonesim.simulate import run_trajectory
from bonesim.toolpath import DemoPlan, demo_mastoidectomy
from bonesim.trajectory import Trajectory

from .fakes import BONE, NERVE


@pytest.fixture(scope="module")
def phantom_path():
    case = load_case("phantom")
    vol = case.load_volume()
    plan = DemoPlan(burr_radius_mm=2.5)
    t, pos, axis, drill = demo_mastoidectomy(vol.labels, vol.spacing_mm, vol.origin_mm,
                                             case.structures, case.camera.eye_mm,
                                             case.camera.focal_mm, plan)
    return case, vol, plan, t, pos, axis, drill


def _distance_to(vol, mask, pos):
    d = ndimage.distance_transform_edt(~mask) * vol.spacing_mm
    idx = np.floor((pos - vol.origin_mm) / vol.spacing_mm + 0.5).astype(int)
    ok = np.all((idx >= 0) & (idx < np.array(mask.shape)), axis=1)
    return d[tuple(idx[ok].T)]


def test_path_keeps_clear_of_danger_but_approaches_sinus_and_nerve(phantom_path):
    case, vol, plan, t, pos, axis, drill = phantom_path
    assert np.all(np.diff(t) > 0) and drill.any()
    np.testing.assert_allclose(np.linalg.norm(axis, axis=1), 1.0)
    danger = np.isin(vol.labels, [i + 1 for i, s in enumerate(case.structures)
                                  if s.kind != "bone"])
    clearance = _distance_to(vol, danger, pos) - plan.burr_radius_mm
    # the burr surface never comes closer than the margin (less a voxel's
    # quantization of the distance map)
    assert clearance.min() >= plan.margin_mm - vol.spacing_mm
    for name in ("sigmoid_sinus", "facial_nerve"):
        near = _distance_to(vol, vol.labels == case.index(name), pos).min()
        assert near - plan.burr_radius_mm < 2.5, f"path never approaches {name}"


@pytest.mark.slow
def test_demo_run_drills_bone_without_injury(phantom_path):
    case, vol, plan, t, pos, axis, drill = phantom_path
    n = len(t)
    traj = Trajectory(t_s=t, pos_mm=pos, axis=axis, drill=drill,
                      speed_rpm=np.full(n, 60000.0), direction=np.ones(n, np.int8))
    model = load_model("phantom", "cutting-5mm")
    summary = run_trajectory(model, traj, surface=False)
    assert summary["voxels_removed"] > 10000
    assert set(summary["removed_by_structure"]) == {"bone"}
    assert summary["injuries"] == []


def test_planner_errors_are_clear():
    labels = np.zeros((10, 10, 10), np.uint8)
    with pytest.raises(BonesimError, match="no bone"):
        demo_mastoidectomy(labels, 0.5, (0, 0, 0), [BONE], (20, 2, 2), (2, 2, 2))
    labels[2:8, 2:8, 2:8] = 1
    with pytest.raises(BonesimError, match="coincide"):
        demo_mastoidectomy(labels, 0.5, (0, 0, 0), [BONE, NERVE], (2, 2, 2), (2, 2, 2))
    with pytest.raises(BonesimError, match="no bone lies under"):
        demo_mastoidectomy(labels, 0.5, (0, 0, 0), [BONE], (30, 30, 50), (30, 30, 40),
                           DemoPlan(region_radius_mm=0.5))
    # the same view straight above the bone does plan a path
    t, pos, axis, drill = demo_mastoidectomy(labels, 0.5, (0, 0, 0), [BONE], (2, 2, 50),
                                             (2, 2, 40), DemoPlan(region_radius_mm=0.5))
    assert drill.any() and pos[:, 2].min() < 3.5 + 2.5
