"""The haptic loop: :func:`bonesim.model.step` at >= 1 kHz in its own process.

Why a process: a Python thread beside the window shares one interpreter lock
with VTK, whose rendering calls hold it for tens of milliseconds with software
OpenGL, so a 1 kHz thread would stall. A separate process has its own lock and
its own core. The state it changes lives in shared memory
(:mod:`bonesim.shared`): the tissue density, the touched flags and the event
rings, so the window, sound and recorder read removals without ever making the
loop wait (the CHAI3D voxel-example pattern: the servo loop publishes, the
graphics loop consumes).

Two small shared float64 arrays connect the sides:

``io`` (window -> loop)
    target pose (mouse), drill, speed, direction, burr index, reset and quit
    requests; see the ``IN_*`` indices.
``status`` (loop -> window)
    tool pose, force, immersed volume, drill state, steps, epoch, readiness;
    see the ``ST_*`` indices.

The loop also writes each measured period into the ``periods`` ring, from
which :meth:`HapticLoop.rate_stats` computes the loop rate and its p50/p99,
and one record per step into the ``samples`` ring (device reading, stepped
pose, drill state, forces; see :data:`bonesim.events.OTHER_RINGS`): the
recorder and the tutoring server drain it from their own processes
(:func:`attach`), so the loop itself never touches a disk or a socket.

The loop process asks for real-time scheduling (``SCHED_FIFO``) and runs with
Python's garbage collector frozen; ``status[ST_REALTIME]`` says whether the
operating system granted the priority (it needs the right to, e.g. root or
``CAP_SYS_NICE``; without it the loop still runs, at normal priority).
"""
from __future__ import annotations

import gc
import math
import os
import time

import numpy as np

from . import events
from .devices import (DeviceReading, NullDevice, ScriptedDevice, SharedInputDevice,
                      VirtualCoupling)
from .haptics import O_MAG, O_N_IMMERSED, O_TX, O_TZ, O_VOLUME
from .model import Model, Sample, make_state, reset_state, state_arrays_spec, step
from .shared import SharedArrays, die_with_parent, end_process, start_process, wait_ready

__all__ = ["IN_POS", "IN_AXIS", "IN_DRILL", "IN_SPEED", "IN_DIR", "IN_BURR", "IN_RESET",
           "IN_QUIT", "N_IN", "ST_T", "ST_POS", "ST_AXIS", "ST_FORCE", "ST_MAG",
           "ST_VOLUME", "ST_IMMERSED", "ST_DRILL", "ST_SPEED", "ST_DIR", "ST_BURR",
           "ST_STEPS", "ST_EPOCH", "ST_READY", "ST_DONE", "ST_OVERRUNS",
           "ST_HAND_FORCE", "ST_REALTIME", "N_ST", "PERIOD_RING", "SPIN_S",
           "START_TIMEOUT_S", "RT_PRIORITY", "attach", "push_sample", "HapticLoop"]

# io: window -> loop
IN_POS, IN_AXIS = 0, 3
(IN_DRILL, IN_SPEED, IN_DIR, IN_BURR, IN_RESET, IN_QUIT) = range(6, 12)
N_IN = 16
# status: loop -> window
ST_T, ST_POS, ST_AXIS, ST_FORCE = 0, 1, 4, 7
(ST_MAG, ST_VOLUME, ST_IMMERSED, ST_DRILL, ST_SPEED, ST_DIR, ST_BURR, ST_STEPS,
 ST_EPOCH, ST_READY, ST_DONE, ST_OVERRUNS, ST_HAND_FORCE, ST_REALTIME) = range(10, 24)
N_ST = 32
#: Periods kept for rate statistics.
PERIOD_RING = 1 << 16
#: The loop sleeps until this long before its deadline, then spins [s].
SPIN_S = 0.0004
#: How long :meth:`HapticLoop.start` waits for the loop to warm up [s].
START_TIMEOUT_S = 120.0
#: Real-time (SCHED_FIFO) priority the loop asks for; granted where allowed.
RT_PRIORITY = 20


def _ask_realtime() -> bool:
    """Best effort: real-time scheduling for this process. True if granted."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
        return True
    except (AttributeError, OSError, PermissionError):
        try:
            os.nice(-10)
        except (AttributeError, OSError, PermissionError):
            pass
        return False


def _loop_spec(model: Model) -> list:
    return state_arrays_spec(model) + events.ring_arrays_spec("samples") + [
        ("io", (N_IN,), np.float64), ("status", (N_ST,), np.float64),
        ("periods", (PERIOD_RING,), np.float64), ("periods.head", (1,), np.int64)]


def attach(handle) -> tuple:
    """Open a running loop's shared memory from another process.

    Returns
    -------
    shared : SharedArrays
        Keep it alive while the rings are used; ``close()`` it after.
    rings : dict of str -> events.Ring
        ``samples``, ``tissue`` and ``touched``.
    """
    sh = SharedArrays.attach(handle)
    rings = {name: events.ring_from_arrays(name, sh.arrays)
             for name in ("samples", "tissue", "touched")}
    return sh, rings


def push_sample(ring: events.Ring, t: float, state, hand_mm, axis, drill: bool,
                speed: float, direction: int, burr: int, epoch: int, buttons: int,
                force_n, vib_n) -> None:
    """Append one step's record to the ``samples`` ring (a few microseconds).

    ``axis`` is the axis exactly as handed to :func:`~bonesim.model.step` (not
    the normalized ``state.axis``), so that re-stepping the records
    reproduces the run bit for bit.
    """
    f = ring.fields
    q = int(ring.head[0]) & (f["t_s"].shape[0] - 1)
    out = state.out
    f["t_s"][q] = t
    f["pos_mm"][q] = state.pos_mm
    f["axis"][q] = axis
    f["hand_mm"][q] = hand_mm
    f["drill"][q] = drill
    f["speed_rpm"][q] = speed
    f["direction"][q] = direction
    f["burr"][q] = burr
    f["epoch"][q] = epoch
    f["buttons"][q] = buttons
    f["force_n"][q] = force_n
    f["tangential_n"][q] = out[O_TX:O_TZ + 1]
    f["vibration_n"][q] = vib_n
    f["mag_n"][q] = out[O_MAG]
    f["volume_mm3"][q] = out[O_VOLUME]
    ring.head[0] += 1               # publish after the record is complete


def _make_device(spec, io):
    kind = spec[0]
    if kind == "mouse":
        return SharedInputDevice(io, slice(IN_POS, IN_POS + 3), slice(IN_AXIS, IN_AXIS + 3))
    if kind == "scripted":
        return ScriptedDevice(spec[1], loop=bool(spec[2]) if len(spec) > 2 else False)
    if kind == "null":
        return NullDevice(*spec[1:])
    raise ValueError(f"unknown device backend {kind!r}")


def _loop_main(handle, model: Model, burrs, device_spec, rate_hz: float,
               run_s: float | None, vibration: bool) -> None:
    """Body of the haptic process."""
    from .loading import warmup

    die_with_parent()
    sh = SharedArrays.attach(handle)
    arr = sh.arrays
    io, status = arr["io"], arr["status"]
    periods, p_head = arr["periods"], arr["periods.head"]
    from .vibration import Vibration

    models = [model if b is None else model.with_burr(b) for b in burrs]
    vibs = [Vibration(m.burr, rate_hz) if vibration else None for m in models]
    state = make_state(models[0], arr)
    samples = events.ring_from_arrays("samples", arr)
    no_vib = np.zeros(3)
    for m in models:                       # scratch for the largest burr, once
        state.fit_scratch(m)
    device = _make_device(device_spec, io)
    coupling = VirtualCoupling() if not math.isfinite(device.caps.max_force_n) \
        and isinstance(device, SharedInputDevice) else None
    warmup()
    if vibration:
        from .vibration import warmup as vibration_warmup

        vibration_warmup()
        for v in vibs:                     # first calls out of the timed loop
            v.sample(0.0, np.array([0.0, 0.0, -1.0]), False, False, 0.0, 0.0)
            v.reset()
    device.open()
    device.read(0.0)
    status[ST_REALTIME] = 1.0 if _ask_realtime() else 0.0
    # everything the loop needs exists now; no collector pauses from here on
    gc.collect()
    gc.freeze()
    gc.disable()
    out_f = np.zeros(3)
    period = 1.0 / rate_hz
    pmask = periods.shape[0] - 1
    epoch = io[IN_RESET]
    burr = int(io[IN_BURR])
    clock = time.perf_counter
    t0 = clock()
    last = t0
    deadline = t0
    overruns = 0
    status[ST_READY] = 1.0
    try:
        while io[IN_QUIT] == 0.0:
            now = clock()
            periods[p_head[0] & pmask] = now - last
            p_head[0] += 1
            last = now
            t = now - t0
            if run_s is not None and t >= run_s:
                break
            if io[IN_RESET] != epoch:
                # keep the event counters running across resets, so that
                # consumers in other processes (recorder, tutor) lose nothing
                reset_state(models[burr], state, rings=False)
                if coupling is not None:
                    coupling.pos = None
                epoch = io[IN_RESET]
                status[ST_EPOCH] = epoch
                events.push_event(state.tissue, events.RESET, t, n=int(epoch))
            b = int(io[IN_BURR])
            if b != burr and 0 <= b < len(models):
                burr = b
                events.push_event(state.tissue, events.BURR, t, n=burr)
            m = models[burr]
            r: DeviceReading = device.read(t)
            pos = r.pos_mm
            if coupling is not None:
                dt = period if math.isnan(state.t_s) else t - state.t_s
                pos = coupling.update(pos, state.force_n, dt)
            drill = bool(io[IN_DRILL]) if r.drill is None else r.drill
            speed = io[IN_SPEED] if r.speed_rpm is None else r.speed_rpm
            direction = (1 if io[IN_DIR] >= 0 else -1) if r.direction is None \
                else r.direction
            f = step(m, state, Sample(t, pos, r.axis, drill, speed, direction))
            fv = no_vib
            if vibs[burr] is not None:
                # felt, not simulated: added to what the device renders only
                fv = vibs[burr].sample(t, state.axis, drill, state.out[O_N_IMMERSED] > 0,
                                       state.out[O_MAG], speed)
                out_f[:] = f
                out_f += fv
                norm = math.sqrt(out_f[0] ** 2 + out_f[1] ** 2 + out_f[2] ** 2)
                if norm > m.device.max_force_n:
                    out_f *= m.device.max_force_n / norm
                f = out_f
            device.write_force(f)
            push_sample(samples, t, state, r.pos_mm, r.axis, drill, speed, direction, burr,
                        int(epoch), r.buttons, f, fv)
            status[ST_T] = t
            status[ST_POS:ST_POS + 3] = state.pos_mm
            status[ST_AXIS:ST_AXIS + 3] = state.axis
            status[ST_FORCE:ST_FORCE + 3] = f
            status[ST_MAG] = state.out[O_MAG]
            status[ST_VOLUME] = state.out[O_VOLUME]
            status[ST_IMMERSED] = state.out[O_N_IMMERSED]
            status[ST_DRILL] = drill
            status[ST_SPEED] = speed
            status[ST_DIR] = direction
            status[ST_BURR] = burr
            status[ST_STEPS] = state.n_steps
            if coupling is not None:
                status[ST_HAND_FORCE] = coupling.hand_force_n(r.pos_mm)
            deadline += period
            rest = deadline - clock()
            if rest > SPIN_S:
                time.sleep(rest - SPIN_S)
            while clock() < deadline:
                pass
            if clock() - deadline > period:        # fell behind: do not burst
                overruns += 1
                status[ST_OVERRUNS] = overruns
                deadline = clock()
    finally:
        device.close()
        status[ST_DONE] = 1.0
        sh.close()


class HapticLoop:
    """Runs the haptic loop in a child process and exposes its shared state.

    Parameters
    ----------
    model : Model
        The model (its burr is burr 0).
    burrs : sequence of Burr, optional
        Further burrs the user can switch to (indices 1, 2, ...).
    device : tuple
        ``("mouse",)`` (the window writes the target pose; a virtual coupling
        keeps the tool on the bone), ``("scripted", trajectory[, loop])`` or
        ``("null", pos_mm, axis)``.
    rate_hz : float
        Servo rate [Hz].
    run_s : float, optional
        Stop by itself after this long [s] (benchmarks, scripted runs).
    vibration : bool
        Add the burr's synthesized vibration to the force sent to the device.

    Attributes
    ----------
    state : State
        A view of the loop's state in shared memory (grid density, touched
        flags, rings) for consumers such as
        :class:`bonesim.replica.TissueReplica`. Only the loop writes it,
        except the touched flags that consumers clear.
    io, status : ndarray
        The shared command and status arrays (see the module docstring).
    """

    def __init__(self, model: Model, burrs=(), device=("mouse",), rate_hz: float = 1000.0,
                 run_s: float | None = None, vibration: bool = True):
        self.model = model
        self.burrs = [None] + list(burrs)
        self.device = tuple(device)
        self.rate_hz = float(rate_hz)
        self.run_s = run_s
        self.vibration = bool(vibration)
        self._sh = SharedArrays.create(_loop_spec(model))
        self.state = make_state(model, self._sh.arrays)
        self.io = self._sh["io"]
        self.status = self._sh["status"]
        self._periods = events.Ring({"period": self._sh["periods"]}, self._sh["periods.head"])
        #: One record per haptic step (see :func:`push_sample`).
        self.samples = events.ring_from_arrays("samples", self._sh.arrays)
        self.io[IN_AXIS:IN_AXIS + 3] = (0.0, 0.0, -1.0)
        self.io[IN_SPEED] = model.burr.default_speed_rpm
        self.io[IN_DIR] = 1.0
        self._proc = None

    # ----------------------------------------------------------- lifecycle
    def start(self, timeout_s: float = START_TIMEOUT_S) -> "HapticLoop":
        """Start the process and wait until it is warm and stepping."""
        self._proc = start_process(
            _loop_main, "bonesim-haptic",
            (self._sh.handle, self.model, [b for b in self.burrs], self.device,
             self.rate_hz, self.run_s, self.vibration))
        got = wait_ready(self._proc, lambda: self.status[ST_READY] != 0.0, timeout_s)
        if got == "exited":
            raise RuntimeError("the haptic loop process exited during start-up "
                               f"(exit code {self._proc.exitcode})")
        if got == "timeout":
            self.stop()
            raise RuntimeError("the haptic loop did not start in time")
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Ask the loop to quit and wait for it."""
        self.io[IN_QUIT] = 1.0
        if self._proc is not None:
            end_process(self._proc, timeout_s)
            self._proc = None

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for a loop started with ``run_s`` to finish; True if it did."""
        if self._proc is None:
            return True
        self._proc.join(timeout_s)
        return not self._proc.is_alive()

    def close(self) -> None:
        """Stop the loop and free the shared memory."""
        self.stop()
        self._sh.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    @property
    def handle(self) -> tuple:
        """Shared-memory handle for other processes (sound, recorder)."""
        return self._sh.handle

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    # ------------------------------------------------------------ commands
    def set_target(self, pos_mm, axis=None) -> None:
        """Where the hand (mouse) wants the tool [mm], and its axis."""
        self.io[IN_POS:IN_POS + 3] = pos_mm
        if axis is not None:
            self.io[IN_AXIS:IN_AXIS + 3] = axis

    def set_drill(self, on: bool, speed_rpm: float | None = None,
                  direction: int | None = None) -> None:
        self.io[IN_DRILL] = 1.0 if on else 0.0
        if speed_rpm is not None:
            self.io[IN_SPEED] = speed_rpm
        if direction is not None:
            self.io[IN_DIR] = 1.0 if direction >= 0 else -1.0

    def set_burr(self, index: int) -> None:
        if not 0 <= index < len(self.burrs):
            raise IndexError(f"burr index {index} out of range 0..{len(self.burrs) - 1}")
        self.io[IN_BURR] = index

    def reset(self) -> float:
        """Ask the loop to restore the case; returns the new epoch."""
        self.io[IN_RESET] += 1.0
        return float(self.io[IN_RESET])

    # --------------------------------------------------------------- stats
    @property
    def steps_measured(self) -> int:
        """Loop periods measured so far (for slicing :meth:`recent_periods`)."""
        return self._periods.count

    def recent_periods(self, n: int = 2000) -> np.ndarray:
        """The last ``n`` measured loop periods [s]."""
        head = self._periods.count
        start = max(0, head - min(n, self._periods.capacity - 1))
        return self._periods.read(start, head)["period"]

    def rate_stats(self, n: int = 2000) -> dict:
        """Loop rate [Hz] and period p50/p99 [ms] over the last ``n`` steps."""
        p = self.recent_periods(n)
        p = p[1:] if len(p) > 1 else p
        if len(p) == 0:
            return {"rate_hz": 0.0, "period_p50_ms": 0.0, "period_p99_ms": 0.0, "n": 0}
        return {"rate_hz": float(1.0 / p.mean()),
                "period_p50_ms": float(np.percentile(p, 50) * 1e3),
                "period_p99_ms": float(np.percentile(p, 99) * 1e3),
                "n": int(len(p))}
