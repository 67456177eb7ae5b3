"""The devices of a tutoring session: the instructor's hand (``tutor serve
--device``) and the trainee's driven device (``tutor join --device``,
``tutor playback --device``).

Both come from the device registry (:mod:`bonesim.devices.registry`, the
backends ``bonesim run --device`` takes) and are probed for their own
record, as ``run`` does. The instructor's goes to the haptic loop as
``("device", backend)``, which puts it behind the safety layer
(:class:`~bonesim.devices.safety.SafeDevice`: safe start, force limits,
bad samples, unplugging) with the mouse as fallback. The trainee's is put
behind the same :class:`~bonesim.devices.safety.SafeDevice` here, with no
fallback (an unplugged trainee device holds its last pose and gets no
force) and a safe start that waits for a still stylus but not for a small
commanded force (the law pulls toward a moving instructor: that force may
never be small); the force then ramps in over the layer's ramp time. Each
side's :func:`~bonesim.devices.registry.device_record` is what
its session header (or summary) keeps.
"""
from __future__ import annotations

import numpy as np

from bonesim.errors import BonesimError

__all__ = ["case_frame", "instructor_backend", "trainee_device"]

#: The tool starts this far in front of the camera's focal point [mm]
#: (as the simulator's window places it).
START_STANDOFF_MM = 25.0


def case_frame(case) -> tuple:
    """``(start_mm, view)`` for a case: where the tool starts [mm] and the
    case-frame directions of the screen's right, up and toward the eye (3
    rows), as the simulator's window gives them to a backend."""
    cam = case.camera
    view = np.subtract(cam.focal_mm, cam.eye_mm).astype(float)
    view /= np.linalg.norm(view)
    start = np.asarray(cam.focal_mm, float) - START_STANDOFF_MM * view
    back = -view
    right = np.cross(view, cam.up)
    right /= np.linalg.norm(right)
    return start, (right, np.cross(back, right), back)


def _backend(name: str, start_mm, view, who: str):
    from bonesim.devices.registry import AUXILIARY, BACKENDS, device_record, make_device, probe

    if name in BACKENDS and BACKENDS[name][0] is None:          # the mouse
        raise BonesimError(f"{who}: the mouse drives the tool only in the window",
                           field="--device")
    if name in AUXILIARY:
        raise BonesimError(f"{name!r} is no pose device (it goes with one)", field="--device")
    dev = make_device(name, start_mm=start_mm, view=view)     # unknown names: one line
    probe(name, dev)                                          # the device's own record
    return dev, device_record(name, dev)


def instructor_backend(name: str, case):
    """The instructor's device ``name`` for ``case``: ``(backend, record)``;
    the haptic loop puts it behind the safety layer (``("device", backend)``).

    Raises
    ------
    BonesimError
        An unknown backend, the mouse (window only), a pedal, a missing
        library or device: one line naming ``--device``.
    """
    start, view = case_frame(case)
    return _backend(name, start, view, "tutor serve --device mouse")


def trainee_device(name: str, start_mm, case):
    """The trainee's device ``name`` behind the safety layer, opened, its
    origin at ``start_mm`` (the instructor's tool when the trainee joins,
    case frame [mm]): ``(SafeDevice, record)``.

    Raises
    ------
    BonesimError
        As :func:`instructor_backend`; also a device that renders no force
        (the SpaceMouse): the trainee's device must be driven.
    """
    import math

    from bonesim.devices.safety import SafeDevice, SafetyLimits

    _, view = case_frame(case)
    dev, record = _backend(name, np.asarray(start_mm, float), view,
                           "tutor join --device mouse")
    if not math.isfinite(dev.caps.max_force_n):
        raise BonesimError(f"the trainee device {name!r} renders no force; tutoring drives "
                           "the trainee's device (a Touch, or the simulated hand)",
                           field="--device")
    # the safe start waits for a still stylus only: the law's force pulls
    # toward a moving instructor (it may never be small), and ramps in over
    # ramp_s (with the link gain's own fade-in)
    limits = SafetyLimits(start_force_n=math.inf)
    safe = SafeDevice(dev, limits=limits)
    safe.open()
    return safe, record
