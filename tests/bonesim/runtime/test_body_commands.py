"""Bodies through the haptic loop's command ring: split and moved by hand,
recorded, replayed bit for bit, and followed by replicas."""
from __future__ import annotations


import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.bodies import IDENTITY_POSE, pose_matrix, publish_split
from bonesim.io.case import load_case
from bonesim.runtime.commands import MoveBody, SplitBox
from bonesim.runtime.haptic_loop import HapticLoop
from bonesim.engine.haptics import O_MAG
from bonesim.io.loading import load_model
from bonesim.engine.model import Sample, make_state, reset_state, step
from bonesim.runtime.record import Recorder
from bonesim.session.header import make_header
from bonesim.session.replay import replay, verify
from bonesim.engine.replica import TissueReplica
from bonesim.session.reader import read_session
from tests.bonesim.waiting import wait_drill_off, wait_steps, wait_until


#: Drilling after the cut [s].
DRILL_S = 1.0
#: The hand-made cut is the plane through the burr's centre normal to this axis.
AXIS_CUT = 1


@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-5mm")


def _target():
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    return np.array([23.0, 3.0, -2.0]) + 3.0 * view, view


@pytest.fixture(scope="module")
def split_run(model, tmp_path_factory):
    """Mouse drilling with the bone split by hand, through the ring, into two
    bodies across the drilled spot (identity poses), recorded; then one body
    moved far away."""
    path = tmp_path_factory.mktemp("bodies") / "split.h5"
    target, view = _target()
    lo = np.zeros(3, int)
    hi = np.array(model.grid.shape) - 1
    loop = HapticLoop(model)
    rec = Recorder(loop, path, make_header(model, input_device="mouse"))
    live = None
    try:
        rec.start()
        loop.start()
        live = TissueReplica(model, loop.state, snapshot=False)
        loop.set_target(target, view)
        loop.set_drill(True, speed_rpm=60000.0)
        assert wait_until(lambda: loop.state.n_removed > 20)
        # cut through where the burr now drills
        at = np.asarray(loop.status["pos_mm"], float)
        lo[:] = np.rint((at - model.grid.origin_mm) / model.spacing_mm).astype(int)
        lo[AXIS_CUT - 1] = lo[AXIS_CUT - 2] = 0      # the half beyond one plane
        loop.send(SplitBox, lo=lo, hi=hi, body=0)
        assert wait_until(lambda: loop.state.n_bodies == 2)
        n0 = loop.state.n_removed
        t0 = float(loop.status["t_s"])
        # at least a second of drilling across the cut
        assert wait_until(lambda: loop.state.n_removed > n0 + 150
                     and float(loop.status["t_s"]) > t0 + DRILL_S)
        # the tool off the bone before the drill stops (a stopped tool would
        # push the split-off body: bonesim.runtime.rigid_commands)
        loop.set_target(target - 20.0 * view, view)
        assert wait_until(lambda: np.linalg.norm(np.asarray(loop.status["pos_mm"]) - target) > 15.0)
        loop.set_drill(False)
        assert wait_drill_off(loop)
        # a replica following the loop holds its tissue
        live.drain()
        np.testing.assert_array_equal(live.grid.density == 0, loop.state.grid.density == 0)
        np.testing.assert_array_equal(live.state.body, loop.state.body)
        pose = np.array([0.0, 0.0, 80.0, *IDENTITY_POSE[3:]])
        loop.send(MoveBody, body=1, pose=pose)
        assert wait_until(lambda: loop.state.pose[1][2] == 80.0)
        assert wait_steps(loop, 50)
        rec.close()
        live.drain()
        np.testing.assert_array_equal(live.state.pose, loop.state.pose)
        loop_body = loop.state.body.copy()
        applied = int(loop.status["commands_applied"])
    finally:
        loop.close()
    return read_session(path), loop_body, applied


def test_split_and_move_through_the_ring_are_recorded(split_run):
    s, loop_body, applied = split_run
    assert applied == 2
    k = s.tissue["kind"]
    split = k == events.SPLIT
    assert split.sum() > 100 and (s.tissue["body"][split] == 1).all()
    assert (loop_body == 1).sum() == split.sum()
    assert (s.tissue["n"][split] == split.sum()).all()
    pose = np.flatnonzero(k == events.POSE)
    assert len(pose) == 1 and s.tissue["value"][pose[0], 2] == 80.0
    # drilling, the split in one block, more drilling across the cut (both
    # bodies lose voxels), then the move
    rem = np.flatnonzero(k == events.REMOVED)
    first, last = np.flatnonzero(split)[[0, -1]]
    assert last - first + 1 == split.sum() and rem[0] < first and rem[-1] < pose[0]
    after = rem[rem > last]
    assert set(np.unique(s.tissue["body"][after]).tolist()) == {0, 1}


def test_a_run_split_at_the_identity_is_the_one_body_run(split_run, model):
    s, loop_body, _ = split_run
    report = verify(s)
    assert report["ok"], report
    out = replay(s)
    np.testing.assert_array_equal(out["state"].body, loop_body)
    # the same samples on the bone as one body, up to the move: the same
    # removals and forces
    t_move = float(s.tissue["t_s"][s.tissue["kind"] == events.POSE][0])
    one = {k: v for k, v in s.tissue.items()}
    keep = ~np.isin(one["kind"], (events.SPLIT, events.POSE)) & (one["t_s"] < t_move)
    one = {k: v[keep] for k, v in one.items()}
    st = make_state(model)
    smp = s.samples
    got = []
    cur = events.Cursor(st.tissue, 0)
    n = int(np.searchsorted(smp["t_s"], t_move))
    assert n > 1000 and one["kind"].size > 100
    mag = np.zeros(n)
    for q in range(n):
        step(model, st, Sample(float(smp["t_s"][q]), smp["pos_mm"][q], smp["axis"][q],
                               bool(smp["drill"][q]), float(smp["speed_rpm"][q]),
                               int(smp["direction"][q])))
        mag[q] = st.out[O_MAG]
        if q % 5000 == 0:
            got.append(cur.drain())
    got.append(cur.drain())
    got = events.concat(got)
    for f in ("kind", "label", "t_s", "ijk", "n", "value"):
        np.testing.assert_array_equal(got[f], one[f], err_msg=f)
    np.testing.assert_array_equal(mag, smp["mag_n"][:n])


def test_replica_of_the_recorded_stream_equals_replay_at_the_end(split_run, model):
    s, loop_body, _ = split_run
    rep = TissueReplica(model)
    ev = {k: v for k, v in s.tissue.items() if k != "visible"}
    for a in range(0, len(ev["kind"]), 777):
        rep.apply({k: v[a:a + 777] for k, v in ev.items()})
    out = replay(s)["state"]
    np.testing.assert_array_equal(rep.grid.density == 0, out.grid.density == 0)
    for name in ("body", "pose", "alive", "bounds"):
        np.testing.assert_array_equal(getattr(rep.state, name), getattr(out, name))
    np.testing.assert_array_equal(rep.state.pose_m[1], pose_matrix(rep.state.pose[1]))


def test_bad_body_commands_are_refused_where_sent():
    with pytest.raises(ValueError, match="lo <= hi"):
        SplitBox.encode(lo=(5, 0, 0), hi=(4, 9, 9))
    with pytest.raises(ValueError, match="not unit"):
        MoveBody.encode(body=1, pose=(0, 0, 0, 2.0, 0, 0, 0))


def test_replica_at_every_reset_of_a_recorded_stream(model):
    """The stream of a run with resets and bodies, applied by a replica,
    equals the producer's tissue just before each reset and at the end."""
    st = make_state(model)
    target, view = _target()
    axis = -view
    snaps, t = [], 0.0
    for epoch in range(3):
        if epoch:
            snaps.append((st.tissue.count, st.grid.density.copy(), st.body.copy()))
            t += 1e-3
            reset_state(model, st, rings=False)
            events.push_event(st.tissue, events.RESET, t, n=epoch)
        ijk = np.rint((target - model.grid.origin_mm) / model.spacing_mm).astype(int)
        publish_split(st, 0, np.argwhere(np.ones((6, 6, 6))) + ijk - 3 + epoch, t)
        for q in range(300):
            t += 1e-3
            step(model, st, Sample(t, target - view * 0.002 * q, axis, True, 60000.0, 1))
    snaps.append((st.tissue.count, st.grid.density.copy(), st.body.copy()))
    ev = st.tissue.read(0)
    rep = TissueReplica(model)
    pos = 0
    for count, dens, body in snaps:
        rep.apply({k: v[pos:count] for k, v in ev.items()})
        pos = count
        np.testing.assert_array_equal(rep.grid.density == 0, dens == 0)
        np.testing.assert_array_equal(rep.state.body, body)


def test_playback_shows_each_body_where_it_stands(split_run, model):
    """Played back, the recorded run ends with two surfaces, each only its
    body's voxels, the moved one at its recorded pose; seeking forward in
    steps across the split and the move gives what one seek to the end gives."""
    from bonesim.engine.surface import Surface
    from bonesim.session.playback import Player

    s, loop_body, _ = split_run
    stepped = Player(s, model, [model.burr])
    for t in np.linspace(0.0, stepped.timeline.duration, 23):
        stepped.seek(float(t))
    direct = Player(s, model, [model.burr])
    direct.seek(direct.timeline.duration)
    for p in (stepped, direct):
        rep = p.replica
        assert sorted(rep.body_surfaces) == [0, 1]
        np.testing.assert_array_equal(rep.state.body, loop_body)
        assert rep.body_matrix(1)[2, 3] == 80.0 and rep.body_matrix(0)[2, 3] == 0.0
        for b, surf in rep.body_surfaces.items():
            fresh = Surface.of_model(model, rep.body_grids[b])
            assert surf.canonical() == fresh.canonical(), b
    assert stepped.stats["forward"] > 5
    # body 0's grid: the replica's tissue with body 1 emptied
    from bonesim.engine.body_surfaces import masked_density

    rep = direct.replica
    np.testing.assert_array_equal(rep.body_grids[0].density, masked_density(rep.state, 0))
    # body 1's surface holds exactly body 1's voxels: its vertices are theirs,
    # drawn within a voxel of their centres
    g1 = direct.replica.body_grids[1]
    s1 = direct.replica.body_surfaces[1]
    ijk = s1.ijk[s1.vertex_slots]
    d = np.array([g1.density_at(*v) for v in ijk[:500]])
    assert (d > 0).all()
    centres = g1.origin_mm + g1.spacing_mm * ijk
    assert np.abs(s1.pos[s1.vertex_slots] - centres).max() < g1.spacing_mm


def test_a_large_split_through_the_ring_is_sliced_recorded_and_replays_bit_for_bit(
        model, tmp_path):
    """The half of the phantom beyond a plane through the drilled spot becomes
    body 1 (a box split); then the fragment finder's command moves all of
    body 1 into body 2 (a part far larger than a step's budget: in slices,
    one block of SPLIT events per step) while the burr drills on; recorded,
    and ``bonesim replay --verify`` replays it bit for bit."""
    from bonesim.cli.main import main
    from bonesim.engine.bodies import body_voxel_counts
    from bonesim.engine.slicing import voxels_per_step
    from bonesim.runtime.commands import SplitPart

    path = tmp_path / "large_split.h5"
    target, view = _target()
    hi = np.array(model.grid.shape) - 1
    loop = HapticLoop(model)
    rec = Recorder(loop, path, make_header(model, input_device="mouse"))
    try:
        rec.start()
        loop.start()
        loop.set_target(target, view)
        loop.set_drill(True, speed_rpm=60000.0)
        assert wait_until(lambda: loop.state.n_removed > 20)
        at = np.asarray(loop.status["pos_mm"], float)
        lo = np.rint((at - model.grid.origin_mm) / model.spacing_mm).astype(int)
        lo[AXIS_CUT - 1] = lo[AXIS_CUT - 2] = 0
        loop.send(SplitBox, lo=lo, hi=hi, body=0)
        assert wait_until(lambda: loop.state.n_bodies == 2)
        n1 = int(body_voxel_counts(loop.state)[1])
        assert n1 > 10 * voxels_per_step()
        b1 = loop.state.bounds[1]
        # a voxel of body 1 with bone: the first of its box in (i, j, k) order
        from bonesim.engine.fragments import body_mask

        seed = np.argwhere(body_mask(loop.state, 1, b1[:3], b1[3:]))[0] + b1[:3]
        h0 = loop.state.tissue.count
        loop.send(SplitPart, body=1, seed=seed, lo=b1[:3], hi=b1[3:], n=n1, epoch=0)
        loop.set_target(target + 4.0 * view, view)        # on into the bone meanwhile
        assert wait_until(lambda: loop.state.n_bodies == 3)
        seen = [-1]

        def settled():                    # no SPLIT record for 0.1 s: the split is done
            import time
            time.sleep(0.1)
            ev = loop.state.tissue.read(h0)
            n2 = int(((ev["kind"] == events.SPLIT) & (ev["body"] == 2)).sum())
            done, seen[0] = n2 == seen[0], n2
            return done
        assert wait_until(settled, 60.0)
        loop.set_drill(False)
        assert wait_drill_off(loop)
        rec.close()
    finally:
        loop.close()
    s = read_session(path)
    ev = s.tissue
    split2 = (ev["kind"] == events.SPLIT) & (ev["body"] == 2)
    assert split2.sum() == seen[0] > 10 * voxels_per_step()
    steps = np.unique(ev["t_s"][split2])
    assert len(steps) >= split2.sum() // (voxels_per_step() + 26)   # one block per step
    assert main(["replay", str(path), "--verify"]) == 0
