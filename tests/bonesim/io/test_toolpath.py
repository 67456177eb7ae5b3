"""The planned demo mastoidectomy: drills bone, approaches danger, keeps its
margin at the source resolution whatever the grid, rinses between passes
without touching bone."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bonesim.engine import events
from bonesim.io.case import load_case
from bonesim.physics.clearance import Clearance
from bonesim.errors import BonesimError
from bonesim.io.loading import load_model
from bonesim.engine.model import make_model, make_state, step
from bonesim.io.toolpath import (DemoPlan, _segment_clear, _trace_floors, default_plan_path,
                                 demo_mastoidectomy, demo_trajectory, load_demo_plan)
from bonesim.io.trajectory import Trajectory

from tests.bonesim.fakes import BONE, NERVE

PLAN = load_demo_plan()
R = 2.5                                    # cutting-5mm


def box_clearance(points, labels, spacing, origin, group, reach):
    """Reference, independent of bonesim.physics.clearance: the distance [mm] from
    each point to the nearest box of a voxel in ``group`` (every voxel of the
    map, each the box of its spacing), exact up to ``reach`` (beyond: inf)."""
    spacing = np.broadcast_to(np.asarray(spacing, float), (3,))
    centres = np.asarray(origin) + spacing * np.argwhere(np.isin(labels, group))
    tree = cKDTree(centres)
    half_diag = np.linalg.norm(spacing) / 2
    out = np.full(len(points), np.inf)
    near = np.isfinite(tree.query(points, distance_upper_bound=reach + half_diag)[0])
    for q in np.flatnonzero(near):
        c = centres[tree.query_ball_point(points[q], reach + half_diag)]
        gap = np.maximum(np.abs(points[q] - c) - spacing / 2, 0.0)
        out[q] = min(np.sqrt((gap ** 2).sum(-1)).min(), out[q])
    return out


def danger_of(structures):
    return [s for s, st in enumerate(structures, start=1) if st.kind != "bone"]


@pytest.fixture(scope="module")
def phantom():
    case = load_case("phantom")
    return case, case.load_volume(), demo_trajectory(case, "cutting-5mm")


def test_path_keeps_its_margin_and_approaches_sinus_and_nerve(phantom):
    case, vol, traj = phantom
    assert np.all(np.diff(traj.t_s) > 0) and traj.drill.any()
    np.testing.assert_allclose(np.linalg.norm(traj.axis, axis=1), 1.0)
    nat = vol.native_labels
    clear = R + PLAN.margin_mm
    d = box_clearance(traj.pos_mm, nat.labels, nat.spacing_mm, nat.origin_mm,
                      danger_of(case.structures), clear + 1.0)
    assert d.min() >= clear - 1e-6                     # every sample, every move
    for name in ("sigmoid_sinus", "facial_nerve"):
        near = box_clearance(traj.pos_mm, nat.labels, nat.spacing_mm, nat.origin_mm,
                             [case.index(name)], clear + 2.0).min()
        assert near - R < PLAN.margin_mm + 0.5, f"path never approaches {name}"


def test_demo_trajectory_is_deterministic(phantom):
    from bonesim.io.toolpath import demo_trajectory

    case, _, traj = phantom
    again = demo_trajectory(case, "cutting-5mm")
    np.testing.assert_array_equal(again.pos_mm, traj.pos_mm)
    np.testing.assert_array_equal(again.suction, traj.suction)
    assert np.all(traj.speed_rpm == 60000.0) and np.all(traj.direction == 1)


def test_floors_and_segment_checks_against_dense_sampling():
    """The planner's two proofs on a clearance field: every depth above a
    traced floor is clear and the floor is where it stops being so; a move
    found clear is clear at every point, one clear by a margin is found so."""
    rng = np.random.default_rng(5)
    lab = np.zeros((40, 40, 40), np.uint8)
    for _ in range(12):
        lo = rng.integers(0, 36, 3)
        hi = lo + rng.integers(1, 6, 3)
        lab[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = 1
    cl = Clearance(lab, (0.3, 0.4, 0.5), (0, 0, 0), [1])
    clear = 2.0

    def dist(p):
        return cl.distance(p)

    base = np.column_stack([rng.uniform(0, 12, 200), rng.uniform(0, 16, 200),
                            np.full(200, -8.0)])
    view = np.array([0.0, 0.0, 1.0])
    floor = _trace_floors(dist, base, view, clear, 40.0)
    for b, f in zip(base, floor):
        if not np.isfinite(f):
            assert dist(b)[0] < clear                       # starts too close
            continue
        t = np.linspace(0.0, f, 400)
        assert dist(b + t[:, None] * view).min() >= clear - 1e-9
        if f < 40.0:
            assert dist(b + f * view)[0] < clear + 2e-3
    found = 0
    for _ in range(300):
        p, q = rng.uniform(-3, 20, (2, 3))
        dense = dist(p + np.linspace(0, 1, 3000)[:, None] * (q - p)).min()
        ok = _segment_clear(dist, p, q, clear)
        if ok:
            found += 1
            assert dense >= clear - 1e-9
        elif dense >= clear + 0.05:
            raise AssertionError(f"a move clear by {dense - clear:.3f} mm was refused")
    assert 30 < found < 270


# ------------------------------------------------------------------ rinses
def runs(flags):
    """(start, stop) index pairs of the runs of True."""
    f = np.concatenate([[False], flags, [False]]).astype(int)
    edges = np.flatnonzero(np.diff(f))
    return list(zip(edges[::2], edges[1::2]))


def test_rinses_irrigate_then_suction_between_passes(phantom):
    _, _, traj = phantom
    assert not np.any(traj.drill & (traj.suction | traj.irrigation))
    rinse = traj.suction | traj.irrigation
    dt = np.diff(traj.t_s, append=traj.t_s[-1])
    drilled = np.cumsum(dt * traj.drill)
    starts = []
    for a, b in runs(rinse | ~traj.drill):
        if not rinse[a:b].any():
            continue
        starts.append(a)
        seg = slice(a, b)
        # each rinse: irrigation first, then suction
        first_irr = np.flatnonzero(traj.irrigation[seg])
        first_suc = np.flatnonzero(traj.suction[seg])
        assert first_irr.size and first_suc.size
        assert first_irr[-1] < first_suc[0]
    # between rinses, at least rinse_every_s of drilling; one after the last pass
    gaps = np.diff(drilled[np.array(starts)], prepend=0.0)
    assert len(starts) >= 3 and np.all(gaps[:-1] >= PLAN.rinse_every_s - 1e-6)
    assert gaps[-1] > 0.0
    assert not traj.drill[starts[-1]:].any()
    # the rinses sweep the cavity: the tip goes below the first pass's depth,
    # within the drilled disc
    view = traj.axis[0]
    depth = traj.pos_mm @ view
    first_pass = depth[traj.drill].min() + PLAN.layer_mm
    assert np.any(depth[traj.suction] > first_pass + 5.0)
    # and they do not take over the plan: drilling stays most of the time
    assert dt[traj.suction | traj.irrigation].sum() < 0.25 * dt[traj.drill].sum()


# ---------------------------------------------- source resolution, any orientation
FINE_MM = 0.25


@pytest.fixture(scope="module")
def fine_phantom():
    from bonesim.io.phantom import phantom_volume

    case = load_case("phantom")
    return case, phantom_volume(7, FINE_MM, (52.0, 52.0, 52.0))


def export_and_read(tmp_path, case, labels, spacing, orientation):
    """Write a label stack (the given axis code) and read it back as a case
    volume on the engine's 0.5 mm grid."""
    from bonesim.io.volumes import load_volume, write_label_stack

    folder = tmp_path / orientation
    write_label_stack(folder, labels, [s.display_color for s in case.structures],
                      orientation=orientation)
    size = _stack_size(labels.shape, spacing, orientation)
    return load_volume("label-stack", folder, kinds=[s.kind for s in case.structures],
                       colors=[s.display_color for s in case.structures], voxel_mm=0.5,
                       pattern="*.png", size_mm=size, orientation=orientation)


def _stack_size(shape, spacing, orientation):
    """Extent [mm] along the stack's columns, rows and slices: each image axis
    runs along the patient axis its letter names."""
    axis_of = {"L": 0, "R": 0, "P": 1, "A": 1, "S": 2, "I": 2}
    return tuple(float(shape[axis_of[ch]] * spacing[axis_of[ch]]) for ch in orientation)


@pytest.mark.parametrize("orientation,step", [("LPS", (1, 1, 1)), ("PLI", (1, 1, 1)),
                                              ("IAR", (1, 2, 1)), ("RAS", (2, 1, 1))])
def test_margin_holds_at_the_source_resolution(tmp_path, fine_phantom, orientation, step):
    """Fine (and anisotropic) label-stack exports of the phantom, written in
    permuted / flipped orientations and read back: every planned burr centre
    keeps the margin measured on the source voxels."""
    case, fine = fine_phantom
    labels = np.ascontiguousarray(fine.labels[::step[0], ::step[1], ::step[2]])
    spacing = FINE_MM * np.array(step, float)
    vol = export_and_read(tmp_path, case, labels, spacing, orientation)
    nat = vol.native_labels
    assert np.array_equal(nat.labels, labels)                 # back in the patient frame
    np.testing.assert_allclose(nat.spacing_mm, spacing)
    danger = danger_of(case.structures)
    cam = case.camera
    plan = dataclasses.replace(PLAN, burr_radius_mm=R)
    traj = demo_mastoidectomy(vol.labels, vol.spacing_mm, vol.origin_mm, case.structures,
                              cam.eye_mm, cam.focal_mm, plan,
                              Clearance.from_native(nat, danger))
    clear = R + plan.margin_mm
    d = box_clearance(traj.pos_mm, nat.labels, nat.spacing_mm, nat.origin_mm, danger,
                      clear + 1.0)
    assert d.min() >= clear - 1e-6
    assert d.min() < clear + 0.1                              # and it does come close
    assert traj.suction.any() and traj.irrigation.any() and traj.drill.any()


def test_the_grid_alone_would_not_keep_the_margin(fine_phantom):
    """Planned on the 0.5 mm grid, the same plan comes closer than its margin
    to the source voxels: why the clearance is measured on the native map."""
    from bonesim.io.volumes import resample_isotropic

    case, fine = fine_phantom
    labels, origin = resample_isotropic(fine.labels, np.full(3, FINE_MM), fine.origin_mm,
                                        0.5, order=0)
    cam = case.camera
    danger = danger_of(case.structures)
    traj = demo_mastoidectomy(labels, 0.5, origin, case.structures, cam.eye_mm,
                              cam.focal_mm, PLAN)
    d = box_clearance(traj.pos_mm, fine.labels, FINE_MM, fine.origin_mm, danger,
                      R + PLAN.margin_mm + 1.0)
    assert d.min() < R + PLAN.margin_mm - 0.05


# ------------------------------------------------------------ simulation
def drive(model, traj):
    """Step the model through the trajectory at 1 kHz; the force magnitude of
    every step [N]."""
    r = traj.resample(1000.0)
    state = make_state(model)
    force = np.empty(len(r))
    for q in range(len(r)):
        force[q] = np.linalg.norm(step(model, state, r.sample(q)))
    return r, state, force


@pytest.mark.slow
def test_demo_run_drills_bone_rinses_without_contact(phantom):
    case, vol, traj = phantom
    model = load_model("phantom", "cutting-5mm")
    r, state, force = drive(model, traj)
    removed = state.removed_by_label
    assert removed[1] > 25000 and removed[2:].sum() == 0      # bone only
    assert len(events.injuries(state.tissue.read(0))["t_s"]) == 0
    assert r.suction.sum() > 5000 and r.irrigation.sum() > 2000
    # the suction / irrigation tip never touches bone: no force at all
    assert np.all(force[r.suction | r.irrigation] == 0.0)
    assert np.any(force[r.drill] > 0.5)


@pytest.mark.slow
def test_fine_anisotropic_export_run_injures_nothing(tmp_path, fine_phantom):
    from bonesim.io.burrs import load_burr

    case, fine = fine_phantom
    labels = np.ascontiguousarray(fine.labels[:, :, ::2])
    spacing = FINE_MM * np.array([1.0, 1.0, 2.0])
    vol = export_and_read(tmp_path, case, labels, spacing, "PIR")
    model = make_model(vol.labels, vol.spacing_mm, case.structures,
                       load_burr("cutting-5mm"), origin_mm=vol.origin_mm)
    danger = danger_of(case.structures)
    cam = case.camera
    traj = demo_mastoidectomy(vol.labels, vol.spacing_mm, vol.origin_mm, case.structures,
                              cam.eye_mm, cam.focal_mm, PLAN,
                              Clearance.from_native(vol.native_labels, danger))
    r, state, force = drive(model, traj)
    assert state.removed_by_label[1] > 20000 and state.removed_by_label[2:].sum() == 0
    assert len(events.injuries(state.tissue.read(0))["t_s"]) == 0
    assert np.all(force[r.suction | r.irrigation] == 0.0)


# ------------------------------------------------------------ plan file, errors
def test_shipped_plan_is_the_documented_defaults():
    assert PLAN == DemoPlan()


BAD_PLANS = [
    ("margin_mm = 1.0", "", "missing required key(s) 'margin_mm'"),
    ("margin_mm = 1.0", "margin_mm = 1.0\nburr_radius_mm = 2.0",
     "unknown key(s) 'burr_radius_mm'"),
    ("layer_mm = 1.0", "layer_mm = 0.0", "'layer_mm' must be a finite number > 0"),
    ("n_layers = 20", "n_layers = 2.5", "'n_layers' must be an integer"),
    ("irrigation_every = 2", "irrigation_every = 0", "'irrigation_every' must be >= 1"),
    ("line_overlap = 0.5", "line_overlap = 1.5", "'line_overlap' must be <= 0.99"),
    ("rinse_gap_mm = 0.5", 'rinse_gap_mm = "small"', "'rinse_gap_mm' must be a number"),
]


@pytest.mark.parametrize("old,new,fragment", BAD_PLANS)
def test_bad_plan_files_name_file_and_key(tmp_path, old, new, fragment):
    text = default_plan_path().read_text()
    assert old in text
    path = tmp_path / "demo_plan.toml"
    path.write_text(text.replace(old, new))
    with pytest.raises(BonesimError) as e:
        load_demo_plan(path)
    assert fragment in str(e.value) and str(path) in str(e.value)
    assert e.value.field == "plan"


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
    # a nerve lying on the bone, right under the view: nothing is clear
    nerve = labels.copy()
    nerve[:, :, 8:] = 2
    with pytest.raises(BonesimError, match="no bone lies under|no travel height"):
        demo_mastoidectomy(nerve, 0.5, (0, 0, 0), [BONE, NERVE], (2, 2, 50), (2, 2, 40),
                           DemoPlan(region_radius_mm=0.5))
    with pytest.raises(ValueError, match="lacks structure"):
        demo_mastoidectomy(nerve, 0.5, (0, 0, 0), [BONE, NERVE], (2, 2, 50), (2, 2, 40),
                           DemoPlan(region_radius_mm=0.5),
                           Clearance(nerve, 0.5, (0, 0, 0), []))
    # the same view straight above the bone does plan a path, and suctions
    # (the 3 mm cube is too shallow a cavity to irrigate below the travel plane)
    traj = demo_mastoidectomy(labels, 0.5, (0, 0, 0), [BONE], (2, 2, 50), (2, 2, 40),
                              DemoPlan(region_radius_mm=0.5))
    assert isinstance(traj, Trajectory)
    assert traj.drill.any() and traj.pos_mm[:, 2].min() < 3.5 + 2.5
    assert traj.suction.any()
