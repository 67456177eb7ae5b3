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
from dataclasses import dataclass
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class DeviceCaps:
    """What a device can do, in physical units.

    Attributes
    ----------
    name : str
        Backend name.
    max_force_n : float
        Largest continuous force the device can render [N] (``inf`` if it
        renders none, e.g. a scripted trajectory).
    workspace_mm : tuple of 3 float
        Usable translation range along x, y, z [mm].
    max_stiffness_n_per_mm : float
        Largest stable virtual stiffness [N/mm].
    rate_hz : float
        Nominal servo rate [Hz].
    """

    name: str
    max_force_n: float
    workspace_mm: tuple
    max_stiffness_n_per_mm: float
    rate_hz: float = 1000.0

    def __post_init__(self):
        if not self.max_force_n > 0:
            raise ValueError(f"device {self.name}: max_force_n must be positive")
        if not self.max_stiffness_n_per_mm > 0:
            raise ValueError(f"device {self.name}: max_stiffness_n_per_mm must be positive")
        if len(self.workspace_mm) != 3 or min(self.workspace_mm) <= 0:
            raise ValueError(f"device {self.name}: workspace_mm must be 3 positive lengths")


#: A trajectory or script drives the tool: no force limit beyond the burr's.
SCRIPTED = DeviceCaps("scripted", math.inf, (math.inf, math.inf, math.inf), math.inf)


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
    """Plays a :class:`bonesim.trajectory.Trajectory` (pose and drill state).

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
    """The mouse/keyboard device: the window writes the target pose into a
    shared array (see :mod:`bonesim.haptic_loop`), the haptic loop reads it.

    Parameters
    ----------
    io : ndarray
        The loop's shared input array; ``io[IN_POS:IN_POS+3]`` and
        ``io[IN_AXIS:IN_AXIS+3]`` hold the target pose.
    """

    caps = MOUSE_CAPS

    def __init__(self, io, pos_slice=slice(0, 3), axis_slice=slice(3, 6)):
        self.io = io
        self._pos = pos_slice
        self._axis = axis_slice

    def open(self) -> None:
        pass

    def read(self, t_s: float) -> DeviceReading:
        return DeviceReading(self.io[self._pos].copy(), _unit(self.io[self._axis]))

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


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    n = float(np.sqrt(v @ v))
    if not n > 0:
        return np.array([0.0, 0.0, -1.0])
    return v / n
