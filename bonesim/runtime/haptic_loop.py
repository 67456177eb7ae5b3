"""The haptic loop: :func:`bonesim.engine.world.world_step` at >= 1 kHz in its own process.

Why a process: a Python thread beside the window shares one interpreter lock
with VTK, whose rendering calls hold it for tens of milliseconds with software
OpenGL, so a 1 kHz thread would stall. A separate process has its own lock and
its own core. The state it changes lives in shared memory
(:mod:`bonesim.runtime.shared`): the tissue density, the touched flags and the event
rings, so the window, sound and recorder read removals without ever making the
loop wait (the CHAI3D voxel-example pattern: the servo loop publishes, the
graphics loop consumes).

:class:`HapticLoop` is a :class:`bonesim.runtime.child.ChildProcess` (start-up,
errors and quit as for every child process). Three things connect the sides:

``control`` (window -> loop, a stream)
    named fields (:data:`CONTROL`): the mouse's target pose, drill on/off,
    speed and direction, read at every step.
``commands`` ring (window -> loop, discrete)
    reset, burr change, tool change, bodies, plates (:mod:`bonesim.runtime.commands`,
    :mod:`bonesim.runtime.rigid_commands`): taken before each step, decoded
    into world commands and handed to the world step, which applies them in
    order before the rigid and haptic steps (one call per period).
``status`` (loop -> window)
    named fields (:data:`STATUS`): tool pose, force, immersed volume, drill
    state, steps, epoch, burr, tool, commands applied;
    ``loop.status["epoch"]``.

The loop also writes each measured period into the ``periods`` ring, from
which :meth:`HapticLoop.rate_stats` computes the loop rate and its p50/p99,
and one record per step into the ``samples`` ring (device reading, stepped
pose, drill state, forces; see :data:`bonesim.engine.events.OTHER_RINGS`): the
recorder and the tutoring server drain it from their own processes
(:func:`attach`), so the loop itself never touches a disk or a socket. With
an instrumented handle (``pedal``) the loop also writes the handle's angles
into the ``handle`` ring (:mod:`bonesim.runtime.handle_stream`).

The loop process asks for real-time scheduling (``SCHED_FIFO``) and runs with
Python's garbage collector frozen; ``status["realtime"]`` says whether the
operating system granted the priority (it needs the right to, e.g. root or
``CAP_SYS_NICE``; without it the loop still runs, at normal priority).
"""
from __future__ import annotations

import gc
import math
import os
import time

import numpy as np

from bonesim.devices.interface import DeviceReading
from bonesim.devices.mouse import SharedInputDevice, VirtualCoupling
from bonesim.devices.null import NullDevice
from bonesim.devices.safety import UNPLUGGED
from bonesim.devices.scripted import ScriptedDevice
from bonesim.engine import events
from bonesim.engine.haptics import O_MAG, O_N_IMMERSED, O_TX, O_TZ, O_VOLUME
from bonesim.engine.model import Model, Sample, make_state, state_arrays_spec
from bonesim.engine.world import world_step
from bonesim.runtime import commands
from bonesim.runtime.child import ChildProcess
from bonesim.runtime.commands import (
    CommandQueue,
    CommandSender,
    LoopContext,
    Reset,
    SetBurr,
    SetTool,
)
from bonesim.runtime.handle_stream import HandleTap, handle_of
from bonesim.runtime.shared import SharedArrays
from bonesim.runtime.rigid_commands import warmup_rigid

__all__ = ["STATUS", "CONTROL", "PERIOD_RING", "SPIN_S", "SPIN_REALTIME_S", "START_TIMEOUT_S", "RT_PRIORITY",
           "attach", "push_sample", "HapticLoop"]

#: The loop's status fields (loop -> window), after the process base's.
STATUS = (
    # odd while the per-step fields below (t_s .. steps, hand_force_n) are
    # being written, even once they are one step's: a reader that sees the
    # same even value before and after its copy has one step's snapshot
    # (bonesim.runtime.shared.read_seqlocked)
    ("seq", np.int64),
    ("t_s", np.float64),                    # loop time of the last step [s]
    ("pos_mm", np.float64, (3,)),           # tool centre [mm]
    ("axis", np.float64, (3,)),             # unit drill axis
    ("force_n", np.float64, (3,)),          # sent to the device [N]
    ("mag_n", np.float64),                  # normal force magnitude [N]
    ("volume_mm3", np.float64),             # immersed volume [mm^3]
    ("immersed", np.float64),               # immersed samples
    ("drill", np.uint8),
    ("speed_rpm", np.float64),
    ("direction", np.int8),
    ("burr", np.int32),                     # burr index
    ("tool", np.int32),                     # tool index (bonesim.engine.world_commands.TOOLS)
    ("steps", np.int64),                    # steps since the last reset
    ("epoch", np.int64),                    # case resets so far
    ("overruns", np.int64),                 # periods that fell a whole period behind
    ("hand_force_n", np.float64),           # virtual coupling's pull on the hand [N]
    ("realtime", np.uint8),                 # real-time priority granted
    ("commands_read", np.int64),            # command records taken
    ("commands_applied", np.int64),
    ("commands_rejected", np.int64),
    ("command_error", f"S{commands.ERROR_TEXT_BYTES}"),   # the last rejection
    ("device_state", np.uint8),             # bonesim.devices.safety.STATES index
    ("device_rejected", np.int64),          # device samples rejected (NaN, jump, stale)
    ("device_unplugs", np.int64),           # times the device went away
    ("camera_rate", np.float64, (6,)),      # rate device, camera mode: pan [mm/s], orbit [deg/s]
    ("pedal", np.uint8),                    # foot pedal: 0 none, 1 connected, 2 unplugged
    # a real device's record as opened (and re-opened): max force [N], workspace
    # x, y, z [mm], max stiffness [N/mm]; NaN before (see _publish_caps)
    ("device_caps", np.float64, (5,)),
    # an instrumented handle's angles last recorded [deg] (NaN: none)
    ("handle_deg", np.float64, (events.HANDLE_CHANNELS,)),
)
#: The window's continuous inputs (window -> loop), after the process base's.
CONTROL = (
    ("target_mm", np.float64, (3,)),        # where the hand (mouse) wants the tool [mm]
    ("axis", np.float64, (3,)),             # the drill axis it wants
    ("drill", np.uint8),
    ("speed_rpm", np.float64),
    ("direction", np.int8),                 # +1 forward, -1 reverse
)
#: Periods kept for rate statistics.
PERIOD_RING = 1 << 16
#: The loop sleeps until this long before its deadline, then spins [s].
SPIN_S = 0.0004
#: The same with real-time priority granted, whose wake-ups are prompt [s]:
#: the same periods (p99 1.008 against 1.007 ms in one A/B run) at under
#: half the processor (24 % of a core against 53 %), which a 2-core
#: machine's window and dust then have.
SPIN_REALTIME_S = 0.0001
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


def attach(handle) -> tuple:
    """Open a running loop's shared memory from another process.

    Returns
    -------
    shared : SharedArrays
        Keep it alive while the rings are used; ``close()`` it after.
    rings : dict of str -> events.Ring
        ``samples``, ``tissue`` and ``touched``; ``handle`` (an
        instrumented handle's angles, :mod:`bonesim.runtime.handle_stream`).
    """
    sh = SharedArrays.attach(handle)
    rings = {name: events.ring_from_arrays(name, sh.arrays)
             for name in ("samples", "tissue", "touched")}
    if "handle.head" in sh.arrays:         # a loop with an instrumented handle's ring
        rings["handle"] = events.ring_from_arrays("handle", sh.arrays)
    return sh, rings


def push_sample(ring: events.Ring, t: float, state, hand_mm, axis, drill: bool,
                speed: float, direction: int, burr: int, epoch: int, buttons: int,
                force_n, vib_n) -> None:
    """Append one step's record to the ``samples`` ring (a few microseconds).

    ``axis`` is the axis exactly as handed to :func:`~bonesim.engine.world.world_step` (not
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


def _make_device(spec, control):
    kind = spec[0]
    if kind == "mouse":
        return SharedInputDevice(control["target_mm"], control["axis"])
    if kind == "scripted":
        return ScriptedDevice(spec[1], loop=bool(spec[2]) if len(spec) > 2 else False)
    if kind == "null":
        return NullDevice(*spec[1:])
    if kind == "device":               # a real backend, behind the safety layer
        return _safe_device(spec, control)
    raise ValueError(f"unknown device backend {kind!r}")


def _safe_device(spec, control):
    """``("device", backend[, settings])``: ``backend`` an instance or a
    registered name (:mod:`bonesim.devices.registry`); the mouse takes over
    while it is unplugged."""
    from bonesim.devices.safety import SafeDevice

    dev = spec[1]
    if isinstance(dev, str):
        from bonesim.devices.registry import make_device

        dev = make_device(dev, spec[2] if len(spec) > 2 else None)
    return SafeDevice(dev, fallback=SharedInputDevice(control["target_mm"], control["axis"]))


def _publish_caps(status, caps) -> None:
    """The record a device opened with, into ``status["device_caps"]``."""
    status["device_caps"] = (caps.max_force_n, *caps.workspace_mm, caps.max_stiffness_n_per_mm)


def _run_loop(child, model: Model, burrs, device_spec, rate_hz: float,
              run_s: float | None, vibration: bool, known: tuple, pedal=None) -> None:
    """Body of the haptic process (:meth:`HapticLoop.run`)."""
    from bonesim.io.loading import warmup
    from bonesim.physics.vibration import Vibration

    arr = child.arrays
    status, control = child.status, child.control
    periods, p_head = arr["periods"], arr["periods.head"]
    # one model holding the burr table: a sample names its burr
    m = model.with_burrs([b for b in burrs if b is not None])
    vibs = [Vibration(b, rate_hz) if vibration else None for b in m.burrs]
    # scratch for the largest burr, once; the rigids stepped at the loop's rate
    state = make_state(m, arr, rate_hz=rate_hz)
    samples = child.rings["samples"]
    no_vib = np.zeros(3)
    device = _make_device(device_spec, control)
    coupling = VirtualCoupling() if not math.isfinite(device.caps.max_force_n) \
        and isinstance(device, SharedInputDevice) else None
    safe = device if device_spec[0] == "device" else None
    if safe is not None:
        coupling = VirtualCoupling()       # for the mouse while the device is away
    ctx = LoopContext(m, state, device, coupling, status)
    queue = CommandQueue(child.rings["commands"], known)
    warmup()
    warmup_rigid()                         # fragments and plates in motion
    if vibration:
        from bonesim.physics.vibration import warmup as vibration_warmup

        vibration_warmup()
        for v in vibs:                     # first calls out of the timed loop
            v.sample(0.0, np.array([0.0, 0.0, -1.0]), False, False, 0.0, 0.0)
            v.reset()
    if pedal is not None:                  # drill on/off and speed from a foot pedal
        from bonesim.devices.pedal import PedalGuard

        if isinstance(pedal, str):
            from bonesim.devices.registry import make_device

            pedal = make_device(pedal, pedal_ok=True)
        pedal = PedalGuard(pedal)
        pedal.open()
    tap = None                             # an instrumented handle's angles, recorded
    if pedal is not None and handle_of(pedal) is not None:
        tap = HandleTap(child.rings["handle"], handle_of(pedal), status["handle_deg"])
    status["device_caps"] = math.nan
    status["handle_deg"] = math.nan
    device.open()
    replugs = 0
    if safe is not None:
        _publish_caps(status, safe.caps)
    try:
        device.read(0.0)
        status["realtime"] = 1 if _ask_realtime() else 0
        spin = SPIN_REALTIME_S if status["realtime"] else SPIN_S
        # the fields read or written every step, bound once
        quit_f, drill_in, speed_in, dir_in = (control[k] for k in
                                              ("quit", "drill", "speed_rpm", "direction"))
        (st_t, st_pos, st_axis, st_force, st_mag, st_volume, st_immersed, st_drill,
         st_speed, st_dir, st_burr, st_steps, st_overruns, st_hand) = (
            status[k] for k in ("t_s", "pos_mm", "axis", "force_n", "mag_n", "volume_mm3",
                                "immersed", "drill", "speed_rpm", "direction", "burr",
                                "steps", "overruns", "hand_force_n"))
        st_dev, st_rej, st_unplugs, st_cam = (status[k] for k in (
            "device_state", "device_rejected", "device_unplugs", "camera_rate"))
        st_pedal, st_seq = status["pedal"], status["seq"]
        cam_rate = getattr(safe.device, "camera_rate", None) if safe is not None else None
        # everything the loop needs exists now; no collector pauses from here on
        gc.collect()
        gc.freeze()
        gc.disable()
        out_f = np.zeros(3)
        failed = queue.failed              # bound once: the hot path allocates nothing
        period = 1.0 / rate_hz
        pmask = periods.shape[0] - 1
        clock = time.perf_counter
        t0 = clock()
        last = t0
        deadline = t0
        overruns = 0
        child.ready()
        while quit_f == 0:
            now = clock()
            periods[p_head[0] & pmask] = now - last
            p_head[0] += 1
            last = now
            t = now - t0
            if run_s is not None and t >= run_s:
                break
            ctx.t_s = t
            cmds = queue.take(ctx)             # reset, burr, tool, bodies: () when none
            r: DeviceReading = device.read(t)
            pos = r.pos_mm
            if safe is not None and not safe.coupled:
                coupling.pos = None            # re-seeded where the tool is at a hand-over
            elif coupling is not None:
                if coupling.pos is None and safe is not None and state.n_steps > 0:
                    coupling.reset(state.pos_mm)
                dt = period if math.isnan(state.t_s) else t - state.t_s
                pos = coupling.update(pos, state.force_n, dt)
            drill = bool(drill_in) if r.drill is None else r.drill
            speed = float(speed_in) if r.speed_rpm is None else r.speed_rpm
            direction = (1 if dir_in >= 0 else -1) if r.direction is None else r.direction
            if pedal is not None:
                drill, speed = pedal.apply(t, drill, speed)
                st_pedal[...] = 1 if pedal.connected else 2
            # commands, rigid motion and the haptic step: the world step
            f = world_step(m, state, Sample(t, pos, r.axis, drill, speed, direction,
                                            state.burr), cmds, failed)
            if cmds:
                queue.settle(ctx)              # counted; epoch and tool published
            burr = state.burr
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
            if safe is not None:
                f = safe.sent_n                # what the device renders, after the limits
                st_dev[...] = safe.state
                st_rej[...] = safe.n_rejected
                st_unplugs[...] = safe.unplugs
                if safe.replugs != replugs:    # re-opened: maybe another arm
                    replugs = safe.replugs
                    _publish_caps(status, safe.caps)
                if cam_rate is not None:
                    st_cam[...] = 0.0 if safe.state == UNPLUGGED else cam_rate
            push_sample(samples, t, state, r.pos_mm, r.axis, drill, speed, direction, burr,
                        state.epoch, r.buttons, f, fv)
            if tap is not None:
                tap(t)
            st_seq[...] += 1                    # odd: a step's snapshot is being written
            st_t[...] = t
            st_pos[...] = state.pos_mm
            st_axis[...] = state.axis
            st_force[...] = f
            st_mag[...] = state.out[O_MAG]
            st_volume[...] = state.out[O_VOLUME]
            st_immersed[...] = state.out[O_N_IMMERSED]
            st_drill[...] = drill
            st_speed[...] = speed
            st_dir[...] = direction
            st_burr[...] = burr
            st_steps[...] = state.n_steps
            if coupling is not None and coupling.pos is not None:
                st_hand[...] = coupling.hand_force_n(r.pos_mm)
            st_seq[...] += 1                    # even: one step's snapshot
            deadline += period
            rest = deadline - clock()
            if rest > spin:
                time.sleep(rest - spin)
            while clock() < deadline:
                pass
            if clock() - deadline > period:        # fell behind: do not burst
                overruns += 1
                st_overruns[...] = overruns
                deadline = clock()
    finally:
        device.close()
        if pedal is not None:
            pedal.close()


class HapticLoop(ChildProcess):
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
        ``("null", pos_mm, axis)``, or ``("device", backend[, settings])``: a
        real device (an instance, or a name in :mod:`bonesim.devices.registry`)
        behind :class:`bonesim.devices.safety.SafeDevice`, the mouse taking
        over while it is unplugged (``status["device_state"]``).
    rate_hz : float
        Servo rate [Hz].
    run_s : float, optional
        Stop by itself after this long [s] (benchmarks, scripted runs).
    vibration : bool
        Add the burr's synthesized vibration to the force sent to the device.
    pedal : FootPedal or str, optional
        A foot pedal (:mod:`bonesim.devices.pedal`; an instance or a
        registered name) giving drill on/off and speed (``status["pedal"]``).

    Attributes
    ----------
    state : State
        A view of the loop's state in shared memory (grid density, touched
        flags, rings) for consumers such as
        :class:`bonesim.engine.replica.TissueReplica`. Only the loop writes it,
        except the touched flags that consumers clear.
    status, control : ndarray
        The shared status and control records (:data:`STATUS`,
        :data:`CONTROL`; the module docstring).
    samples : events.Ring
        One record per haptic step (see :func:`push_sample`).
    """

    NAME = "bonesim-haptic"
    STATUS = STATUS
    CONTROL = CONTROL
    RINGS = ("samples", "commands", "handle")
    START_TIMEOUT_S = START_TIMEOUT_S

    def __init__(self, model: Model, burrs=(), device=("mouse",), rate_hz: float = 1000.0,
                 run_s: float | None = None, vibration: bool = True, pedal=None):
        self.model = model
        self.burrs = [None] + list(burrs)
        self.device = tuple(device)
        self.rate_hz = float(rate_hz)
        self.run_s = run_s
        self.vibration = bool(vibration)
        self.pedal = pedal
        super().__init__()
        self.state = make_state(model, self.arrays)
        self._periods = events.Ring({"period": self.arrays["periods"]},
                                    self.arrays["periods.head"])
        self.samples = self.rings["samples"]
        self._sender = CommandSender(self.rings["commands"], self.status)
        self._known = None
        self._epoch = 0
        self.control["axis"] = (0.0, 0.0, -1.0)
        self.control["speed_rpm"] = model.burr.default_speed_rpm
        self.control["direction"] = 1

    # ------------------------------------------------------ process parts
    def shared_spec(self) -> list:
        return state_arrays_spec(self.model) + [
            ("periods", (PERIOD_RING,), np.float64), ("periods.head", (1,), np.int64)]

    def child_args(self) -> dict:
        # every command registered now and importable by the loop's process
        # travels there (by reference); a class defined in a function cannot
        self._known = tuple(c for c in commands.registered()
                            if "<locals>" not in c.__qualname__)
        return {"model": self.model, "burrs": list(self.burrs), "device_spec": self.device,
                "rate_hz": self.rate_hz, "run_s": self.run_s, "vibration": self.vibration,
                "known": self._known, "pedal": self.pedal}

    @classmethod
    def run(cls, child, **kwargs) -> None:
        _run_loop(child, **kwargs)

    # ------------------------------------------------------------ commands
    def set_target(self, pos_mm, axis=None) -> None:
        """Where the hand (mouse) wants the tool [mm], and its axis."""
        self.control["target_mm"] = pos_mm
        if axis is not None:
            self.control["axis"] = axis

    def set_drill(self, on: bool, speed_rpm: float | None = None,
                  direction: int | None = None) -> None:
        """Drill on/off, and optionally its speed [rpm] and direction (sign)."""
        self.control["drill"] = 1 if on else 0
        if speed_rpm is not None:
            self.control["speed_rpm"] = speed_rpm
        if direction is not None:
            self.control["direction"] = 1 if direction >= 0 else -1

    def send(self, command, **params) -> int:
        """Send a command (:mod:`bonesim.runtime.commands`: a class or its name) to
        the loop; returns its sequence number.

        Raises
        ------
        UnknownCommand
            No such command, or one the loop does not know (registered
            after it started, or defined inside a function).
        CommandOverflow
            The loop has not taken the commands already sent.
        """
        cls = commands.command_class(command)
        if self._known is not None and cls not in self._known:
            raise commands.UnknownCommand(
                f"the haptic loop does not know command {cls.name!r} (kind {cls.kind}): it "
                "was registered after the loop started, or inside a function (define "
                "commands at module level)", field="kind")
        return self._sender.send(cls, **params)

    def set_burr(self, index: int) -> None:
        """Switch to burr ``index`` (0: the model's)."""
        if not 0 <= index < len(self.burrs):
            raise IndexError(f"burr index {index} out of range 0..{len(self.burrs) - 1}")
        self.send(SetBurr, index=index)

    def set_tool(self, tool) -> None:
        """Switch the tool (:data:`bonesim.engine.world_commands.TOOLS`: index or name)."""
        self.send(SetTool, tool=tool)

    def reset(self) -> int:
        """Ask the loop to restore the case; returns the epoch it will announce
        in ``status["epoch"]``."""
        self.send(Reset)
        self._epoch += 1
        return self._epoch

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
