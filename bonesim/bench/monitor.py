"""Benchmarks of the nerve monitor (:mod:`bonesim.runtime.monitor`, :mod:`bonesim.net.monitor_link`).

``monitor_update_us``
    One update of :class:`~bonesim.runtime.monitor.NerveMonitor` on the phantom (both
    monitored nerves) with the five haptic samples a 200 Hz update drains
    from a 1 kHz loop: distances, activity law, Poisson spikes. Reference in
    the same run: the distance part by brute force (numpy, every nerve voxel),
    reported as the lookup's speed-up (distances to the nerves' surface voxels'
    boxes at the case's source resolution).
``monitor_loopback_latency_p99_ms``
    A :class:`~bonesim.net.monitor_link.MonitorServer` in its own process, fed
    synthetic updates at 200 Hz (rates, distances, Poisson spikes), streams
    to a :class:`~bonesim.net.monitor_link.MonitorConsole` in this process over
    127.0.0.1 for a few seconds. Latency is ``receive time - send time`` on
    the shared monotonic clock; loss counts the DATA packets missing from the
    numbering. Figures are wall-clock on whatever machine runs them.
"""
from __future__ import annotations

import multiprocessing as mp
import select
import time

import numpy as np

from bonesim.runtime.shared import end_process

__all__ = ["SAMPLES_PER_UPDATE", "bench_update", "bench_loopback", "bench_monitor"]

_KEY = bytes(range(64, 96))
#: Samples per monitor update (1 kHz loop, 200 Hz monitor).
SAMPLES_PER_UPDATE = 5


def _pcts(a, scale):
    a = np.asarray(a) * scale
    return {"p50": round(float(np.percentile(a, 50)), 3),
            "p99": round(float(np.percentile(a, 99)), 3)}


def bench_update(quick: bool = False) -> dict:
    from bonesim.io.loading import load_model
    from bonesim.runtime.monitor import UPDATE_HZ, NerveMonitor

    model = load_model("phantom", "cutting-5mm")
    nm = NerveMonitor(model, seed=0)
    f0 = nm.fields[0]
    target = f0.voxels_mm[len(f0.voxels_mm) // 2]
    n_upd = 500 if quick else 5000
    n = n_upd * SAMPLES_PER_UPDATE
    gap = 2.5 + np.linspace(10.0, 0.0, n)             # a lateral approach, burr 5 mm
    pos = target + gap[:, None] * np.array([1.0, 0.0, 0.0])
    t = np.arange(1, n + 1) * 1e-3
    force = np.full(n, 1.0)
    drill = np.ones(n, bool)
    for q in range(20):                                # warm
        s = slice(q * SAMPLES_PER_UPDATE, (q + 1) * SAMPLES_PER_UPDATE)
        nm.update_many(t[s] - 1.0, pos[s], force[s], drill[s])
    nm.reset()
    cost = np.empty(n_upd)
    clock = time.perf_counter
    for q in range(n_upd):
        s = slice(q * SAMPLES_PER_UPDATE, (q + 1) * SAMPLES_PER_UPDATE)
        a = clock()
        nm.update_many(t[s], pos[s], force[s], drill[s])
        cost[q] = clock() - a
    # distances alone: the lookup against brute force over every nerve voxel
    m = 200 if quick else 1000
    pts = pos[:: max(n // m, 1)][:m]
    a = clock()
    look = nm.distances(pts, 0.0)
    t_look = clock() - a
    a = clock()
    brute = np.stack([np.sqrt((np.maximum(np.abs(pts[:, None, :] - f.voxels_mm[None])
                                          - f.spacing_mm / 2, 0.0) ** 2).sum(-1)).min(1)
                      for f in nm.fields], axis=1)          # to every surface voxel's box
    t_brute = clock() - a
    err = float(np.max(look - brute))
    pc = _pcts(cost, 1e6)
    return {
        "monitor_update_us": {
            "value": pc["p50"], "unit": "us", "p99_us": pc["p99"], "updates": n_upd,
            "samples_per_update": SAMPLES_PER_UPDATE, "nerves": nm.names,
            "cpu_share_at_update_hz": round(pc["p50"] * 1e-6 * UPDATE_HZ, 4),
            "distance_lookup_us_per_point": round(t_look / len(pts) * 1e6, 3),
            "brute_force_us_per_point": round(t_brute / len(pts) * 1e6, 3),
            "lookup_speedup_vs_brute_force": round(t_brute / t_look, 1),
            "lookup_max_excess_mm": round(err, 4),
            "nerve_voxels": [len(f.voxels_mm) for f in nm.fields]},
    }


def _server(seconds: float, conn) -> None:
    from bonesim.runtime.monitor import ActivityParams
    from bonesim.net.monitor_link import MonitorServer

    srv = MonitorServer(["facial_nerve", "chorda_tympani"], [(250, 230, 60), (240, 150, 40)],
                        ActivityParams(), _KEY, host="127.0.0.1", port=0, update_hz=200.0)
    conn.send(srv.port)
    rng = np.random.default_rng(0)
    period = 1.0 / 200.0
    clock = time.monotonic
    # serve the joins until told to go
    while not conn.poll(0.0):
        srv.poll(clock())
        time.sleep(0.002)
    conn.recv()
    deadline = clock()
    for q in range(int(seconds / period)):
        tq = q * period
        rates = np.array([40.0, 300.0])
        cnt = rng.poisson(rates * period)
        st = np.sort(tq - period + rng.random(int(cnt.sum())) * period)
        sn = np.repeat(np.arange(2, dtype=np.uint8), cnt)[np.argsort(rng.random(cnt.sum()))]
        srv.add(tq, rates, [3.0, 0.5], st, sn)
        srv.poll(clock())
        deadline += period
        rest = deadline - clock()
        if rest > 0:
            time.sleep(rest)
    srv.close()
    conn.send(srv.stats())


def bench_loopback(quick: bool = False) -> dict:
    from bonesim.net.monitor_link import MonitorConsole

    seconds = 1.0 if quick else 5.0
    ctx = mp.get_context("spawn")
    mine, theirs = ctx.Pipe()
    proc = ctx.Process(target=_server, args=(seconds, theirs), daemon=True,
                       name="bonesim-bench-monitor-server")
    proc.start()
    con = None
    try:
        if not mine.poll(60.0):
            raise RuntimeError("the benchmark's monitor server did not start")
        port = mine.recv()
        con = MonitorConsole("127.0.0.1", port, _KEY)
        con.connect(30.0)
        mine.send("go")
        end = time.monotonic() + seconds + 30.0
        while con.counters["byes"] == 0 and time.monotonic() < end:
            select.select([con.sock], [], [], 0.05)
            con.poll()
        srv = mine.recv() if mine.poll(10.0) else {}
        s = con.stats()
    finally:
        end_process(proc, 10.0)
        if con is not None:
            con.close()
    lat = s["latency_ms"]
    p50, p99 = lat.get("p50"), lat.get("p99")
    loss = s["loss_fraction"] if s["data"] else 1.0
    return {
        "monitor_loopback_latency_p99_ms": {
            "value": p99, "unit": "ms", "p50_ms": p50,
            "max_ms": lat.get("max"),
            "loss_fraction": loss, "packets_received": s["data"], "lost": s["lost"],
            "packets_sent": srv.get("sent"), "spikes_sent": srv.get("spikes_sent"),
            "spikes_received": s["spikes"], "seconds": seconds,
            "drops": {k: v for k, v in s["packets"].items() if k != "accepted"},
            "setup": "MonitorServer process (200 Hz updates, 50 Hz stream) -> console in "
                     "this process over 127.0.0.1 UDP, HMAC-SHA256 packets"},
        "monitor_loopback_loss_fraction": {"value": loss, "unit": "fraction"},
    }


def bench_monitor(quick: bool = False) -> dict:
    """Both monitor benchmarks."""
    out = bench_update(quick)
    out.update(bench_loopback(quick))
    return out
