"""The shading file: how the bone surface is placed and shaded.

``bonesim/data/shading.toml`` (or a file of the same layout given to
:func:`load_shading`) holds three tables:

``[normals]``
    ``sigma_voxels``: standard deviation [voxels] of the Gaussian that
    smooths the density into the field whose gradient gives the vertex
    normals and whose level set places the vertices
    (:mod:`bonesim.engine.normals`).
``[surface]`` (optional; defaults below)
    ``iso_density``, ``max_out_voxels``, ``max_in_voxels``: where on that
    smoothed field a vertex sits, and how far [voxels] it may move from its
    voxel's centre along its normal, out of the bone and into it.
``[thin_bone]``
    ``start_mm``, ``full_mm``, ``max_weight``: where bone over a non-bone
    structure starts to take on that structure's colour, where the blend
    is strongest, and how strong it gets; ``cone_rays`` and ``cone_deg``
    (optional): the rays around the normal that average the thickness
    (:mod:`bonesim.engine.thin_bone`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from bonesim.errors import BonesimError
from bonesim.tomlfile import check_keys, get_number, read_toml

__all__ = ["ShadingParams", "default_shading_path", "load_shading", "MAX_CONE_RAYS",
           "MAX_CONE_DEG", "MAX_IN_VOXELS", "MAX_OUT_VOXELS"]

#: Most rays on the thin-bone cone (besides the central ray).
MAX_CONE_RAYS = 16
#: Widest half-angle of the thin-bone cone [deg]: rays further from the
#: normal measure the bone's thickness too obliquely to mean much.
MAX_CONE_DEG = 60.0
#: Largest shift of a vertex into the bone [voxels] (see ``max_in_voxels``).
MAX_IN_VOXELS = 0.5
#: Largest shift of a vertex out of the bone [voxels] (a surface voxel's
#: corner lies sqrt(3)/2 voxel from its centre).
MAX_OUT_VOXELS = 0.9


@dataclass(frozen=True)
class ShadingParams:
    """Tunables of the surface placement and shading (module docstring).

    Attributes
    ----------
    sigma_voxels : float
        Standard deviation of the smoothing Gaussian [voxels].
    start_mm : float
        Bone thickness at and above which there is no tint [mm].
    full_mm : float
        Thickness at and below which the tint is strongest [mm].
    max_weight : float
        Strongest blend toward the structure's colour, in [0, 1].
    iso_density : float
        Level of the smoothed density the vertices are moved onto, in (0, 1).
    max_out_voxels, max_in_voxels : float
        Longest move of a vertex along its normal out of the bone / into it
        [voxels], at most :data:`MAX_OUT_VOXELS` / :data:`MAX_IN_VOXELS`.
    cone_rays : int
        Thin-bone rays on a cone around the central ray (0 .. :data:`MAX_CONE_RAYS`).
    cone_deg : float
        Half-angle of that cone [deg], in [0, :data:`MAX_CONE_DEG`].
    """

    sigma_voxels: float = 2.0
    start_mm: float = 3.0
    full_mm: float = 0.5
    max_weight: float = 0.6
    iso_density: float = 0.5
    max_out_voxels: float = 0.75
    max_in_voxels: float = 0.4
    cone_rays: int = 4
    cone_deg: float = 20.0

    def __post_init__(self):
        for name in ("sigma_voxels", "start_mm", "full_mm", "max_weight", "iso_density",
                     "max_out_voxels", "max_in_voxels", "cone_deg"):
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
        if not 0 < self.iso_density < 1:
            raise ValueError(f"iso_density must be in (0, 1), got {self.iso_density}")
        if not 0 <= self.max_out_voxels <= MAX_OUT_VOXELS:
            raise ValueError(f"max_out_voxels must be in [0, {MAX_OUT_VOXELS}], got "
                             f"{self.max_out_voxels}")
        if not 0 <= self.max_in_voxels <= MAX_IN_VOXELS:
            raise ValueError(f"max_in_voxels must be in [0, {MAX_IN_VOXELS}], got "
                             f"{self.max_in_voxels}")
        c = self.cone_rays
        if isinstance(c, bool) or not isinstance(c, int) or not 0 <= c <= MAX_CONE_RAYS:
            raise ValueError(f"cone_rays must be an integer in [0, {MAX_CONE_RAYS}], got {c!r}")
        if not 0 <= self.cone_deg <= MAX_CONE_DEG:
            raise ValueError(f"cone_deg must be in [0, {MAX_CONE_DEG}], got {self.cone_deg}")


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
    d = ShadingParams()
    doc = read_toml(path)
    check_keys(doc, ("normals", "surface", "thin_bone"), path, "",
               required=("normals", "thin_bone"))
    nt = doc["normals"]
    check_keys(nt, ("sigma_voxels",), path, "normals", required=("sigma_voxels",))
    sigma = get_number(nt, "sigma_voxels", path, "normals", minimum=0.1, maximum=10.0)
    sf = doc.get("surface", {})
    check_keys(sf, ("iso_density", "max_out_voxels", "max_in_voxels"), path, "surface")
    iso = get_number(sf, "iso_density", path, "surface", d.iso_density, minimum=0.01,
                     maximum=0.99)
    out = get_number(sf, "max_out_voxels", path, "surface", d.max_out_voxels, minimum=0.0,
                     maximum=MAX_OUT_VOXELS)
    inn = get_number(sf, "max_in_voxels", path, "surface", d.max_in_voxels, minimum=0.0,
                     maximum=MAX_IN_VOXELS)
    tb = doc["thin_bone"]
    keys = ("start_mm", "full_mm", "max_weight")
    check_keys(tb, keys + ("cone_rays", "cone_deg"), path, "thin_bone", required=keys)
    start = get_number(tb, "start_mm", path, "thin_bone", minimum=0.0)
    full = get_number(tb, "full_mm", path, "thin_bone", minimum=0.0)
    wmax = get_number(tb, "max_weight", path, "thin_bone", minimum=0.0, maximum=1.0)
    rays = get_number(tb, "cone_rays", path, "thin_bone", d.cone_rays, minimum=0,
                      maximum=MAX_CONE_RAYS, integer=True)
    cone = get_number(tb, "cone_deg", path, "thin_bone", d.cone_deg, minimum=0.0,
                      maximum=MAX_CONE_DEG)
    if not math.isfinite(start):
        raise BonesimError(f"'start_mm' must be finite, got {start!r}", path, "thin_bone")
    if not full < start:
        raise BonesimError(f"'full_mm' ({full}) must be below 'start_mm' ({start})",
                           path, "thin_bone")
    return ShadingParams(sigma_voxels=float(sigma), start_mm=float(start),
                         full_mm=float(full), max_weight=float(wmax), iso_density=float(iso),
                         max_out_voxels=float(out), max_in_voxels=float(inn),
                         cone_rays=int(rays), cone_deg=float(cone))
