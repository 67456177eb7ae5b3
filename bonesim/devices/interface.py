"""The one device interface every backend implements.

A backend is a class with ``caps`` (a :class:`~bonesim.engine.device_caps.DeviceCaps`
record in units) and ``open``, ``read(t_s) -> DeviceReading``,
``write_force(force_n)`` and ``close``. Backends live one per module beside
this one (:mod:`~bonesim.devices.null`, :mod:`~bonesim.devices.scripted`,
:mod:`~bonesim.devices.mouse`, :mod:`~bonesim.devices.simulated_hand`);
backends of real devices import their SDKs lazily, inside their module.
"""
from __future__ import annotations

from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np

from bonesim.engine.device_caps import SCRIPTED, DeviceCaps
from bonesim.errors import BonesimError

__all__ = ["DeviceCaps", "SCRIPTED", "DeviceReading", "DeviceDisconnected", "Device",
           "unit_axis"]


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
    t_s : float, optional
        When the device measured this pose, on the loop's clock [s]; ``None``
        for backends that measure at the moment they are read. A pose older
        than the safety layer's limit is stale
        (:class:`~bonesim.devices.safety.SafeDevice`).
    """

    pos_mm: np.ndarray
    axis: np.ndarray
    buttons: int = 0
    drill: bool | None = None
    speed_rpm: float | None = None
    direction: int | None = None
    t_s: float | None = None


class DeviceDisconnected(BonesimError):
    """The device went away (unplugged, powered off, its link broken).

    Backends raise it from ``read`` or ``write_force``;
    :class:`bonesim.devices.safety.SafeDevice` catches it, zeroes the force,
    hands over to the mouse and tries to reconnect.
    """


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


def unit_axis(v) -> np.ndarray:
    """``v`` normalized; the default drill axis (0, 0, -1) for a zero vector."""
    v = np.asarray(v, dtype=float)
    n = float(np.sqrt(v @ v))
    if not n > 0:
        return np.array([0.0, 0.0, -1.0])
    return v / n
