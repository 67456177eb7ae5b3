"""The look of the 3D window, read from ``bonesim/data/render.toml``.

Material of the bone and of the structures, the microscope's lights, the
dust sprites, the hidden burr's silhouette, the side panel, the stereo
default and the bone surface's level of detail: every tunable of the picture
lives in that file, documented there (units in the key names, colours RGB
0-1). :func:`load_style` checks every
value and raises :class:`bonesim.errors.BonesimError` naming the file, the
table and the key; :func:`default_style` is the shipped file, read once.

No VTK here.
"""
from __future__ import annotations

import functools
from pathlib import Path
from types import SimpleNamespace

from bonesim.errors import BonesimError
from bonesim.tomlfile import check_keys, get_number, get_str, get_vector, read_toml

__all__ = ["RenderStyle", "load_style", "default_style", "style_path"]

_N, _RGB, _S = "number", "rgb", "str"
# table -> key -> (kind, minimum, maximum)
_SCHEMA = {
    "bone": {"ambient": (_N, 0, 1), "diffuse": (_N, 0, 1), "specular": (_N, 0, 1),
             "specular_power": (_N, 1, 128), "specular_rgb": (_RGB,)},
    "structures": {"ambient": (_N, 0, 1), "diffuse": (_N, 0, 1), "specular": (_N, 0, 1),
                   "specular_power": (_N, 1, 128)},
    "lights": {"headlight_intensity": (_N, 0, 2), "headlight_rgb": (_RGB,),
               "fill_intensity": (_N, 0, 2), "fill_rgb": (_RGB,),
               "fill_elevation_deg": (_N, -90, 90), "fill_azimuth_deg": (_N, -180, 180)},
    "dust": {"dry_rgb": (_RGB,), "wet_rgb": (_RGB,), "radius_cells": (_N, 0.05, 2),
             "opacity": (_N, 0, 1), "wet_opacity": (_N, 0, 1), "fade_s": (_N, 1e-3, 1e6),
             "aged": (_N, 0, 1)},
    "hidden_burr": {"rgb": (_RGB,), "opacity": (_N, 0.05, 1), "min_depth_mm": (_N, 0, 100)},
    "panel": {"width_fraction": (_N, 0.1, 0.5), "min_width_px": (_N, 60, 2000),
              "max_width_px": (_N, 60, 4000), "rgb": (_RGB,), "hint": (_S,)},
    "stereo": {"eye_separation_mm": (_N, 0, 200)},
    "lod": {"max_voxel_px": (_N, 0, 100), "min_triangles": (_N, 0, 1e9),
            "near_mm": (_N, 0, 1000), "coarse_mm": (_N, 0, 1000),
            "coarse_max_voxel_px": (_N, 0, 100), "coarse_min_cos": (_N, -1, 1),
            "coarse_slack_mm": (_N, 0, 1000), "dust_keep_one_in": (_N, 1, 16)},
}


class RenderStyle(SimpleNamespace):
    """The parsed file: one attribute per table (``bone``, ``structures``,
    ``lights``, ``dust``, ``hidden_burr``, ``panel``, ``stereo``, ``lod``), each a
    namespace of its keys (numbers as float, colours as 3-tuples); ``path``
    is the file read."""


def style_path() -> Path:
    """Path of the shipped ``render.toml``."""
    from bonesim.resources import data_path

    return data_path("render.toml")


def load_style(path=None) -> RenderStyle:
    """Read and check a render style file (default: the shipped one).

    Every table and key of the shipped file is required (no silent
    defaults); unknown keys are rejected.
    """
    path = style_path() if path is None else Path(path)
    doc = read_toml(path)
    check_keys(doc, _SCHEMA, path, "render style", required=_SCHEMA)
    out = {"path": path}
    for table, keys in _SCHEMA.items():
        t = doc[table]
        check_keys(t, keys, path, table, required=keys)
        vals = {}
        for key, spec in keys.items():
            if spec[0] == _N:
                vals[key] = float(get_number(t, key, path, table, minimum=spec[1],
                                             maximum=spec[2]))
            elif spec[0] == _RGB:
                rgb = tuple(float(v) for v in get_vector(t, key, path, table))
                if not all(0.0 <= v <= 1.0 for v in rgb):
                    raise BonesimError(f"'{key}' must be RGB values from 0 to 1, got "
                                       f"{list(rgb)}", path, table)
                vals[key] = rgb
            else:
                vals[key] = get_str(t, key, path, table)
        out[table] = SimpleNamespace(**vals)
    if out["panel"].min_width_px > out["panel"].max_width_px:
        raise BonesimError("'min_width_px' must not exceed 'max_width_px'", path, "panel")
    return RenderStyle(**out)


@functools.lru_cache(maxsize=1)
def default_style() -> RenderStyle:
    """The shipped style (read once per process)."""
    return load_style()
