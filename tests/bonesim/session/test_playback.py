"""Playback logic without VTK: timeline lookups, seeking the grid and surface,
the clock, video timing, the progress bar and the video writer."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.errors import BonesimError
from bonesim.engine.model import Sample, reset_state, step
from bonesim.session.playback import SPEEDS, PlaybackClock, Player, Timeline, hud_info
from bonesim.progress import format_clock
from bonesim.engine.surface import Surface

RATE_HZ = 1000.0


def _segment(start, stop, n):
    return np.linspace(start, stop, n)


def drill_run(model, state, plan, snap_every=100):
    """Step ``plan`` (list of ("move", positions) / ("reset", None)) at 1 kHz and
    collect what a recorder would store, plus live density snapshots.

    Returns (samples, removals, injuries, snapshots) where snapshots maps
    session time [s] -> (epoch, density copy) after that step."""
    cols = {k: [] for k in ("t_s", "pos_mm", "axis", "drill", "speed_rpm", "direction",
                            "burr", "epoch", "force_n")}
    rem = {k: [] for k in ("t_s", "ijk", "label", "epoch")}
    inj = {k: [] for k in ("t_s", "label", "kind", "pos_mm", "voxels")}
    snaps = {}
    epoch, q = 0, 0
    axis = np.array([0.0, 0.0, -1.0])
    cur = events.Cursor(state.tissue)

    def drain():
        ev = cur.drain()
        r, i = events.removals(ev), events.injuries(ev)
        for k in ("t_s", "ijk", "label"):
            rem[k].extend(r[k])
        rem["epoch"].extend([epoch] * len(r["t_s"]))
        for k in inj:
            inj[k].extend(i[k])

    for kind, path in plan:
        if kind == "reset":
            drain()
            reset_state(model, state)
            cur = events.Cursor(state.tissue)
            epoch += 1
            continue
        for p in path:
            t = q / RATE_HZ
            f = step(model, state, Sample(t, p, axis, True, 60000.0, 1))
            for k, v in (("t_s", t), ("pos_mm", np.array(p)), ("axis", axis), ("drill", 1),
                         ("speed_rpm", 60000.0), ("direction", 1), ("burr", 0),
                         ("epoch", epoch), ("force_n", f.copy())):
                cols[k].append(v)
            if q % snap_every == snap_every - 1:
                drain()
                snaps[round(t, 6)] = (epoch, state.grid.density.copy())
            q += 1
    drain()
    samples = {k: np.array(v) for k, v in cols.items()}
    removals = {"t_s": np.array(rem["t_s"], float),
                "ijk": np.array(rem["ijk"], np.int32).reshape(-1, 3),
                "label": np.array(rem["label"], np.uint8),
                "epoch": np.array(rem["epoch"], np.int32)}
    removals["visible"] = np.full(len(removals["t_s"]), -1, np.int8)
    injuries = {"t_s": np.array(inj["t_s"], float), "label": np.array(inj["label"], np.uint8),
                "kind": np.array(inj["kind"], np.uint8),
                "pos_mm": np.array(inj["pos_mm"], float).reshape(-1, 3),
                "voxels": np.array(inj["voxels"], np.int32)}
    return samples, removals, injuries, snaps


def fake_session(camera: bool = True):
    """A recorded-session stand-in with the attributes of
    ``bonesim.session.reader.read_session``'s result: 1.8 s on the nerve block (a
    pit, a sweep over the nerve, a reset at 1.2 s, a second pit).

    Returns (session, snapshots)."""
    from tests.bonesim.render.scenes import nerve_block

    model, state = nerve_block()
    down = np.stack([np.full(400, 8.0), np.full(400, 4.0), _segment(10.0, 6.0, 400)], 1)
    sweep = np.stack([np.full(800, 8.0), _segment(4.0, 11.0, 800), np.full(800, 5.6)], 1)
    again = np.stack([np.full(600, 4.0), np.full(600, 4.0), _segment(10.0, 6.5, 600)], 1)
    samples, removals, injuries, snaps = drill_run(
        model, state, [("move", down), ("move", sweep), ("reset", None), ("move", again)])
    cam = {"t_s": np.zeros(0), "eye_mm": np.zeros((0, 3)), "focal_mm": np.zeros((0, 3)),
           "up": np.zeros((0, 3))}
    if camera:
        ct = np.arange(0.0, 1.81, 0.1)
        eye = np.stack([8.0 + 10.0 * ct, np.full(ct.size, 8.0), np.full(ct.size, 60.0)], 1)
        cam = {"t_s": ct, "eye_mm": eye, "focal_mm": np.tile([8.0, 8.0, 6.0], (ct.size, 1)),
               "up": np.tile([0.0, 1.0, 0.0], (ct.size, 1))}
    header = {"schema": 1, "case": {"name": model.name}, "burrs": [{"name": "fake"}],
              "voxel_mm": model.spacing_mm, "rate_hz": RATE_HZ}
    session = SimpleNamespace(header=header, complete=True, samples=samples, removals=removals,
                              injuries=injuries, camera=cam, events=[(1.2, "reset", "")],
                              load_model=lambda: model, burr_models=lambda: [model],
                              path=None)
    return session, snaps


@pytest.fixture(scope="module")
def recorded():
    return fake_session()


def fresh_replay(model, tl, t):
    """Reference: the initial density with every removal of the epoch at
    ``t`` made at or before ``t`` zeroed, voxel by voxel."""
    g = model.grid.copy()
    e = tl.epoch_at(t)
    for ti, ijk, ep in zip(tl.rem_t, tl.rem_ijk, tl.rem_epoch):
        if ep == e and ti <= tl.t0 + t:
            b = g.brick_index(*map(int, ijk))
            i, j, k = (int(v) & 7 for v in ijk)
            g.density[b, (i << 6) | (j << 3) | k] = 0.0
    return g


def test_fake_run_has_what_the_tests_need(recorded):
    s, snaps = recorded
    tl = Timeline(s)
    assert tl.duration == pytest.approx(1.799)
    assert set(tl.rem_epoch.tolist()) == {0, 1}
    assert (tl.rem_epoch == 0).sum() > 100 and (tl.rem_epoch == 1).sum() > 20
    assert tl.reset_t == pytest.approx([1.2])
    assert len(tl.inj_t) > 0 and set(tl.inj_label.tolist()) == {2}   # the nerve
    assert len(snaps) == 18


def test_timeline_lookups(recorded):
    s, _ = recorded
    tl = Timeline(s)
    assert tl.sample_index(0.0) == 0 and tl.sample_index(0.0105) == 10
    assert tl.sample_index(99) == len(s.samples["t_s"]) - 1
    assert tl.sample_index(-5) == 0
    assert tl.epoch_at(1.1995) == 0 and tl.epoch_at(1.2) == 1
    e, lo, hi = tl.removal_range(1.0)
    assert e == 0 and lo == 0 and tl.rem_t[hi - 1] <= 1.0 < tl.rem_t[hi]
    e, lo, hi = tl.removal_range(1.2)           # just after the reset: nothing yet
    assert e == 1 and hi == lo == int((tl.rem_epoch == 0).sum())
    e, lo, hi = tl.removal_range(tl.duration)
    assert hi == len(tl.rem_t)
    eye, focal, up = tl.camera_at(0.25)          # halfway between 0.2 and 0.3
    assert eye == pytest.approx([10.5, 8.0, 60.0]) and up == pytest.approx([0, 1, 0])
    assert tl.camera_at(5.0)[0] == pytest.approx([25.99, 8.0, 60.0])   # clamped to 1.799 s
    with pytest.raises(ValueError):
        tl.clamp(float("nan"))


def test_seeks_give_the_fresh_replay_grid_and_the_built_surface(recorded):
    s, _ = recorded
    p = Player(s)
    tl, model = p.timeline, p.model
    times = [0.3, 0.5, 0.501, 0.9, 0.6, 1.19, 1.25, 1.7, 0.95, 1.799, 0.0, 1.5]
    modes = []
    for t in times:
        modes.append(p.seek(t)["mode"])
        ref = fresh_replay(model, tl, t)
        np.testing.assert_array_equal(p.grid.density, ref.density, err_msg=f"t={t}")
        built = Surface.of_model(model, ref)
        diff = p.surface.canonical().differences(built.canonical())
        assert not diff, (t, diff)
    # forward seeks were incremental (none removed between 0.5 and 0.501 s);
    # backward ones and the jumps across the reset rebuilt
    assert modes == ["forward", "forward", "none", "forward", "rebuild", "forward",
                     "rebuild", "forward", "rebuild", "rebuild", "rebuild", "rebuild"]
    assert p.stats["rebuilds"] == 1 + modes.count("rebuild")
    assert p.seek(1.5)["mode"] == "none"


def test_replayed_occupancy_equals_the_live_run(recorded):
    """Removals alone rebuild exactly which voxels the live run had emptied."""
    s, snaps = recorded
    p = Player(s, surface=False)
    for t, (epoch, live) in sorted(snaps.items(), key=lambda kv: -kv[0]):  # backward too
        p.seek(t)
        assert p.timeline.epoch_at(t) == epoch
        np.testing.assert_array_equal(p.grid.density > 0, live > 0, err_msg=f"t={t}")
        # partial density loss is not recorded: replayed voxels are intact or empty
        assert set(np.unique(p.grid.density).tolist()) <= {0.0, 1.0}


def test_forward_seek_reports_the_removed_voxels(recorded):
    s, _ = recorded
    p = Player(s)
    p.seek(0.4)
    out = p.seek(0.8)
    e, lo, hi = p.timeline.removal_range(0.8)
    _, _, hi0 = p.timeline.removal_range(0.4)
    assert out["mode"] == "forward"
    np.testing.assert_array_equal(out["removed"], p.timeline.rem_ijk[hi0:hi])


def test_frame_and_hud(recorded, monkeypatch):
    import bonesim.session.playback

    s, _ = recorded
    p = Player(s)
    tl = p.timeline
    last_inj = float(tl.inj_t[-1])
    f = p.frame(last_inj + 0.5)
    i = tl.sample_index(last_inj + 0.5)
    assert f.index == i and f.pos_mm == pytest.approx(s.samples["pos_mm"][i])
    assert f.force_n == pytest.approx(np.linalg.norm(s.samples["force_n"][i]))
    assert f.drill and f.direction == 1 and f.burr.name == "fake"
    e, lo, hi = tl.removal_range(last_inj + 0.5)
    assert f.voxels_removed == hi - lo > 0
    assert f.volume_removed_mm3 == pytest.approx((hi - lo) * 0.125)
    assert f.injuries == ["nerve"] and f.recent and f.recent[0].startswith("Nerve (")
    monkeypatch.setattr(bonesim.session.playback, "INJURY_NOTICE_S", 0.4)
    assert p.frame(last_inj + 0.39).recent and p.frame(last_inj + 0.41).recent == []
    monkeypatch.undo()
    assert p.frame(1.3).injuries == []          # a reset clears the list, like the app
    assert p.frame(1.3).recent == []
    info = hud_info(f, p.model, speed=2.0, playing=True, notices=["recording incomplete"])
    assert info["playback"] == "2x  playing" and info["injuries"] == ["nerve"]
    assert info["time"] == f"{format_clock(last_inj + 0.5)} / 0:01.8"
    assert info["removed"].startswith(f"{hi - lo:,} voxels")
    assert "INJURY Nerve (" in info["message"] and "recording incomplete" in info["message"]
    assert "since reset 1" in hud_info(p.frame(1.7), p.model)["removed"]
    assert p.t == 0.0                            # frame() does not seek


def test_bad_sessions_raise_clear_errors(recorded):
    s, _ = recorded

    def variant(**changes):
        v = SimpleNamespace(**vars(s))
        for group, cols in changes.items():
            d = dict(getattr(s, group))
            d.update(cols)
            setattr(v, group, d)
        v.path = "run.h5"
        return v

    with pytest.raises(BonesimError, match=r"run.h5 \[samples/t_s\]: .*no haptic samples"):
        Timeline(variant(samples={"t_s": np.zeros(0)}))
    with pytest.raises(BonesimError, match=r"\[samples/pos_mm\]: expected shape"):
        Timeline(variant(samples={"pos_mm": np.zeros((3, 3))}))
    back = s.samples["t_s"].copy()
    back[5] = -1.0
    with pytest.raises(BonesimError, match="non-decreasing"):
        Timeline(variant(samples={"t_s": back}))
    v = SimpleNamespace(**vars(s))
    v.removals = {k: a for k, a in s.removals.items() if k != "epoch"}
    with pytest.raises(BonesimError, match=r"removals/epoch"):
        Timeline(v)
    burr = s.samples["burr"].copy()
    burr[-1] = 3
    with pytest.raises(BonesimError, match=r"burr index 3 .* 1 burr"):
        Player(variant(samples={"burr": burr}))


def test_clock():
    c = PlaybackClock(10.0)
    assert not c.playing and c.t == 0.0 and c.speed == 1.0
    c.advance(1.0)
    assert c.t == 0.0                            # paused
    assert c.toggle() and c.advance(0.5) == 0.5
    assert c.faster() == 2.0 and c.advance(1.0) == 2.5
    for _ in range(10):
        c.faster()
    assert c.speed == SPEEDS[-1] == 8.0
    for _ in range(10):
        c.slower()
    assert c.speed == SPEEDS[0] == 0.25
    assert c.skip(-5) == 0.0 and c.skip(20) == 10.0
    c.seek(9.9)
    c.speed = 1.0
    c.advance(1.0)
    assert c.t == 10.0 and not c.playing         # stops at the end
    assert c.toggle() and c.t == 0.0             # play again from the start
    with pytest.raises(ValueError):
        PlaybackClock(1.0, speed=0.0)


# ------------------------------------------------------- real session files
@pytest.fixture(scope="module")
def demo_file(tmp_path_factory):
    """A recorded scripted run: 8 s of the planned demo from its first drilling
    sample (bonesim.runtime.simulate with record=)."""
    from bonesim.io.case import load_case
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.io.loading import load_model
    from bonesim.runtime.simulate import run_trajectory

    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    traj = t.at_times(t.t_s[start:start + 800])
    path = tmp_path_factory.mktemp("pb") / "demo.h5"
    run_trajectory(load_model("phantom", "cutting-5mm"), traj, surface=False, record=path)
    return path


def _engine_density(model, session, t):
    """The live engine's density at playback time ``t``: the recorded samples
    stepped again from the initial tissue (as bonesim.session.replay.replay does)."""
    from bonesim.engine.model import make_state

    s = session.samples
    state = make_state(model)
    n = int(np.searchsorted(s["t_s"], s["t_s"][0] + t, side="right"))
    for q in range(n):
        step(model, state, Sample(float(s["t_s"][q]), s["pos_mm"][q], s["axis"][q],
                                  bool(s["drill"][q]), float(s["speed_rpm"][q]),
                                  int(s["direction"][q])))
    return state.grid.density


def test_recorded_file_seeks_match_the_engine(demo_file):
    from bonesim.session.reader import read_session

    s = read_session(demo_file)
    p = Player(s)
    assert p.timeline.duration == pytest.approx(s.duration_s) and p.timeline.duration > 7
    # hundreds of removal batches to seek through (412 over the phantom's mastoid cortex)
    assert len(p.timeline.rem_t) > 300 and p.timeline.cam_t.size == 1   # scripted: the one eye
    for t in (6.0, 2.5, 4.0):                    # forward, backward, forward
        p.seek(t)
        live = _engine_density(p.model, s, t)
        np.testing.assert_array_equal(p.grid.density > 0, live > 0, err_msg=f"t={t}")
        np.testing.assert_array_equal(p.grid.density,
                                      fresh_replay(p.model, p.timeline, t).density)
    f = p.frame()
    assert f.burr.name == "cutting-5mm" and f.voxels_removed > 0
    assert hud_info(f, p.model)["time"] == "0:04.0 / " + format_clock(p.timeline.duration)


@pytest.mark.slow
def test_live_recording_with_a_reset_and_a_burr_change_plays_back(tmp_path):
    """A live haptic-loop recording (mouse device) across a burr change and a
    case reset: playback at the end equals the engine's replay of the file,
    and the HUD names the second burr."""
    from bonesim.io.burrs import load_burr
    from bonesim.io.case import load_case
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.io.loading import load_model
    from bonesim.runtime.record import Recorder
    from bonesim.session.header import make_header
    from bonesim.session.replay import replay
    from bonesim.session.reader import read_session
    from tests.bonesim.waiting import wait_drill_off, wait_until

    model = load_model("phantom", "cutting-5mm")
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    burr2 = load_burr("diamond-3mm")
    path = tmp_path / "live.h5"
    loop = HapticLoop(model, burrs=[burr2])
    rec = Recorder(loop, path, make_header(model, [burr2], input_device="mouse"))

    try:
        rec.start()
        loop.start()
        loop.set_target(np.array([23.0, 3.0, -2.0]) + 3.0 * view, view)
        loop.set_drill(True, speed_rpm=60000.0)
        assert wait_until(lambda: loop.state.n_removed > 30, 30.0)
        epoch = loop.reset()
        assert wait_until(lambda: loop.status["epoch"] == epoch, 30.0)
        loop.set_burr(1)
        n1 = loop.state.n_removed
        assert wait_until(lambda: loop.state.n_removed > n1 + 20, 30.0)
        loop.set_drill(False)
        assert wait_drill_off(loop)
        rec.close()
    finally:
        loop.close()
    s = read_session(path)
    assert set(np.unique(s.removals["epoch"]).tolist()) == {0, 1}
    p = Player(s)
    assert len(p.timeline.reset_t) == 1
    p.seek(p.timeline.duration)
    final = replay(s)["state"].grid.density
    np.testing.assert_array_equal(p.grid.density > 0, final > 0)
    built = Surface.of_model(p.model, p.grid)
    assert not p.surface.canonical().differences(built.canonical())
    f = p.frame()
    assert f.epoch == 1 and f.burr.name == "diamond-3mm"
    # back into the first epoch, just before the reset (the first epoch's
    # removals can all fall in its last 20 ms: the burr sinks in fast)
    before = p.timeline.reset_t[0] - 0.0005
    p.seek(before)
    r = s.removals
    n0 = int(((r["epoch"] == 0) & (r["t_s"] <= p.timeline.t0 + before)).sum())
    assert p.frame().burr.name == "cutting-5mm" and p.frame().voxels_removed == n0 > 20
    np.testing.assert_array_equal(p.grid.density,
                                  fresh_replay(p.model, p.timeline, before).density)


def test_cli_playback_errors(demo_file, tmp_path, capsys, monkeypatch):
    from bonesim.cli.main import main

    assert main(["playback", str(tmp_path / "none.h5")]) == 2
    assert "none.h5: no such session file" in capsys.readouterr().err
    assert main(["playback", str(demo_file), "--video", str(tmp_path / "a.mp4"),
                 "--size", "161x120"]) == 2
    assert "must be even for H.264" in capsys.readouterr().err
    assert main(["playback", str(demo_file), "--video", str(tmp_path / "no" / "a.mp4")]) == 2
    assert "output folder does not exist" in capsys.readouterr().err
    assert main(["playback", str(demo_file), "--video", str(tmp_path / "a.mp4"),
                 "--start", "5", "--end", "3"]) == 2
    assert "end 3 s is not after start 5 s" in capsys.readouterr().err
    assert main(["playback", str(demo_file), "--video", str(tmp_path / "a.mp4"),
                 "--speed", "0"]) == 2
    assert "[--speed]: 0 x is outside the physical bounds" in capsys.readouterr().err
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["playback", str(demo_file)]) == 2
    assert "no display found" in capsys.readouterr().err
