"""A passive hand holding a force-feedback stylus: the stand-in for a
trainee's device without hardware."""
from __future__ import annotations

import math

import numpy as np

from bonesim.devices.interface import DeviceCaps, DeviceReading, unit_axis

__all__ = ["TOUCH_CAPS", "SIM_HAND_CAPS", "SimulatedHandDevice"]


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
        self.axis = unit_axis(axis)
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
