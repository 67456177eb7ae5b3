"""A USB foot pedal over hidapi: drill on/off and speed.

Supported out of the box: the Infinity IN-USB-2 transcription pedal (USB id
05f3:00ff, three pedals; each input report is two bytes, a little-endian
bit mask: 1 left, 2 middle, 4 right, no report id). Any other pedal that
reports its switches as bits of an input report is described in the config::

    [devices.pedal]
    usb_id = "1234:abcd"     # vendor:product, hex
    report_byte = 0          # byte of the report holding the bits
    drill_bit = 1            # masks
    slower_bit = 0           # 0: no such pedal
    faster_bit = 0

The drill runs while the drill pedal is held (a surgical foot control);
each press of the slower / faster pedal changes the speed by
``speed_step_rpm`` within [``min_speed_rpm``, ``max_speed_rpm``]. Until a
speed pedal is pressed the speed is the window's. :class:`PedalGuard` is
what the haptic loop runs: an unplugged pedal stops the drill at once, it
is looked for again every ``reconnect_s`` (re-enumerated: hot-plug), and
on its return the drill stays off until the pedal is pressed again.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from bonesim.devices.hidlink import NEEDS_HID, HidLink, hid_missing, matching
from bonesim.devices.interface import DeviceDisconnected
from bonesim.errors import BonesimError

__all__ = ["PedalModel", "MODELS", "NEEDS", "SETTINGS", "library_missing", "connected",
           "FootPedal", "PedalGuard", "DEVICE"]


@dataclass(frozen=True)
class PedalModel:
    """How a pedal reports: the byte holding the bits and each pedal's mask."""

    name: str
    report_byte: int
    drill_bit: int
    slower_bit: int
    faster_bit: int


#: USB (vendor, product) id -> model.
MODELS = {(0x05F3, 0x00FF): PedalModel("Infinity IN-USB-2", 0, 0x02, 0x01, 0x04)}
NEEDS = "a USB foot pedal (Infinity IN-USB-2, or one described in the config); " + NEEDS_HID
#: Settings (``[devices.pedal]``): name -> (default, meaning).
SETTINGS = {
    "usb_id": ("", "vendor:product (hex) of a pedal not in the built-in table"),
    "report_byte": (0, "byte of the report holding the pedal bits"),
    "drill_bit": (1, "mask of the drill pedal"),
    "slower_bit": (0, "mask of the slower pedal (0: none)"),
    "faster_bit": (0, "mask of the faster pedal (0: none)"),
    "speed_step_rpm": (5000.0, "speed change per press [rpm]"),
    "min_speed_rpm": (5000.0, "slowest speed [rpm]"),
    "max_speed_rpm": (80000.0, "fastest speed [rpm]"),
    "start_speed_rpm": (60000.0, "speed the first speed-pedal press steps from [rpm]"),
    "reconnect_s": (0.5, "an unplugged pedal is looked for this often [s]"),
    "serial": ("", "open only the pedal with this serial number"),
}


def library_missing() -> str | None:
    return hid_missing()


def connected() -> list[str]:
    return [f"{d['model'].name} ({d['vendor_id']:04x}:{d['product_id']:04x})"
            for d in matching(MODELS)]


def _models(s: dict) -> dict:
    uid = s.get("usb_id", "")
    if not uid:
        return MODELS
    try:
        v, p = (int(x, 16) for x in str(uid).split(":"))
        model = PedalModel(f"pedal {uid}", int(s.get("report_byte", 0)),
                           int(s.get("drill_bit", 1)), int(s.get("slower_bit", 0)),
                           int(s.get("faster_bit", 0)))
    except (TypeError, ValueError):
        raise BonesimError(f"usb_id {uid!r} is not vendor:product in hex (e.g. 05f3:00ff)",
                           field="devices.pedal.usb_id") from None
    return {(v, p): model}


class FootPedal:
    """The pedal (module docstring): :meth:`poll` gives the drill state and speed.

    Parameters
    ----------
    settings : dict
        See :data:`SETTINGS`.
    calibration : dict, optional
        Unused.

    Attributes
    ----------
    ignored : int
        Reports too short to hold the pedal byte.
    released : bool
        A report had the drill pedal up since this was last cleared (a lift
        and press within one poll is not lost).
    """

    def __init__(self, settings: dict | None = None, calibration: dict | None = None):
        s = dict(settings or {})
        unknown = sorted(set(s) - set(SETTINGS))
        if unknown:
            raise BonesimError(f"unknown setting(s) {unknown}; known: {sorted(SETTINGS)}",
                               field="devices.pedal")
        self.settings = s
        self.calibration = calibration
        g = lambda k: s.get(k, SETTINGS[k][0])          # noqa: E731
        self.step = float(g("speed_step_rpm"))
        self.lo, self.hi = float(g("min_speed_rpm")), float(g("max_speed_rpm"))
        self.start_speed = float(g("start_speed_rpm"))
        self.reconnect_s = float(g("reconnect_s"))
        if not 0 < self.lo <= self.hi or self.step <= 0:
            raise BonesimError("need 0 < min_speed_rpm <= max_speed_rpm and speed_step_rpm > 0",
                               field="devices.pedal")
        self.link = HidLink(_models(s), "foot pedal", g("serial") or None)
        self.mask = 0
        self.speed_rpm: float | None = None
        self.ignored = 0
        self.released = False

    def open(self) -> None:
        self.link.open()
        self.mask = 0
        self.released = False

    def close(self) -> None:
        self.link.close()

    def poll(self, t_s: float) -> tuple:
        """``(drill, speed_rpm)`` now; ``speed_rpm`` None until a speed pedal
        was pressed. Raises :class:`DeviceDisconnected` if the pedal went away."""
        m = self.link.model
        for rep in self.link.reports():
            if len(rep) <= m.report_byte:
                self.ignored += 1
                continue
            new = int(rep[m.report_byte])
            pressed = new & ~self.mask
            self.mask = new
            if not new & m.drill_bit:
                self.released = True
            for bit, sign in ((m.slower_bit, -1.0), (m.faster_bit, 1.0)):
                if bit and pressed & bit:
                    base = self.start_speed if self.speed_rpm is None else self.speed_rpm
                    self.speed_rpm = min(max(base + sign * self.step, self.lo), self.hi)
        return bool(self.mask & m.drill_bit), self.speed_rpm


class PedalGuard:
    """Runs a pedal in the haptic loop: faults stop the drill (module docstring).

    Attributes
    ----------
    connected : bool
    unplugs : int
    """

    def __init__(self, pedal):
        self.pedal = pedal
        self.connected = False
        self.unplugs = 0
        self._retry_at = 0.0
        self._armed = True

    def open(self) -> None:
        self.pedal.open()
        self.connected = True

    def close(self) -> None:
        self.pedal.close()

    def apply(self, t_s: float, drill: bool, speed_rpm: float) -> tuple:
        """The drill state and speed after the pedal: ``(drill, speed_rpm)``."""
        if not self.connected:
            if t_s >= self._retry_at:
                try:
                    self.pedal.open()
                    self.connected = True
                    self._armed = False        # off until the pedal is pressed again
                except (BonesimError, OSError):
                    self._retry_at = t_s + self.pedal.reconnect_s
            if not self.connected:
                return False, speed_rpm
        try:
            on, speed = self.pedal.poll(t_s)
        except (DeviceDisconnected, OSError):
            self.pedal.close()
            self.connected = False
            self.unplugs += 1
            self._retry_at = t_s + self.pedal.reconnect_s
            return False, speed_rpm
        if not on or self.pedal.released:
            self._armed = True
        self.pedal.released = False
        on = on and self._armed
        return on, (speed_rpm if speed is None or not math.isfinite(speed) else speed)


DEVICE = FootPedal
