"""3D Systems Touch / Phantom Omni through OpenHaptics, via the pyopenhaptics
binding (``import pyOpenHaptics`` lazily; it loads the vendor's HD library,
``libHD.so``, when imported).

The HD library runs its own servo loop (the scheduler) and calls our
callback there every millisecond, between ``hdBeginFrame`` and
``hdEndFrame`` (the binding's ``hd_callback`` wrapper): the callback copies
the stylus transform and buttons out and the latest commanded force in. The
haptic loop's :meth:`OpenHapticsDevice.read` and
:meth:`OpenHapticsDevice.write_force` only touch those copies, so the loop
never waits on the device. A callback that stops ticking for ``lost_s`` (the
wrapper ends it on an HD error, e.g. ``HD_COMM_ERROR`` when the arm is
unplugged) is an unplug; opening again initializes the device again.

Frames: the HD library reports the stylus in its own frame (x right, y up, z
toward the user) [mm], the stylus pointing along its -z axis. ``frame`` (3
rows: the case-frame directions of device x, y, z; the window passes the
view's right, up and toward-the-eye directions) and ``origin_mm`` (the case
point at the device's origin; the window passes the tool's start) map it to
the case frame; forces go back through the transpose. On opening, the
device's own continuous force limit, stiffness and workspace replace the
default record (:data:`CAPS`, a Touch's).
"""
from __future__ import annotations

import contextlib
import io
import math
import time

import numpy as np

from bonesim.devices.interface import DeviceCaps, DeviceDisconnected, DeviceReading, unit_axis
from bonesim.devices.simulated_hand import TOUCH_CAPS
from bonesim.errors import BonesimError

__all__ = ["CAPS", "NEEDS", "SETTINGS", "START_KEY", "FRAME_KEY", "INSTALL_BINDING",
           "INSTALL_LIBRARY", "MAX_STALE_ERRORS", "READS_OWN_RECORD", "library_missing",
           "connected",
           "OpenHapticsDevice", "DEVICE"]

CAPS = DeviceCaps("touch", TOUCH_CAPS.max_force_n, TOUCH_CAPS.workspace_mm,
                  TOUCH_CAPS.max_stiffness_n_per_mm)
INSTALL_BINDING = "pyopenhaptics not installed: pip install pyopenhaptics"
INSTALL_LIBRARY = ("the OpenHaptics HD library (libHD.so) is not found: install 3D Systems' "
                   "OpenHaptics and the Touch device driver, and put libHD.so on the library "
                   "path (LD_LIBRARY_PATH)")
NEEDS = ("a 3D Systems Touch / Phantom Omni with its driver; OpenHaptics (libHD.so) and "
         "pyopenhaptics (pip install pyopenhaptics)")
#: Settings (``[devices.touch]``): name -> (default, meaning).
SETTINGS = {
    "device_name": ("Default Device", "OpenHaptics device name (Touch Setup)"),
    "origin_mm": ([0.0, 0.0, 0.0], "case point at the device's origin [mm]"),
    "frame": ([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
              "case-frame directions of device x (right), y (up), z (toward the user)"),
    "lost_s": (0.1, "no servo tick this long: the device is gone [s]"),
}
START_KEY = "origin_mm"
FRAME_KEY = "frame"
#: The device reports its own limits when opened
#: (:func:`bonesim.devices.registry.probe`).
READS_OWN_RECORD = True
#: Most errors cleared from the HD library's error stack before opening.
MAX_STALE_ERRORS = 64


def _binding():
    """``(hd, hd_callback, hd_define)`` of pyOpenHaptics."""
    try:
        from pyOpenHaptics import hd, hd_callback, hd_define
    except ImportError as exc:
        raise BonesimError(INSTALL_BINDING) from exc
    except OSError as exc:                    # CDLL("libHD.so") failed
        raise BonesimError(INSTALL_LIBRARY) from exc
    return hd, hd_callback, hd_define


def library_missing() -> str | None:
    try:
        _binding()
    except BonesimError as exc:
        return str(exc)
    return None


def connected() -> list[str]:
    # the HD library names no device without initializing it (which would
    # take it from another program); say what will be opened
    return ["the OpenHaptics default device (probed when opened)"]


class OpenHapticsDevice:
    """A Touch-class arm through OpenHaptics (module docstring).

    Parameters
    ----------
    settings : dict
        See :data:`SETTINGS`.
    calibration : dict, optional
        Unused (OpenHaptics calibrates the arm itself).

    Attributes
    ----------
    caps : DeviceCaps
        :data:`CAPS` until opened, then the device's own.
    ticks : int
        Servo callbacks run since opening.
    model : str
        The device's model and vendor strings (after opening).
    """

    def __init__(self, settings: dict | None = None, calibration: dict | None = None):
        s = dict(settings or {})
        unknown = sorted(set(s) - set(SETTINGS))
        if unknown:
            raise BonesimError(f"unknown setting(s) {unknown}; known: {sorted(SETTINGS)}",
                               field="devices.touch")
        self.settings = s
        self.calibration = calibration
        g = lambda k: s.get(k, SETTINGS[k][0])          # noqa: E731
        try:
            self.name = str(g("device_name"))
            self.origin = np.array(g("origin_mm"), float).reshape(3)
            self.R = np.array(g("frame"), float).reshape(3, 3).T
            self.lost_s = float(g("lost_s"))
        except (TypeError, ValueError) as exc:
            raise BonesimError(f"bad setting ({exc})", field="devices.touch") from None
        self.caps = CAPS
        self.ticks = 0
        self.model = ""
        self._id = None
        self._cb = None
        self._dev_pos = np.zeros(3)
        self._dev_z = np.array([0.0, 0.0, 1.0])
        self._buttons = 0
        self._force = [0.0, 0.0, 0.0]
        self._last_tick = -math.inf

    def open(self) -> None:
        """Initialize the device, read its limits and start the servo callback."""
        hd, hd_callback, d = _binding()
        self.close()
        for _ in range(MAX_STALE_ERRORS):      # errors left from before (an unplug)
            if hd._get_error().errorCode == d.HD_SUCCESS:
                break
        quiet = contextlib.redirect_stdout(io.StringIO())      # the binding prints
        with quiet:
            hid = hd.init_device(self.name)
        # the binding's get_error() has no entry for some codes (HD_COMM_ERROR):
        # read the code itself
        if hid is None or hid in (d.HD_INVALID_HANDLE, d.HD_BAD_HANDLE) \
                or hd._get_error().errorCode != d.HD_SUCCESS:
            raise BonesimError(f"OpenHaptics device {self.name!r} did not initialize (is it "
                               "plugged in and set up in Touch Setup?)")
        self._id = hid
        self.model = f"{hd.get_vendor()} {hd.get_model()}"
        cont = hd._get_doublev(d.HD_NOMINAL_MAX_CONTINUOUS_FORCE, d.HDdouble).value
        stiff = hd._get_doublev(d.HD_NOMINAL_MAX_STIFFNESS, d.HDdouble).value
        ws = list(hd._get_doublev(d.HD_USABLE_WORKSPACE_DIMENSIONS, d.HDdouble * 6))
        self.caps = DeviceCaps("touch", float(cont),
                               tuple(float(ws[3 + i] - ws[i]) for i in range(3)), float(stiff))
        self._force = [0.0, 0.0, 0.0]
        self.ticks = 0

        def servo():
            m = hd.get_transform()
            buttons = hd.get_buttons()
            hd.set_force(self._force)
            if hd._get_error().errorCode != d.HD_SUCCESS:
                return                          # no fresh pose: the tick does not count
            self._dev_pos[0], self._dev_pos[1], self._dev_pos[2] = m[3][0], m[3][1], m[3][2]
            self._dev_z[0], self._dev_z[1], self._dev_z[2] = m[2][0], m[2][1], m[2][2]
            self._buttons = buttons
            self.ticks += 1
            self._last_tick = time.perf_counter()

        self._cb = hd_callback.hd_callback(servo)      # kept: the library holds a pointer
        self._last_tick = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            hd.enable_force()
        hd.start_scheduler()
        hd_callback.hdAsyncSheduler(self._cb)

    def read(self, t_s: float) -> DeviceReading:
        """The stylus at its last servo tick, in the case frame."""
        if self._id is None or time.perf_counter() - self._last_tick > self.lost_s:
            raise DeviceDisconnected(f"OpenHaptics device {self.name!r}: no servo tick for "
                                     f"{self.lost_s:g} s (unplugged?)")
        pos = self.origin + self.R @ self._dev_pos
        return DeviceReading(pos, unit_axis(-(self.R @ self._dev_z)), int(self._buttons))

    def write_force(self, force_n) -> None:
        """The force [N] (case frame) the next servo ticks render."""
        f = self.R.T @ np.asarray(force_n, float)
        self._force = [float(f[0]), float(f[1]), float(f[2])]

    def close(self) -> None:
        if self._id is None:
            return
        hd, _, _ = _binding()
        self._force = [0.0, 0.0, 0.0]
        try:
            hd.stop_scheduler()
            hd.close_device(self._id)
        finally:
            self._id = None


DEVICE = OpenHapticsDevice
