"""An instrumented handle read through an Ontrak ADU100 USB data-acquisition
box over pyusb (``import usb`` lazily): potentiometers on the handle's lever
and wheel give angles by a two-point calibration.

The ADU100 (USB id 0a07:0064) is a low-speed HID-class device; pyusb talks
to it directly: interface 0, interrupt OUT endpoint 0x01 and IN endpoint
0x81, 8-byte packets. A command is ``0x01`` followed by ASCII text, padded
with zeros to 8 bytes; a command that reads something queues an answer of
the same form (``0x01``, ASCII digits, zeros). ``RUN<ch><gain>`` reads
analog input ``ch`` unipolar at gain index ``gain`` (0: the widest range)
and answers the count, 0 to 65535.

Calibration (the user opens the handle fully, then closes it fully; linear
in between, as the reference instrument does): per channel the raw counts
``open`` and ``closed`` map to ``open_deg`` and ``closed_deg``; stored per
device (its serial number) in the user's config
(:func:`bonesim.devices.config.set_calibration`), run by
``bonesim calibrate adu100-handle``.

USB reads take milliseconds, so a poller thread in the haptic process asks
for each channel in turn and keeps the latest counts; :meth:`ADU100Handle.poll`
(the foot pedal's interface, :class:`bonesim.devices.pedal.PedalGuard` runs
it) never waits. Squeezing the lever drives the drill: past
``drill_on_fraction`` of the way from open to closed the drill runs, its
speed rising linearly to ``max_speed_rpm`` when fully closed.
"""
from __future__ import annotations

import errno
import math
import threading

import numpy as np

from bonesim.devices.interface import DeviceDisconnected
from bonesim.errors import BonesimError

__all__ = ["VENDOR_ID", "PRODUCT_ID", "EP_OUT", "EP_IN", "PACKET", "MAX_COUNTS", "NEEDS",
           "SETTINGS", "DEFAULT_OPEN_DEG", "DEFAULT_CLOSED_DEG", "CAL_SAMPLES",
           "encode_command", "decode_answer", "calibrate", "angles_deg", "run_calibration",
           "library_missing", "connected", "READS_OWN_RECORD", "ADU100Handle", "DEVICE"]

VENDOR_ID = 0x0A07
PRODUCT_ID = 0x0064            # 100
EP_OUT = 0x01
EP_IN = 0x81
#: Bytes in every command and answer.
PACKET = 8
#: Largest analog reading [counts].
MAX_COUNTS = 65535
PYUSB_INSTALL = ("pyusb not importable: pip install pyusb (and the system's libusb-1.0; "
                 "on Linux a udev rule giving your user access to the device)")
NEEDS = ("an Ontrak ADU100 with the handle's potentiometers on its analog inputs; pyusb "
         "(pip install pyusb) with libusb-1.0 and access to the device")
#: Settings (``[devices.adu100-handle]``): name -> (default, meaning).
SETTINGS = {
    "channels": ([1, 2], "analog inputs read: lever, then wheel"),
    "gain": (0, "gain index of the analog reads (0: widest range)"),
    "timeout_ms": (100, "USB transfer timeout [ms]"),
    "drill_on_fraction": (0.2, "the drill runs past this fraction of the lever's travel"),
    "max_speed_rpm": (80000.0, "drill speed with the lever fully closed [rpm]"),
    "reconnect_s": (0.5, "an unplugged box is looked for this often [s]"),
    "serial": ("", "open only the box with this serial number"),
}
#: Default angles of the calibration's two points [deg], per channel (lever,
#: wheel): the lever's jaws open 30 deg and shut; the wheel turned from one
#: stop to the other over half a turn. The user's instrument may differ
#: (``bonesim calibrate adu100-handle --open-deg ... --closed-deg ...``).
DEFAULT_OPEN_DEG = (30.0, 0.0)
DEFAULT_CLOSED_DEG = (0.0, 180.0)
#: Readings averaged at each calibration point.
CAL_SAMPLES = 20
#: Calibration keys, per channel lists.
CAL_KEYS = ("channels", "open", "closed", "open_deg", "closed_deg")
#: Opening finds the box's own calibration (by its serial number)
#: (:func:`bonesim.devices.registry.probe`).
READS_OWN_RECORD = True


def encode_command(text: str) -> bytes:
    """The 8-byte packet of an ASCII command."""
    raw = text.encode("ascii")
    if len(raw) > PACKET - 1:
        raise ValueError(f"ADU100 command {text!r} longer than {PACKET - 1} characters")
    return bytes([1]) + raw + bytes(PACKET - 1 - len(raw))


def decode_answer(packet) -> int:
    """The integer an answer packet carries.

    Raises
    ------
    ValueError
        Not an answer (first byte not 1, no digits).
    """
    b = bytes(packet)
    if len(b) < 2 or b[0] != 1:
        raise ValueError(f"not an ADU100 answer: {b!r}")
    text = b[1:].split(b"\0", 1)[0].decode("ascii", "replace").strip()
    if not text.isdigit():
        raise ValueError(f"ADU100 answer {text!r} is not a count")
    return int(text)


def calibrate(open_counts, closed_counts, open_deg=0.0, closed_deg=30.0, channels=(1, 2)):
    """A calibration record from the counts read fully open and fully closed.

    Raises
    ------
    BonesimError
        A channel did not move (open and closed read the same).
    """
    o = [float(x) for x in open_counts]
    c = [float(x) for x in closed_counts]
    od = [float(open_deg)] * len(o) if np.isscalar(open_deg) else [float(x) for x in open_deg]
    cd = ([float(closed_deg)] * len(o) if np.isscalar(closed_deg)
          else [float(x) for x in closed_deg])
    for ch, a, b in zip(channels, o, c):
        if abs(a - b) < 1.0:
            raise BonesimError(f"analog input {ch} read {a:.0f} both open and closed: is its "
                               "potentiometer connected?", field="calibration")
    return {"channels": [int(x) for x in channels], "open": o, "closed": c,
            "open_deg": od, "closed_deg": cd}


def angles_deg(cal: dict, counts) -> np.ndarray:
    """Angles [deg] of raw ``counts``: linear between the calibration's points
    (extrapolated beyond them)."""
    o, c = np.asarray(cal["open"], float), np.asarray(cal["closed"], float)
    od, cd = np.asarray(cal["open_deg"], float), np.asarray(cal["closed_deg"], float)
    f = (np.asarray(counts, float) - o) / (c - o)
    return od + f * (cd - od)


def run_calibration(handle, ask, open_deg=DEFAULT_OPEN_DEG, closed_deg=DEFAULT_CLOSED_DEG,
                    samples: int = CAL_SAMPLES, path=None) -> dict:
    """Two-point calibration of ``handle`` with the user, stored in the config.

    ``ask(prompt)`` waits for the user (``input`` on a terminal). The
    calibration is stored under the box's serial number and as ``default``.
    Returns it (with ``serial`` and the config ``path``).
    """
    from bonesim.devices.config import set_calibration

    n = len(handle.channels)
    od, cd = list(open_deg)[:n], list(closed_deg)[:n]
    if len(od) < n or len(cd) < n:
        raise BonesimError(f"give {n} open and {n} closed angles (one per channel)",
                           field="--open-deg/--closed-deg")
    handle.open(poll=False)
    try:
        ask("Open the handle fully (and turn the wheel to its first stop), then press Enter")
        o = np.mean([handle.read_counts() for _ in range(samples)], axis=0)
        ask("Close the handle fully (and turn the wheel to its other stop), then press Enter")
        c = np.mean([handle.read_counts() for _ in range(samples)], axis=0)
    finally:
        handle.close()
    cal = calibrate(o, c, od, cd, handle.channels)
    cal["serial"] = handle.serial
    for key in {handle.serial or "default", "default"}:
        where = set_calibration("adu100-handle", key, cal, path)
    return {**cal, "path": str(where)}


def _usb():
    try:
        import usb.core
        import usb.util
    except ImportError as exc:
        raise BonesimError(PYUSB_INSTALL) from exc
    return usb


def library_missing() -> str | None:
    try:
        _usb()
    except BonesimError as exc:
        return str(exc)
    return None


def connected(usb_backend=None) -> list[str]:
    usb = _usb()
    try:
        devs = list(usb.core.find(find_all=True, idVendor=VENDOR_ID, idProduct=PRODUCT_ID,
                                  backend=usb_backend))
    except usb.core.NoBackendError:
        return []
    return [f"ADU100 (bus {d.bus} address {d.address})" for d in devs]


class ADU100Handle:
    """The instrumented handle (module docstring).

    Parameters
    ----------
    settings : dict
        See :data:`SETTINGS`.
    calibration : dict, optional
        From :func:`calibrate`; without one, :meth:`poll` reports the lever
        open (no drilling) and :attr:`angles` is NaN.
    usb_backend : usb.backend.IBackend, optional
        pyusb's backend (default: pyusb's choice, libusb-1.0).

    Attributes
    ----------
    counts : (n,) float64
        Latest raw reading per channel (NaN before the first).
    serial : str
        The box's serial number (after :meth:`open`).
    reads : int
        Complete polls of all channels.
    """

    def __init__(self, settings: dict | None = None, calibration: dict | None = None,
                 usb_backend=None):
        s = dict(settings or {})
        unknown = sorted(set(s) - set(SETTINGS))
        if unknown:
            raise BonesimError(f"unknown setting(s) {unknown}; known: {sorted(SETTINGS)}",
                               field="devices.adu100-handle")
        self.settings = s
        g = lambda k: s.get(k, SETTINGS[k][0])          # noqa: E731
        self.channels = [int(c) for c in g("channels")]
        self.gain = int(g("gain"))
        self.timeout_ms = int(g("timeout_ms"))
        self.on_fraction = float(g("drill_on_fraction"))
        self.max_speed = float(g("max_speed_rpm"))
        self.reconnect_s = float(g("reconnect_s"))
        self.want_serial = str(g("serial")) or None
        self.calibration = None if calibration is None else self._checked(calibration)
        self.usb_backend = usb_backend
        self.counts = np.full(len(self.channels), math.nan)
        self.serial = ""
        self.reads = 0
        self.released = False
        self._dev = None
        self._thread = None
        self._stop = threading.Event()
        self._error: str | None = None

    def _checked(self, cal: dict) -> dict:
        missing = [k for k in CAL_KEYS if k not in cal]
        if missing:
            raise BonesimError(f"calibration lacks {missing}; run bonesim calibrate "
                               "adu100-handle", field="calibration.adu100-handle")
        if [int(c) for c in cal["channels"]] != self.channels:
            raise BonesimError(f"calibration is for channels {cal['channels']}, the "
                               f"settings read {self.channels}; calibrate again",
                               field="calibration.adu100-handle")
        return dict(cal)

    # ------------------------------------------------------------ USB
    def _find(self):
        usb = _usb()
        try:
            devs = list(usb.core.find(find_all=True, idVendor=VENDOR_ID, idProduct=PRODUCT_ID,
                                      backend=self.usb_backend))
        except usb.core.NoBackendError as exc:
            raise BonesimError(f"pyusb finds no USB backend ({exc}): install libusb-1.0") \
                from exc
        for d in devs:
            serial = ""
            try:
                serial = usb.util.get_string(d, d.iSerialNumber) or ""
            except (usb.core.USBError, ValueError):
                pass
            if self.want_serial is None or serial == self.want_serial:
                return d, serial
        raise BonesimError("no ADU100 connected (looked for USB id 0a07:0064"
                           + (f", serial {self.want_serial}" if self.want_serial else "") + ")")

    def command(self, text: str) -> None:
        """Send an ASCII command."""
        self._dev.write(EP_OUT, encode_command(text), self.timeout_ms)

    def answer(self) -> int:
        """Read the answer a command queued."""
        return decode_answer(self._dev.read(EP_IN, PACKET, self.timeout_ms))

    def read_counts(self) -> np.ndarray:
        """Read every channel now (blocking; the poller and calibration use it)."""
        out = np.empty(len(self.channels))
        for i, ch in enumerate(self.channels):
            self.command(f"RUN{ch}{self.gain}")
            out[i] = self.answer()
        return out

    def _stored_calibration(self) -> None:
        """The user's calibration of this box (by serial number), unless the
        one given is for it."""
        if self.calibration is not None and \
                self.calibration.get("serial", self.serial) == self.serial:
            return
        from bonesim.devices.config import calibration

        cal = calibration("adu100-handle", self.serial)
        if cal is not None:
            self.calibration = self._checked(cal)

    def open(self, poll: bool = True) -> None:
        """Find the box (again after an unplug), claim it and (``poll``)
        start the poller."""
        usb = _usb()
        self.close()
        dev, self.serial = self._find()
        self._stored_calibration()
        try:
            try:
                if dev.is_kernel_driver_active(0):
                    dev.detach_kernel_driver(0)
            except (NotImplementedError, usb.core.USBError):
                pass
            dev.set_configuration()
            usb.util.claim_interface(dev, 0)
        except usb.core.USBError as exc:
            raise BonesimError(f"ADU100 found but cannot be opened ({exc}); check the "
                               "permissions of its USB device node") from exc
        self._dev = dev
        self.counts[:] = self.read_counts()    # one reading before the loop relies on it
        self.reads = 1
        self._error = None
        if not poll:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._poll_forever, name="adu100-poller",
                                        daemon=True)
        self._thread.start()

    def _poll_forever(self) -> None:
        usb = _usb()
        while not self._stop.is_set():
            try:
                c = self.read_counts()
            except usb.core.USBTimeoutError:
                continue                       # try again; the latest counts stand
            except (usb.core.USBError, ValueError, AttributeError) as exc:
                gone = getattr(exc, "errno", None) in (errno.ENODEV, errno.EIO, errno.EPIPE)
                self._error = ("unplugged" if gone else "failed") + f": {exc}"
                return
            self.counts[:] = c
            self.reads += 1

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(1.0)
        self._thread = None
        if self._dev is not None:
            usb = _usb()
            try:
                usb.util.dispose_resources(self._dev)
            except Exception:                  # noqa: BLE001 - it may be gone
                pass
            self._dev = None

    # ------------------------------------------------------- readings
    @property
    def angles(self) -> np.ndarray:
        """Angles of the channels [deg] (NaN without a calibration)."""
        if self.calibration is None:
            return np.full(len(self.channels), math.nan)
        return angles_deg(self.calibration, self.counts)

    def readings_into(self, angles, counts) -> None:
        """The latest counts and their angles [deg] (as :attr:`angles`) written
        into ``angles`` and ``counts`` (equal length arrays; entries past the
        channels, and angles without a calibration, are NaN), allocating no
        array (the haptic loop records them: :mod:`bonesim.runtime.handle_stream`)."""
        angles[:] = math.nan
        counts[:] = math.nan
        cal = self.calibration
        for i in range(min(len(self.channels), len(counts))):
            c = float(self.counts[i])
            counts[i] = c
            if cal is not None:
                o, od = cal["open"][i], cal["open_deg"][i]
                angles[i] = od + (c - o) / (cal["closed"][i] - o) * (cal["closed_deg"][i] - od)

    def lever_fraction(self) -> float:
        """How far the lever is closed: 0 open, 1 closed (clipped)."""
        if self.calibration is None or not self.counts[0] == self.counts[0]:
            return 0.0
        o, c = self.calibration["open"][0], self.calibration["closed"][0]
        return float(min(1.0, max(0.0, (self.counts[0] - o) / (c - o))))

    def poll(self, t_s: float) -> tuple:
        """``(drill, speed_rpm)`` from the lever (the pedal interface).

        Raises
        ------
        DeviceDisconnected
            The poller lost the box.
        """
        if self._error is not None or self._dev is None:
            raise DeviceDisconnected(f"ADU100: {self._error or 'not open'}")
        f = self.lever_fraction()
        on = f >= self.on_fraction
        if not on:
            self.released = True
        return on, (self.max_speed * f if on else None)


DEVICE = ADU100Handle
