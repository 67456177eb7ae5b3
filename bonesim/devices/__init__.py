"""Haptic and input devices: one interface, one module per backend.

:mod:`~bonesim.devices.interface` declares what every backend implements
(``caps`` in units, ``open``, ``read``, ``write_force``, ``close``);
:mod:`~bonesim.devices.null`, :mod:`~bonesim.devices.scripted`,
:mod:`~bonesim.devices.mouse` (mouse and keyboard with a virtual coupling) and
:mod:`~bonesim.devices.simulated_hand` (the stand-in for a trainee's desk
device) are the backends that need no hardware. Backends of real devices
import their SDKs lazily, inside their own module.
"""

__all__: list[str] = []
