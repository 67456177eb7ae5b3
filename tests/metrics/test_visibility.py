"""Voxel visibility recomputed from session files (metrics.visibility).

The recorded runs go through the recorder's own writer path (the
``Drainer`` with its live ``VisibilityTracker``, the ``SessionWriter``): a
scripted run recorded by ``bonesim.runtime.simulate`` and a run stepped here
with a moving camera logged at the frame rate, a burr change, a split, a
moved fragment and a case reset, drained at irregular intervals as the
writer process does. The offline verdicts must equal the live ones.
"""
from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.model import make_model
from bonesim.session.reader import Session, read_session
from metrics.visibility import (StructureVisibility, VisibilityResult, recompute_visible,
                                visibility, visible_fraction)

from tests.bonesim.fakes import MATERIALS, FakeBurr, FakeStructure
from tests.bonesim.waiting import wait_drill_off


# ------------------------------------------------------------ recorded runs
def _rotate(v, axis, angle):
    """Rodrigues: ``v`` turned by ``angle`` [rad] about unit ``axis``."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return (v * math.cos(angle) + np.cross(axis, v) * math.sin(angle)
            + axis * np.dot(axis, v) * (1 - math.cos(angle)))


def record_run(path, n_traj=1500, *, camera_turn_deg=0.0, reset_at=None, burr_at=None,
               split_at=None, seed=0):
    """Step the phantom demo (``n_traj`` trajectory samples from its first
    drilling one, at the haptic rate) and record it through the recorder's
    writer path. ``camera_turn_deg``: the logged eye orbits the case
    camera's focal point about its up axis by this much over the run (none
    logged when 0: the case camera). ``reset_at``, ``burr_at``, ``split_at``:
    fractions of the run at which to reset the case, switch to the second
    burr, and split a box of bone around the burr into a body that is then
    lifted 40 mm away. Returns the path."""
    from bonesim.engine.bodies import publish_pose, publish_split_box
    from bonesim.engine.model import Sample, make_state, reset_state, step
    from bonesim.io.burrs import load_burr
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.physics.visibility import VisibilityTracker
    from bonesim.runtime.haptic_loop import push_sample
    from bonesim.runtime.record import Drainer
    from bonesim.session.writer import SessionWriter
    from bonesim.session.header import make_header

    case = load_case("phantom")
    model = load_model("phantom", "cutting-5mm")
    burr2 = load_burr("diamond-3mm")
    model2 = model.with_burrs([burr2])
    t = demo_trajectory(case, "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    smp = t.at_times(t.t_s[start:start + n_traj]).resample(model.haptic_rate_hz)
    n = len(smp.t_s)
    at = {k: (None if f is None else int(f * n))
          for k, f in (("reset", reset_at), ("burr", burr_at), ("split", split_at))}
    state = make_state(model2)
    ring = events.Ring.create(1 << 14, **events.OTHER_RINGS["samples"][1])
    cam_ring = events.Ring.create(1 << 12, **events.OTHER_RINGS["camera"][1])
    writer = SessionWriter(path, make_header(model, [burr2], input_device="scripted"))
    cam = case.camera
    tracker = VisibilityTracker([model, model.with_burr(burr2)], cam.eye_mm)
    drainer = Drainer(writer, {"samples": ring, "tissue": state.tissue, "camera": cam_ring},
                      tracker)
    rng = np.random.default_rng(seed)
    next_drain = int(rng.integers(10, 300))
    focal, eye0 = np.asarray(cam.focal_mm, float), np.asarray(cam.eye_mm, float)
    epoch = burr = 0
    zero = np.zeros(3)
    for q in range(n):
        tq = float(smp.t_s[q])
        if q == at["reset"]:
            reset_state(model2, state, rings=False)
            epoch += 1
            events.push_event(state.tissue, events.RESET, tq, n=epoch)
        if q == at["burr"]:
            burr = 1
            events.push_event(state.tissue, events.BURR, tq, n=1)
        if q == at["split"]:
            g = state.grid
            c = np.round((smp.pos_mm[q] - g.origin_mm) / g.spacing_mm).astype(np.int64)
            dst, k = publish_split_box(state, 0, c - 8, c + 8, tq)
            assert k > 0
            publish_pose(state, dst, (40.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0), tq)
        s = Sample(tq, smp.pos_mm[q], smp.axis[q], bool(smp.drill[q]),
                   float(smp.speed_rpm[q]), int(smp.direction[q]), burr)
        f = step(model2, state, s)
        push_sample(ring, tq, state, smp.pos_mm[q], smp.axis[q], s.drill, s.speed_rpm,
                    s.direction, burr, epoch, 0, f, zero)
        if camera_turn_deg and q % 16 == 15:           # a frame: the window logs its eye
            eye = focal + _rotate(eye0 - focal, cam.up, math.radians(camera_turn_deg) * q / n)
            r = cam_ring
            k = r.count & (r.capacity - 1)
            r.fields["t_s"][k] = tq
            r.fields["eye_mm"][k] = eye
            r.fields["focal_mm"][k] = focal
            r.fields["up"][k] = cam.up
            r.head[0] += 1
        if q == next_drain:
            drainer.drain()
            writer.flush()
            next_drain = q + int(rng.integers(10, 300))
    drainer.drain()
    writer.close()
    return Path(path)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A scripted run recorded by bonesim.runtime.simulate (case camera)."""
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.runtime.simulate import run_trajectory

    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    path = tmp_path_factory.mktemp("vis") / "sim.h5"
    run_trajectory(load_model("phantom", "cutting-5mm"), t.at_times(t.t_s[start:start + 600]),
                   surface=False, record=path)
    return read_session(path)


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    """Moving camera, burr change, split and moved fragment, then a reset."""
    path = tmp_path_factory.mktemp("vis") / "moving.h5"
    return read_session(record_run(path, camera_turn_deg=75.0, split_at=0.4, burr_at=0.55,
                                   reset_at=0.75, seed=3))


def test_offline_equals_live_on_a_simulated_recording(simulated):
    s = simulated
    rem = s.tissue["kind"] == events.REMOVED
    assert rem.sum() > 200 and len(s.camera["t_s"]) == 1     # the one eye of a script
    assert (s.tissue["visible"][rem] >= 0).all()        # the recorder judged them
    got = recompute_visible(s)
    np.testing.assert_array_equal(got, s.tissue["visible"])
    r = visibility(s)
    assert r.live_mismatches == 0 and r.n_removed == rem.sum()


def test_offline_equals_live_with_a_moving_camera_reset_burr_change_and_split(moving):
    s = moving
    kinds = s.tissue["kind"]
    for k in (events.RESET, events.BURR, events.SPLIT, events.POSE):
        assert (kinds == k).any(), k
    rem = kinds == events.REMOVED
    assert len(s.camera["t_s"]) > 100 and rem.sum() > 300
    assert set(np.unique(s.removals["epoch"]).tolist()) == {0, 1}
    live = s.tissue["visible"]
    assert (live[rem] >= 0).all() and (live[rem] == 0).any() and (live[rem] == 1).any()
    np.testing.assert_array_equal(recompute_visible(s), live)
    r = visibility(s)
    assert r.live_mismatches == 0
    assert 0.0 < r.fraction < 1.0
    # the camera matters: judged from the case camera alone, verdicts change
    still = Session(s.path, s.schema, s.header, s.complete, s.samples, s.tissue,
                    {k: v[:0] for k, v in s.camera.items()})
    assert not np.array_equal(recompute_visible(still), live)


def test_removal_centres_are_the_voxels_in_the_case_frame(simulated):
    r = visibility(simulated)
    g = simulated.load_model().grid
    ijk = simulated.removals["ijk"]
    np.testing.assert_allclose(r.centre_mm, g.origin_mm + g.spacing_mm * ijk)


# ------------------------------------------------------- naive references
def _naive(r: VisibilityResult, names, t0, t1, window_s):
    by = {}
    for lab, v in zip(r.label.tolist(), r.visible.tolist()):
        n, k = by.get(names[lab], (0, 0))
        by[names[lab]] = (n + 1, k + (v == 1))
    m = max(1, math.ceil((t1 - t0) / window_s - 1e-9))
    win = [[0, 0] for _ in range(m)]
    for t, v in zip(r.t_s.tolist(), r.visible.tolist()):
        w = 0
        while w + 1 < m and t0 + window_s * (w + 1) <= t:
            w += 1
        win[w][0] += 1
        win[w][1] += v == 1
    frac = [k / n if n else math.nan for n, k in win]
    cum, a, b = [], 0, 0
    for n, k in win:
        a, b = a + n, b + k
        cum.append(b / a if a else math.nan)
    return by, win, frac, cum


@pytest.mark.parametrize("window_s", [0.37, 1.0, 100.0])
def test_per_structure_and_over_time_fractions_match_a_naive_count(moving, window_s):
    s = moving
    r = visibility(s, window_s=window_s)
    names = {st["label"]: st["name"] for st in s.header["structures"]}
    t0, t1 = float(s.samples["t_s"][0]), float(s.samples["t_s"][-1])
    by, win, frac, cum = _naive(r, names, t0, t1, window_s)
    assert {k: (v.n_removed, v.n_visible) for k, v in r.by_structure.items()} == by
    for v in r.by_structure.values():
        assert v.fraction == v.n_visible / v.n_removed
    assert r.window_removed.tolist() == [w[0] for w in win]
    assert r.window_visible.tolist() == [w[1] for w in win]
    np.testing.assert_allclose(r.window_fraction, frac, equal_nan=True)
    np.testing.assert_allclose(r.cumulative_fraction, cum, equal_nan=True)
    np.testing.assert_allclose(r.window_start_s, t0 + window_s * np.arange(len(win)))
    assert r.fraction == np.mean(r.visible == 1) == visible_fraction(s)
    assert r.n_removed == sum(w[0] for w in win) and r.n_visible == sum(w[1] for w in win)


# ---------------------------------------------------------- hand-built case
BONE = FakeStructure("bone", "bone")
DURA = FakeStructure("dura", "soft", (200, 60, 60))


def _tiny_model():
    """An 8^3 voxel grid (1 mm): a bone column x = y = 4, z = 1..4, and a dura
    voxel at (2, 2, 2)."""
    labels = np.zeros((8, 8, 8), np.uint8)
    labels[4, 4, 1:5] = 1
    labels[2, 2, 2] = 2
    return make_model(labels, 1.0, [BONE, DURA], FakeBurr(radius_mm=0.4),
                      materials=MATERIALS, oversample=4)


def _session(rows, samples_t, camera=None, path="tiny.h5"):
    """An in-memory session: ``rows`` of (kind, t_s, ijk, label, n)."""
    ev = events.empty_events(len(rows))
    for q, (kind, t, ijk, label, n) in enumerate(rows):
        ev["kind"][q], ev["t_s"][q], ev["ijk"][q] = kind, t, ijk
        ev["label"][q], ev["n"][q] = label, n
    ev["visible"] = np.full(len(rows), -1, np.int8)
    ts = np.asarray(samples_t, float)
    epoch = np.zeros(len(ts), np.int32)
    for kind, t, _, _, n in rows:
        if kind == events.RESET:
            epoch[ts >= t] = n
    samples = {"t_s": ts, "pos_mm": np.full((len(ts), 3), 50.0),   # burr far away
               "burr": np.zeros(len(ts), np.uint8), "epoch": epoch}
    cam = camera or {"t_s": np.zeros(0), "eye_mm": np.zeros((0, 3))}
    header = {"structures": [{"label": 1, "name": "bone", "kind": "bone"},
                             {"label": 2, "name": "dura", "kind": "soft"}]}
    return Session(Path(path), 2, header, True, samples, ev, cam)


R = events.REMOVED
ABOVE, BELOW = [4.0, 4.0, 30.0], [4.0, 4.0, -30.0]


def test_a_tiny_case_where_each_verdict_is_known():
    m = _tiny_model()
    # bottom up under the eye above: hidden by the voxels still above it; the
    # top one is visible; the dura voxel (not under bone) is visible
    rows = [(R, 0.0, (4, 4, 1), 1, 0), (R, 0.0, (4, 4, 2), 1, 0), (R, 1.0, (4, 4, 3), 1, 0),
            (R, 1.0, (4, 4, 4), 1, 0), (R, 1.0, (2, 2, 2), 2, 0)]
    s = _session(rows, [0.0, 1.0])
    r = visibility(s, window_s=1.0, models=[m], eye_mm=ABOVE)
    assert r.visible.tolist() == [0, 0, 0, 1, 1]
    assert r.fraction == pytest.approx(2 / 5)
    assert r.by_structure == {"bone": StructureVisibility(1, 4, 1, 0.25),
                              "dura": StructureVisibility(2, 1, 1, 1.0)}
    assert r.window_removed.tolist() == [5] and r.live_mismatches == 0
    np.testing.assert_allclose(r.centre_mm[-1], [2.0, 2.0, 2.0])
    # the eye logged below from t = 0.5 on: the removals at t = 1 look down
    # the cleared column (4, 4, 3 is under 4, 4, 4 ... from below: clear)
    cam = {"t_s": np.array([0.5]), "eye_mm": np.array([BELOW])}
    r = visibility(_session(rows, [0.0, 1.0], cam), models=[m], eye_mm=ABOVE)
    assert r.visible.tolist() == [0, 0, 1, 1, 1]
    # a reset puts the column back: (4, 4, 4) seen from below is hidden again
    rows2 = rows[:2] + [(events.RESET, 1.0, (0, 0, 0), 0, 1), (R, 1.0, (4, 4, 4), 1, 0)]
    r = visibility(_session(rows2, [0.0, 1.0], cam), models=[m], eye_mm=ABOVE)
    assert r.visible.tolist() == [0, 0, 0] and r.epoch.tolist() == [0, 0, 1]
    # the recorded column is compared with the recomputed one
    s = _session(rows, [0.0, 1.0])
    s.tissue["visible"][:] = [0, 0, 1, 1, -1]
    assert visibility(s, models=[m], eye_mm=ABOVE).live_mismatches == 1


# --------------------------------------------------------------- bad input
def test_a_run_without_removals_gives_zero_counts_and_nan_fractions():
    s = _session([], [0.0, 0.5, 2.0])
    r = visibility(s, window_s=1.0, models=[])       # no model needed: nothing to judge
    assert r.n_removed == 0 and r.n_visible == 0 and math.isnan(r.fraction)
    assert r.by_structure == {} and r.window_removed.tolist() == [0, 0]
    assert np.isnan(r.window_fraction).all() and np.isnan(r.cumulative_fraction).all()
    assert r.summary()["visible_fraction"] is None
    assert r.centre_mm.shape == (0, 3)
    assert math.isnan(visible_fraction(s, models=[]))
    assert recompute_visible(s, models=[_tiny_model()]).tolist() == []
    empty = _session([], [])
    assert visibility(empty, models=[]).window_removed.tolist() == [0]


def test_bad_input_raises_value_errors_naming_the_problem():
    m = _tiny_model()
    rows = [(R, 1.0, (4, 4, 4), 1, 0)]
    s = _session(rows, [0.0, 1.0])
    with pytest.raises(ValueError, match="window_s"):
        visibility(s, window_s=0.0, models=[m], eye_mm=ABOVE)
    with pytest.raises(ValueError, match="eye_mm"):              # fake model: no case camera
        visibility(s, models=[m])
    with pytest.raises(ValueError, match="eye_mm"):
        visibility(s, models=[m], eye_mm=[1.0, np.nan, 0.0])
    with pytest.raises(ValueError, match="samples of their steps"):
        visibility(_session(rows, [0.0]), models=[m], eye_mm=ABOVE)
    bad = _session(rows, [0.0, 1.0])
    bad.samples["burr"][:] = 3
    with pytest.raises(ValueError, match="burr index 3"):
        visibility(bad, models=[m], eye_mm=ABOVE)
    with pytest.raises(ValueError, match="models"):
        recompute_visible(s, models=[])
    with pytest.raises(ValueError, match="samples"):
        visibility(SimpleNamespace(samples=None, tissue={}, camera={}))


# --------------------------------------------------------------------- view
IMAGES = Path(__file__).parent / "images"


def test_render_matches_the_reference_image(moving, tmp_path):
    """The view of the moving-camera run (400 x 300) against the stored
    reference; regenerate after an intended change with
    ``BONESIM_UPDATE_IMAGES=1`` (the test then writes it and skips)."""
    import os

    from bonesim.render.gl import select_backend
    from bonesim.render.imagecmp import compare_images, diff_image, read_png, write_png
    from metrics.visibility import HIDDEN_RGB, render_visibility

    select_backend(offscreen=True)
    out = render_visibility(moving, tmp_path / "vis.png", size=(400, 300))
    img = read_png(out)
    assert img.shape == (300, 400, 3)
    # red hidden voxels are drawn (the run has some), and text
    red = np.all(np.abs(img.astype(int) - HIDDEN_RGB) < 40, axis=-1)
    assert red.sum() > 10
    ref_path = IMAGES / "visibility.png"
    if os.environ.get("BONESIM_UPDATE_IMAGES") == "1":
        write_png(ref_path, img)
        pytest.skip(f"wrote {ref_path}")
    ref = read_png(ref_path)
    res = compare_images(img, ref)
    if not res:
        write_png(tmp_path / "visibility-diff.png", diff_image(img, ref))
    assert res, f"{res.reason} (actual and diff images in {tmp_path})"
    # only the chosen structures are meshed; unknown names are refused
    with pytest.raises(ValueError, match="structures"):
        render_visibility(moving, tmp_path / "x.png", structures=["spleen"])
    with pytest.raises(ValueError, match="size"):
        render_visibility(moving, tmp_path / "x.png", size=(0, 10))
    nerve = read_png(render_visibility(moving, tmp_path / "nerve.png", size=(400, 300),
                                       structures=["facial_nerve"]))
    assert not compare_images(nerve, img)


@pytest.mark.slow
def test_offline_equals_live_on_a_live_loop_recording_with_a_moving_camera(tmp_path):
    """The haptic loop and the recorder's writer process, the window's camera
    logged at 120 Hz while it swings +-80 degrees about the case camera's up
    axis: every live verdict is recomputed from the file."""
    import time

    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.runtime.record import Recorder
    from bonesim.session.header import make_header

    model = load_model("phantom", "cutting-5mm")
    cam = load_case("phantom").camera
    focal, eye0 = np.asarray(cam.focal_mm, float), np.asarray(cam.eye_mm, float)
    view = (focal - eye0) / np.linalg.norm(focal - eye0)
    path = tmp_path / "live.h5"
    loop = HapticLoop(model)
    rec = Recorder(loop, path, make_header(model, input_device="mouse"))
    try:
        rec.start()
        loop.start()
        loop.set_target(np.array([23.0, 3.0, -2.0]) + 3.0 * view, view)
        loop.set_drill(True, speed_rpm=60000.0)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 5.0:
            a = math.radians(80.0) * math.sin(2.0 * (time.monotonic() - t0))
            rec.camera(focal + _rotate(eye0 - focal, cam.up, a), focal, cam.up)
            time.sleep(1 / 120)
        loop.set_drill(False)
        assert wait_drill_off(loop)
        rec.close()
    finally:
        loop.close()
    s = read_session(path)
    rem = s.tissue["kind"] == events.REMOVED
    assert rem.sum() > 100 and len(s.camera["t_s"]) > 100
    live = s.tissue["visible"]
    assert (live[rem] == 0).any() and (live[rem] == 1).any()
    np.testing.assert_array_equal(recompute_visible(s), live)
