"""3Dconnexion SpaceMouse over hidapi: 6-DOF rate input driving the tool, or
the camera while a button toggles it.

Report layout (little-endian signed 16-bit axis values, about +-350 at full
deflection), as the common models send it:

===========  =============================================================
report id 1  translation x, y, z (bytes 1-6); on the newer models (the
             wireless ones, the universal receiver) the same report carries
             rotation too (bytes 7-12): a 13-byte report
report id 2  rotation about x, y, z (bytes 1-6), older models only
report id 3  buttons, one bit each (bytes 1..)
===========  =============================================================

Axes as reported: x right, y toward the user, z down (the cap pushed down is
+z). This backend turns them into a right-handed *device frame* x right, y
away from the user, z up (a half turn about x: ``(x, -y, -z)`` for both
translation and rotation), then into the case frame through the ``frame``
setting (3 rows: the case-frame directions of device x, y, z; by default the
window passes the view's right, up and toward-the-eye directions, so pushing
the cap down moves the tool into the picture).

The tool moves at ``translation_mm_s`` at full deflection and turns at
``rotation_deg_s``; a deadband ignores small deflections. Its position stays
within ``workspace_mm`` of where it started. Button 0 toggles camera mode:
the tool holds and the deflection becomes :attr:`SpaceMouse.camera_rate`
(pan [mm/s] and orbit [deg/s], case frame), which the haptic loop publishes
for the window. A device that sends no report for ``report_timeout_s``
while deflected is taken to be at rest (a hung report stream must not
drive the tool on). A read error is an unplug
(:class:`~bonesim.devices.interface.DeviceDisconnected`); opening again
enumerates again (hot-plug).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bonesim.devices.hidlink import NEEDS_HID, HidLink, hid_missing, matching
from bonesim.devices.interface import DeviceCaps, DeviceReading, unit_axis
from bonesim.errors import BonesimError

__all__ = ["FULL_SCALE", "MODELS", "CAPS", "NEEDS", "SETTINGS", "START_KEY", "FRAME_KEY",
           "CAMERA_BUTTON", "SpaceMouseModel", "parse_report", "library_missing",
           "connected", "SpaceMouse", "DEVICE"]

#: Axis value at full deflection [counts].
FULL_SCALE = 350.0
#: Button (bit) that toggles camera mode.
CAMERA_BUTTON = 0


@dataclass(frozen=True)
class SpaceMouseModel:
    """One model: its name and whether it sends rotation in report 1."""

    name: str
    combined: bool


#: USB (vendor, product) id -> model: 3Dconnexion's (0x256f) and the older
#: Logitech-made (0x046d) ones.
MODELS = {
    (0x046D, 0xC626): SpaceMouseModel("SpaceNavigator", False),
    (0x046D, 0xC627): SpaceMouseModel("SpaceExplorer", False),
    (0x046D, 0xC62B): SpaceMouseModel("SpaceMouse Pro", False),
    (0x046D, 0xC625): SpaceMouseModel("SpacePilot", False),
    (0x046D, 0xC629): SpaceMouseModel("SpacePilot Pro", False),
    (0x256F, 0xC635): SpaceMouseModel("SpaceMouse Compact", False),
    (0x256F, 0xC641): SpaceMouseModel("SpaceMouse (USB)", False),
    (0x256F, 0xC62E): SpaceMouseModel("SpaceMouse Wireless", True),
    (0x256F, 0xC63A): SpaceMouseModel("SpaceMouse Wireless (2nd gen)", True),
    (0x256F, 0xC632): SpaceMouseModel("SpaceMouse Pro Wireless", True),
    (0x256F, 0xC638): SpaceMouseModel("SpaceMouse Pro Wireless (Bluetooth)", True),
    (0x256F, 0xC633): SpaceMouseModel("SpaceMouse Enterprise", True),
    (0x256F, 0xC652): SpaceMouseModel("3Dconnexion Universal Receiver", True),
}

#: A rate device: it renders no force; its pose goes through the virtual
#: coupling like the mouse's.
CAPS = DeviceCaps("spacemouse", math.inf, (200.0, 200.0, 200.0), 1.0, 1000.0)
NEEDS = "a 3Dconnexion SpaceMouse (USB or its wireless receiver); " + NEEDS_HID
#: Settings (``[devices.spacemouse]``): name -> (default, meaning).
SETTINGS = {
    "translation_mm_s": (40.0, "tool speed at full deflection [mm/s]"),
    "rotation_deg_s": (60.0, "tool turn rate at full deflection [deg/s]"),
    "camera_mm_s": (60.0, "camera pan speed at full deflection [mm/s]"),
    "camera_deg_s": (45.0, "camera orbit rate at full deflection [deg/s]"),
    "deadband": (0.05, "deflections below this fraction of full scale are ignored"),
    "report_timeout_s": (0.25, "no report this long while deflected: at rest [s]"),
    "workspace_mm": (200.0, "the tool stays within this cube around its start [mm]"),
    "start_mm": ([0.0, 0.0, 0.0], "where the tool starts, case frame [mm]"),
    "axis": ([0.0, 0.0, -1.0], "the drill axis at the start"),
    "frame": ([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
              "case-frame directions of device x (right), y (away), z (up)"),
    "serial": ("", "open only the device with this serial number"),
}
START_KEY = "start_mm"
FRAME_KEY = "frame"


def _i16(r, k: int) -> int:
    v = r[k] | (r[k + 1] << 8)
    return v - 65536 if v >= 32768 else v


def parse_report(report) -> tuple:
    """``(kind, values)`` of one input report: ``("t", (x, y, z))``,
    ``("r", (rx, ry, rz))``, ``("tr", (x, y, z, rx, ry, rz))`` in raw counts,
    ``("buttons", mask)``, or ``(None, why)`` for a report this backend does
    not use (another id, too short)."""
    n = len(report)
    if n == 0:
        return None, "empty report"
    rid = report[0]
    if rid == 1 and n >= 13:
        return "tr", tuple(_i16(report, 1 + 2 * i) for i in range(6))
    if rid in (1, 2) and n >= 7:
        return ("t" if rid == 1 else "r"), tuple(_i16(report, 1 + 2 * i) for i in range(3))
    if rid == 3 and n >= 2:
        mask = 0
        for i, b in enumerate(report[1:5]):
            mask |= int(b) << (8 * i)
        return "buttons", mask
    return None, f"report id {rid} with {n} bytes"


def library_missing() -> str | None:
    return hid_missing()


def connected() -> list[str]:
    return [f"{d['model'].name} ({d['vendor_id']:04x}:{d['product_id']:04x})"
            for d in matching(MODELS)]


def _setting(s: dict, k: str):
    return s.get(k, SETTINGS[k][0])


def _rotate(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``v`` turned by the rotation vector ``w`` [rad] (Rodrigues)."""
    a = math.sqrt(float(w @ w))
    if a == 0.0:
        return v
    k = w / a
    return v * math.cos(a) + np.cross(k, v) * math.sin(a) + k * float(k @ v) * (1 - math.cos(a))


class SpaceMouse:
    """The SpaceMouse backend (module docstring).

    Parameters
    ----------
    settings : dict
        See :data:`SETTINGS`.
    calibration : dict, optional
        Unused (kept in the header).

    Attributes
    ----------
    camera_mode : bool
    camera_rate : (6,) float64
        Pan [mm/s] and orbit [deg/s] asked for in camera mode (case frame).
    ignored : int
        Reports of ids or lengths this backend does not use.
    """

    caps = CAPS

    def __init__(self, settings: dict | None = None, calibration: dict | None = None):
        s = dict(settings or {})
        unknown = sorted(set(s) - set(SETTINGS))
        if unknown:
            raise BonesimError(f"unknown setting(s) {unknown}; known: {sorted(SETTINGS)}",
                               field="devices.spacemouse")
        self.settings = s
        self.calibration = calibration
        try:
            self.v_mm_s = float(_setting(s, "translation_mm_s"))
            self.w_rad_s = math.radians(float(_setting(s, "rotation_deg_s")))
            self.cam_mm_s = float(_setting(s, "camera_mm_s"))
            self.cam_deg_s = float(_setting(s, "camera_deg_s"))
            self.deadband = float(_setting(s, "deadband"))
            self.timeout_s = float(_setting(s, "report_timeout_s"))
            self.half_ws = 0.5 * float(_setting(s, "workspace_mm"))
            self.start = np.array(_setting(s, "start_mm"), float).reshape(3)
            axis0 = np.array(_setting(s, "axis"), float).reshape(3)
            frame = np.array(_setting(s, "frame"), float).reshape(3, 3)
        except (TypeError, ValueError) as exc:
            raise BonesimError(f"bad setting ({exc})", field="devices.spacemouse") from None
        self.R = frame.T                       # device vector -> case frame
        self.axis0 = unit_axis(axis0)
        self.link = HidLink(MODELS, "SpaceMouse", _setting(s, "serial") or None)
        self.raw = np.zeros(6)
        self.buttons = 0
        self.camera_mode = False
        self.camera_rate = np.zeros(6)
        self.ignored = 0
        self.pos = self.start.copy()
        self.axis = self.axis0.copy()
        self._t = math.nan
        self._last_report_t = -math.inf

    def open(self) -> None:
        self.link.open()
        self.raw[:] = 0.0

    def close(self) -> None:
        self.link.close()

    def write_force(self, force_n) -> None:
        pass                                   # renders no force

    def _take(self, t_s: float) -> None:
        for rep in self.link.reports():
            kind, v = parse_report(rep)
            if kind is None:
                self.ignored += 1
                continue
            self._last_report_t = t_s
            if kind == "t":
                self.raw[:3] = v
            elif kind == "r":
                self.raw[3:] = v
            elif kind == "tr":
                self.raw[:] = v
            else:
                pressed = v & ~self.buttons
                if pressed >> CAMERA_BUTTON & 1:
                    self.camera_mode = not self.camera_mode
                self.buttons = v

    def _deflection(self, t_s: float) -> np.ndarray:
        """Deflection in [-1, 1] per axis, device frame (x right, y away, z up)."""
        if t_s - self._last_report_t > self.timeout_s:
            return np.zeros(6)
        u = np.clip(self.raw / FULL_SCALE, -1.0, 1.0)
        u[np.abs(u) < self.deadband] = 0.0
        u[[1, 2, 4, 5]] *= -1.0                # HID (right, toward, down) -> (right, away, up)
        return u

    def read(self, t_s: float) -> DeviceReading:
        """Drain the reports, then move the tool (or ask the camera to move)
        at the deflection's rate since the previous read."""
        self._take(t_s)
        dt = 0.0 if not self._t == self._t else max(0.0, t_s - self._t)
        self._t = t_s
        u = self._deflection(t_s)
        v = self.R @ u[:3]
        w = self.R @ u[3:]
        if self.camera_mode:
            self.camera_rate[:3] = v * self.cam_mm_s
            self.camera_rate[3:] = w * self.cam_deg_s
        else:
            self.camera_rate[:] = 0.0
            if dt > 0:
                self.pos += v * (self.v_mm_s * dt)
                np.clip(self.pos, self.start - self.half_ws, self.start + self.half_ws,
                        out=self.pos)
                self.axis = unit_axis(_rotate(self.axis, w * (self.w_rad_s * dt)))
        return DeviceReading(self.pos.copy(), self.axis.copy(), int(self.buttons))


DEVICE = SpaceMouse
