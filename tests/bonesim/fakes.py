"""Small in-memory structures, burrs and materials for engine tests.

They carry exactly the fields the engine reads, so kernel tests do not depend
on the shipped data files (those are tested on their own).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from bonesim.engine.haptics_budget import BudgetSettings
from bonesim.engine.model import make_model, make_state


class FakeStructure(NamedTuple):
    name: str
    kind: str
    display_color: tuple = (230, 220, 200)


class FakeBurr(NamedTuple):
    radius_mm: float = 1.5
    r_max: float = 4.0
    falloff: float = 2.0
    k_low: float = 1.0
    k_high: float = 4.0
    n_t_fraction: float = 0.02
    k_tan: float = 0.05
    max_force_n: float = 4.0
    default_speed_rpm: float = 60000.0
    name: str = "fake"


class FakeMaterial(NamedTuple):
    stiffness: float
    removal: float
    injury: bool


MATERIALS = {
    "bone": FakeMaterial(1.0, 1.0, False),
    "critical": FakeMaterial(0.6, 0.5, True),
    "soft": FakeMaterial(0.25, 1.5, True),
}

#: Budget limits that never bind: the per-voxel kernels at any oversampling
#: (the tests of those kernels at 3x and more on 0.5 mm voxels).
NO_BUDGET = BudgetSettings(min_spacing_mm=1e-3, budget_s=1e-3)

BONE = FakeStructure("bone", "bone")
NERVE = FakeStructure("nerve", "critical", (240, 220, 40))


def block_model(shape=(40, 40, 40), fill_z=20, burr=None, spacing=0.5, structures=None,
                labels=None, **kw):
    """A model of a bone block filling ``k < fill_z`` (top surface facing +z)."""
    if labels is None:
        labels = np.zeros(shape, np.uint8)
        labels[:, :, :fill_z] = 1
    structures = [BONE] if structures is None else structures
    m = make_model(labels, spacing, structures, burr or FakeBurr(), materials=MATERIALS, **kw)
    return m, make_state(m)


def wait_for(cond, timeout_s: float = 20.0) -> bool:
    """Poll ``cond()`` every 10 ms until it is true (True) or ``timeout_s``
    passes (False): for state another process changes."""
    import time

    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


def force_tiles(surf, shift: int = 1) -> None:
    """Tile every update of ``surf`` into windows of ``2**shift`` voxels (the
    path of removals spread far apart), so tiles meet everywhere."""
    surf._win_limit = -1
    surf._tile_shift = shift
