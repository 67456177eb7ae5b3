"""The nerve monitor over the network: DATA payloads, the server and the
remote console on an in-memory network (loss, forged, replayed and malformed
packets, link loss), then the real monitor process over 127.0.0.1 and the
``bonesim monitor`` command."""
from __future__ import annotations

import math
import socket

import numpy as np
import pytest

from bonesim.net import monitor_link as MN
from bonesim.net import packets as net
from bonesim.runtime.monitor import ActivityParams

from tests.bonesim.tutoring.test_tutor import MemoryNet

KEY = bytes(range(7, 39))
SERVER = ("10.0.0.1", MN.DEFAULT_PORT)
CONSOLE = ("10.0.0.3", 50001)
NAMES = ["facial_nerve", "chorda_tympani"]
COLORS = [(250, 230, 60), (240, 150, 40)]
P = ActivityParams()
DT = 1.0 / 200.0                                      # the monitor's update period


# ------------------------------------------------------------------ payloads
def test_data_payload_round_trip_and_length_checks():
    buf = bytearray(net.MAX_PAYLOAD)
    k = 2
    t = np.array([1.25, 1.2512, 1.3])
    n = pack_n = MN.pack_data(buf, 3.5, 700, 41, [4.0, 150.5], [2.25, math.inf], t,
                              np.array([0, 1, 0], np.uint8))
    assert n == MN.DATA.size + MN.NERVE_BYTES * k + MN.SPIKE_BYTES * 3
    d = MN.unpack_data(bytes(buf[:n]))
    assert (d["t_s"], d["updates"], d["number"]) == (3.5, 700, 41)
    np.testing.assert_array_equal(d["rate"], np.float32([4.0, 150.5]))
    np.testing.assert_array_equal(d["dist"], np.float32([2.25, math.inf]))
    np.testing.assert_array_equal(d["spike_t"], t)
    np.testing.assert_array_equal(d["spike_nerve"], [0, 1, 0])
    for bad in (bytes(buf[:pack_n - 1]), bytes(buf[:pack_n]) + b"\0", b"\0" * 5):
        with pytest.raises(net.PacketError) as e:
            MN.unpack_data(bad)
        assert e.value.reason == "length"
    # the largest spike count fits the datagram limit, one more does not
    m = MN.max_spikes(k)
    n = MN.pack_data(buf, 0.0, 0, 0, [0, 0], [0, 0], np.zeros(m), np.zeros(m, np.uint8))
    assert n <= net.MAX_PAYLOAD < n + MN.SPIKE_BYTES
    with pytest.raises(ValueError, match="do not fit"):
        MN.pack_data(buf, 0.0, 0, 0, [0, 0], [0, 0], np.zeros(m + 1), np.zeros(m + 1))


# -------------------------------------------------- server and console in memory
class FakeMonitor:
    """Updates like the monitor process: rates and distances by a formula,
    Poisson spikes from a seeded generator; keeps everything it produced."""

    def __init__(self, seed=0, rate_hz=(40.0, 300.0)):
        self.rng = np.random.default_rng(seed)
        self.rate_hz = np.asarray(rate_hz)
        self.rows, self.spikes = [], []

    def update(self, t):
        rates = self.rate_hz * (1.0 + 0.5 * math.sin(t))
        dist = np.array([max(2.9 - t, 0.1), 9.0])      # the burr nears the first
        cnt = self.rng.poisson(rates * DT)
        st = np.concatenate([t - DT + self.rng.random(c) * DT for c in cnt])
        sn = np.repeat(np.arange(2, dtype=np.uint8), cnt)
        o = np.argsort(st)
        st, sn = st[o], sn[o]
        self.rows.append((t, rates.astype(np.float32), dist.astype(np.float32)))
        self.spikes.extend(zip(st, sn))
        return rates, dist, st, sn


def _pair(drop=0.0, seed=0, attack=None):
    netw = MemoryNet(drop=drop, seed=seed)
    srv = MN.MonitorServer(NAMES, COLORS, P, KEY, port=SERVER[1],
                           sock=netw.endpoint(SERVER), update_hz=200.0)
    con = MN.MonitorConsole(SERVER[0], SERVER[1], KEY, sock=netw.endpoint(CONSOLE))
    return netw, srv, con


def _run(srv, con, mon, t0, t1, netw=None, attack=None, serve=True):
    for q in range(int(round(t0 / DT)), int(round(t1 / DT))):
        t = q * DT
        if serve:
            srv.add(t, *mon.update(t))
            srv.poll(t)
        if attack is not None:
            attack(q, t, netw, con)
        con.poll(t)


def test_console_receives_every_update_and_spike_in_order():
    netw, srv, con = _pair()
    mon = FakeMonitor()
    _run(srv, con, mon, 0.0, 3.0)
    assert con.names == NAMES and con.info["colors"] == [list(c) for c in COLORS]
    assert con.info["params"]["warn_mm"] == P.warn_mm and con.info["update_hz"] == 200.0
    s = con.stats()
    assert s["lost"] == 0 and s["link_ok"] and s["packets"]["accepted"] == s["data"] + 1
    # streaming began at the first ACK; from then on the console has every
    # 4th update (50 Hz of 200 Hz) and every spike, in order
    h = con.history(10.0)
    t = h["t_s"]
    rows = {round(r[0], 9): r for r in mon.rows}
    assert len(t) > 2.8 * MN.STREAM_HZ and np.all(np.diff(t) == pytest.approx(4 * DT))
    for q, tq in enumerate(t):
        np.testing.assert_array_equal(h["rate"][q], rows[round(tq, 9)][1])
        np.testing.assert_array_equal(h["dist"][q], rows[round(tq, 9)][2])
    first = srv.counters["spikes_sent"]
    i0 = [x for x, _ in mon.spikes].index(h["spike_t"][0])     # streaming began here
    sent = mon.spikes[i0:i0 + first]
    assert first > 500 and len(h["spike_t"]) == first == s["spikes"]
    assert len(mon.spikes) - i0 - first < 20            # the rest: after the last packet
    np.testing.assert_array_equal(h["spike_t"], [x for x, _ in sent])
    np.testing.assert_array_equal(h["spike_nerve"], [c for _, c in sent])
    # the window of the history
    h1 = con.history(1.0)
    assert h1["now"] == t[-1] and h1["t_s"].min() >= t[-1] - 1.0
    assert h1["spike_t"].min() >= t[-1] - 1.0 and len(h1["spike_t"]) < len(h["spike_t"])
    # the console's text: a line per nerve, a warning below warn_mm, the link
    lines = con.lines()
    assert len(lines) == 3 and lines[0].startswith("Facial nerve ") and "link ok" in lines[2]
    assert lines[1].startswith("Chorda tympani ")                  # clinical names on screen
    assert con.titles == ["Facial nerve", "Chorda tympani"] and con.names == NAMES
    assert "WARNING" in lines[0] and "WARNING" not in lines[1]      # 0.1 mm vs 9 mm


def test_a_burst_of_spikes_is_split_over_packets():
    netw, srv, con = _pair()
    mon = FakeMonitor(rate_hz=(4.0, 4.0))
    _run(srv, con, mon, 0.0, 0.5)
    burst = np.sort(np.random.default_rng(1).uniform(0.49, 0.5, 1000))
    before = con.counters["spikes"]
    srv.add(0.5, [400.0, 4.0], [0.0, 9.0], burst, np.zeros(1000, np.uint8))
    sent = srv.poll(0.5 + 1.0)
    con.poll(0.5 + 1.0)
    assert sent == math.ceil(1000 / MN.max_spikes(2))
    assert con.counters["spikes"] - before == 1000 and con.counters["lost"] == 0
    np.testing.assert_array_equal(con.history(10.0)["spike_t"][-1000:], burst)


def test_loss_is_counted_and_the_trace_goes_on():
    netw, srv, con = _pair(drop=0.1, seed=5)
    mon = FakeMonitor()
    _run(srv, con, mon, 0.0, 4.0)
    s = con.stats()
    data_sent = srv.counters["sent"]
    assert 0.05 < s["loss_fraction"] < 0.16
    # every packet after the first received is either received or counted lost
    assert s["data"] + s["lost"] <= data_sent <= s["data"] + s["lost"] + 12
    assert s["link_ok"] and s["link_lost"] == 0          # 10 % loss is no outage
    h = con.history(10.0)
    assert np.all(np.diff(h["t_s"]) > 0) and np.all(np.diff(h["spike_t"]) >= 0)
    assert 0.8 * srv.counters["spikes_sent"] < s["spikes"] < srv.counters["spikes_sent"]


def test_forged_replayed_and_malformed_packets_change_nothing():
    clean_net, clean_srv, clean = _pair()
    _run(clean_srv, clean, FakeMonitor(), 0.0, 2.0)
    forger = net.Codec(bytes(32))                      # wrong key
    captured = []

    def attack(q, t, netw, con):
        srv = servers[0]
        mine = [d for s, dd, d in netw.taps if s == SERVER and dd == CONSOLE]
        if q == 100:
            captured.extend(mine[-20:])
        if q % 3 or q == 0:
            return
        buf = bytearray(net.MAX_PAYLOAD)
        n = MN.pack_data(buf, t, 1, 10 ** 6, [400.0, 400.0], [0.0, 0.0], [t], [0])
        q_ = netw.queues[CONSOLE]
        q_.append((forger.encode(MN.KIND_DATA, buf[:n], con.nonce, t_s=t), SERVER))
        if captured:
            q_.append((captured[q % len(captured)], SERVER))        # replayed
        q_.append((b"\x00" * 40, SERVER))                            # garbage
        if mine:
            q_.append((mine[-1][:-2], SERVER))                       # truncated
            flipped = bytearray(mine[-1])
            flipped[50] ^= 4
            q_.append((bytes(flipped), SERVER))                      # altered
        # authentic (the server's own codec), but a DATA payload that lies
        # about its sizes
        q_.append((srv.session.codec.encode(MN.KIND_DATA, bytes(buf[:n - 1]), con.nonce, t_s=t),
                   SERVER))

    netw, srv, con = _pair()
    servers = [srv]
    _run(srv, con, FakeMonitor(), 0.0, 2.0, netw=netw, attack=attack)
    a, b = clean.history(10.0), con.history(10.0)
    for key in ("t_s", "rate", "dist", "spike_t", "spike_nerve"):
        np.testing.assert_array_equal(a[key], b[key])
    c = con.inbox.counters
    n_attacks = 2.0 / DT / 3 - 1
    assert c["auth"] >= 2 * n_attacks - 5               # forged + altered
    assert c["duplicate"] >= (400 - 100) / 3 - 2        # replays from q = 100 on
    assert c["malformed"] >= 3 * n_attacks - 5          # garbage, truncated, lying payload
    assert c["accepted"] == clean.inbox.counters["accepted"]
    assert con.counters["lost"] == 0 and con.stats()["rates_hz"] == clean.stats()["rates_hz"]


def test_link_loss_is_reported_and_the_console_rejoins():
    netw, srv, con = _pair()
    mon = FakeMonitor()
    _run(srv, con, mon, 0.0, 1.0)
    assert con.link_ok and "link ok" in con.lines()[-1]
    joins = con.counters["joins_sent"]
    _run(srv, con, mon, 1.0, 1.0 + MN.LINK_LOSS_S - 0.02, serve=False)
    assert con.link_ok                                 # not yet
    _run(srv, con, mon, 1.0 + MN.LINK_LOSS_S - 0.02, 2.0, serve=False)
    assert not con.link_ok and con.counters["link_lost"] == 1
    assert "LINK LOST" in con.lines()[-1]
    # the server returns (a restarted simulator: new server, new nonce)
    srv2 = MN.MonitorServer(NAMES, COLORS, P, KEY, port=SERVER[1],
                            sock=netw.endpoint(SERVER))
    _run(srv2, con, mon, 2.0, 3.5)
    assert con.link_ok and con.counters["joins_sent"] > joins
    assert srv2.counters["joins"] == 1 and con.history(0.5)["t_s"].max() > 3.4


def test_server_bye_and_silent_consoles_are_forgotten():
    netw, srv, con = _pair()
    mon = FakeMonitor()
    _run(srv, con, mon, 0.0, 0.5)
    assert srv.n_clients == 1 and srv.stats()["streaming"] == 1
    con.close()                                         # console says BYE
    srv.poll(0.6)
    assert srv.n_clients == 0
    netw, srv, con = _pair()
    _run(srv, con, mon, 0.0, 0.5)
    for q in range(int(MN.CLIENT_TIMEOUT_S / DT) + 10):   # the console goes quiet
        srv.add(0.5 + q * DT, *mon.update(0.5 + q * DT))
        srv.poll(0.5 + q * DT)
    assert srv.n_clients == 0 and srv.counters["peers_dropped"] == 1
    netw, srv, con = _pair()
    _run(srv, con, mon, 0.0, 0.5)
    srv.close()                                         # server says BYE
    con.poll(0.51)
    assert con.counters["byes"] == 1 and not con.link_ok


def test_unauthenticated_joins_get_no_answer():
    netw, srv, con = _pair()
    forger = net.Codec(bytes(32))
    netw.queues[SERVER].append((forger.encode(net.KIND_JOIN, bytes(net.JOIN_PAD), 1234, t_s=0.0), CONSOLE))
    netw.queues[SERVER].append((b"junk" * 20, CONSOLE))
    srv.add(0.0, [4.0, 4.0], [9.0, 9.0], [], [])
    srv.poll(0.0)
    assert srv.rx["auth"] == 1 and srv.rx["malformed"] == 1 and srv.n_clients == 0
    assert not netw.queues[CONSOLE]                     # nothing was sent back


def test_server_rejects_bad_arguments_and_a_taken_port():
    with pytest.raises(ValueError, match="stream_hz"):
        MN.MonitorServer(NAMES, COLORS, P, KEY, port=0, stream_hz=0)
    with pytest.raises(ValueError, match=r"colors must be \(2, 3\)"):
        MN.MonitorServer(NAMES, COLORS[:1], P, KEY, port=0)
    with pytest.raises(ValueError, match="cannot stream 0 nerves"):
        MN.MonitorServer([], [], P, KEY, port=0)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        from bonesim.errors import BonesimError

        with pytest.raises(BonesimError, match="cannot bind UDP 127.0.0.1"):
            MN.MonitorServer(NAMES, COLORS, P, KEY, host="127.0.0.1",
                             port=s.getsockname()[1])


def test_console_reports_a_silent_server_or_a_wrong_key():
    from bonesim.errors import BonesimError

    quiet = net.udp_socket("127.0.0.1", 0)             # bound, never answers
    con = MN.MonitorConsole("127.0.0.1", quiet.getsockname()[1], KEY)
    with pytest.raises(BonesimError, match="no answer from the nerve monitor"):
        con.connect(0.3)
    con.close()
    quiet.close()
    srv = MN.MonitorServer(NAMES, COLORS, P, bytes(range(32)), host="127.0.0.1", port=0)
    srv.add(0.0, [4.0, 4.0], [9.0, 9.0], [], [])
    con = MN.MonitorConsole("127.0.0.1", srv.port, KEY)
    import threading

    stop = threading.Event()

    def serve():
        while not stop.is_set():
            srv.poll(con.clock())
            stop.wait(0.005)

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    try:
        with pytest.raises(BonesimError, match="no answer .* the key file"):
            con.connect(1.0)
        assert srv.rx["auth"] >= 2 and srv.n_clients == 0      # joins were refused
    finally:
        stop.set()
        th.join()
        con.close()
        srv.close()


# ------------------------------------------------------ real processes, loopback
@pytest.fixture(scope="module")
def phantom_model():
    from bonesim.io.loading import load_model

    return load_model("phantom", "cutting-5mm")


def _free_port():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    return port


@pytest.mark.slow
def test_monitor_process_streams_to_a_console_over_loopback(phantom_model):
    import time

    from bonesim.runtime.haptic_loop import HapticLoop
    from bonesim.runtime.monitor import MonitorProcess, NerveMonitor

    from tests.bonesim.runtime.test_monitor import approach_trajectory

    field = NerveMonitor(phantom_model, P).fields[0]
    traj = approach_trajectory(field, seconds=3.0)
    loop = HapticLoop(phantom_model, device=("scripted", traj), vibration=False)
    mon = con = None
    try:
        mon = MonitorProcess(loop, P, seed=4, serve={"key": KEY, "host": "127.0.0.1",
                                                     "port": 0}).start()
        con = MN.MonitorConsole("127.0.0.1", mon.port, KEY)
        con.connect(30.0)
        loop.start()
        end = time.monotonic() + 60.0
        while not con.t_s >= traj.t_s[-1] + 0.5 and time.monotonic() < end:
            con.poll()
            time.sleep(0.002)
        for _ in range(50):                       # the last packets in flight
            con.poll()
            time.sleep(0.002)
        view = mon.view.history(10.0)
        stats, s = mon.stats(), con.stats()
        mh = con.history(10.0)
    finally:
        if mon is not None:
            mon.close()
        if con is not None:
            end = time.monotonic() + 5.0
            while con.counters["byes"] == 0 and time.monotonic() < end:
                con.poll()
                time.sleep(0.01)
            byes = con.counters["byes"]
            con.close()
        loop.close()
    assert byes == 1                                  # the server said goodbye
    assert s["names"] == NAMES and stats["consoles"] == 1
    assert s["packets"]["accepted"] > 100 and s["lost"] == 0, s
    assert sum(v for k, v in s["packets"].items() if k != "accepted") == 0, s
    # the console's readings are the monitor's, at the monitor's update times
    t = mh["t_s"]
    assert len(t) > 0.5 * MN.STREAM_HZ * traj.t_s[-1]
    i = np.searchsorted(view["t_s"], t)
    assert np.all(view["t_s"][i] == t)
    np.testing.assert_array_equal(mh["rate"], view["rate"][i])
    np.testing.assert_array_equal(mh["dist"], view["dist"][i])
    assert mh["dist"][0, 0] > 5.0 and mh["dist"][-1, 0] < 0.5        # the approach
    # every spike since streaming began, in order
    sel = view["spike_t"] >= mh["spike_t"][0]
    np.testing.assert_array_equal(mh["spike_t"], view["spike_t"][sel][:len(mh["spike_t"])])
    assert len(mh["spike_t"]) >= np.count_nonzero(sel) - 20 and len(mh["spike_t"]) > 50
    # loopback latency is measured (one machine, one monotonic clock); how
    # low it is on this machine is the bench's (monitor_loopback_latency_p99_ms)
    assert 0.0 <= s["latency_ms"]["p50"] <= s["latency_ms"]["max"], s["latency_ms"]


def _cli(argv, capsys):
    from bonesim.cli.main import main

    rc = main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.mark.slow
def test_cli_run_serves_the_monitor_and_the_console_follows(tmp_path, capsys,
                                                           phantom_model):
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    from bonesim.runtime.monitor import NerveMonitor
    from bonesim.io.trajectory import write_trajectory

    from tests.bonesim.runtime.test_monitor import approach_trajectory

    key = net.write_key(tmp_path / "k")
    traj = approach_trajectory(NerveMonitor(phantom_model, P).fields[0], seconds=4.0)
    write_trajectory(tmp_path / "t.csv", traj)
    port = _free_port()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(Path(MN.__file__).parents[2]),
                                         env.get("PYTHONPATH", "")])
    run = subprocess.Popen(
        [sys.executable, "-m", "bonesim.cli", "run", "--offscreen", "--script",
         str(tmp_path / "t.csv"), "--frames", "60", "--no-record", "--no-sound",
         "--size", "320", "240", "--monitor-port", str(port), "--monitor-host",
         "127.0.0.1", "--key-file", str(key), "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    try:
        rc, out, err = _cli(["monitor", "127.0.0.1", "--port", str(port), "--key-file",
                             str(key), "--timeout", "90", "--no-sound", "--wav",
                             str(tmp_path / "clicks.wav"), "--json"], capsys)
        r_out, r_err = run.communicate(timeout=180)
    finally:
        if run.poll() is None:
            run.kill()
    assert rc == 0, err
    assert run.returncode == 0, r_err
    assert f"nerve monitor on 127.0.0.1:{port} (Facial nerve, Chorda tympani)" in r_err
    assert f"nerve monitor of 127.0.0.1:{port}: Facial nerve, Chorda tympani" in err
    console, summary = json.loads(out), json.loads(r_out)
    assert console["names"] == NAMES and console["byes"] == 1 and console["data"] > 50
    assert console["packets"]["auth"] == 0 and console["spikes"] > 0
    assert console["clicks"]["scheduled"] == console["spikes"]
    assert (tmp_path / "clicks.wav").stat().st_size > 44
    m = summary["monitor"]
    assert m["nerves"] == NAMES and m["port"] == port and m["update_hz"] > 50
    assert m["packets_sent"] > 50 and m["consoles"] == 1     # (taken before the end)


def test_cli_errors_are_clear(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv(net.KEY_ENV, raising=False)
    rc, out, err = _cli(["monitor", "127.0.0.1", "--timeout", "0.2"], capsys)
    assert rc == 2 and "no key" in err
    key = net.write_key(tmp_path / "k")
    rc, out, err = _cli(["monitor", "127.0.0.1", "--port", str(_free_port()), "--key-file",
                         str(key), "--timeout", "0.3"], capsys)
    assert rc == 2 and "no answer from the nerve monitor" in err
    rc, out, err = _cli(["run", "--offscreen", "--no-monitor", "--monitor-port", "0",
                         "--key-file", str(key)], capsys)
    assert rc == 2 and "cannot go with --no-monitor" in err
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        from bonesim.errors import BonesimError
        from bonesim.runtime.haptic_loop import HapticLoop
        from bonesim.io.loading import load_model
        from bonesim.runtime.monitor import MonitorProcess

        loop = HapticLoop(load_model("phantom", "cutting-5mm"), device=("null",))
        try:
            with pytest.raises(BonesimError, match="cannot bind UDP 127.0.0.1"):
                MonitorProcess(loop, serve={"key": KEY, "host": "127.0.0.1",
                                            "port": s.getsockname()[1]}).start()
        finally:
            loop.close()


def test_bench_monitor_quick_smoke():
    from bonesim.bench.suite import BENCHMARKS
    from bonesim.bench.monitor import bench_monitor

    out = bench_monitor(quick=True)
    assert BENCHMARKS["monitor_loopback_latency_p99_ms"].__name__ == "bench_monitor"
    u = out["monitor_update_us"]
    assert u["unit"] == "us" and 0 < u["value"] <= u["p99_us"] and u["updates"] == 500
    assert u["lookup_max_excess_mm"] <= 0.05 and u["lookup_speedup_vs_brute_force"] > 1
    r = out["monitor_loopback_latency_p99_ms"]
    assert r["unit"] == "ms" and 0 < r["p50_ms"] <= r["value"] <= r["max_ms"]
    assert r["packets_received"] + r["lost"] <= r["packets_sent"]
    assert r["spikes_received"] <= r["spikes_sent"] and r["spikes_sent"] > 0
    assert out["monitor_loopback_loss_fraction"]["value"] == r["loss_fraction"]
