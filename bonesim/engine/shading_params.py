"""The shading file: how the bone surface is shaded.

``bonesim/data/shading.toml`` (or a file of the same layout given to
:func:`load_shading`) holds two tables:

``[normals]``
    ``sigma_voxels``: standard deviation [voxels] of the Gaussian whose
    derivative gives the vertex normals (:mod:`bonesim.engine.normals`).
``[thin_bone]``
    ``start_mm``, ``full_mm``, ``max_weight``: where bone over a non-bone
    structure starts to take on that structure's colour, where the blend
    is strongest, and how strong it gets (:mod:`bonesim.engine.thin_bone`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from bonesim.errors import BonesimError
from bonesim.tomlfile import check_keys, get_number, read_toml

__all__ = ["ShadingParams", "default_shading_path", "load_shading"]


@dataclass(frozen=True)
class ShadingParams:
    """Tunables of the surface shading (see the module docstring).

    Attributes
    ----------
    sigma_voxels : float
        Standard deviation of the normals' Gaussian [voxels].
    start_mm : float
        Bone thickness at and above which there is no tint [mm].
    full_mm : float
        Thickness at and below which the tint is strongest [mm].
    max_weight : float
        Strongest blend toward the structure's colour, in [0, 1].
    """

    sigma_voxels: float = 2.0
    start_mm: float = 3.0
    full_mm: float = 0.5
    max_weight: float = 0.6

    def __post_init__(self):
        for name in ("sigma_voxels", "start_mm", "full_mm", "max_weight"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"ShadingParams.{name} must be a finite number, got {v!r}")
        if not self.sigma_voxels > 0:
            raise ValueError(f"sigma_voxels must be > 0, got {self.sigma_voxels}")
        if not 0 <= self.full_mm < self.start_mm:
            raise ValueError(f"need 0 <= full_mm < start_mm, got full_mm={self.full_mm}, "
                             f"start_mm={self.start_mm}")
        if not 0 <= self.max_weight <= 1:
            raise ValueError(f"max_weight must be in [0, 1], got {self.max_weight}")


def default_shading_path() -> Path:
    """Path of the shipped ``shading.toml``."""
    from bonesim.resources import data_path

    return data_path("shading.toml")


def load_shading(path: str | Path | None = None) -> ShadingParams:
    """Read and check a shading file.

    Parameters
    ----------
    path : str or Path, optional
        Default: the shipped ``bonesim/data/shading.toml``.

    Returns
    -------
    ShadingParams

    Raises
    ------
    BonesimError
        If the file is missing or malformed, a table or key is unknown or
        missing, or a value has the wrong type or range.
    """
    if path is None:
        return _default_params()
    return _read_params(Path(path))


@lru_cache(maxsize=1)
def _default_params() -> ShadingParams:
    return _read_params(default_shading_path())


def _read_params(path: Path) -> ShadingParams:
    doc = read_toml(path)
    check_keys(doc, ("normals", "thin_bone"), path, "", required=("normals", "thin_bone"))
    nt = doc["normals"]
    check_keys(nt, ("sigma_voxels",), path, "normals", required=("sigma_voxels",))
    sigma = get_number(nt, "sigma_voxels", path, "normals", minimum=0.1, maximum=10.0)
    tb = doc["thin_bone"]
    keys = ("start_mm", "full_mm", "max_weight")
    check_keys(tb, keys, path, "thin_bone", required=keys)
    start = get_number(tb, "start_mm", path, "thin_bone", minimum=0.0)
    full = get_number(tb, "full_mm", path, "thin_bone", minimum=0.0)
    wmax = get_number(tb, "max_weight", path, "thin_bone", minimum=0.0, maximum=1.0)
    if not math.isfinite(start):
        raise BonesimError(f"'start_mm' must be finite, got {start!r}", path, "thin_bone")
    if not full < start:
        raise BonesimError(f"'full_mm' ({full}) must be below 'start_mm' ({start})",
                           path, "thin_bone")
    return ShadingParams(sigma_voxels=float(sigma), start_mm=float(start),
                         full_mm=float(full), max_weight=float(wmax))
