"""The dust model's constants (:class:`DustParams`), checked on creation.

Used by :class:`bonesim.physics.dust.DustGrid`; the rules that use them are in
:mod:`bonesim.physics.dust.rules`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["DustParams"]


@dataclass(frozen=True)
class DustParams:
    """Constants of the dust model.

    Attributes
    ----------
    bulking : float
        Dust volume per volume of bone removed [-]: one removed voxel becomes
        ``bulking`` cells of dust. Drilled bone leaves chips and powder that
        pack loosely (roughly 35-45 % voids), so 1.6 by default.
    settle_rate : float
        Most dust that gravity moves across one cell face per second
        [cells/s].
    spill_rate : float
        Fraction of the excess density difference a supported cell passes to
        a lateral neighbour per second [1/s] (at most 0.2 per step).
    repose : float
        Density difference between side-by-side cells that stands without
        spilling [cells], in ``[0, 1)``: the steepness of piles.
    suction_rate : float
        Default suction rate: dust removed per second from each cell within
        the suction radius [cells/s].
    push_search : int
        How many cells beyond the tool surface the push looks for a free
        cell [cells].
    split_gravity : bool
        Share gravity among the axes by the components of ``g`` (True), or
        move dust along the dominant axis only (False).
    sprite_threshold : float
        Cells with more dust than this are rendered [cells].
    sprite_cover : float
        A cell whose neighbour above holds at least this much dust is
        covered and not rendered (:meth:`DustGrid.sprites` ``top_only``)
        [cells].
    sprite_jitter : float
        Largest offset of a sprite from its cell centre along each axis
        [cell edges], in ``[0, 0.5]``.
    wet_settle_rate, wet_spill_rate : float
        ``settle_rate`` and ``spill_rate`` of wet dust [cells/s], [1/s]:
        a paste runs faster than dry chips.
    wet_repose : float
        ``repose`` of wet dust [cells]: 0, it spreads flat.
    wetting_rate : float
        Dry dust turned wet per second in each cell within the irrigation
        radius [cells/s].
    initial_bricks : int
        Size of the brick pool at construction (it grows as needed).
    water_flow_mm3_s : float
        Irrigation water poured per second [mm^3/s] (about 0.9 mL/min;
        :mod:`bonesim.physics.dust.water`).
    water_settle_rate : float
        Most water gravity moves across one cell face per second [cells/s].
    water_spread_rate : float
        Fraction of the water-level difference a supported cell passes to a
        lateral neighbour per second [1/s] (at most 0.2 per step).
    water_suction_rate : float
        Water suction takes per second from each cell in reach [cells/s].
    soak_water : float
        Water a cell must hold for its dry dust to soak [cells].
    """

    bulking: float = 1.6
    settle_rate: float = 40.0
    spill_rate: float = 40.0
    repose: float = 0.5
    suction_rate: float = 200.0
    push_search: int = 3
    split_gravity: bool = True
    sprite_threshold: float = 0.02
    sprite_cover: float = 0.5
    sprite_jitter: float = 0.4
    wet_settle_rate: float = 120.0
    wet_spill_rate: float = 200.0
    wet_repose: float = 0.0
    wetting_rate: float = 50.0
    initial_bricks: int = 64
    water_flow_mm3_s: float = 15.0
    water_settle_rate: float = 400.0
    water_spread_rate: float = 100.0
    water_suction_rate: float = 600.0
    soak_water: float = 0.05

    def __post_init__(self):
        for name in ("bulking", "settle_rate", "spill_rate", "suction_rate",
                     "sprite_threshold", "sprite_cover", "wet_settle_rate",
                     "wet_spill_rate", "wetting_rate", "water_flow_mm3_s",
                     "water_settle_rate", "water_spread_rate", "water_suction_rate",
                     "soak_water"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"DustParams.{name} must be finite and >= 0, got {v}")
        for name in ("repose", "wet_repose"):
            v = getattr(self, name)
            if not (0.0 <= v < 1.0):
                raise ValueError(f"DustParams.{name} must lie in [0, 1), got {v}")
        if not (0.0 <= self.sprite_jitter <= 0.5):
            raise ValueError(f"DustParams.sprite_jitter must lie in [0, 0.5], "
                             f"got {self.sprite_jitter}")
        if int(self.push_search) != self.push_search or self.push_search < 1:
            raise ValueError(f"DustParams.push_search must be a positive integer, "
                             f"got {self.push_search}")
        if int(self.initial_bricks) != self.initial_bricks or self.initial_bricks < 1:
            raise ValueError("DustParams.initial_bricks must be a positive integer")
