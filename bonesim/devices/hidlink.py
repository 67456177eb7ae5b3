"""USB HID devices through hidapi (the ``hid`` module of the ``hidapi``
package, imported lazily): matching by vendor/product id, opening by path,
draining pending input reports without blocking, and hot-plug (a failed
read is an unplug; opening again enumerates again).

:class:`HidLink` is shared by the HID backends (:mod:`bonesim.devices.spacemouse`,
:mod:`bonesim.devices.pedal`); it uses only what the binding offers:
``hid.enumerate``, ``hid.device()`` with ``open_path``, ``set_nonblocking``,
``read``, ``close`` and ``get_manufacturer_string`` / ``get_product_string``.
"""
from __future__ import annotations

from bonesim.devices.interface import DeviceDisconnected
from bonesim.errors import BonesimError

__all__ = ["HID_INSTALL", "NEEDS_HID", "MAX_REPORT_BYTES", "MAX_REPORTS_PER_READ", "hid_module",
           "hid_missing", "matching", "HidLink"]

#: What to install when ``import hid`` fails.
HID_INSTALL = ("hidapi not importable: pip install hidapi (and the system's libhidapi "
               "or libusb; on Linux a udev rule giving your user access to /dev/hidraw*)")
#: What every HID backend needs besides its device.
NEEDS_HID = "the hidapi Python package (pip install hidapi) and read access to /dev/hidraw*"
#: Longest input report read [bytes].
MAX_REPORT_BYTES = 64
#: Most reports drained in one servo tick (a bound on the time spent).
MAX_REPORTS_PER_READ = 32


def hid_module():
    """The hidapi binding (``import hid``)."""
    try:
        import hid
    except ImportError as exc:
        raise BonesimError(HID_INSTALL) from exc
    return hid


def hid_missing() -> str | None:
    try:
        hid_module()
    except BonesimError as exc:
        return str(exc)
    return None


def matching(models: dict) -> list[dict]:
    """Enumerated HID devices whose ``(vendor_id, product_id)`` is a key of
    ``models``; each dict as ``hid.enumerate`` gives it, plus ``model``."""
    hid = hid_module()
    out = []
    for d in hid.enumerate(0, 0):
        key = (int(d["vendor_id"]), int(d["product_id"]))
        if key in models:
            out.append({**d, "model": models[key]})
    return out


class HidLink:
    """One HID device of a set of models, opened by path, read without blocking.

    Parameters
    ----------
    models : dict
        ``(vendor_id, product_id) -> model`` (anything; the backend's spec).
    what : str
        Name in messages (``SpaceMouse``).
    serial : str, optional
        Open only the device with this serial number.

    Attributes
    ----------
    model :
        The matched model's spec (after :meth:`open`).
    info : dict
        Its enumeration record.
    """

    def __init__(self, models: dict, what: str, serial: str | None = None):
        self.models = models
        self.what = what
        self.serial = serial
        self.dev = None
        self.model = None
        self.info: dict = {}

    def open(self) -> None:
        """Enumerate and open the first matching device (again after an unplug).

        Raises
        ------
        BonesimError
            None is connected (naming the models looked for), or it cannot be opened.
        """
        self.close()
        hid = hid_module()
        found = [d for d in matching(self.models)
                 if self.serial is None or d.get("serial_number") == self.serial]
        if not found:
            ids = ", ".join(f"{v:04x}:{p:04x}" for v, p in self.models)
            raise BonesimError(f"no {self.what} connected (looked for USB ids {ids}"
                               + (f", serial {self.serial}" if self.serial else "") + ")")
        d = found[0]
        dev = hid.device()
        try:
            dev.open_path(d["path"])
            dev.set_nonblocking(1)
        except (OSError, ValueError) as exc:
            try:
                dev.close()
            except Exception:                  # noqa: BLE001
                pass
            raise BonesimError(f"{self.what} {d['vendor_id']:04x}:{d['product_id']:04x} found "
                               f"but cannot be opened ({exc}); check the permissions of its "
                               "/dev/hidraw node") from exc
        self.dev = dev
        self.model = d["model"]
        self.info = {k: d.get(k) for k in ("vendor_id", "product_id", "serial_number",
                                           "product_string", "manufacturer_string")}
        try:
            self.info["product_string"] = dev.get_product_string() or self.info["product_string"]
            self.info["manufacturer_string"] = (dev.get_manufacturer_string()
                                                or self.info["manufacturer_string"])
        except OSError:
            pass

    def reports(self) -> list:
        """Every input report pending now (lists of ints), oldest first.

        Raises
        ------
        DeviceDisconnected
            The read failed (the device went away).
        """
        if self.dev is None:
            raise DeviceDisconnected(f"{self.what}: not open")
        out = []
        try:
            for _ in range(MAX_REPORTS_PER_READ):
                r = self.dev.read(MAX_REPORT_BYTES)
                if not r:
                    break
                out.append(r)
        except (OSError, ValueError) as exc:
            self.close()
            raise DeviceDisconnected(f"{self.what}: read failed ({exc})") from exc
        return out

    def close(self) -> None:
        if self.dev is not None:
            try:
                self.dev.close()
            except Exception:                      # noqa: BLE001 - it may be gone
                pass
            self.dev = None
