"""A live run with every tool of the reference simulator at once: cut-plane
strokes free a block of cortex, the fragment finder splits it off, a plate
is placed on it and affixed, and the block is lifted out with the plate. The
recording replays bit for bit and plays back to where the run left things."""
from __future__ import annotations


import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.bodies import IDENTITY_POSE
from bonesim.engine.cut_plane import plane_pose
from bonesim.io.loading import load_model
from bonesim.runtime.commands import CutPlane, MoveBody
from bonesim.runtime.fragment_finder import FragmentFinder
from bonesim.runtime.haptic_loop import HapticLoop
from bonesim.runtime.record import Recorder
from bonesim.session.header import make_header
from bonesim.runtime.rigid_commands import AffixPlate, PlacePlate
from bonesim.session.reader import read_session
from bonesim.session.replay import replay, verify
from tests.bonesim.waiting import SETTLE_STEPS, wait_steps, wait_tool_at, wait_until

#: A block of the lateral cortex (the face at x of about 20 mm, looked at
#: along -x): its outer face's centre 1 mm off the bone [mm], its size along
#: y and z [mm], its depth [mm]; slots half a millimetre wide.
CENTRE_MM = np.array([21.0, 4.0, 0.0])
SIZE_MM = (26.0, 8.0)
DEPTH_MM = 3.5
SLOT_MM = 0.5
INTO = np.array([-1.0, 0.0, 0.0])
#: How far the block is lifted out [mm].
LIFT_MM = 12.0
#: The straight plate (24 mm long along its mesh x, bottom facing mesh -z)
#: dropped onto the block lengthwise: mesh x along case y, mesh z along +x
#: (a turn of 120 degrees about (1, 1, 1)), 1.5 mm above the bone.
PLATE_POSE = (22.5, 4.0, 0.0, 0.5, 0.5, 0.5, 0.5)


def _largest_new_body(state) -> int:
    """The body (other than 0) holding the most bone voxels."""
    solid = state.grid.density > 0
    n = [int(np.count_nonzero(solid & (state.body == b))) for b in range(int(state.n_bodies))]
    return int(np.argmax(n[1:])) + 1


def _strokes():
    """The four walls and the floor of the block, as CutPlane parameters."""
    wy, hz = SIZE_MM
    walls = (((0.0, hz / 2), wy, SLOT_MM), ((0.0, -hz / 2), wy, SLOT_MM),
             ((wy / 2, 0.0), SLOT_MM, hz), ((-wy / 2, 0.0), SLOT_MM, hz))
    out = [dict(pose=plane_pose(CENTRE_MM + (0.0, dy, dz), INTO, (0, 1, 0)), width_mm=w,
                height_mm=h, depth_mm=DEPTH_MM + 1.0) for (dy, dz), w, h in walls]
    out.append(dict(pose=plane_pose(CENTRE_MM + (DEPTH_MM + 1.0) * INTO, INTO, (0, 1, 0)),
                    width_mm=wy + SLOT_MM, height_mm=hz + SLOT_MM, depth_mm=SLOT_MM))
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    model = load_model("phantom", "cutting-5mm")
    path = tmp_path_factory.mktemp("tools") / "tools.h5"
    loop = HapticLoop(model)
    rec = Recorder(loop, path, make_header(model, input_device="mouse"))
    finder = None
    try:
        rec.start()
        loop.start()
        loop.set_drill(False)
        loop.set_target(CENTRE_MM - 30.0 * INTO, INTO)      # well off the bone: a stopped
        assert wait_tool_at(loop, CENTRE_MM - 30.0 * INTO)  # tool would push the block
        finder = FragmentFinder(model, loop.state, loop.status, snapshot=False)
        for params in _strokes():
            loop.send(CutPlane, **params)
        assert wait_until(lambda: loop.state.n_bodies >= 2,
                     poll=lambda: finder.poll(loop.send)), "the block was not split off"
        assert wait_steps(loop, 300)
        finder.poll(loop.send)                              # any specks of the cuts
        assert wait_steps(loop, 300)
        body = _largest_new_body(loop.state)               # the block
        # a plate dropped onto the block, left to settle, affixed
        applied = int(loop.status["commands_applied"])
        loop.send(PlacePlate, plate="straight-4", pose=PLATE_POSE)
        assert wait_until(lambda: int(loop.status["commands_applied"]) > applied)
        assert wait_steps(loop, SETTLE_STEPS)
        loop.send(AffixPlate)
        assert wait_until(lambda: int(loop.status["commands_applied"]) > applied + 1)
        assert wait_steps(loop, 300)
        # the block lifted out along the line of sight, the plate with it
        pose = np.array(IDENTITY_POSE, float)
        pose[:3] = -LIFT_MM * INTO
        loop.send(MoveBody, body=body, pose=pose)
        assert wait_until(lambda: tuple(loop.state.pose[body][:3]) == tuple(pose[:3]))
        assert wait_steps(loop, 200)
        rejected = int(loop.status["commands_rejected"])
        error = bytes(loop.status["command_error"]).decode(errors="replace")
        stats = dict(finder.stats)
        rec.close()
    finally:
        if finder is not None:
            finder.close()
        loop.close()
    return model, read_session(path), body, rejected, error, stats


def test_cuts_split_and_plate_are_in_the_recorded_stream(run):
    model, s, body, rejected, error, stats = run
    assert rejected == 0, error
    k = s.tissue["kind"]
    assert (k == events.CUT).sum() == 5
    assert stats["split"] >= 1 and (k == events.SPLIT).sum() > 100      # a block, not a speck
    assert (s.tissue["body"][k == events.SPLIT] >= 1).all()
    plates = np.flatnonzero(k == events.PLATE)
    assert len(plates) > 1 and s.tissue["label"][plates[-1]] == body + 1   # affixed to it
    # the cuts removed voxels; the split moved the block, it did not remove it
    assert (k == events.REMOVED).sum() > 500


def test_the_run_replays_bit_for_bit(run):
    _, s, body, _, _, _ = run
    report = verify(s)
    assert report["ok"], report
    last = s.tissue["value"][np.flatnonzero((s.tissue["kind"] == events.POSE)
                                            & (s.tissue["body"] == body))[-1]]
    np.testing.assert_array_equal(replay(s)["state"].pose[body], last)


def test_playback_ends_with_the_block_lifted_and_the_plate_on_it(run):
    from bonesim.session.playback import Player

    model, s, body, _, _, _ = run
    p = Player(s, model, [model.burr], surface=False)
    p.seek(p.timeline.duration)
    rep = p.replica
    assert rep.state.n_bodies == body + 1
    np.testing.assert_allclose(rep.state.pose[body][:3], -LIFT_MM * INTO)
    k = s.tissue["kind"]
    plates = np.flatnonzero(k == events.PLATE)
    (slot, (cat, pose, host)), = rep.plates.items()
    np.testing.assert_array_equal(pose, s.tissue["value"][plates[-1]])
    assert host == body
    # the plate rose with the block
    first = s.tissue["value"][plates[0]]
    assert pose[:3] @ -INTO > first[:3] @ -INTO + 0.8 * LIFT_MM
