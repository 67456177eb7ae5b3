"""The simulated hand (:class:`~bonesim.devices.simulated_hand.SimulatedHandDevice`)
as a registered backend: ``bonesim run --device simulated-hand`` exercises the
whole real-device path (safety layer, header, replay) without hardware."""
from __future__ import annotations

from bonesim.devices.simulated_hand import SIM_HAND_CAPS, SimulatedHandDevice
from bonesim.errors import BonesimError

__all__ = ["CAPS", "NEEDS", "SETTINGS", "START_KEY", "library_missing", "connected", "DEVICE"]

CAPS = SIM_HAND_CAPS
NEEDS = "nothing (a simulated hand)"
#: Settings keys (``[devices.simulated-hand]``) and their meaning.
SETTINGS = {"rest_mm": "where the hand rests, case frame [mm] (3 numbers)"}
#: The setting that places the hand where the tool starts.
START_KEY = "rest_mm"


def library_missing() -> str | None:
    return None


def connected() -> list[str]:
    return ["simulated hand"]


class SimulatedHandBackend(SimulatedHandDevice):
    """The simulated hand, built from settings (``rest_mm``)."""

    def __init__(self, settings: dict | None = None, calibration: dict | None = None):
        settings = dict(settings or {})
        unknown = sorted(set(settings) - set(SETTINGS))
        if unknown:
            raise BonesimError(f"unknown setting(s) {unknown}; known: {sorted(SETTINGS)}",
                               field="devices.simulated-hand")
        rest = settings.get("rest_mm", (0.0, 0.0, 0.0))
        if len(rest) != 3:
            raise BonesimError("rest_mm must be 3 numbers [mm]",
                               field="devices.simulated-hand.rest_mm")
        super().__init__(rest_mm=[float(x) for x in rest])
        self.settings = settings
        self.calibration = calibration


DEVICE = SimulatedHandBackend
