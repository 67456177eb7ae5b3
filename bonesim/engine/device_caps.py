"""What a device can do, in physical units: the record the engine's
:class:`~bonesim.engine.model.Model` holds, apart from the device backends
(:mod:`bonesim.devices`) so that the engine needs none of them."""
from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["DeviceCaps", "SCRIPTED"]


@dataclass(frozen=True)
class DeviceCaps:
    """What a device can do, in physical units.

    Attributes
    ----------
    name : str
        Backend name.
    max_force_n : float
        Largest continuous force the device can render [N] (``inf`` if it
        renders none, e.g. a scripted trajectory).
    workspace_mm : tuple of 3 float
        Usable translation range along x, y, z [mm].
    max_stiffness_n_per_mm : float
        Largest stable virtual stiffness [N/mm].
    rate_hz : float
        Nominal servo rate [Hz].
    """

    name: str
    max_force_n: float
    workspace_mm: tuple
    max_stiffness_n_per_mm: float
    rate_hz: float = 1000.0

    def __post_init__(self):
        if not self.max_force_n > 0:
            raise ValueError(f"device {self.name}: max_force_n must be positive")
        if not self.max_stiffness_n_per_mm > 0:
            raise ValueError(f"device {self.name}: max_stiffness_n_per_mm must be positive")
        if len(self.workspace_mm) != 3 or min(self.workspace_mm) <= 0:
            raise ValueError(f"device {self.name}: workspace_mm must be 3 positive lengths")


#: A trajectory or script drives the tool: no force limit beyond the burr's.
SCRIPTED = DeviceCaps("scripted", math.inf, (math.inf, math.inf, math.inf), math.inf)
