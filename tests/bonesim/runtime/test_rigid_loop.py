"""A fragment pushed by the tool and a plate placed and affixed through the
real haptic loop, recorded and replayed bit for bit."""
from __future__ import annotations


import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.bodies import IDENTITY_POSE
from bonesim.io.case import load_case
from bonesim.io.loading import load_model
from bonesim.runtime.commands import SplitBox
from bonesim.runtime.haptic_loop import HapticLoop
from bonesim.runtime.record import Recorder
from bonesim.session.header import make_header
from bonesim.runtime.rigid_commands import AffixPlate, PlacePlate
from bonesim.session.reader import read_session
from bonesim.session.replay import replay, verify
from tests.bonesim.waiting import SETTLE_STEPS, wait_steps, wait_tool_at, wait_until


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    model = load_model("phantom", "cutting-5mm")
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    target = np.array([23.0, 3.0, -2.0]) + 3.0 * view
    path = tmp_path_factory.mktemp("rigid") / "rigid.h5"
    loop = HapticLoop(model)
    rec = Recorder(loop, path, make_header(model, input_device="mouse"))
    try:
        rec.start()
        loop.start()
        loop.set_drill(False)
        loop.set_target(target - 4.0 * view, view)          # above the bone
        assert wait_tool_at(loop, target - 4.0 * view)
        # the bone under the tool, 12 voxels across, made a fragment
        c = np.rint((target - model.grid.origin_mm) / model.spacing_mm).astype(int)
        loop.send(SplitBox, lo=c - 6, hi=c + 6, body=0)
        assert wait_until(lambda: loop.state.n_bodies == 2)
        # the stopped tool presses on it
        loop.set_target(target + 2.0 * view, view)
        assert wait_until(lambda: tuple(loop.state.pose[1]) != IDENTITY_POSE)
        assert wait_steps(loop, 300)                        # it is pushed a while
        loop.set_target(target - 6.0 * view, view)          # the tool away
        assert wait_tool_at(loop, target - 6.0 * view)
        loop.send(PlacePlate, plate="straight-4")
        assert wait_until(lambda: int(loop.status["commands_applied"]) == 2)
        assert wait_steps(loop, SETTLE_STEPS)               # it falls and rests
        loop.send(AffixPlate)
        assert wait_until(lambda: int(loop.status["commands_applied"]) == 3)
        assert wait_steps(loop, 200)
        rejected = int(loop.status["commands_rejected"])
        error = bytes(loop.status["command_error"]).decode(errors="replace")
        rec.close()
        pose = loop.state.pose[1].copy()
    finally:
        loop.close()
    return model, read_session(path), pose, rejected, error


def test_the_push_and_the_plate_are_in_the_recorded_stream(run):
    _, s, pose, rejected, error = run
    assert rejected == 0, error
    k = s.tissue["kind"]
    poses = k == events.POSE
    assert poses.sum() > 10 and (s.tissue["body"][poses] == 1).all()
    plates = np.flatnonzero(k == events.PLATE)
    assert len(plates) > 10
    # placed free, came to rest, affixed to a body last
    assert s.tissue["label"][plates[0]] == 0 and s.tissue["label"][plates[-1]] >= 1


def test_the_recorded_run_replays_bit_for_bit(run):
    model, s, _, _, _ = run
    report = verify(s)
    assert report["ok"], report
    # the replay ends with the fragment where the recording last saw it
    last = s.tissue["value"][np.flatnonzero(s.tissue["kind"] == events.POSE)[-1]]
    np.testing.assert_array_equal(replay(s)["state"].pose[1], last)


def test_playback_shows_the_fragment_and_the_plate_where_the_run_left_them(run):
    from bonesim.session.playback import Player

    model, s, _, _, _ = run
    p = Player(s, model, [model.burr], surface=False)
    half = p.timeline.duration / 2
    p.seek(p.timeline.duration)
    rep = p.replica
    k = s.tissue["kind"]
    last_pose = s.tissue["value"][np.flatnonzero(k == events.POSE)[-1]]
    np.testing.assert_array_equal(rep.state.pose[1], last_pose)
    plates = np.flatnonzero(k == events.PLATE)
    (slot, (cat, pose, host)), = rep.plates.items()
    assert slot == s.tissue["body"][plates[-1]] and cat == 0 and host >= 0
    np.testing.assert_array_equal(pose, s.tissue["value"][plates[-1]])
    # seeking back before the plate was placed shows none
    p.seek(min(half, float(s.tissue["t_s"][plates[0]]) - p.timeline.t0 - 0.01))
    assert p.replica.plates == {}
