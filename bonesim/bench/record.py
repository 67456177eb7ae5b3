"""Benchmarks of session recording (:mod:`bonesim.runtime.record`).

``recording_overhead_us``
    What recording adds to one haptic step: the loop's only recording work is
    :func:`bonesim.runtime.haptic_loop.push_sample` (one record into a shared ring),
    timed per call while the phantom demo is drilled, next to the step
    itself for scale.
``recording_writer_rows_per_s``
    Throughput of the writer: ring records drained into an HDF5 file
    (uncompressed, as live recordings are) in the batches the writer
    process sees at 1 kHz (one flush per
    :data:`~bonesim.runtime.record.FLUSH_S`), samples plus removals, including the
    flush. It must stay far above the 1 kHz the loop produces.
``session_bytes_per_minute``
    Size of a finished (compacted) session file per minute of drilling: the
    phantom's planned mastoidectomy from its first drilling sample, recorded
    through :func:`bonesim.runtime.simulate.run_trajectory` (samples, tissue
    events, the header), 60 s (20 s with ``quick``).
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["bench_recording", "bench_session_size"]


def _demo_samples(model, n: int):
    from bonesim.io.case import load_case
    from bonesim.io.toolpath import demo_trajectory

    t = demo_trajectory(load_case("phantom"), model.burr.name)
    start = int(np.flatnonzero(t.drill)[0])
    return t.at_times(t.t_s[start:]).resample(model.haptic_rate_hz), start


def bench_recording(quick=False) -> dict:
    from bonesim.engine import events
    from bonesim.runtime.haptic_loop import push_sample
    from bonesim.engine.model import Sample, make_state, step
    from bonesim.io.loading import load_model, warmup
    from bonesim.runtime.record import Drainer, FLUSH_S
    from bonesim.session.writer import SessionWriter
    from bonesim.session.header import make_header

    warmup()
    model = load_model("phantom", "cutting-5mm")
    n = 4000 if quick else 20000
    r, _ = _demo_samples(model, n)
    n = min(n, len(r.t_s))
    state = make_state(model)
    ring = events.Ring.create(1 << 16, **events.OTHER_RINGS["samples"][1])
    zero = np.zeros(3)
    perf = time.perf_counter_ns
    step_ns = np.empty(n, np.int64)
    push_ns = np.empty(n, np.int64)
    for q in range(n):
        smp = Sample(r.t_s[q], r.pos_mm[q], r.axis[q], bool(r.drill[q]),
                     float(r.speed_rpm[q]), int(r.direction[q]))
        t0 = perf()
        f = step(model, state, smp)
        t1 = perf()
        push_sample(ring, smp.t_s, state, smp.pos_mm, smp.axis, smp.drill, smp.speed_rpm,
                    smp.direction, 0, 0, 0, f, zero)
        t2 = perf()
        step_ns[q] = t1 - t0
        push_ns[q] = t2 - t1
    overhead = float(np.percentile(push_ns, 50)) / 1e3
    step_us = float(np.percentile(step_ns, 50)) / 1e3

    # writer: the ring just filled (n samples, the run's removals), drained
    # in 1 kHz-sized batches with a flush each, into a fresh file
    batch = max(int(round(FLUSH_S * model.haptic_rate_hz)), 1)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.h5"
        writer = SessionWriter(path, make_header(model), compact=False)
        sub = events.Ring({k: v for k, v in ring.fields.items()}, np.zeros(1, np.int64))
        rem = state.tissue
        sub_rem = events.Ring(rem.fields, np.zeros(1, np.int64))
        drainer = Drainer(writer, {"samples": sub, "tissue": sub_rem})
        n_rem = rem.count
        t0 = time.perf_counter()
        for q in range(0, n, batch):
            top = min(q + batch, n)
            sub.head[0] = top
            sub_rem.head[0] = int(np.searchsorted(rem.fields["t_s"][:n_rem],
                                                  r.t_s[top - 1], side="right"))
            drainer.drain()
            writer.flush()
        wall = time.perf_counter() - t0
        writer.close()
        size = path.stat().st_size
    rows = drainer.rows
    return {
        "recording_overhead_us": {
            "value": round(overhead, 2), "unit": "us",
            "p99_us": round(float(np.percentile(push_ns, 99)) / 1e3, 2),
            "haptic_step_p50_us": round(step_us, 2),
            "fraction_of_step": round(overhead / step_us, 3) if step_us else None,
            "steps": int(n)},
        "recording_writer_rows_per_s": {
            "value": round(rows / wall), "unit": "rows/s",
            "rows": int(rows), "batch_samples": batch,
            "headroom_vs_1khz": round(rows / wall / model.haptic_rate_hz, 1),
            "bytes_per_sample": round(size / n, 1)},
    }


def bench_session_size(quick=False) -> dict:
    """``session_bytes_per_minute``: see the module docstring."""
    from bonesim.io.loading import load_model
    from bonesim.runtime.simulate import run_trajectory

    model = load_model("phantom", "cutting-5mm")
    traj, _ = _demo_samples(model, 0)
    run_s = 20.0 if quick else 60.0
    part = traj.at_times(traj.t_s[traj.t_s <= traj.t_s[0] + run_s])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "run.h5"
        out = run_trajectory(model, part, record=path, surface=False)
        if not out.get("record_ok", False):
            from bonesim.errors import BonesimError

            raise BonesimError(f"session_bytes_per_minute: the recording did not complete "
                               f"({out.get('record_error')})")
        size = path.stat().st_size
    minutes = float(part.t_s[-1] - part.t_s[0]) / 60.0
    return {"session_bytes_per_minute": {
        "value": round(size / minutes), "unit": "bytes/min",
        "file_bytes": int(size), "run_s": round(minutes * 60.0, 3),
        "removed_voxels": int(out.get("voxels_removed", 0)),
        "what": "a compacted session file of the phantom's planned mastoidectomy "
                "(cutting burr from its first drilling sample), per minute"}}
