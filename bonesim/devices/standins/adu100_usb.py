"""A pyusb backend (``usb.backend.IBackend``) that stands in for libusb with
an Ontrak ADU100 on the bus, so that pyusb's own Python code (``usb.core``,
``usb.util``, ``usb.control``) runs over it.

The box answers at the transfer level as the real one does: descriptors (a
low-speed HID-class device 0a07:0064, one configuration, interface 0 with
interrupt IN 0x81 and OUT 0x01 of 8 bytes, string descriptors for the
serial number), and 8-byte interrupt packets: ``0x01`` + an ASCII command
(``RUN<ch><gain>`` reads analog input ``ch``) + zero padding; a read
command queues an answer ``0x01`` + zero-padded decimal digits, which the
next interrupt IN transfer returns (a timeout when none is queued). An
unplugged box fails every transfer with ENODEV, as libusb's backend does.
"""
from __future__ import annotations

import errno
import threading
from collections import deque
from types import SimpleNamespace

import usb.backend
import usb.core

__all__ = ["FakeADU100", "FakeUsbBackend"]

LANGID_EN_US = 0x0409


class FakeADU100:
    """One ADU100: ``analog[ch]`` (counts, or a function of the number of
    reads so far) is what ``RUN<ch>x`` answers."""

    def __init__(self, serial: str = "B02597", bus: int = 1, address: int = 17):
        self.serial = serial
        self.bus, self.address = bus, address
        self.analog = {0: 0, 1: 0, 2: 0}
        self.answers: deque = deque()
        self.lock = threading.Lock()
        self._plugged = True
        self.commands: list = []
        self.claimed = False

    @property
    def plugged(self) -> bool:
        """Connected; pulling it out loses the answers it held (a box plugged
        back in starts empty, powered up anew)."""
        return self._plugged

    @plugged.setter
    def plugged(self, on: bool) -> None:
        with self.lock:                          # not between a command and its answer
            self._plugged = bool(on)
            if not on:
                self.answers.clear()
                self.claimed = False

    def value(self, ch: int) -> int:
        v = self.analog[ch]
        return int(v() if callable(v) else v)


def _gone():
    return usb.core.USBError("No such device (it may have been disconnected)", -4,
                             errno.ENODEV)


class FakeUsbBackend(usb.backend.IBackend):
    """The stand-in backend: pass it as ``backend=`` to ``usb.core.find``."""

    def __init__(self, *boxes: FakeADU100):
        self.boxes = list(boxes)
        self.transfers = 0

    # --------------------------------------------------------- descriptors
    def enumerate_devices(self):
        return [b for b in self.boxes if b.plugged]

    def get_device_descriptor(self, dev):
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0110, bDeviceClass=0,
            bDeviceSubClass=0, bDeviceProtocol=0, bMaxPacketSize0=8, idVendor=0x0A07,
            idProduct=0x0064, bcdDevice=0x0100, iManufacturer=1, iProduct=2,
            iSerialNumber=3, bNumConfigurations=1, address=dev.address, bus=dev.bus,
            port_number=1, port_numbers=(1,), speed=1)           # low speed

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(config)
        return SimpleNamespace(bLength=9, bDescriptorType=2, wTotalLength=41,
                               bNumInterfaces=1, bConfigurationValue=1, iConfiguration=0,
                               bmAttributes=0x80, bMaxPower=50, extra_descriptors=[])

    def get_interface_descriptor(self, dev, intf, alt, config):
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError((intf, alt, config))
        return SimpleNamespace(bLength=9, bDescriptorType=4, bInterfaceNumber=0,
                               bAlternateSetting=0, bNumEndpoints=2, bInterfaceClass=3,
                               bInterfaceSubClass=0, bInterfaceProtocol=0, iInterface=0,
                               extra_descriptors=[])

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if ep not in (0, 1):
            raise IndexError(ep)
        return SimpleNamespace(bLength=7, bDescriptorType=5,
                               bEndpointAddress=(0x81, 0x01)[ep], bmAttributes=3,
                               wMaxPacketSize=8, bInterval=10, bRefresh=0, bSynchAddress=0,
                               extra_descriptors=[])

    # -------------------------------------------------------------- handles
    def open_device(self, dev):
        if not dev.plugged:
            raise _gone()
        return dev

    def close_device(self, dev_handle):
        pass

    def set_configuration(self, dev_handle, config_value):
        if not dev_handle.plugged:
            raise _gone()

    def get_configuration(self, dev_handle):
        return 1

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        pass

    def claim_interface(self, dev_handle, intf):
        if not dev_handle.plugged:
            raise _gone()
        dev_handle.claimed = True

    def release_interface(self, dev_handle, intf):
        dev_handle.claimed = False

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def detach_kernel_driver(self, dev_handle, intf):
        pass

    def attach_kernel_driver(self, dev_handle, intf):
        pass

    # ------------------------------------------------------------ transfers
    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data,
                      timeout):
        if not dev_handle.plugged:
            raise _gone()
        if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:   # string
            index = wValue & 0xFF
            if index == 0:
                payload = LANGID_EN_US.to_bytes(2, "little")
            else:
                text = {1: "Ontrak Control Systems Inc.", 2: "ADU100",
                        3: dev_handle.serial}.get(index)
                if text is None:
                    raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
                payload = text.encode("utf-16-le")
            desc = bytes([2 + len(payload), 3]) + payload
            n = min(len(desc), len(data))
            data[:n] = type(data)("B", desc[:n])
            return n
        raise usb.core.USBError("Pipe error", -9, errno.EPIPE)

    def intr_write(self, dev_handle, ep, intf, data, timeout):
        with dev_handle.lock:
            return self._intr_write(dev_handle, ep, intf, data)

    def _intr_write(self, dev_handle, ep, intf, data):
        if not dev_handle.plugged:
            raise _gone()
        if ep != 0x01 or intf != 0 or not dev_handle.claimed:
            raise usb.core.USBError("Invalid parameter", -2, errno.EINVAL)
        pkt = bytes(data)
        if len(pkt) != 8 or pkt[0] != 1:
            return len(pkt)                      # the box ignores what it cannot parse
        cmd = pkt[1:].split(b"\0", 1)[0].decode("ascii")
        dev_handle.commands.append(cmd)
        self.transfers += 1
        if cmd.startswith("RUN") and len(cmd) == 5 and cmd[3:].isdigit():
            ch = int(cmd[3])
            if ch in dev_handle.analog:
                text = f"{dev_handle.value(ch):05d}".encode()
                dev_handle.answers.append(bytes([1]) + text + bytes(7 - len(text)))
        return len(pkt)

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        if not dev_handle.plugged:
            raise _gone()
        if ep != 0x81 or intf != 0:
            raise usb.core.USBError("Invalid parameter", -2, errno.EINVAL)
        if not dev_handle.answers:
            raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
        pkt = dev_handle.answers.popleft()
        n = min(len(pkt), len(buff))
        buff[:n] = type(buff)("B", pkt[:n])
        self.transfers += 1
        return n
