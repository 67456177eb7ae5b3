"""Faithful stand-ins for device hardware at the lowest level each library
offers, for tests and benchmarks without hardware:

:mod:`~bonesim.devices.standins.hid_bus`
    a stand-in for the hidapi binding (``import hid``) over a bus of fake
    HID devices fed recorded report bytes;
:mod:`~bonesim.devices.standins.adu100_usb`
    a pyusb backend (``usb.backend.IBackend``) with an Ontrak ADU100 that
    answers its ASCII commands at the transfer level;
:mod:`~bonesim.devices.standins.hd_library`
    builds ``hd_stub.c``, a stub of the OpenHaptics HD library's C functions
    over a simulated arm, into a shared library (needs a C compiler).
"""

__all__: list[str] = []
