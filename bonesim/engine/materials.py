"""Material properties per structure kind (bone, critical, soft).

Every structure of a case has a *kind*. Its material says how hard it pushes
back on the burr, how fast the burr removes it and whether touching it is an
injury. The values live in ``bonesim/data/materials.toml``; a user may pass a
file of their own with the same layout: one table per kind, each with

``stiffness`` (number >= 0)
    Factor on each immersed sample's contribution to the contact force
    (1 = bone).
``removal`` (number >= 0)
    Factor on the removal rate (1 = bone).
``injury`` (bool)
    Whether contact with or removal of this kind emits an injury event.
``description`` (string, optional)
    What the kind covers.

All of :data:`MATERIAL_KINDS` must be defined, and no other kind.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from bonesim.errors import BonesimError
from bonesim.tomlfile import check_keys, get_number, read_toml

__all__ = ["MATERIAL_KINDS", "Material", "default_materials_path", "load_materials"]

#: Structure kinds the engine knows, in the order :func:`load_materials` returns.
MATERIAL_KINDS = ("bone", "critical", "soft")

_KEYS = ("stiffness", "removal", "injury", "description")
_REQUIRED = ("stiffness", "removal", "injury")


@dataclass(frozen=True)
class Material:
    """How one kind of structure responds to the burr.

    Attributes
    ----------
    kind : str
        ``"bone"``, ``"critical"`` or ``"soft"``.
    stiffness : float
        Factor (dimensionless) on each immersed sample's force contribution.
    removal : float
        Factor (dimensionless) on the removal rate.
    injury : bool
        Touching or removing this kind emits an injury event.
    description : str
        What the kind covers.
    """

    kind: str
    stiffness: float
    removal: float
    injury: bool
    description: str = ""


def default_materials_path() -> Path:
    """Path of the shipped ``materials.toml``."""
    from bonesim.resources import data_path

    return data_path("materials.toml")


def _factor(table: dict, key: str, path: Path, where: str) -> float:
    value = get_number(table, key, path, where, minimum=0.0)
    if not math.isfinite(value):
        raise BonesimError(f"'{key}' must be finite, got {value!r}", path, where)
    return float(value)


def load_materials(path: str | Path | None = None) -> dict[str, Material]:
    """Read and check the material table.

    Parameters
    ----------
    path : str or Path, optional
        A materials file; default: the shipped ``bonesim/data/materials.toml``.

    Returns
    -------
    dict of str to Material
        Keyed by kind, in the order of :data:`MATERIAL_KINDS`.

    Raises
    ------
    BonesimError
        If the file is missing or malformed, a kind is missing or unknown, a
        key is unknown or missing, or a value has the wrong type or range.
    """
    path = default_materials_path() if path is None else Path(path)
    doc = read_toml(path)
    unknown = sorted(set(doc) - set(MATERIAL_KINDS))
    if unknown:
        raise BonesimError(f"unknown material kind(s) {', '.join(map(repr, unknown))}; "
                           f"the kinds are {', '.join(MATERIAL_KINDS)}", path)
    missing = [k for k in MATERIAL_KINDS if k not in doc]
    if missing:
        raise BonesimError(f"missing material kind(s) {', '.join(map(repr, missing))}; "
                           f"every one of {', '.join(MATERIAL_KINDS)} needs a table", path)
    out: dict[str, Material] = {}
    for kind in MATERIAL_KINDS:
        table = doc[kind]
        check_keys(table, _KEYS, path, kind, required=_REQUIRED)
        injury = table["injury"]
        if not isinstance(injury, bool):
            raise BonesimError(f"'injury' must be true or false, got {injury!r}",
                               path, kind)
        description = table.get("description", "")
        if not isinstance(description, str):
            raise BonesimError(f"'description' must be a string, got {description!r}",
                               path, kind)
        out[kind] = Material(kind=kind,
                             stiffness=_factor(table, "stiffness", path, kind),
                             removal=_factor(table, "removal", path, kind),
                             injury=injury, description=description)
    return out
