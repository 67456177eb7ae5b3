"""An in-process servo run through a device, as the haptic loop's device path
does it (:func:`bonesim.runtime.haptic_loop._run_loop`): read the device
(behind the safety layer, the mouse as fallback), put a rate device through
the virtual coupling, step the engine, write the force."""
from __future__ import annotations

import math
import time

import numpy as np

from bonesim.devices.mouse import VirtualCoupling
from bonesim.devices.null import NullDevice
from bonesim.devices.safety import SafeDevice
from bonesim.engine.model import Sample, make_state, step

__all__ = ["drive", "finish"]


def drive(model, backend, n: int, rate_hz: float = 1000.0, *, t0: float = 0.0,
          before=None, drill: bool = False, speed_rpm: float = 60000.0, pedal=None,
          run=None, realtime: bool = False, limits=None, record=None, header=None):
    """Step ``n`` ticks; ``before(k, t)`` runs before each (queue reports,
    unplug). Returns a dict of per-tick arrays and the run objects; pass
    ``run`` (a previous result) to continue it. ``realtime``: tick on the
    wall clock (for devices that run their own clock). ``record``: a session
    file the run is recorded to (with ``header``), as the recorder would;
    :func:`finish` closes it."""
    if run is None:
        kw = {} if limits is None else {"limits": limits}
        safe = SafeDevice(backend, fallback=NullDevice((0.0, 0.0, 80.0)), **kw)
        safe.open()
        run = {"safe": safe, "state": make_state(model), "coupling": VirtualCoupling(),
               "pedal": pedal, "recording": None}
        if record is not None:
            from bonesim.runtime.handle_stream import handle_of
            from bonesim.runtime.simulate import _Recording

            run["recording"] = _Recording(model, run["state"], record, header,
                                          handle_of(pedal) if pedal is not None else None)
        if pedal is not None:
            pedal.open()
    safe, state, coupling = run["safe"], run["state"], run["coupling"]
    out = {k: [] for k in ("t", "hand", "pos", "axis", "force", "drill", "speed", "state",
                           "buttons")}
    wall0 = time.perf_counter() - t0
    for k in range(n):
        t = t0 + k / rate_hz
        if realtime:                   # sleeping: the device's own threads get the GIL
            rest = t - (time.perf_counter() - wall0)
            if rest > 0:
                time.sleep(rest)
        if before is not None:
            before(k, t)
        r = safe.read(t)
        pos = r.pos_mm
        if safe.coupled:
            if coupling.pos is None and state.n_steps > 0:
                coupling.reset(state.pos_mm)
            dt = 1.0 / rate_hz if math.isnan(state.t_s) else t - state.t_s
            pos = coupling.update(pos, state.force_n, dt)
        else:
            coupling.pos = None
        d, s = drill, speed_rpm
        if run["pedal"] is not None:
            d, s = run["pedal"].apply(t, d, s)
        smp = Sample(t, pos, r.axis, d, s, 1, 0)
        f = step(model, state, smp)
        safe.write_force(f)
        if run["recording"] is not None:
            run["recording"].push(smp, safe.sent_n)
        for key, v in (("t", t), ("hand", r.pos_mm.copy()), ("pos", state.pos_mm.copy()),
                       ("axis", state.axis.copy()), ("force", safe.sent_n.copy()),
                       ("drill", d), ("speed", s), ("state", safe.state),
                       ("buttons", r.buttons)):
            out[key].append(v)
    run["out"] = {k: np.array(v) for k, v in out.items()}
    return run


def finish(run) -> None:
    """Close the run's device (and its recording)."""
    if run.get("recording") is not None:
        run["recording"].close()
        run["recording"] = None
    run["safe"].close()
