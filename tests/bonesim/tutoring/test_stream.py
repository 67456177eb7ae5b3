"""Tutoring carries the tissue-event stream: the STATE packet's records and
their version, the server's log and the late joiner's snapshot, and the
trainee's replica, its ``changes`` ring and the recording source following
removals, resets, splits and poses. The sessions run in one thread on the
virtual clock and in-memory network of :mod:`tests.bonesim.tutoring.test_tutor`."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bonesim.devices.simulated_hand import SimulatedHandDevice
from bonesim.engine import events
from bonesim.engine.replica import TissueReplica
from bonesim.errors import BonesimError
from bonesim.net import packets as net
from bonesim.runtime.commands import MoveBody, Reset
from bonesim.net import tutor_protocol
from bonesim.tutoring import server as tutor_server
from bonesim.tutoring import servo as tutor_servo
from bonesim.tutoring import sources as tutor_sources
from tests.bonesim.fakes import block_model
from tests.bonesim.tutoring.test_tutor import (
    DT,
    KEY,
    SERVER,
    TRAINEE,
    Instructor,
    MemoryNet,
    _occupancy,
    _replay_changes,
    _run,
    _same_tissue,
    _session,
    _snapshot,
    _split_and_move,
)


# --------------------------------------------------------------- wire format
def _records(k, seed=0):
    """``k`` tissue-event records of every kind with arbitrary fields."""
    rng = np.random.default_rng(seed)
    rec = np.zeros(k, tutor_protocol.RECORD)
    rec["kind"] = np.arange(k) % len(events.KIND_NAMES)
    rec["body"] = rng.integers(0, 64, k)
    rec["label"] = rng.integers(0, 9, k)
    rec["t_s"] = rng.uniform(0, 100, k)
    rec["ijk"] = rng.integers(-5, 1 << 20, (k, 3))
    rec["n"] = rng.integers(-3, 1 << 30, k)
    rec["value"] = rng.normal(0, 10, (k, events.N_VALUE))
    return rec


def test_state_payload_round_trip_and_length_checks():
    assert tutor_protocol.RECORD.itemsize == 83 and list(tutor_protocol.RECORD.names) == list(
        events.TISSUE_FIELDS)
    assert tutor_protocol.MAX_EVENTS == (net.MAX_PAYLOAD - tutor_protocol.STATE.size) // 83 >= 14
    buf = bytearray(net.MAX_PAYLOAD)
    rec = _records(tutor_protocol.MAX_EVENTS)
    n = tutor_protocol.pack_state(buf, 1.5, [1, 2, 3], [0, 0, -1], [0.1, 0.2, 0.3], 60000.0, 1.25,
                         7.5, 3, 5, 1, -1, 2, 1000, 900, rec)
    assert n <= net.MAX_PAYLOAD
    st = tutor_protocol.InstructorState()
    log_len, first, got = tutor_protocol.unpack_state(bytes(buf[:n]), st)
    assert (log_len, first) == (1000, 900)
    for f in events.TISSUE_FIELDS:                  # every column, bit for bit
        np.testing.assert_array_equal(got[f], rec[f])
    assert st.t_s == 1.5 and st.pos_mm.tolist() == [1, 2, 3] and st.force_n[2] == 0.3
    assert (st.epoch, st.buttons, st.drill, st.direction, st.burr) == (3, 5, 1, -1, 2)
    assert st.speed_rpm == 60000.0 and st.mag_n == 1.25 and st.volume_mm3 == 7.5
    for bad in (bytes(buf[:n - 1]), bytes(buf[:10])):
        with pytest.raises(net.PacketError) as ei:
            tutor_protocol.unpack_state(bad, tutor_protocol.InstructorState())
        assert ei.value.reason == "length"
    nan = bytearray(buf[:n])
    tutor_protocol.STATE.pack_into(nan, 0, math.nan, *([0.0] * 12), 0, 0, 0, 0, 0,
                          events.TISSUE_EVENT_VERSION, 0, 0, 0)
    with pytest.raises(net.PacketError, match="non-finite"):
        tutor_protocol.unpack_state(bytes(nan[:tutor_protocol.STATE.size]), tutor_protocol.InstructorState())


def _state_of_version(version, t=0.0):
    """A STATE payload without events whose records claim ``version``."""
    buf = bytearray(tutor_protocol.STATE.size)
    tutor_protocol.STATE.pack_into(buf, 0, t, *([0.0] * 12), 0, 0, 0, 1, 0, version, 1, 0, 0)
    return bytes(buf)


def test_a_state_of_an_unknown_record_version_is_refused_naming_the_packet():
    for v in (0, events.TISSUE_EVENT_VERSION + 1, 255):
        with pytest.raises(net.PacketError) as ei:
            tutor_protocol.unpack_state(_state_of_version(v), tutor_protocol.InstructorState())
        assert ei.value.reason == "version"
        msg = str(ei.value)
        assert "STATE packet" in msg and f"version {v}" in msg
        assert f"reads version {events.TISSUE_EVENT_VERSION}" in msg
    st = tutor_protocol.InstructorState()
    tutor_protocol.unpack_state(_state_of_version(events.TISSUE_EVENT_VERSION), st)
    assert st.valid
    with pytest.raises(net.PacketError, match="WELCOME packet carries tissue-event "
                                              "records of no version"):
        tutor_protocol.check_tissue_version(None, "WELCOME")


# ------------------------------------------------ the stream, live
def test_changes_ring_replays_to_the_replica_under_loss_and_a_reset():
    model, inst, netw, srv, src, trainee = _session(drop=0.10, seed=5)
    src.changes = events.tissue_ring(1 << 14)
    _run(model, inst, srv, trainee, 0.0, 2.2)
    q = 2200
    while src.have < srv.log.n and q < 6000:     # the go-backs finish
        _run(model, inst, srv, trainee, q * DT, (q + 1) * DT)
        q += 1
    assert netw.dropped > 100 and src.counters["nacks_sent"] > 0
    g, resets = _replay_changes(model, src.changes)
    assert resets == src.counters["resets"] == 1             # the log's leading RESET
    # each event once, in the server's order
    assert src.changes.count == src.have == src.counters["events_applied"] > 100
    got = src.changes.read(0)
    for f, a in srv.log.columns().items():
        np.testing.assert_array_equal(got[f], a)
    np.testing.assert_array_equal(_occupancy(g), _occupancy(src.grid))
    inst.command(Reset, q * DT)                              # the instructor resets
    _run(model, inst, srv, trainee, q * DT, q * DT + 0.1)
    before = resets
    g, resets = _replay_changes(model, src.changes)
    assert resets == before + 1 and src.epoch == 1
    np.testing.assert_array_equal(_occupancy(g), _occupancy(src.grid))
    np.testing.assert_array_equal(_occupancy(g), _occupancy(inst.state.grid))
    # the window's replica, fed the ring, is the source's
    window = TissueReplica(model)
    window.apply(src.changes.read(0))
    _same_tissue(window.state, inst.state)


def test_tutored_replica_equals_the_instructors_tissue_through_splits_poses_and_a_reset():
    """Removals, a split of two bodies, their poses (the instructor then
    drills into a moved body), a case reset, a new split and pose and more
    drilling: under 5 % loss the trainee's replica, and a window's replica
    fed its changes ring, end equal to the instructor's tissue (occupancy,
    bodies, poses, body of every voxel)."""
    model, inst, netw, srv, src, trainee = _session(drop=0.05, seed=11)
    src.changes = events.tissue_ring(1 << 16)
    _run(model, inst, srv, trainee, 0.0, 2.0)        # the drilling starts at ~1.85 s
    assert inst.state.n_removed > 10
    _split_and_move(inst, 2.0, 0.4)
    _run(model, inst, srv, trainee, 2.0, 2.2)
    gone = _occupancy(model.grid) & ~_occupancy(inst.state.grid)
    assert (inst.state.body[gone] == 2).sum() > 10   # drilled into the moved body
    inst.command(Reset, 2.2)
    _run(model, inst, srv, trainee, 2.2, 2.4)
    _split_and_move(inst, 2.4, -0.3)
    _run(model, inst, srv, trainee, 2.4, 2.7)
    q = 2700
    while src.have < srv.log.n and q < 8000:         # the go-backs finish
        _run(model, inst, srv, trainee, q * DT, (q + 1) * DT)
        q += 1
    assert netw.dropped > 50 and src.counters["nacks_sent"] > 0
    kinds = set(srv.log.columns()["kind"].tolist())
    assert {events.RESET, events.REMOVED, events.SPLIT, events.POSE} <= kinds
    assert src.have == srv.log.n and src.epoch == srv.epoch == src.replica.epoch == 1
    assert inst.state.n_removed > 10 and inst.state.alive.sum() == 3
    _same_tissue(src.replica.state, inst.state)
    window = TissueReplica(model)
    window.apply(src.changes.read(0))
    assert window.epoch == 1
    _same_tissue(window.state, inst.state)


def test_server_started_mid_session_sends_what_was_already_drilled():
    model, state = block_model()
    inst = Instructor(model, state)
    for q in range(2000):                                     # drilled before serving
        inst.step(q * DT)
    _split_and_move(inst, 2.0, 0.4)
    for q in range(2000, 2200):
        inst.step(q * DT)
    assert state.n_removed > 50
    netw = MemoryNet()
    srv = tutor_server.Streamer(netw.endpoint(SERVER), KEY, inst.samples, state.tissue,
                         tutor_protocol.session_info(model), snapshot=lambda: _snapshot(model, state))
    src = tutor_sources.NetworkSource(SERVER[0], SERVER[1], KEY, model=model,
                              sock=netw.endpoint(TRAINEE))
    trainee = tutor_servo.Trainee(src, SimulatedHandDevice())
    _run(model, inst, srv, trainee, 2.2, 2.6)
    assert src.have == srv.log.n > 1000                       # caught up in bursts
    _same_tissue(src.replica.state, state)


def test_snapshot_of_a_tissue_applies_to_it():
    model, inst, *_ = _session()
    for q in range(2000):
        inst.step(q * DT)
    _split_and_move(inst, 2.0, 0.4)
    for q in range(2000, 2200):
        inst.step(q * DT)
    inst.command(MoveBody, 2.2, body=0, pose=(0.1, 0.2, 0.3, 1, 0, 0, 0))
    snap = _snapshot(model, inst.state, epoch=4, t_s=2.2)
    assert snap["kind"][0] == events.RESET and snap["n"][0] == 4
    assert (snap["t_s"] == 2.2).all()
    assert set(snap["kind"].tolist()) == {events.RESET, events.SPLIT, events.POSE,
                                          events.REMOVED}
    r = TissueReplica(model)
    r.apply(snap)
    assert r.epoch == 4
    _same_tissue(r.state, inst.state)
    # a fresh tissue is its RESET alone
    _, fresh = block_model()
    assert len(_snapshot(model, fresh)["kind"]) == 1


def test_a_trainee_refuses_an_unknown_record_version_naming_the_packet():
    model, inst, netw, srv, src, trainee = _session()
    _run(model, inst, srv, trainee, 0.0, 0.1)
    assert src.state.valid
    forged = net.Codec(KEY).encode(tutor_protocol.KIND_STATE,
                                   _state_of_version(events.TISSUE_EVENT_VERSION + 1, 0.1),
                                   src.nonce, t_s=0.1)
    netw.queues[TRAINEE].append((forged, SERVER))
    with pytest.raises(BonesimError, match=r"STATE packet carries tissue-event records "
                                           r"of version 3; this trainee reads version 2"):
        src.poll(0.1)
    # a server announcing another version in its WELCOME is refused at once
    model, state = block_model()
    inst = Instructor(model, state)
    netw = MemoryNet()
    info = dict(tutor_protocol.session_info(model), tissue_version=99)
    srv = tutor_server.Streamer(netw.endpoint(SERVER), KEY, inst.samples, state.tissue, info)
    src = tutor_sources.NetworkSource(SERVER[0], SERVER[1], KEY, model=model,
                              sock=netw.endpoint(TRAINEE))
    src.poll(0.0)                                              # JOIN
    inst.step(0.0)
    srv.tick(0.0)                                              # WELCOME
    with pytest.raises(BonesimError, match="WELCOME packet carries tissue-event records "
                                           "of version 99"):
        src.poll(0.001)


# ------------------------------------------------- a recorded stream
def _fake_session():
    """test_playback's stand-in session (a reset at 1.2 s) with the tissue
    stream its schema-1-style tables migrate to."""
    from bonesim.session.schema_v1 import migrate
    from tests.bonesim.session.test_playback import fake_session

    session, _ = fake_session()
    session.events = [(1.2, "reset", "1")]      # as the app logged it: the new epoch
    session.tissue, _ = migrate(session.removals, session.injuries, session.events)
    return session


def test_recording_source_publishes_its_changes(tmp_path):
    session = _fake_session()
    model = session.load_model()
    src = tutor_sources.RecordingSource(session, model=model)
    src.changes = events.tissue_ring(1 << 14)
    for q in range(0, 1900, 7):
        src.poll(q * DT)
        if q in (1106, 1799):                   # before and after the reset
            g, resets = _replay_changes(model, src.changes)
            np.testing.assert_array_equal(_occupancy(g), _occupancy(src.grid))
            assert resets == (1 if q < 1200 else 2) and src.state.epoch == resets - 1
    assert src.ended and src.done
    # the starting RESET, then the whole stream in order (the recorded reset too)
    assert src.changes.count == len(session.tissue["t_s"]) + 1
    got = src.changes.read(1)
    for f in events.TISSUE_FIELDS:
        np.testing.assert_array_equal(got[f], session.tissue[f])


def test_recording_source_started_late_skips_what_a_reset_undid():
    session = _fake_session()
    model = session.load_model()
    src = tutor_sources.RecordingSource(session, model=model, start_s=1.5)
    src.changes = events.tissue_ring(1 << 14)
    src.poll(10.0)
    got = src.changes.read(0)
    assert got["kind"][0] == events.RESET and (got["kind"] == events.RESET).sum() == 1
    assert (got["t_s"] >= 1.2 - 1e-9).all() and src.replica.epoch == 1
    assert src.applied == int(np.searchsorted(session.tissue["t_s"], 1.5, side="right"))
    ref, _ = _replay_changes(model, src.changes)
    np.testing.assert_array_equal(_occupancy(ref), _occupancy(src.grid))


def test_recording_source_ends_on_the_recordings_last_state():
    session = _fake_session()
    model = session.load_model()
    src = tutor_sources.RecordingSource(session, model=model)
    for t in (0.0, 0.5, 1.0, 1.5):               # coarse polls: the end falls between
        src.poll(t)
        assert not src.done
    src.poll(2.5)
    tl = src.timeline
    assert src.done and src.t == tl.duration and src.last_valid_s == 2.5
    np.testing.assert_array_equal(src.state.pos_mm, session.samples["pos_mm"][-1])
    epoch, lo, hi = tl.removal_range(tl.duration)
    assert src.applied == len(session.tissue["t_s"])      # the last events too
    ref = model.grid.copy()
    from bonesim.engine.grid import sync_replica

    sync_replica(ref, ref, tl.rem_ijk[lo:hi], np.zeros((0, 3), np.int32))
    np.testing.assert_array_equal(_occupancy(src.grid), _occupancy(ref))
    src.poll(3.0)                                # silence after the end
    assert src.last_valid_s == 2.5
