"""Headless runs (bonesim.runtime.simulate): the closest approach at native resolution."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.io.loading import load_model
from bonesim.io.anatomy import clinical_name
from bonesim.runtime.simulate import (CLEARANCE_EVERY, approach_text, closest_approach,
                                      run_trajectory)
from bonesim.io.trajectory import Trajectory


@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-4mm")


@pytest.fixture(scope="module")
def native_boxes(model):
    """Centres and labels of every source voxel of a structure that is not bone."""
    nat = model.case.load_volume().native_labels
    ijk = np.argwhere(nat.labels > 1)
    return (nat.origin_mm + ijk * nat.spacing_mm, nat.labels[tuple(ijk.T)],
            nat.spacing_mm / 2)


def naive_gaps(model, boxes, pts):
    """Reference: per point, the distance to the nearest of those voxel boxes
    minus the burr's radius, and that voxel's structure."""
    c, lab, half = boxes
    out = []
    for p in pts:
        d = np.linalg.norm(np.maximum(np.abs(c - p) - half, 0.0), axis=1)
        k = int(np.argmin(d))
        out.append((d[k] - model.burr.radius_mm, int(lab[k])))
    return out


def test_closest_approach_matches_brute_force(model, native_boxes):
    rng = np.random.default_rng(5)
    nat = model.clearance
    # points near the structures, some inside them
    some = np.concatenate([nat.surface_mm(s)[::97] for s in nat.structures])
    pts = some[rng.choice(len(some), 25, replace=False)] + rng.normal(0, 2.0, (25, 3))
    gap, label, at = closest_approach(model, pts)
    ref = naive_gaps(model, native_boxes, pts)
    k = int(np.argmin([g for g, _ in ref]))
    assert at == k and label == ref[k][1]
    assert gap == pytest.approx(ref[k][0], abs=1e-9)
    assert closest_approach(model, np.zeros((0, 3))) == (float("inf"), 0, -1)


def test_run_reports_the_drilling_burrs_closest_approach(model, native_boxes):
    # a line at 10 mm/s past the facial nerve, drilling only on its second half
    nerve = model.clearance.surface_mm(model.case.index("facial_nerve")).mean(axis=0)
    t = np.linspace(0.0, 1.0, 11)
    start, end = nerve + [30.0, 0.0, 0.0], nerve + [8.0, 0.0, 0.0]
    pos = start + (end - start) * t[:, None]
    drill = (t >= 0.5).astype(np.uint8)
    traj = Trajectory(t_s=t, pos_mm=pos, axis=np.tile([1.0, 0.0, 0.0], (11, 1)),
                      drill=drill, speed_rpm=np.full(11, 60000.0),
                      direction=np.ones(11, np.int8))
    out = run_trajectory(model, traj, surface=False)
    c = out["closest_approach"]
    fine = traj.resample(model.haptic_rate_hz)
    q = np.arange(0, len(fine.t_s), CLEARANCE_EVERY)
    q = q[fine.drill[q].astype(bool)]
    ref = min(naive_gaps(model, native_boxes, fine.pos_mm[q]))
    assert c["clearance_mm"] == pytest.approx(ref[0], abs=1e-3)
    assert c["structure"] == model.structure_name(ref[1])       # the code name, for files
    assert c["display_name"] == clinical_name(c["structure"])      # the name on screen
    assert c["native_spacing_mm"] == [0.5, 0.5, 0.5] and c["t_s"] >= 0.5   # drilling only


def test_distance_lines_name_their_structure():
    assert approach_text(1.0, "facial_nerve") == "1.00 mm to the Facial nerve"
    assert approach_text(0.254, "SS") == "0.25 mm to the Sigmoid sinus"


def test_simulate_summary_names_the_structure(model, capsys):
    """The human summary of ``bonesim simulate`` names the closest structure
    by its clinical name; ``--json`` keeps the code name beside it."""
    from bonesim.cli.drilling import _print_summary

    s = {"case": "phantom", "burr": "cutting-4mm", "steps": 10, "duration_s": 0.01,
         "wall_s": 0.1, "voxels_removed": 3, "volume_removed_mm3": 0.375,
         "removed_by_structure": {"bone": 2, "chorda_tympani": 1},
         "injuries": [{"t_s": 0.005, "kind": "removal", "structure": "chorda_tympani",
                       "voxels": 1}],
         "closest_approach": {"clearance_mm": -0.2, "structure": "chorda_tympani",
                              "display_name": "Chorda tympani", "t_s": 0.005,
                              "native_spacing_mm": [0.5, 0.5, 0.5]},
         "force_n": {"mean": 0.1, "mean_in_contact": 0.2, "max": 0.3},
         "haptic_step_us": {"p50": 10.0, "p99": 20.0}}
    _print_summary(s)
    out = capsys.readouterr().out
    assert "removed 3 voxels (0.375 mm^3): Bone 2, Chorda tympani 1" in out
    assert "removal  Chorda tympani (1 voxels)" in out
    assert ("closest approach of the drilling burr: -0.20 mm to the Chorda tympani at "
            "0.01 s") in out
    assert "chorda_tympani" not in out


def test_a_fragment_split_lifted_and_dropped_in_simulate_replays_bit_for_bit(model, tmp_path):
    """simulate runs the world step: a piece split off, grabbed by the burr
    at its top and lifted 8 mm against gravity, let go (the tool leaving
    upwards), falls and rests in its bed; the tool then drills into it where
    it lies. The recording replays bit for bit, poses and all."""
    from bonesim.bench.rigid import PIECE_HI, PIECE_LO
    from bonesim.engine import events
    from bonesim.engine.rigid import gravity_direction
    from bonesim.engine.world_commands import Grab, Release, SplitBox
    from bonesim.session.reader import read_session
    from bonesim.session.replay import replay, verify

    g = model.grid
    down = gravity_direction(model)
    centre = g.origin_mm + g.spacing_mm * (np.add(PIECE_LO, PIECE_HI) / 2.0)
    # the piece's top: its last bone voxel on the line up from its centre
    top = max(s for s in np.arange(0.0, 20.0, 0.05)
              if _solid(g, centre - s * down))
    base = centre - (top + g.spacing_mm / 2 + model.burr.radius_mm - 0.3) * down
    lift_mm = 8.0
    t = np.round(np.arange(0.0, 2.6 + 1e-9, 0.01), 6)
    # up 8 mm (0.3 .. 1.3 s), 6 mm more at once after the release (1.4 s),
    # then down 1 mm below where the top was (2.0 .. 2.2 s), drilling
    up = np.clip((t - 0.3) / 1.0, 0.0, 1.0) * lift_mm + (t >= 1.41) * 6.0 \
        - np.clip((t - 2.0) / 0.2, 0.0, 1.0) * (lift_mm + 7.0)
    traj = Trajectory(t_s=t, pos_mm=base - up[:, None] * down,
                      axis=np.tile(down, (len(t), 1)), drill=(t >= 2.0).astype(np.uint8),
                      speed_rpm=np.full(len(t), 60000.0), direction=np.ones(len(t), np.int8))
    path = tmp_path / "rigid.h5"
    cmds = [(0.005, SplitBox(0, PIECE_LO, PIECE_HI)), (0.01, Grab(1)), (1.4, Release())]
    out = run_trajectory(model, traj, surface=False, record=path, commands=cmds)
    assert out["record_ok"]
    s = read_session(path)
    poses = events.select(s.tissue, events.POSE)
    assert len(poses["t_s"]) > 1000 and (poses["body"] == 1).all()
    rise = poses["value"][:, :3] @ -down          # the piece's rise against gravity [mm]
    held = poses["t_s"] <= 1.4
    assert rise[held].max() == pytest.approx(lift_mm, abs=0.1)   # carried by the tool
    assert abs(rise[-1]) < 0.1                    # fell back into its bed when let go
    assert poses["t_s"][-1] < 2.0                 # and came to rest before the drilling
    assert np.abs(poses["value"][-1, :3]).max() > 0.0    # not exactly where it was
    rem = events.removals(s.tissue)
    assert len(rem["body"]) > 10 and (rem["body"] == 1).all()   # drilled where it lies
    report = verify(s)
    assert report["ok"] and report["identical"], report
    rep = replay(s)
    np.testing.assert_array_equal(rep["state"].pose[1], poses["value"][-1])
    np.testing.assert_array_equal(events.select(rep["tissue"], events.POSE)["value"],
                                  poses["value"])


def _solid(g, p) -> bool:
    from bonesim.engine.grid import voxel_offset

    ijk = np.rint((p - g.origin_mm) / g.spacing_mm).astype(int)
    b = g.brick_index(*ijk)
    return b >= 0 and g.density[b, voxel_offset(*ijk)] > 0


def test_a_reset_and_a_burr_change_in_simulate_are_recorded_and_replayed(model, tmp_path):
    """A reset given to simulate is a new epoch in the samples and a RESET
    event; the burr column's change a BURR event; replay rebuilds both as
    world commands (bonesim.session.replay.recorded_commands) and verifies."""
    from bonesim.engine import events
    from bonesim.engine.world_commands import Reset, SetBurr
    from bonesim.io.burrs import load_burr
    from bonesim.session.reader import read_session
    from bonesim.session.replay import recorded_commands, verify

    g = model.grid
    cam = model.case.camera
    eye = np.asarray(cam.eye_mm, float)
    into = np.subtract(cam.focal_mm, eye)
    into /= np.linalg.norm(into)
    # the first bone on the camera's ray; the burr 1 mm off it, then 2.5 mm in
    hit = next(eye + s * into for s in np.arange(0.0, 300.0, 0.1) if _solid(g, eye + s * into))
    t = np.round(np.arange(0.0, 1.0 + 1e-9, 0.01), 6)
    along = -model.burr.radius_mm - 1.0 + 3.5 * np.clip(t / 0.25, 0.0, 1.0)
    traj = Trajectory(t_s=t, pos_mm=hit + along[:, None] * into,
                      axis=np.tile(into, (len(t), 1)), drill=np.ones(len(t), np.uint8),
                      speed_rpm=np.full(len(t), 60000.0), direction=np.ones(len(t), np.int8),
                      burr=(t >= 0.15).astype(np.int32))
    path = tmp_path / "reset.h5"
    out = run_trajectory(model, traj, surface=False, record=path,
                         burrs=[load_burr("diamond-3mm")], commands=[(0.5, Reset())])
    assert out["record_ok"]
    s = read_session(path)
    ep = s.samples["epoch"]
    q_reset = int(np.flatnonzero(ep == 1)[0])
    assert s.samples["t_s"][q_reset] == pytest.approx(0.5) and (ep[q_reset:] == 1).all()
    kinds = s.tissue["kind"]
    assert (kinds == events.RESET).sum() == 1 and (kinds == events.BURR).sum() == 1
    assert s.tissue["n"][kinds == events.RESET].tolist() == [1]
    assert s.tissue["t_s"][kinds == events.RESET].tolist() == [s.samples["t_s"][q_reset]]
    rem = events.removals(s.tissue)
    assert (rem["t_s"] < 0.5).sum() > 0 and (rem["t_s"] >= 0.5).sum() > 0   # both epochs cut
    cmds = recorded_commands(s)
    q_burr = int(np.flatnonzero(s.samples["burr"] == 1)[0])
    assert [type(c) for c in cmds[q_burr]] == [SetBurr] and cmds[q_burr][0].index == 1
    assert [type(c) for c in cmds[q_reset]] == [Reset] and cmds[q_reset][0].epoch == 1
    assert set(cmds) == {q_burr, q_reset}
    report = verify(s)
    assert report["ok"], report
