"""A stand-in for the hidapi binding (``import hid``): ``enumerate`` and a
``device`` class with the binding's methods, over a bus of fake devices
whose input reports the test queues (recorded report bytes) and which can
be unplugged and plugged back in.

Behaviour copied from the binding (cython-hidapi): ``read`` on a device not
opened raises ``ValueError``; a failed open or read raises ``OSError``;
non-blocking ``read`` returns ``[]`` when no report is pending; reports come
back as lists of ints, truncated to ``max_length``.
"""
from __future__ import annotations

import sys
import types
from collections import deque
from contextlib import contextmanager

__all__ = ["FakeBus", "install", "installed"]


class FakeDev:
    def __init__(self, path: bytes, vid: int, pid: int, serial: str, product: str,
                 manufacturer: str):
        self.path, self.vid, self.pid = path, vid, pid
        self.serial, self.product, self.manufacturer = serial, product, manufacturer
        self.queue: deque = deque()
        self.plugged = True


class FakeBus:
    """The devices on the fake USB bus."""

    def __init__(self):
        self.devs: dict = {}
        self.opens = 0
        self.calls: list = []

    def plug(self, path: bytes, vid: int, pid: int, serial: str = "S0",
             product: str = "device", manufacturer: str = "maker") -> FakeDev:
        d = self.devs.get(path)
        if d is None:
            d = self.devs[path] = FakeDev(path, vid, pid, serial, product, manufacturer)
        d.plugged = True
        return d

    def unplug(self, path: bytes) -> None:
        self.devs[path].plugged = False
        self.devs[path].queue.clear()

    def send(self, path: bytes, *reports) -> None:
        """Queue input reports (bytes or lists of ints)."""
        for r in reports:
            self.devs[path].queue.append(list(bytes(r)))

    # ---------------------------------------------------------- binding
    def enumerate(self, vendor_id: int = 0, product_id: int = 0) -> list:
        self.calls.append("enumerate")
        return [{"path": d.path, "vendor_id": d.vid, "product_id": d.pid,
                 "serial_number": d.serial, "release_number": 0x100,
                 "manufacturer_string": d.manufacturer, "product_string": d.product,
                 "usage_page": 1, "usage": 8, "interface_number": 0}
                for d in self.devs.values() if d.plugged
                and vendor_id in (0, d.vid) and product_id in (0, d.pid)]

    def module(self):
        bus = self

        class device:                                   # noqa: N801 - the binding's name
            def __init__(self):
                self._d = None
                self._nonblocking = 0

            def open(self, vendor_id=0, product_id=0, serial_number=None):
                for d in bus.devs.values():
                    if d.plugged and (d.vid, d.pid) == (vendor_id, product_id) and \
                            serial_number in (None, d.serial):
                        self._d = d
                        bus.opens += 1
                        return
                raise OSError("open failed")

            def open_path(self, path):
                d = bus.devs.get(path)
                if d is None or not d.plugged:
                    raise OSError("open failed")
                self._d = d
                bus.opens += 1

            def set_nonblocking(self, v):
                self._check()
                self._nonblocking = int(v)
                return 0

            def _check(self):
                if self._d is None:
                    raise ValueError("not open")

            def read(self, max_length, timeout_ms=0):
                self._check()
                if not self._d.plugged:
                    raise OSError("read error")
                if not self._d.queue:
                    if not self._nonblocking and timeout_ms == 0:
                        raise AssertionError("a blocking read would hang the servo loop")
                    return []
                return self._d.queue.popleft()[:max_length]

            def write(self, buff):
                self._check()
                if not self._d.plugged:
                    raise OSError("write error")
                return len(buff)

            def get_manufacturer_string(self):
                self._check()
                return self._d.manufacturer

            def get_product_string(self):
                self._check()
                return self._d.product

            def get_serial_number_string(self):
                self._check()
                return self._d.serial

            def close(self):
                self._d = None

        mod = types.ModuleType("hid")
        mod.device = device
        mod.enumerate = self.enumerate
        mod.version_str = "fake"
        return mod


def install(monkeypatch) -> FakeBus:
    """Put a fresh fake bus's ``hid`` module in ``sys.modules`` (a pytest
    ``monkeypatch`` undoes it)."""
    bus = FakeBus()
    monkeypatch.setitem(sys.modules, "hid", bus.module())
    return bus


@contextmanager
def installed():
    """A fresh fake bus's ``hid`` module in ``sys.modules`` while in the block."""
    bus = FakeBus()
    before = sys.modules.get("hid")
    sys.modules["hid"] = bus.module()
    try:
        yield bus
    finally:
        if before is None:
            sys.modules.pop("hid", None)
        else:
            sys.modules["hid"] = before
