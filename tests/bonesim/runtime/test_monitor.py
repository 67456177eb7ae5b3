"""Nerve monitor: which structures, the activity law, distance lookups, spikes,
the monitor process, clicks and the network console."""
from __future__ import annotations

import pytest

from bonesim.io import case as C
from bonesim.errors import BonesimError
from tests.bonesim.io.test_case import tiny_volume, write_case


# --------------------------------------------------------- monitored structures
def test_phantom_monitors_facial_nerve_and_chorda():
    c = C.load_case("phantom")
    assert [s.name for s in c.structures if s.monitor] == ["facial_nerve", "chorda_tympani"]
    assert C.case_info(c)["monitored"] == ["facial_nerve", "chorda_tympani"]


def test_monitor_flag_default_roundtrip_and_errors(tmp_path):
    tiny_volume(tmp_path)
    c = C.load_case(write_case(tmp_path))
    # a nerve that is neither the facial nerve nor the chorda: listed, off
    assert not any(s.monitor for s in c.structures)
    assert [s.name for s in c.structures if s.monitor_available] == ["nerve"]
    c = C.load_case(write_case(tmp_path, replace=[("label = 2", "label = 2\nmonitor = false")]))
    assert not any(s.monitor for s in c.structures)
    c = C.load_case(write_case(tmp_path, replace=[('name = "nerve"', 'name = "facial nerve"')]))
    assert [s.name for s in c.structures if s.monitor] == ["facial nerve"]   # on by default
    c = C.load_case(write_case(tmp_path, replace=[("label = 2", "label = 2\nmonitor = true")]))
    assert [s.name for s in c.structures if s.monitor] == ["nerve"]
    back = C.load_case(C.export_case(c, "nrrd", tmp_path / "out"))
    assert [s.monitor for s in back.structures] == [False, True]
    for repl, fragment in [(("label = 2", 'label = 2\nmonitor = "yes"'),
                            "'monitor' must be true or false, got 'yes'"),
                           (("label = 1", "label = 1\nmonitor = true"),
                            "'monitor' = true on a structure of kind 'bone'")]:
        path = write_case(tmp_path, replace=[repl])
        with pytest.raises(BonesimError) as e:
            C.load_case(path)
        assert fragment in str(e.value) and str(path) in str(e.value)
        assert e.value.field == ("structures[1]" if "yes" in repl[1] else "structures[0]")


# ---------------------------------------------------------------- monitor
import math

import numpy as np

from bonesim.runtime import monitor as M
from bonesim.physics.nerve_activity import activity
from bonesim.runtime.monitor import NerveMonitor
from tests.bonesim.fakes import wait_for

P = M.load_activity_params()


# -------------------------------------------------------------- distance field
@pytest.fixture(scope="module")
def phantom_model():
    from bonesim.io.loading import load_model

    return load_model("phantom", "cutting-5mm")


@pytest.fixture(scope="module")
def phantom_monitor(phantom_model):
    return NerveMonitor(phantom_model, P, seed=3)


def brute_distance(points, voxels_mm, spacing_mm):
    """Reference: smallest distance from each point to the box of any nerve
    voxel (centres ``voxels_mm``, edges ``spacing_mm``)."""
    half = np.broadcast_to(np.asarray(spacing_mm, float), (3,)) / 2
    out = np.empty(len(points))
    for a in range(0, len(points), 256):
        gap = np.abs(points[a:a + 256, None, :] - voxels_mm[None]) - half
        out[a:a + 256] = np.sqrt((np.maximum(gap, 0.0) ** 2).sum(-1)).min(1)
    return out


def nerve_voxels_mm(vol, label):
    """Centres of every voxel of a structure in a volume's native map."""
    nat = vol.native_labels
    return nat.origin_mm + nat.spacing_mm * np.argwhere(nat.labels == label), nat.spacing_mm


def test_phantom_nerves_are_the_monitored_ones(phantom_monitor, phantom_model):
    nm = phantom_monitor
    assert nm.names == ["facial_nerve", "chorda_tympani"] and nm.n == 2
    assert nm.titles == ["Facial nerve", "Chorda tympani"]           # for the screen
    assert nm.clearance is phantom_model.clearance         # the model's, not rebuilt
    counts = phantom_model.grid.counts_by_label(len(phantom_model.structures))
    for f, lab in zip(nm.fields, nm.labels):
        assert 0 < len(f.voxels_mm) <= counts[lab]          # the nerve's surface voxels
        assert f.nbytes < 4e6                    # surface voxels, not the whole volume
    assert nm.colors.tolist() == [[250, 230, 40], [250, 150, 30]]


def test_distance_matches_brute_force(phantom_monitor, phantom_model):
    rng = np.random.default_rng(11)
    vol = phantom_model.case.load_volume()
    for f, lab in zip(phantom_monitor.fields, phantom_monitor.labels):
        vox, h = nerve_voxels_mm(vol, lab)
        lo, hi = vox.min(0) - 12.0, vox.max(0) + 12.0
        p = np.concatenate([lo + rng.random((3000, 3)) * (hi - lo),      # around
                            vox[rng.integers(0, len(vox), 300)],          # inside
                            lo - 40 * rng.random((50, 3))])               # far away
        ref = brute_distance(p, vox, h)
        np.testing.assert_allclose(f.distance(p), ref, rtol=0, atol=1e-9)
        column = phantom_monitor.labels.index(lab)
        np.testing.assert_allclose(phantom_monitor.distances(p, 0.0)[:, column], ref,
                                   rtol=0, atol=1e-9)


def test_distances_come_from_the_native_map_not_the_grid(phantom_model):
    """A case whose source is finer than the engine's grid: the monitor
    measures on the source."""
    import dataclasses as dc

    from bonesim.physics.clearance import Clearance
    from bonesim.io.phantom import phantom_volume

    fine = phantom_volume(7, 0.25, (52.0, 52.0, 52.0))
    nerves = [5, 6]
    model = dc.replace(phantom_model, clearance=Clearance.from_native(fine.native_labels,
                                                                     nerves))
    nm = NerveMonitor(model, P)
    grid_nm = NerveMonitor(dc.replace(phantom_model, clearance=None), P)
    rng = np.random.default_rng(2)
    for c, lab in enumerate(nm.labels):
        vox, h = nerve_voxels_mm(fine, lab)
        p = vox.mean(0) + rng.normal(scale=4.0, size=(2000, 3))
        ref = brute_distance(p, vox, h)
        np.testing.assert_allclose(nm.distances(p, 0.0)[:, c], ref, rtol=0, atol=1e-9)
        # the grid (0.5 mm) answers otherwise
        assert np.abs(grid_nm.distances(p, 0.0)[:, c] - ref).max() > 0.05


def test_burr_surface_distance_subtracts_the_radius(phantom_monitor):
    f = phantom_monitor.fields[0]
    p = f.voxels_mm[len(f.voxels_mm) // 2] + np.array([4.0, 0.0, 0.0])
    d = phantom_monitor.distances(p)
    assert d.shape == (1, 2)
    assert d[0, 0] == pytest.approx(f.distance(p)[0] - 2.5)
    assert phantom_monitor.distances(p, radius_mm=0.5)[0, 0] == pytest.approx(d[0, 0] + 2.0)
    r = np.array([0.5, 1.0, 2.5])
    many = phantom_monitor.distances(np.tile(p, (3, 1)), radius_mm=r)
    np.testing.assert_allclose(many[:, 0], f.distance(p)[0] - r)


# ---------------------------------------------------------------------- spikes
# ------------------------------------------------------------------ bodies
_TURN = (4.0, -3.0, 7.5, 0.5, 0.5, -0.5, 0.5)          # a third of a turn, and a shift


def _nerve_split(model, label, share=1.0, pose=_TURN):
    """A state whose first ``share`` of the nerve's voxels (in index order)
    were split off as body 1 and placed at ``pose``."""
    from bonesim.engine.bodies import publish_split, set_pose
    from bonesim.engine.model import make_state

    st = make_state(model)
    _, lab = model.grid.to_dense()
    ijk = np.argwhere(lab == label)
    dst, n = publish_split(st, 0, ijk[:int(round(share * len(ijk)))], 0.0)
    assert dst == 1 and n > 0
    set_pose(st, 1, pose)
    return st


def _around(nm, q, n=400, seed=4):
    f = nm.fields[q]
    rng = np.random.default_rng(seed)
    return f.voxels_mm.mean(0) + rng.normal(scale=5.0, size=(n, 3))


def test_a_moved_nerve_is_measured_in_its_body_frame(phantom_model):
    from bonesim.engine.bodies import pose_matrix, to_body_frame, to_case_frame

    ref = NerveMonitor(phantom_model, P)
    nm = NerveMonitor(phantom_model, P)
    st = _nerve_split(phantom_model, nm.labels[0])
    nm.follow(st, st.grid.density)
    assert nm.body.tolist() == [1, 0]
    m = pose_matrix(_TURN)
    p = to_case_frame(m, _around(nm, 0))            # around the moved facial nerve
    d = nm.distances(p, 1.0)
    # = the unmoved nerve with the tool moved by the inverse pose
    np.testing.assert_array_equal(d[:, 0], ref.distances(to_body_frame(m, p), 1.0)[:, 0])
    np.testing.assert_array_equal(d[:, 1], ref.distances(p, 1.0)[:, 1])    # chorda stays
    assert d[:, 0].min() < 0.0 < d[:, 0].max()       # the burr reaches into it
    # the moved nerve is no longer where it was cut
    p0 = _around(nm, 0)
    assert (nm.distances(p0, 1.0)[:, 0] > ref.distances(p0, 1.0)[:, 0]).mean() > 0.9
    # the shared-memory view of the same arrays follows the same way
    arrays = {k: getattr(st, k) for k in ("body", "pose", "pose_m", "alive", "bounds")}
    nm2 = NerveMonitor(phantom_model, P)
    nm2.follow(arrays, st.grid.density)
    np.testing.assert_array_equal(nm2.distances(p, 1.0), d)
    nm2.reset()                                      # a new run: one body again
    np.testing.assert_array_equal(nm2.distances(p, 1.0), ref.distances(p, 1.0))


def test_a_split_nerve_is_measured_in_its_majority_body_frame(phantom_model):
    from bonesim.engine.bodies import pose_matrix, to_body_frame

    ref = NerveMonitor(phantom_model, P)
    m = pose_matrix(_TURN)
    for share, body in ((0.7, 1), (0.3, 0)):
        nm = NerveMonitor(phantom_model, P)
        st = _nerve_split(phantom_model, nm.labels[0], share)
        nm.follow(st, st.grid.density)
        assert nm.body[0] == body
        p = _around(nm, 0)
        want = ref.distances(to_body_frame(m, p) if body else p, 1.0)[:, 0]
        np.testing.assert_array_equal(nm.distances(p, 1.0)[:, 0], want)
    # only voxels still present vote: body 1's drilled away, body 0 holds it
    nm = NerveMonitor(phantom_model, P)
    st = _nerve_split(phantom_model, nm.labels[0], 0.7)
    density = st.grid.density.copy()
    density[st.body == 1] = 0.0
    nm.follow(st, density)
    assert nm.body[0] == 0


def test_one_body_at_the_identity_measures_as_before(phantom_model, phantom_monitor):
    from bonesim.engine.model import make_state

    nm = NerveMonitor(phantom_model, P)
    st = make_state(phantom_model)
    p = _around(nm, 0)
    want = phantom_monitor.distances(p)
    nm.follow(st, st.grid.density)
    assert nm.body.tolist() == [0, 0]
    np.testing.assert_array_equal(nm.distances(p), want)
    st2 = _nerve_split(phantom_model, nm.labels[0], 0.5, pose=(0, 0, 0, 1.0, 0, 0, 0))
    nm.follow(st2, st2.grid.density)                 # split, not moved
    np.testing.assert_array_equal(nm.distances(p), want)


# --------------------------------------------------------------- NerveMonitor
def approach(nm, field, seconds=4.0, dt=0.005, start_mm=8.0, end_mm=-0.5, force=1.0,
             drill=True):
    """Move the burr straight toward a nerve voxel; returns (t, rates, dist)."""
    target = field.voxels_mm[len(field.voxels_mm) // 2]
    away = np.array([1.0, 0.0, 0.0])
    n = int(round(seconds / dt))
    t = np.arange(n) * dt
    gap = np.linspace(start_mm, end_mm, n) + nm.radius_mm
    pos = target + gap[:, None] * away
    rates, dist = nm.update_many(t, pos, np.full(n, force), np.full(n, drill))
    return t, rates, dist


def test_monitor_update_rates_and_spikes(phantom_model):
    nm = NerveMonitor(phantom_model, P, seed=5, nerves=["facial_nerve"])
    assert nm.names == ["facial_nerve"]
    t, rates, dist = approach(nm, nm.fields[0])
    far = dist[:, 0] > 6.0
    assert np.all(rates[far, 0] < P.baseline_hz + 1.0)
    assert rates[-1, 0] == pytest.approx(activity(dist[-1, 0], 1.0, True, P))
    assert rates[-1, 0] > 30 * P.baseline_hz
    # same seed, same samples: same spikes; update() matches update_many()
    nm2 = NerveMonitor(phantom_model, P, seed=5, nerves=["facial_nerve"])
    target = nm.fields[0].voxels_mm[len(nm.fields[0].voxels_mm) // 2]
    for q, tq in enumerate(t):
        gap = np.linspace(8.0, -0.5, len(t))[q] + nm.radius_mm
        r = nm2.update(tq, target + [gap, 0.0, 0.0], 1.0, True)
        assert r[0] == pytest.approx(rates[q, 0])
    nm3 = NerveMonitor(phantom_model, P, seed=5, nerves=["facial_nerve"])
    approach(nm3, nm3.fields[0])
    assert np.array_equal(nm3.spikes[0], nm.spikes[0])
    # spike counts follow the rate: many near the nerve, few far away
    nm.reset()
    approach(nm, nm.fields[0], seconds=60.0, start_mm=9.0, end_mm=9.0)   # rest
    assert nm.t_s == pytest.approx(60.0 - 0.005)
    n_rest = len(nm.spikes[0])
    assert abs(n_rest - P.baseline_hz * 60) < 5 * math.sqrt(P.baseline_hz * 60)
    nm.reset()
    _, rates, dist = approach(nm, nm.fields[0], seconds=2.0, start_mm=0.3, end_mm=0.3)
    assert np.all(dist[:, 0] < 0.3 + 1e-9)                               # near
    expect = rates[1:, 0].sum() * 0.005
    assert abs(len(nm.spikes[0]) - expect) < 5 * math.sqrt(expect)
    # a new clock (time going back) starts over without spikes
    nm.update(0.0, target + 20.0, 0.0, False)
    assert len(nm.spikes[0]) == 0 and nm.t_s == 0.0


def test_unknown_or_empty_nerves_are_clear_errors(phantom_model):
    with pytest.raises(ValueError, match="no structure"):
        NerveMonitor(phantom_model, P, nerves=["vagus"])
    from tests.bonesim.fakes import BONE, NERVE, block_model

    labels = np.zeros((16, 16, 16), np.uint8)
    labels[:, :, :8] = 1
    model, _ = block_model(shape=labels.shape, labels=labels, structures=[BONE, NERVE])
    with pytest.raises(BonesimError, match="'nerve' has no voxels: it cannot be monitored"):
        NerveMonitor(model, P, nerves=["nerve"])
    assert NerveMonitor(model, P).n == 0                  # nothing flagged: nothing to do


# ------------------------------------------------------------ monitor process
def approach_trajectory(field, seconds=3.0, start_mm=10.0, end_mm=0.0, drill=True,
                        radius_mm=2.5):
    """A straight lateral approach of the burr surface to a nerve voxel."""
    from bonesim.io.trajectory import Trajectory

    target = field.voxels_mm[len(field.voxels_mm) // 2]
    n = 301
    t = np.linspace(0.0, seconds, n)
    gap = np.linspace(start_mm, end_mm, n) + radius_mm
    pos = target + gap[:, None] * np.array([1.0, 0.0, 0.0])
    return Trajectory(t_s=t, pos_mm=pos, axis=np.tile([-1.0, 0.0, 0.0], (n, 1)),
                      drill=np.full(n, drill), speed_rpm=np.full(n, 60000.0))


@pytest.mark.slow
@pytest.mark.parametrize("source", ["auto", "status"])
def test_monitor_process_follows_a_scripted_loop(phantom_model, phantom_monitor, source):
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.runtime.monitor import MonitorProcess

    traj = approach_trajectory(phantom_monitor.fields[0])
    loop = HapticLoop(phantom_model, device=("scripted", traj), vibration=False)
    mon = None
    try:            # the monitor first: it sees the approach from its start
        mon = MonitorProcess(loop, P, seed=1, source=source).start()
        loop.start()
        assert wait_for(lambda: loop.status["t_s"] > traj.t_s[-1] + 0.5, 30.0)
        assert wait_for(lambda: mon.view.t_s > traj.t_s[-1] + 0.5, 30.0)
        stats = mon.stats()
        hist = mon.view.history(10.0)
        names = mon.view.names
        has_ring = "samples.head" in loop._sh.arrays
    finally:
        if mon is not None:
            mon.close()
        loop.close()
    assert names == ["facial_nerve", "chorda_tympani"]
    assert stats["source"] == ("samples" if has_ring and source == "auto" else "status")
    # it measures and reports its own rate and cost (how fast this machine
    # runs it is the bench's: monitor_update_us), never above its set rate
    assert 0.0 < stats["update_hz"] < 1.5 * M.UPDATE_HZ and stats["cost_p99_us"] > 0
    t, rate, dist = hist["t_s"], hist["rate"], hist["dist"]
    assert len(t) > 2 * M.UPDATE_HZ * 0.5 and np.all(np.diff(t) > 0)
    # the distances are the lookup at the scripted positions (the loop's clock)
    pos = np.array([traj.sample_at(tq).pos_mm for tq in t])
    np.testing.assert_allclose(dist, phantom_monitor.distances(pos), atol=0.02)
    # the rate rose from rest to the burst as the burr came in
    assert rate[0, 0] < 2 * P.baseline_hz and rate[-1, 0] > 20 * P.baseline_hz
    lo, hi = (activity(dist[-1, 0], f, True, P) for f in (0.0, P.force_sat_n))
    assert lo - 1e-3 <= rate[-1, 0] <= hi + 1e-3            # whatever the bone's force
    # the spikes follow the rates (Poisson count within 5 sigma of the integral)
    for c in range(2):
        sel = (hist["spike_nerve"] == c) & (hist["spike_t"] > t[0])
        expect = float(np.sum(rate[1:, c] * np.diff(t)))
        assert abs(np.count_nonzero(sel) - expect) < 5 * math.sqrt(expect) + 3


# ---------------------------------------------------------------------- clicks
from bonesim.sound import clicks as K  # noqa: E402

FS = 48000


def click_reference(n, starts, which, fs=FS, k=2):
    """Slow reference of the click mix: every template added at its start."""
    out = np.zeros(n, np.float64)
    for s, w in zip(starts, which):
        x = K.click_template(fs, w)
        a, b = max(s, 0), min(s + len(x), n)
        if b > a:
            out[a:b] += x[a - s:b - s]
    return np.clip(out, -1, 1).astype(np.float32)


def render_blocks(synth, seconds, block):
    n = int(round(seconds * synth.sample_rate))
    out = np.zeros(n, np.float32)
    for q in range(0, n, block):
        synth.render(out[q:q + block])
    return out


def test_clicks_sound_at_spike_times_plus_the_delay():
    spikes = np.array([0.1, 0.25, 0.2512, 0.4]), np.array([0, 1, 0, 1])
    outs = []
    for block in (1, 97, 256, 48000):
        c = K.ClickSynth(FS, 2)
        c.sync(0.0)
        assert c.schedule(*spikes) == 4
        outs.append(render_blocks(c, 0.6, block))
        assert c.late == 0 and c.dropped == 0
    for o in outs[1:]:
        np.testing.assert_array_equal(o, outs[0])        # block size does not matter
    out = outs[0]
    starts = np.rint((spikes[0] + K.DELAY_S) * FS).astype(int)
    np.testing.assert_allclose(out, click_reference(len(out), starts, spikes[1]), atol=1e-6)
    # silence outside the clicks, sound inside each
    L = len(K.click_template(FS))
    inside = np.zeros(len(out), bool)
    for s in starts:
        inside[s:s + L] = True
        assert np.abs(out[s:s + L]).max() > 0.2
    assert np.all(out[~inside] == 0.0) and out[starts[0]] == 0.0       # zero phase start
    # each nerve its own pitch
    for s, w in zip(starts[[0, 3]], (0, 1)):
        seg = np.zeros(4096)
        seg[:L] = out[s:s + L]
        f = np.fft.rfftfreq(4096, 1 / FS)[np.argmax(np.abs(np.fft.rfft(seg)))]
        assert f == pytest.approx(K.CLICK_HZ * K.NERVE_PITCH_STEP ** w, rel=0.1)


def test_late_spikes_sound_at_once_and_a_full_ring_drops():
    c = K.ClickSynth(FS, 1)
    c.sync(10.0)                               # the caller's clock reads 10 s now
    render_blocks(c, 0.5, 256)                 # ... and 10.5 s after this
    c.schedule([10.2], [0])                    # 0.3 s late (with the delay)
    out = np.zeros(256, np.float32)
    c.render(out)
    assert c.late == 1 and np.abs(out[:200]).max() > 0.2
    c.sync(10.0 + c.rendered / FS + 0.002)     # first after rendering began: settles
    assert c.origin_s == pytest.approx(10.002, abs=1e-9)
    assert not c.sync(10.0 + c.rendered / FS + 0.005)       # within tolerance: kept
    origin = c.origin_s
    assert not c.sync(10.0 + c.rendered / FS + 0.05)        # a transient: kept
    render_blocks(c, 0.2, 256)
    assert not c.sync(10.0 + c.rendered / FS)               # back in tolerance: kept
    render_blocks(c, 0.2, 256)
    for _ in range(3):                                      # a drift held 0.6 s: moves
        assert c.origin_s == origin
        moved = c.sync(10.0 + c.rendered / FS + 0.05)
        render_blocks(c, 0.3, 256)
    assert moved and c.origin_s == pytest.approx(10.05, abs=1e-9)
    assert c.sync(100.0 + c.rendered / FS)                  # a new clock: at once
    assert c.origin_s == pytest.approx(100.0)
    with pytest.raises(ValueError, match="nerve index out of range"):
        c.schedule([11.0], [1])
    c.render(out)                              # the finished click frees its slot
    n = c.schedule(np.full(K.RING + 10, 20.0), np.zeros(K.RING + 10, int))
    assert n == K.RING and c.dropped == 10
    with pytest.raises(RuntimeError, match="before sync"):
        K.ClickSynth(FS, 1).schedule([0.0], [0])


def test_clicks_mix_into_the_drill_sound_and_record_to_wav(tmp_path):
    import wave

    from bonesim.io.burrs import load_burr
    from bonesim.sound.drill import SoundSynth, WavRecorder

    burr = load_burr("cutting-5mm")
    drill = SoundSynth(burr, FS, seed=4)
    drill.set_params(True, burr.default_speed_rpm, 0.5)
    alone = render_blocks(drill, 0.5, 256)
    drill = SoundSynth(burr, FS, seed=4)
    drill.set_params(True, burr.default_speed_rpm, 0.5)
    c = K.ClickSynth(FS, 1)
    c.sync(0.0)
    c.schedule([0.2], [0])
    mix = K.MixedSynth(drill, c)
    n = int(0.5 * FS)
    out = np.zeros(n, np.float32)
    with WavRecorder(tmp_path / "clicks.wav", FS) as rec:
        for q in range(0, n, 256):
            mix.render(out[q:q + 256])
            rec.write(out[q:q + 256])
    s = int(round((0.2 + K.DELAY_S) * FS))
    ref = alone + click_reference(n, [s], [0])
    np.testing.assert_allclose(out, np.clip(ref, -1, 1), atol=1e-6)
    with wave.open(str(tmp_path / "clicks.wav")) as w:
        pcm = np.frombuffer(w.readframes(w.getnframes()), np.int16) / 32767.0
    np.testing.assert_allclose(pcm, out, atol=1.0 / 32767)
    with pytest.raises(ValueError, match="sample rates differ"):
        K.MixedSynth(drill, K.ClickSynth(44100, 1))


@pytest.mark.slow
def test_audio_process_clicks_at_the_monitor_spikes(phantom_model, phantom_monitor, tmp_path):
    import time
    import wave

    from bonesim.runtime.audio import AudioProcess
    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.runtime.monitor import MonitorProcess

    # drill off (no drill sound), the burr resting at the nerve: clicks only
    traj = approach_trajectory(phantom_monitor.fields[0], seconds=0.5, start_mm=0.5,
                               end_mm=0.0, drill=False)
    wav = tmp_path / "clicks.wav"
    with HapticLoop(phantom_model, device=("scripted", traj), vibration=False) as loop:
        mon = MonitorProcess(loop, P, seed=2).start()
        try:
            audio = AudioProcess(loop, wav=wav, monitor=mon).start()
            time.sleep(3.0)
            cs = audio.click_stats()
            audio.close()
            h = mon.view.history(10.0)
        finally:
            mon.close()
    with wave.open(str(wav)) as w:
        fs = w.getframerate()
        x = np.frombuffer(w.readframes(w.getnframes()), np.int16) / 32767.0
    assert len(x) > 2 * fs and len(h["spike_t"]) > 50
    # the clicks of all spikes, on the loop's clock; find the one offset that
    # maps it onto the recording (whole samples by cross-correlation, then the
    # fraction the synth rounded with), then they must coincide sample for sample
    base = (h["spike_t"] + K.DELAY_S) * fs
    starts = np.rint(base).astype(np.int64)
    n_ref = int(starts.max()) + fs
    ref = click_reference(n_ref, starts, h["spike_nerve"], fs)
    corr = np.fft.irfft(np.fft.rfft(ref, 2 * n_ref).conj() * np.fft.rfft(x, 2 * n_ref))
    lag = int(np.argmax(corr))
    lag = lag - 2 * n_ref if lag > n_ref else lag
    skip = int(0.05 * fs)                          # spikes just before the audio started
    best = 1.0
    for shift in (lag - 1, lag, lag + 1):
        for frac in np.arange(-0.5, 0.5, 0.05):
            st = np.rint(base + frac).astype(np.int64) + shift
            ok = (st >= 0) & (st < len(x))
            aligned = click_reference(len(x), st[ok], h["spike_nerve"][ok], fs)
            best = min(best, float(np.mean(np.abs(aligned - x)[skip:] > 2e-3)))
    assert best < 0.02, cs                        # late or re-anchored clicks are rare
    sounding = np.abs(x[skip:]) > 1e-3
    assert sounding.mean() > 0.05                 # ~40 clicks/s of 4 ms each
