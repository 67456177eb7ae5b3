"""Which device backends exist, what each needs, and which are connected.

Every backend but the mouse is one module beside this one; it is imported
only when asked about (:func:`backend_module`), and it imports its SDK only
inside its functions, so listing backends needs no hardware and no SDK. A
backend module provides:

``CAPS``
    its :class:`~bonesim.engine.device_caps.DeviceCaps` (the default; a device
    may report its own when opened);
``NEEDS``
    one line: the library and the hardware it needs;
``library_missing() -> str | None``
    None if its library imports, else one line naming what to install;
``connected() -> list of str``
    the devices of its kind plugged in now (empty without the library);
``DEVICE``
    the class, constructed as ``DEVICE(settings: dict, calibration: dict | None)``;
``READS_OWN_RECORD`` (optional)
    True if the device replaces ``CAPS`` (or its calibration) with its own
    when opened (:func:`probe` reads them before a run).

:func:`make_device` builds a backend with the user's settings and
calibration (:mod:`bonesim.devices.config`); :func:`device_record` is what a
session header keeps of it.
"""
from __future__ import annotations

import importlib
import math

from bonesim.devices import config as _config
from bonesim.errors import BonesimError

__all__ = ["DEFAULT_DEVICE", "BACKENDS", "AUXILIARY", "backend_names", "backend_module", "describe",
           "make_device", "device_caps", "device_record", "probe"]

#: The device ``bonesim run`` uses unless told otherwise.
DEFAULT_DEVICE = "mouse"
#: Backend name -> (module, what it is).
BACKENDS = {
    "mouse": (None, "mouse and keyboard (the default; the window drives the tool)"),
    "simulated-hand": ("bonesim.devices.simulated_backend",
                       "a simulated passive hand on a Touch-class arm (no hardware)"),
    "spacemouse": ("bonesim.devices.spacemouse",
                   "3Dconnexion SpaceMouse: 6-DOF rate input for the tool (button 1: camera)"),
    "touch": ("bonesim.devices.openhaptics",
              "3D Systems Touch / Phantom Omni through OpenHaptics: pose in, force out"),
    "pedal": ("bonesim.devices.pedal",
              "USB foot pedal: drill on/off and speed (bonesim run --pedal)"),
    "adu100-handle": ("bonesim.devices.adu100",
                      "instrumented handle on an Ontrak ADU100: the lever drives the drill "
                      "(bonesim run --pedal adu100-handle)"),
}
#: Backends that are no pose device (they go with one: ``--pedal``).
AUXILIARY = ("pedal", "adu100-handle")


def backend_names() -> list[str]:
    return list(BACKENDS)


def _check(name: str) -> None:
    if name not in BACKENDS:
        raise BonesimError(f"unknown device {name!r}; known: {', '.join(BACKENDS)}",
                           field="--device")


def backend_module(name: str):
    """The backend's module (imported now; its SDK is not)."""
    _check(name)
    mod = BACKENDS[name][0]
    if mod is None:
        raise BonesimError(f"device {name!r} is built into the window, not a backend module")
    return importlib.import_module(mod)


def describe(name: str) -> dict:
    """What ``bonesim devices`` says of a backend: ``name``, ``what``,
    ``needs``, ``library`` (``ok`` or what to install) and ``connected``."""
    _check(name)
    if BACKENDS[name][0] is None:
        return {"name": name, "what": BACKENDS[name][1], "needs": "nothing",
                "library": "ok", "connected": ["always"]}
    m = backend_module(name)
    missing = m.library_missing()
    try:
        found = [] if missing else list(m.connected())
    except Exception as exc:                   # noqa: BLE001 - a listing must not fail
        found = [f"(cannot enumerate: {exc})"]
    return {"name": name, "what": BACKENDS[name][1], "needs": m.NEEDS,
            "library": missing or "ok", "connected": found}


def make_device(name: str, settings: dict | None = None, calibration: dict | None = None,
                device_id: str = "default", start_mm=None, view=None,
                pedal_ok: bool = False):
    """A backend instance with ``settings`` (default: the user's
    ``[devices.NAME]``) and ``calibration`` (default: the stored one).
    ``start_mm``: where the tool starts (case frame [mm]), given to backends
    that place their pose (module attribute ``START_KEY``, a settings key)
    unless the settings place it. ``pedal_ok``: allow an auxiliary backend
    (:data:`AUXILIARY`). ``view``: 3 rows, the case-frame directions
    of the screen's right, up and toward the eye, given to backends that map
    their axes to the view (``FRAME_KEY``) unless the settings map them."""
    m = backend_module(name)
    if name in AUXILIARY and not pedal_ok:
        raise BonesimError(f"{name!r} is no pose device; it goes with one "
                           f"(bonesim run --{name})", field="--device")
    if settings is None or calibration is None:
        cfg = _config.load_config()
        if settings is None:
            settings = _config.device_settings(name, cfg)
        if calibration is None:
            device_id = str(settings.get("serial") or device_id)
            calibration = _config.calibration(name, device_id, cfg)
    missing = m.library_missing()
    if missing:
        raise BonesimError(f"device {name!r}: {missing}")
    key = getattr(m, "START_KEY", None)
    if start_mm is not None and key is not None and key not in settings:
        settings = {**settings, key: [float(x) for x in start_mm]}
    key = getattr(m, "FRAME_KEY", None)
    if view is not None and key is not None and key not in settings:
        settings = {**settings, key: [[float(x) for x in row] for row in view]}
    return m.DEVICE(dict(settings), calibration)


def device_caps(name: str):
    """The backend's default capability record."""
    if BACKENDS.get(name, (0,))[0] is None:
        from bonesim.engine.device_caps import SCRIPTED

        _check(name)
        return SCRIPTED
    return backend_module(name).CAPS


def _finite(x):
    x = float(x)
    return x if math.isfinite(x) else None


def device_record(name: str, device=None) -> dict:
    """What a session header keeps of the input device: backend name, its
    capability record in units, settings and calibration (JSON-ready)."""
    caps = getattr(device, "caps", None)
    if caps is None and name not in AUXILIARY:
        caps = device_caps(name)
    return {"backend": name,
            "caps": None if caps is None else {
                "name": caps.name, "max_force_n": _finite(caps.max_force_n),
                "workspace_mm": [_finite(x) for x in caps.workspace_mm],
                "max_stiffness_n_per_mm": _finite(caps.max_stiffness_n_per_mm),
                "rate_hz": float(caps.rate_hz)},
            "settings": dict(getattr(device, "settings", {}) or {}),
            "calibration": getattr(device, "calibration", None)}


def probe(name: str, device) -> bool:
    """Give ``device`` the record the hardware reports, before a run.

    A backend whose device reads its own record when opened (module
    attribute ``READS_OWN_RECORD``: the Touch's maximum continuous force,
    stiffness and workspace; the ADU100 handle's calibration, stored under
    the box's serial number) is opened once here, through a twin built from
    the same settings and calibration, and closed again; ``device.caps`` and
    ``device.calibration`` become the twin's. The haptic loop opens
    ``device`` itself later, in its own process, after the session header
    and the model (whose limits the physics is built with) must exist:
    probing first puts the record the run uses in both. The loop publishes
    the capability record it opened with (``status["device_caps"]``).

    Returns
    -------
    bool
        Whether the device was probed (False for backends with a fixed record).

    Raises
    ------
    BonesimError
        The device is not there (its backend's message).
    """
    if BACKENDS.get(name, (None,))[0] is None or \
            not getattr(backend_module(name), "READS_OWN_RECORD", False):
        return False
    twin = type(device)(dict(getattr(device, "settings", {}) or {}),
                        getattr(device, "calibration", None))
    twin.open()
    try:
        if hasattr(twin, "caps"):
            device.caps = twin.caps
        device.calibration = twin.calibration
    finally:
        twin.close()
    return True
