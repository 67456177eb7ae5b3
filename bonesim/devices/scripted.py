"""A device that plays a trajectory file (pose and drill state)."""
from __future__ import annotations

import numpy as np

from bonesim.devices.interface import SCRIPTED, DeviceReading

__all__ = ["ScriptedDevice"]


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
