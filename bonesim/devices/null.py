"""A device that does nothing: a fixed pose and no force (tests, headless
runs with an external driver)."""
from __future__ import annotations

import math

import numpy as np

from bonesim.devices.interface import DeviceCaps, DeviceReading, unit_axis

__all__ = ["NULL_CAPS", "NullDevice"]

#: A device that does nothing (tests, headless runs with an external driver).
NULL_CAPS = DeviceCaps("null", math.inf, (math.inf, math.inf, math.inf), math.inf)


class NullDevice:
    """Holds a fixed pose and ignores forces."""

    caps = NULL_CAPS

    def __init__(self, pos_mm=(0.0, 0.0, 0.0), axis=(0.0, 0.0, -1.0)):
        self._reading = DeviceReading(np.asarray(pos_mm, float), unit_axis(axis))
        self.last_force = np.zeros(3)

    def open(self) -> None:
        pass

    def read(self, t_s: float) -> DeviceReading:
        return self._reading

    def write_force(self, force_n) -> None:
        self.last_force[:] = force_n

    def close(self) -> None:
        pass
