"""Mouse and keyboard: the window writes the target pose into shared memory,
and a virtual coupling keeps the tool on the bone."""
from __future__ import annotations

import math

import numpy as np

from bonesim.devices.interface import DeviceCaps, DeviceReading, unit_axis

__all__ = ["MOUSE_CAPS", "SharedInputDevice", "VirtualCoupling"]

#: Mouse and keyboard: no force output; the tool follows through a virtual coupling.
MOUSE_CAPS = DeviceCaps("mouse-keyboard", math.inf, (200.0, 200.0, 200.0), 1.0)


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
        return DeviceReading(self.pos_mm.copy(), unit_axis(self.axis))

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
