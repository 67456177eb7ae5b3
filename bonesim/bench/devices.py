"""Device read/write overhead per haptic step, per backend, over the
hardware stand-ins (:mod:`bonesim.devices.standins`).

One haptic step's device work is what the loop does around the engine's
step: ``read`` the device through the safety layer
(:class:`~bonesim.devices.safety.SafeDevice`) and ``write_force`` back (for
an auxiliary backend, the pedal guard's ``apply``). It is timed alone, per
step, with the stand-in's own work included (the fake HID bus's report
queue, the fake pyusb backend's transfers in the poller thread, the HD
library stub's servo thread running beside it). Figures are wall-clock on
this machine and include the stand-ins' cost, so they bound a real device's
Python-side overhead from above only as far as the stand-in is cheaper than
the real driver; a real device adds its driver's and the bus's latency.
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ["BACKENDS", "STEPS", "QUICK_STEPS", "bench_devices"]

#: Backends timed, as they appear in the figures' names.
BACKENDS = ("simulated_hand", "spacemouse", "pedal", "adu100_handle", "touch")
#: Steps timed per backend (``--quick``: :data:`QUICK_STEPS`).
STEPS = 20000
QUICK_STEPS = 2000
#: A SpaceMouse sends a report about every 16 ms: every this many steps.
REPORT_EVERY = 16


def _figure(ns: np.ndarray, backend: str, note: str) -> dict:
    us = ns / 1e3
    return {"value": round(float(np.percentile(us, 50)), 3), "unit": "us",
            "p99_us": round(float(np.percentile(us, 99)), 3),
            "mean_us": round(float(us.mean()), 3), "steps": int(len(us)),
            "backend": backend, "stand_in": note}


def _time_pose(safe, n: int, before=None) -> np.ndarray:
    perf = time.perf_counter_ns
    f = np.array([0.1, 0.0, -0.2])
    ns = np.empty(n, np.int64)
    for k in range(n):
        t = k * 1e-3
        if before is not None:
            before(k)
        t0 = perf()
        safe.read(t)
        safe.write_force(f)
        ns[k] = perf() - t0
    return ns


def _time_aux(guard, n: int, before=None) -> np.ndarray:
    """The pedal guard's ``apply`` per step, and for a handle the loop's
    recording of its angles (:class:`bonesim.runtime.handle_stream.HandleTap`)."""
    from bonesim.engine import events
    from bonesim.runtime.handle_stream import HandleTap, handle_of

    tap = None
    if handle_of(guard) is not None:
        tap = HandleTap(events.Ring.create(1 << 12, **events.OTHER_RINGS["handle"][1]),
                        handle_of(guard))
    perf = time.perf_counter_ns
    ns = np.empty(n, np.int64)
    for k in range(n):
        if before is not None:
            before(k)
        t0 = perf()
        guard.apply(k * 1e-3, False, 60000.0)
        if tap is not None:
            tap(k * 1e-3)
        ns[k] = perf() - t0
    return ns


def _simulated_hand(n):
    from bonesim.devices.safety import SafeDevice
    from bonesim.devices.simulated_backend import SimulatedHandBackend

    safe = SafeDevice(SimulatedHandBackend())
    safe.open()
    return _figure(_time_pose(safe, n), "simulated-hand", "pure Python")


def _spacemouse(n):
    from bonesim.devices.safety import SafeDevice
    from bonesim.devices.spacemouse import SpaceMouse
    from bonesim.devices.standins.hid_bus import installed

    path = b"/dev/hidraw-bench"
    report = bytes([1, 0x5E, 0x01, 0, 0, 0xA2, 0xFE, 0x10, 0, 0, 0, 0xF0, 0xFF])
    with installed() as bus:
        bus.plug(path, 0x256F, 0xC62E)
        safe = SafeDevice(SpaceMouse())
        safe.open()

        def feed(k):
            if k % REPORT_EVERY == 0:
                bus.send(path, report)
        ns = _time_pose(safe, n, feed)
        safe.close()
    return _figure(ns, "spacemouse", "hidapi binding stand-in, a 13-byte report every "
                   f"{REPORT_EVERY} steps")


def _pedal(n):
    from bonesim.devices.pedal import FootPedal, PedalGuard
    from bonesim.devices.standins.hid_bus import installed

    path = b"/dev/hidraw-pedal"
    with installed() as bus:
        bus.plug(path, 0x05F3, 0x00FF)
        guard = PedalGuard(FootPedal())
        guard.open()

        def feed(k):
            if k % 500 == 0:
                bus.send(path, bytes([2 if k % 1000 == 0 else 0, 0]))
        ns = _time_aux(guard, n, feed)
        guard.close()
    return _figure(ns, "pedal", "hidapi binding stand-in, a press or release every 500 steps")


def _adu100(n):
    from bonesim.devices.adu100 import ADU100Handle, calibrate
    from bonesim.devices.pedal import PedalGuard
    from bonesim.devices.standins.adu100_usb import FakeADU100, FakeUsbBackend

    box = FakeADU100()
    box.analog.update({1: 30000, 2: 1000})
    cal = calibrate([2000, 0], [52000, 60000])
    h = ADU100Handle(None, cal, usb_backend=FakeUsbBackend(box))
    guard = PedalGuard(h)
    guard.open()
    try:
        ns = _time_aux(guard, n)
    finally:
        guard.close()
    return _figure(ns, "adu100-handle", "pyusb over a backend stand-in, poller thread "
                   "running; angles recorded")


def _touch(n):
    from bonesim.devices.openhaptics import OpenHapticsDevice
    from bonesim.devices.safety import SafeDevice
    from bonesim.devices.standins.hd_library import load

    load()
    dev = OpenHapticsDevice({"lost_s": 5.0})
    safe = SafeDevice(dev)
    safe.open()
    try:
        ns = _time_pose(safe, n)
    finally:
        safe.close()
    return _figure(ns, "touch", "pyopenhaptics over the HD library stub, its 1 kHz servo "
                   "thread running")


def bench_devices(quick: bool = False) -> dict:
    """``device_overhead_us_<backend>``: p50 of one step's device read and
    write [us] (p99 and mean in the detail)."""
    n = QUICK_STEPS if quick else STEPS
    out = {}
    for name, fn in (("simulated_hand", _simulated_hand), ("spacemouse", _spacemouse),
                     ("pedal", _pedal), ("adu100_handle", _adu100), ("touch", _touch)):
        out[f"device_overhead_us_{name}"] = fn(n)
    return out
