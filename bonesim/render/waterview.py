"""Irrigation water on screen: the pools' surfaces as a translucent sheet.

The water (:mod:`bonesim.physics.dust.water`) is drawn like the dust
(:mod:`bonesim.render.dustview`: depth-tested, alpha-blended round sprites
facing the camera, one per cell of the water's top layer) but larger, so
that neighbouring sprites merge into a continuous sheet over a pool, and in
a pale blue that lets the wet dust and the cavity floor show through.
:func:`water_style` gives the look :class:`WaterLayer` uses.
"""
from __future__ import annotations

from types import SimpleNamespace

from bonesim.render.dustview import DustLayer

__all__ = ["WATER_RGB", "WATER_RADIUS_CELLS", "WATER_OPACITY", "water_style", "WaterLayer"]

#: Colour of the water sheet (clear irrigation fluid seen over bone).
WATER_RGB = (0.22, 0.52, 0.95)
#: Sprite radius per cell edge for a full cell [cell edges]: > 1/2, so a
#: pool's sprites overlap into one sheet.
WATER_RADIUS_CELLS = 1.0
#: Peak opacity of a full cell's sprite [-].
WATER_OPACITY = 0.6


def water_style() -> SimpleNamespace:
    """The sprite look of water in the fields of the render style's
    ``[dust]`` table (:func:`bonesim.render.dustview.sprite_look`); water
    does not fade with age."""
    return SimpleNamespace(dry_rgb=WATER_RGB, wet_rgb=WATER_RGB,
                           radius_cells=WATER_RADIUS_CELLS, opacity=WATER_OPACITY,
                           wet_opacity=1.0, fade_s=1.0, aged=1.0)


class WaterLayer(DustLayer):
    """The water actor of a scene (a :class:`DustLayer` with the water's look).

    Parameters
    ----------
    renderer : vtkRenderer
    """

    def __init__(self, renderer):
        super().__init__(renderer, water_style())
