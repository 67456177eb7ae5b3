"""Haptic and input devices: one interface, many backends.

Every backend implements :class:`Device` (open, read -> pose/axis/buttons,
write_force, close) and carries a :class:`DeviceCaps` record in units. The
backends here need no hardware: :class:`NullDevice`, :class:`ScriptedDevice`
(a trajectory file) and :class:`SharedInputDevice` (mouse and keyboard, fed by
the window, with :class:`VirtualCoupling` keeping the tool on the bone). Real
haptic devices come as further backends that import their SDKs lazily.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np

from bonesim.engine.device_caps import SCRIPTED, DeviceCaps

__all__ = ["DeviceCaps", "SCRIPTED", "DeviceReading", "Device", "MOUSE_CAPS",
           "NULL_CAPS", "NullDevice", "ScriptedDevice", "SharedInputDevice",
           "VirtualCoupling", "TOUCH_CAPS", "SIM_HAND_CAPS", "SimulatedHandDevice"]


# --------------------------------------------------------------------------
# The device interface
# --------------------------------------------------------------------------
class DeviceReading(NamedTuple):
    """What a device reports at one servo tick.

    Attributes
    ----------
    pos_mm : (3,) float64
        Tool (burr centre) position in the case frame [mm]. For devices that
        render no force (mouse) this is the *target* the hand asks for; the
        haptic loop's virtual coupling moves the tool toward it.
    axis : (3,) float64
        Unit drill axis (handle toward tip).
    buttons : int
        Button bit mask.
    drill, speed_rpm, direction :
        Drill state when the device itself carries it (a scripted
        trajectory, a foot pedal); ``None`` to take it from the user interface.
    """

    pos_mm: np.ndarray
    axis: np.ndarray
    buttons: int = 0
    drill: bool | None = None
    speed_rpm: float | None = None
    direction: int | None = None


@runtime_checkable
class Device(Protocol):
    """One interface for every input/haptic device backend.

    Backends import their SDKs lazily inside :meth:`open`, so listing or
    constructing them never needs the hardware or its libraries.
    """

    caps: DeviceCaps

    def open(self) -> None:
        """Acquire the device (raise :class:`bonesim.errors.BonesimError` if absent)."""

    def read(self, t_s: float) -> DeviceReading:
        """Pose, axis and buttons at time ``t_s`` [s] since the loop started."""

    def write_force(self, force_n: np.ndarray) -> None:
        """Command a force [N] (case frame); devices clamp to ``caps.max_force_n``."""

    def close(self) -> None:
        """Release the device; safe to call twice."""


#: Mouse and keyboard: no force output; the tool follows through a virtual coupling.
MOUSE_CAPS = DeviceCaps("mouse-keyboard", math.inf, (200.0, 200.0, 200.0), 1.0)
#: A device that does nothing (tests, headless runs with an external driver).
NULL_CAPS = DeviceCaps("null", math.inf, (math.inf, math.inf, math.inf), math.inf)


class NullDevice:
    """Holds a fixed pose and ignores forces."""

    caps = NULL_CAPS

    def __init__(self, pos_mm=(0.0, 0.0, 0.0), axis=(0.0, 0.0, -1.0)):
        self._reading = DeviceReading(np.asarray(pos_mm, float), _unit(axis))
        self.last_force = np.zeros(3)

    def open(self) -> None:
        pass

    def read(self, t_s: float) -> DeviceReading:
        return self._reading

    def write_force(self, force_n) -> None:
        self.last_force[:] = force_n

    def close(self) -> None:
        pass


class ScriptedDevice:
    """Plays a :class:`bonesim.io.trajectory.Trajectory` (pose and drill state).

    Parameters
    ----------
    trajectory : Trajectory
        Case-frame path; times are relative to its first sample.
    loop : bool
        Start over at the end instead of holding the last sample.
    """

    caps = SCRIPTED

    def __init__(self, trajectory, loop: bool = False):
        self.trajectory = trajectory
        self.loop = loop
        self.forces: list = []
        self.record_forces = False

    @property
    def duration_s(self) -> float:
        return float(self.trajectory.t_s[-1] - self.trajectory.t_s[0])

    def open(self) -> None:
        pass

    def read(self, t_s: float) -> DeviceReading:
        tr = self.trajectory
        t = t_s
        if self.loop and self.duration_s > 0:
            t = t_s % self.duration_s
        s = tr.sample_at(tr.t_s[0] + t)
        return DeviceReading(s.pos_mm, s.axis, 0, bool(s.drill), float(s.speed_rpm),
                             int(s.direction))

    def finished(self, t_s: float) -> bool:
        return not self.loop and t_s >= self.duration_s

    def write_force(self, force_n) -> None:
        if self.record_forces:
            self.forces.append(np.array(force_n, dtype=float))

    def close(self) -> None:
        pass


class SharedInputDevice:
    """The mouse/keyboard device: the window writes the target pose into
    shared memory (the haptic loop's ``control`` fields ``target_mm`` and
    ``axis``, see :mod:`bonesim.runtime.haptic_loop`), the haptic loop reads it.

    Parameters
    ----------
    pos_mm : (3,) ndarray
        Shared view of the target position [mm].
    axis : (3,) ndarray
        Shared view of the target drill axis (normalized on reading).
    """

    caps = MOUSE_CAPS

    def __init__(self, pos_mm, axis):
        self.pos_mm = pos_mm
        self.axis = axis

    def open(self) -> None:
        pass

    def read(self, t_s: float) -> DeviceReading:
        return DeviceReading(self.pos_mm.copy(), _unit(self.axis))

    def write_force(self, force_n) -> None:
        pass

    def close(self) -> None:
        pass


class VirtualCoupling:
    """Keeps a tool that renders no force resting on the bone.

    The hand (mouse) asks for a target ``x_t``; the tool ``x`` moves under
    the coupling spring ``K (x_t - x)`` plus the bone's contact force ``F``
    through a damper ``b`` (first-order admittance)::

        dx/dt = (K (x_t - x) + F) / b

    At rest the spring balances the bone (``|F| = K |x_t - x|``): pushing the
    mouse deeper presses harder, the harder press removes bone faster, and
    the tool advances as the bone goes. The step is clamped to ``max_speed``.
    The bone force is low-passed (time constant ``force_filter_s``): the
    sampled contact force rises in steps as lattice layers enter the bone,
    and an unfiltered admittance chatters between two layers.

    Parameters
    ----------
    stiffness_n_per_mm : float
        Coupling spring ``K`` [N/mm].
    damping_ns_per_mm : float
        Damper ``b`` [N s/mm].
    max_speed_mm_s : float
        Largest tool speed [mm/s].
    force_filter_s : float
        Time constant of the bone-force low-pass [s].
    """

    def __init__(self, stiffness_n_per_mm=1.0, damping_ns_per_mm=0.02,
                 max_speed_mm_s=200.0, force_filter_s=0.02):
        if min(stiffness_n_per_mm, damping_ns_per_mm, max_speed_mm_s, force_filter_s) <= 0:
            raise ValueError("coupling stiffness, damping, speed and filter must be positive")
        self.k = float(stiffness_n_per_mm)
        self.b = float(damping_ns_per_mm)
        self.vmax = float(max_speed_mm_s)
        self.tau = float(force_filter_s)
        self.pos = None
        self.force = np.zeros(3)

    def reset(self, pos_mm) -> None:
        self.pos = np.array(pos_mm, dtype=float)
        self.force[:] = 0.0

    def update(self, target_mm, force_n, dt_s: float) -> np.ndarray:
        """Advance the tool by ``dt_s`` [s]; returns its new position [mm]."""
        if self.pos is None:
            self.reset(target_mm)
            return self.pos
        self.force += (np.asarray(force_n) - self.force) * min(1.0, dt_s / self.tau)
        v = (self.k * (np.asarray(target_mm) - self.pos) + self.force) / self.b
        speed = float(np.sqrt(v @ v))
        if speed > self.vmax:
            v *= self.vmax / speed
        self.pos += v * dt_s
        return self.pos

    def hand_force_n(self, target_mm) -> float:
        """The force the hand applies through the spring [N]."""
        return float(self.k * np.linalg.norm(np.asarray(target_mm) - self.pos))


#: A 3D Systems Touch (Phantom Omni class), the usual trainee desk device:
#: 3.3 N peak force, 160 x 120 x 70 mm workspace, stable stiffness 0.39 N/mm
#: along its weakest axis (z).
TOUCH_CAPS = DeviceCaps("touch", 3.3, (160.0, 120.0, 70.0), 0.39)
#: The simulated hand renders like a Touch.
SIM_HAND_CAPS = DeviceCaps("simulated-hand", TOUCH_CAPS.max_force_n, TOUCH_CAPS.workspace_mm,
                           TOUCH_CAPS.max_stiffness_n_per_mm)


class SimulatedHandDevice:
    """A passive hand holding a force-feedback stylus: the stand-in for a
    trainee's device when there is no hardware (tutoring tests, headless
    ``bonesim tutor join``).

    The stylus tip and the hand holding it are one point mass ``m`` with the
    hand's viscous damping ``b`` and a weak spring ``k`` pulling it toward
    where the hand would rest; it moves only under the force written to it::

        m x'' = F - b x' - k (x - x_rest)

    :meth:`read` integrates from the previous read to ``t_s`` with the last
    written force held (semi-implicit Euler in sub-steps of at most
    ``max_substep_s``), the way a real device's stylus moves between servo
    ticks. Defaults: 0.15 kg (fingers, hand and stylus at a pen grip),
    8 N s/m damping and a 0.02 N/mm spring: a relaxed hand that lets the
    device lead. They describe a plausible passive trainee, not a measured
    person.

    Parameters
    ----------
    rest_mm : (3,) float
        Where the hand rests, and starts, in the case frame [mm].
    axis : (3,) float
        Drill axis the hand holds (constant).
    mass_kg : float
        Moving mass [kg].
    damping_ns_per_mm : float
        Hand damping ``b`` [N s/mm].
    stiffness_n_per_mm : float
        Spring to the rest point ``k`` [N/mm].
    max_substep_s : float
        Longest integration step [s].
    caps : DeviceCaps
        Limits (default: a Touch's); forces are clamped to ``caps.max_force_n``.

    Attributes
    ----------
    pos_mm, vel_mm_s : (3,) float64
        Current tip position [mm] and velocity [mm/s].
    force_n : (3,) float64
        The force being rendered (after the clamp) [N].
    """

    def __init__(self, rest_mm=(0.0, 0.0, 0.0), axis=(0.0, 0.0, -1.0), mass_kg: float = 0.15,
                 damping_ns_per_mm: float = 0.008, stiffness_n_per_mm: float = 0.02,
                 max_substep_s: float = 0.0005, caps: DeviceCaps = SIM_HAND_CAPS):
        if min(mass_kg, damping_ns_per_mm, max_substep_s) <= 0 or stiffness_n_per_mm < 0:
            raise ValueError("simulated hand: mass, damping and sub-step must be positive, "
                             "stiffness non-negative")
        self.caps = caps
        self.mass_kg = float(mass_kg)
        self.b = float(damping_ns_per_mm)
        self.k = float(stiffness_n_per_mm)
        self.max_substep_s = float(max_substep_s)
        self.rest_mm = np.zeros(3)
        self.pos_mm = np.zeros(3)
        self.vel_mm_s = np.zeros(3)
        self.force_n = np.zeros(3)
        self.axis = _unit(axis)
        self._t = math.nan
        self.place(rest_mm)

    def place(self, rest_mm) -> None:
        """Put the hand at rest at ``rest_mm`` [mm] (no force, no motion)."""
        self.rest_mm[:] = rest_mm
        self.pos_mm[:] = rest_mm
        self.vel_mm_s[:] = 0.0
        self.force_n[:] = 0.0

    def open(self) -> None:
        pass

    def read(self, t_s: float) -> DeviceReading:
        """Advance the hand to ``t_s`` [s] and report it. The arrays returned
        are the device's own (valid until the next call; copy to keep)."""
        if self._t == self._t and t_s > self._t:
            self._advance(t_s - self._t)
        if not self._t == self._t or t_s > self._t:
            self._t = t_s
        return DeviceReading(self.pos_mm, self.axis)

    def _advance(self, dt: float) -> None:
        n = int(math.ceil(dt / self.max_substep_s))
        h = dt / n
        acc_per_n = 1000.0 / self.mass_kg             # [mm/s^2 per N]
        x, v, f, r = self.pos_mm, self.vel_mm_s, self.force_n, self.rest_mm
        b, k = self.b, self.k
        for _ in range(n):
            for a in range(3):
                v[a] += h * acc_per_n * (f[a] - b * v[a] - k * (x[a] - r[a]))
                x[a] += h * v[a]

    def write_force(self, force_n) -> None:
        """Render ``force_n`` [N] (clamped to the device's maximum) until the next write."""
        f = self.force_n
        f[0], f[1], f[2] = force_n[0], force_n[1], force_n[2]
        norm = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        if not norm <= self.caps.max_force_n:          # also catches NaN
            if norm == norm and norm > 0:
                f *= self.caps.max_force_n / norm
            else:
                f[:] = 0.0

    def close(self) -> None:
        self.force_n[:] = 0.0


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    n = float(np.sqrt(v @ v))
    if not n > 0:
        return np.array([0.0, 0.0, -1.0])
    return v / n
