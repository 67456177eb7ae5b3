"""Replay of a run with a large split done in slices (bonesim.engine.split_jobs):
each slice is a block of SPLIT records at its own step, replayed as recorded,
so the run replays bit for bit."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from bonesim.engine import events
from bonesim.engine.bodies import body_voxel_counts
from bonesim.engine.model import make_model
from bonesim.engine.slicing import voxels_per_step
from bonesim.engine.world_commands import SplitPart
from bonesim.io.burrs import load_burr
from bonesim.io.trajectory import Trajectory
from bonesim.runtime.simulate import run_trajectory
from bonesim.session.reader import read_session
from bonesim.session.replay import replay, verify

EDGE = 32
CORNER = (4, 4, 12)


def _case():
    """A floor slab and, 3 mm above it, a 32^3 cube of bone (0.5 mm voxels)."""
    lab = np.zeros((EDGE + 8, EDGE + 8, 12 + EDGE + 8), np.uint8)
    lab[:, :, :6] = 1
    i, j, k = CORNER
    lab[i:i + EDGE, j:j + EDGE, k:k + EDGE] = 1
    bone = SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200))
    return make_model(lab, 0.5, [bone], load_burr("cutting-5mm"))


def test_a_run_with_a_sliced_split_while_drilling_the_part_replays_bit_for_bit(tmp_path):
    model = _case()
    assert EDGE ** 3 > 4 * voxels_per_step()          # several slices
    top = (CORNER[2] + EDGE) * 0.5 - 0.25             # the cube's top face [mm]
    centre = (np.asarray(CORNER[:2]) + EDGE / 2) * 0.5
    t = np.round(np.arange(0.0, 0.4, 0.001), 6)
    # down from 1 mm above the top into the cube, drilling, while it splits
    z = top + 3.5 - np.clip(t / 0.3, 0.0, 1.0) * 5.0
    pos = np.column_stack([np.full(len(t), centre[0]), np.full(len(t), centre[1]), z])
    traj = Trajectory(t, pos, np.tile([0.0, 0.0, -1.0], (len(t), 1)), np.ones(len(t), bool),
                      np.full(len(t), 60000.0))
    lo, hi = np.asarray(CORNER) - 1, np.asarray(CORNER) + EDGE
    cmd = SplitPart(0, CORNER, tuple(lo), tuple(hi), EDGE ** 3, 0)
    path = tmp_path / "sliced.h5"
    out = run_trajectory(model, traj, surface=False, record=path, commands=[(0.25, cmd)])
    assert out["record_ok"]
    s = read_session(path)
    ev = s.tissue
    split = ev["kind"] == events.SPLIT
    times = np.unique(ev["t_s"][split])
    assert len(times) >= 4                              # one block per step, several steps
    rem = events.removals(ev)
    # the burr drilled the cube while it was being split
    during = (rem["t_s"] >= times[0]) & (rem["t_s"] <= times[-1])
    assert len(rem["t_s"]) > 20 and during.sum() > 5
    assert set(np.unique(rem["body"]).tolist()) >= {1}
    report = verify(s, models=[model])
    assert report["ok"] and report["identical"], report
    st = replay(s, models=[model])["state"]
    counts = body_voxel_counts(st)
    # no voxel lost: the cube is in body 1 or removed
    assert counts[1] + int((rem["body"] == 1).sum()) == split.sum()
    assert counts[1] > 0.9 * EDGE ** 3


def test_a_run_with_sliced_strokes_and_a_split_under_way_together_replays_bit_for_bit(
        tmp_path, monkeypatch):
    """Two large cut-plane strokes (the second waits behind the first) and a
    large split, all under way while the burr drills: the CUT records carry
    the rays per step, replay repeats the slicing step for step."""
    from bonesim.engine.cut_plane import plane_pose, quantize_size
    from bonesim.engine.world_commands import CutStroke

    model = _case()
    top = (CORNER[2] + EDGE) * 0.5 - 0.25
    centre = (np.asarray(CORNER[:2]) + EDGE / 2) * 0.5
    t = np.round(np.arange(0.0, 0.35, 0.001), 6)
    z = top + 3.5 - np.clip(t / 0.3, 0.0, 1.0) * 5.0
    pos = np.column_stack([np.full(len(t), centre[0]), np.full(len(t), centre[1]), z])
    traj = Trajectory(t, pos, np.tile([0.0, 0.0, -1.0], (len(t), 1)), np.ones(len(t), bool),
                      np.full(len(t), 60000.0))
    lo, hi = np.asarray(CORNER) - 1, np.asarray(CORNER) + EDGE
    side = plane_pose((CORNER[0] * 0.5 - 0.25, centre[1], CORNER[2] * 0.5 + EDGE * 0.25),
                      (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    um = quantize_size(12.0, 12.0, 3.0)
    cmds = [(0.25, SplitPart(0, CORNER, tuple(lo), tuple(hi), EDGE ** 3, 0)),
            (0.251, CutStroke(side, um)), (0.251, CutStroke(side + (0, 0, 1, 0, 0, 0, 0), um))]
    path = tmp_path / "strokes.h5"
    out = run_trajectory(model, traj, surface=False, record=path, commands=cmds)
    assert out["record_ok"]
    s = read_session(path)
    ev = s.tissue
    cut = np.flatnonzero(ev["kind"] == events.CUT)
    assert len(cut) == 2 and (ev["n"][cut] < 0).all()
    rem = events.removals(ev)
    # the strokes' removals span several steps after their records
    after = rem["t_s"][(rem["t_s"] > ev["t_s"][cut[0]])]
    assert len(np.unique(after)) > 4
    report = verify(s, models=[model])
    assert report["ok"] and report["identical"], report
    # the slicing comes from the records, not from today's data file
    import bonesim.engine.slicing as sj

    monkeypatch.setattr(sj, "voxels_per_step", lambda table="split": 7)
    report = verify(s, models=[model])
    assert report["ok"] and report["identical"], report
