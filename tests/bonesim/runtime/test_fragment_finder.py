"""The fragment finder behind the haptic loop: it follows the tissue events,
finds what removals cut off and has the loop split it off through the command
ring; a recorded run with such splits and shed specks replays bit for bit."""
from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

from bonesim.engine import events
from bonesim.engine.fragments import body_mask, label_parts
from bonesim.engine.model import make_model, make_state
from bonesim.engine.replica import TissueReplica
from bonesim.io.burrs import load_burr
from bonesim.io.case import load_case
from bonesim.io.loading import load_model
from bonesim.runtime.commands import ShedPart, SplitBox, SplitPart
from bonesim.runtime.fragment_finder import FragmentFinder, speck_voxels_of
from bonesim.runtime.haptic_loop import HapticLoop
from bonesim.runtime.record import Recorder
from bonesim.session.header import make_header
from bonesim.session.reader import read_session
from bonesim.session.replay import replay, verify
from tests.bonesim.waiting import wait_drill_off, wait_steps, wait_until

BONE = SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200))


def _bar_model():
    lab = np.zeros((24, 12, 12), np.uint8)
    lab[0:20, 4:6, 4:6] = 1                  # a bar from the grid's face x = 0
    lab[20:22, 4, 4] = 1                     # ... with a 2-voxel tip
    return make_model(lab, 0.5, [BONE], load_burr("cutting-1mm"))


def _drill(state, ijk, t):
    """Remove voxels as the haptic step would: density 0, REMOVED events."""
    g = state.grid
    ijk = np.asarray(ijk, np.int32).reshape(-1, 3)
    bodies = []
    for i, j, k in ijk.tolist():
        b = g.brick_index(i, j, k)
        off = ((i & 7) << 6) | ((j & 7) << 3) | (k & 7)
        g.density[b, off] = 0.0
        state.removed_by_label[g.label[b, off]] += 1
        bodies.append(state.body[b, off])       # a removed voxel keeps its body
    n = len(ijk)
    state.tissue.append(kind=np.full(n, events.REMOVED, np.uint8),
                        body=np.array(bodies, np.uint8), label=np.ones(n, np.uint8),
                        t_s=np.full(n, t), ijk=ijk, n=np.zeros(n, np.int32),
                        value=np.zeros((n, 7)))


def _slab(x):
    return np.array([(x, j, k) for j in (4, 5) for k in (4, 5)])


def _sender(state):
    """Commands applied at once, as the loop would between two steps."""
    ctx = SimpleNamespace(model=None, state=state, t_s=0.0)
    sent = []

    def send(cls, **params):
        cls.apply(ctx, cls.encode(**params))
        sent.append(cls)
        return len(sent) - 1
    return send, sent


def _body_at(state, i, j, k):
    return int(state.body[state.grid.brick_index(i, j, k),
                          ((i & 7) << 6) | ((j & 7) << 3) | (k & 7)])


def test_finder_splits_what_drilling_cut_off_and_sheds_specks():
    m = _bar_model()
    st = make_state(m)
    finder = FragmentFinder(m, st, snapshot=False)
    assert finder.speck_voxels == 8
    send, sent = _sender(st)
    _drill(st, _slab(8)[:2], 0.1)          # half through: still one piece
    assert finder.poll(send) == 0 and st.n_bodies == 1
    _drill(st, _slab(19), 0.2)             # frees the 2-voxel tip: a speck
    assert finder.poll(send) == 1 and sent == [ShedPart] and st.n_bodies == 1
    ev = st.tissue.read(0)
    shed = (ev["kind"] == events.REMOVED) & (ev["n"] == events.REMOVED_SHED)
    assert {tuple(v) for v in ev["ijk"][shed].tolist()} == {(20, 4, 4), (21, 4, 4)}
    _drill(st, _slab(8)[2:], 0.3)          # through at x = 8 and x = 15: two fragments
    _drill(st, _slab(15), 0.3)
    assert finder.poll(send) == 2 and sent[1:] == [SplitPart, SplitPart]
    assert st.n_bodies == 3 and finder.stats["split"] == 2 and finder.stats["shed"] == 1
    assert (st.tissue.read(0)["kind"] == events.SPLIT).sum() == 24 + 12
    assert [_body_at(st, x, 4, 4) for x in (0, 10, 17)] == [0, 1, 2]
    # the finder's replica follows the loop's splits
    finder.poll(send)
    np.testing.assert_array_equal(finder.replica.state.body, st.body)
    np.testing.assert_array_equal(finder.replica.grid.density, st.grid.density)
    # a fragment splits again: body 1 (x = 9..14) cut at x = 12; the larger
    # piece (x = 9..11) keeps body 1
    _drill(st, _slab(12), 0.4)
    assert finder.poll(send) == 1 and st.n_bodies == 4
    assert [_body_at(st, x, 4, 4) for x in (10, 13)] == [1, 3]


def test_finder_thread_queues_and_pump_sends():
    m = _bar_model()
    st = make_state(m)
    finder = FragmentFinder(m, st, snapshot=False).start()
    send, sent = _sender(st)
    try:
        _drill(st, _slab(6), 0.1)
        _drill(st, _slab(12), 0.2)
        end = time.monotonic() + 10.0
        while st.n_bodies < 3 and time.monotonic() < end:
            finder.pump(send)
            time.sleep(0.005)
    finally:
        finder.close()
    assert st.n_bodies == 3 and sent == [SplitPart, SplitPart]
    assert finder.stats["rounds"] >= 1 and finder.error is None


def test_stale_commands_do_nothing():
    m = _bar_model()
    st = make_state(m)
    ctx = SimpleNamespace(model=m, state=st, t_s=0.0)
    st.epoch = 1                            # a reset came after the part was found
    _drill(st, _slab(6), 0.1)
    args = SplitPart.encode(body=0, seed=(7, 4, 4), lo=(7, 4, 4), hi=(19, 5, 5), n=52,
                            epoch=0)
    SplitPart.apply(ctx, args)
    assert st.n_bodies == 1
    st.epoch = 0
    SplitPart.apply(ctx, args)
    assert st.n_bodies == 2
    with pytest.raises(ValueError, match="seed"):
        SplitPart.encode(body=0, seed=(0, 0, 0), lo=(1, 1, 1), hi=(2, 2, 2), n=1, epoch=0)
    with pytest.raises(ValueError, match="n must be a positive"):
        ShedPart.encode(body=0, seed=(1, 1, 1), lo=(1, 1, 1), hi=(2, 2, 2), n=0, epoch=0)


def test_speck_size_comes_from_the_case(tmp_path):
    import shutil

    from bonesim.errors import BonesimError

    src = load_case("phantom").manifest
    dst = tmp_path / "case.toml"
    shutil.copy(src, dst)
    text = dst.read_text().replace("speck_voxels = 8", "speck_voxels = 20")
    dst.write_text(text)
    assert load_case(dst).fragments.speck_voxels == 20
    assert speck_voxels_of(SimpleNamespace(case=load_case(dst))) == 20
    dst.write_text(text.replace("speck_voxels = 20", "speck_voxels = 0"))
    with pytest.raises(BonesimError, match="speck_voxels.*>= 1"):
        load_case(dst)
    dst.write_text(text.replace("speck_voxels = 20", "speck_voxel = 3"))
    with pytest.raises(BonesimError, match="speck_voxel"):
        load_case(dst)


# ------------------------------------------------- the live loop, recorded
@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-5mm")


@pytest.fixture(scope="module")
def fragment_run(model, tmp_path_factory):
    """Mouse drilling with the finder behind the loop; the phantom's 4-voxel
    speck shed (ShedPart); a box split off by hand (SplitBox) and one of its
    pieces split off as a part (SplitPart); more drilling; recorded."""
    path = tmp_path_factory.mktemp("fragments") / "fragments.h5"
    cam = load_case("phantom").camera
    view = np.subtract(cam.focal_mm, cam.eye_mm)
    view /= np.linalg.norm(view)
    target = np.array([23.0, 3.0, -2.0]) + 3.0 * view
    g = model.grid
    loop = HapticLoop(model)
    rec = Recorder(loop, path, make_header(model, input_device="mouse"))
    sent = {}
    try:
        rec.start()
        loop.start()
        finder = FragmentFinder(model, loop.state, loop.status, snapshot=False)
        loop.set_target(target, view)
        loop.set_drill(True, speed_rpm=60000.0)
        assert wait_until(lambda: loop.state.n_removed > 20)
        # the phantom's 4-voxel speck (apart from the bone from the start)
        d, _ = g.to_dense()
        dl, dn = label_parts(d > 0)
        c = int(np.flatnonzero(np.bincount(dl.ravel()) == 4)[0])
        speck = np.argwhere(dl == c)
        sent["speck"] = {tuple(v) for v in speck.tolist()}
        loop.send(ShedPart, body=0, seed=speck[0], lo=speck.min(axis=0),
                  hi=speck.max(axis=0), n=4, epoch=0)
        finder.poll(loop.send)

        def applied(seq):
            return wait_until(lambda: int(loop.status["commands_read"]) > seq)

        at = np.rint((np.asarray(loop.status["pos_mm"], float) - g.origin_mm)
                     / model.spacing_mm).astype(int)
        lo, hi = at - 12, at + 4
        alive = loop.state.alive.copy()          # the finder may have made bodies
        assert applied(loop.send(SplitBox, lo=lo, hi=hi, body=0))
        new, = np.flatnonzero(loop.state.alive & ~alive)
        # a piece of the new body (the box clips the air cells' walls into pieces)
        st = loop.state
        lo1, hi1 = st.bounds[new, :3].astype(int), st.bounds[new, 3:].astype(int)
        lab, n = label_parts(body_mask(st, new, lo1, hi1))
        sizes = np.bincount(lab.ravel())
        sizes[0] = 0
        # the second largest piece, else the whole body (one piece)
        order = np.argsort(sizes, kind="stable")[::-1]
        piece = order[1] if n > 1 else order[0]
        vox = np.argwhere(lab == piece) + lo1
        sent["piece"] = {tuple(v) for v in vox.tolist()}
        alive = loop.state.alive.copy()
        assert applied(loop.send(SplitPart, body=int(new), seed=vox[0], lo=vox.min(axis=0),
                                 hi=vox.max(axis=0), n=int(sizes[piece]), epoch=0))
        sent["src"] = int(new)
        sent["dst"], = np.flatnonzero(loop.state.alive & ~alive)
        n0 = loop.state.n_removed
        for depth in np.arange(1.0, 8.0, 0.5):            # on, deeper, until it cuts
            loop.set_target(target + depth * view, view)
            if wait_until(lambda: loop.state.n_removed > n0 + 100, 1.0):
                break
        assert loop.state.n_removed > n0 + 100
        for _ in range(5):
            finder.poll(loop.send)
            assert wait_steps(loop, 20)
        loop.set_drill(False)
        assert wait_drill_off(loop)
        rec.close()
        finder.poll(loop.send)
        body = loop.state.body.copy()
        rejected = int(loop.status["commands_rejected"])
    finally:
        loop.close()
    return read_session(path), body, sent, finder, rejected


def test_fragment_splits_are_recorded_and_replay_bit_for_bit(fragment_run, model):
    s, body, sent, finder, rejected = fragment_run
    assert rejected == 0 and finder.error is None and finder.stats["rounds"] >= 1
    k = s.tissue["kind"]
    split2 = (k == events.SPLIT) & (s.tissue["body"] == sent["dst"])
    moved = {tuple(v) for v in s.tissue["ijk"][split2].tolist()}
    assert moved and moved <= sent["piece"]          # drilling may take some first
    assert (s.tissue["value"][split2, 0] == sent["src"]).all()
    shed = (k == events.REMOVED) & (s.tissue["n"] == events.REMOVED_SHED)
    assert shed.sum() >= 4
    assert sent["speck"] <= {tuple(v) for v in s.tissue["ijk"][shed].tolist()}
    # shed specks are removals, but not drilled ones
    assert s.removals["shed"].sum() == shed.sum()
    report = verify(s)
    assert report["ok"], report
    out = replay(s)["state"]
    np.testing.assert_array_equal(out.body, body)
    # a replica of the recorded stream holds the same tissue
    rep = TissueReplica(model)
    rep.apply({f: v for f, v in s.tissue.items() if f != "visible"})
    np.testing.assert_array_equal(rep.state.body, out.body)
    np.testing.assert_array_equal(rep.grid.density == 0, out.grid.density == 0)


def test_shed_specks_are_not_drilled_volume(fragment_run):
    from metrics.conduct import last_epoch
    from metrics.regions import region_run

    s, *_ = fragment_run
    _, rem = last_epoch(s)
    assert not rem["shed"].any() and len(rem["ijk"]) == (~s.removals["shed"]).sum()
    run = region_run(s, group="expert", participant="p")
    shed = s.removals["ijk"][s.removals["shed"]]
    flat = np.ravel_multi_index(shed.T.astype(np.int64), tuple(s.header["shape"]))
    assert not np.isin(flat, run.voxels).any()


def test_pump_keeps_what_a_full_ring_refused_and_reports_a_failed_thread():
    from bonesim.runtime.commands import CommandOverflow

    m = _bar_model()
    st = make_state(m)
    finder = FragmentFinder(m, st, snapshot=False)
    send, sent = _sender(st)
    _drill(st, _slab(6), 0.1)
    _drill(st, _slab(12), 0.2)
    finder._out.put(finder.commands())            # a round, as the thread queues it
    finder._queued += 1
    full = {"left": 1}

    def flaky(cls, **params):                      # the ring takes one, then is full
        if full["left"] == 0:
            raise CommandOverflow("full")
        full["left"] -= 1
        return send(cls, **params)
    assert finder.pump(flaky) == 1 and st.n_bodies == 2 and finder._busy()
    assert finder.pump(send) == 1 and st.n_bodies == 3 and not finder._busy()
    finder.error = ValueError("boom")
    with pytest.raises(RuntimeError, match="fragment finder stopped: boom"):
        finder.pump(send)
