"""The plate catalogue: bone plates and distractors as mesh files.

``bonesim/data/tools/plates.toml`` (written with the meshes by
``scripts/make_plates.py``) lists one ``[[plate]]`` table per tool:

.. code-block:: toml

    [[plate]]
    name = "straight-4"             # unique
    kind = "plate"                  # "plate" | "distractor"
    description = "..."             # optional
    mesh = "plate_straight4.ply"    # PLY with vertex normals, beside the TOML
    mass_g = 0.39                   # > 0 [g]
    sample_offset_mm = 0.15         # samples sit this far out along the normals [mm]
    stiffness_n_per_mm = 0.002      # contact stiffness per sample [N/mm]
    samples = 400                   # contact samples kept (evenly strided vertices)
    axis = [1.0, 0.0, 0.0]          # distractor: its axis, mesh frame (default +x)

Mesh frame [mm]: the plate centred on 0, its bottom face facing -z. The
contact samples are the mesh's vertices pushed out along their normals
(:func:`bonesim.engine.rigid_set.mesh_samples`). Every problem is a
:class:`~bonesim.errors.BonesimError` naming the file and the table.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.engine.rigid import MAX_SAMPLES
from bonesim.io.meshes import read_ply
from bonesim.resources import data_path
from bonesim.tomlfile import check_keys, get_number, get_str, get_vector, read_toml

__all__ = ["PLATE_KINDS", "CATALOGUE", "PlateSpec", "load_plates", "default_plates"]

#: What a catalogue entry may be.
PLATE_KINDS = ("plate", "distractor")
#: The shipped catalogue.
CATALOGUE = "tools/plates.toml"
_KEYS = ("name", "kind", "description", "mesh", "mass_g", "sample_offset_mm",
         "stiffness_n_per_mm", "samples", "axis")


@dataclass(frozen=True, eq=False)
class PlateSpec:
    """One plate or distractor.

    Attributes
    ----------
    name, kind, description : str
    mesh : Path
    pos : (n, 3) float64
        Vertices, mesh frame [mm].
    tris : (m, 3) int64
    nrm : (n, 3) float64
        Unit vertex normals.
    mass_kg, offset_mm, stiffness_n_mm : float
        [kg], [mm], [N/mm] per sample.
    samples : int
        Contact samples kept.
    axis : (3,) float64
        Unit axis, mesh frame (a distractor's; +x for plates).
    """

    name: str
    kind: str
    description: str
    mesh: Path
    pos: np.ndarray
    tris: np.ndarray
    nrm: np.ndarray
    mass_kg: float
    offset_mm: float
    stiffness_n_mm: float
    samples: int
    axis: np.ndarray


def load_plates(path: str | Path | None = None) -> tuple:
    """Read a plate catalogue (default: the shipped one), meshes included.

    Returns
    -------
    tuple of PlateSpec
        In file order (a plate's index is its catalogue index, recorded with
        its poses).
    """
    path = Path(data_path(CATALOGUE) if path is None else path)
    doc = read_toml(path)
    check_keys(doc, ("plate",), path, "top level", required=("plate",))
    tables = doc["plate"]
    if not isinstance(tables, list) or not tables:
        raise BonesimError("'plate' must be a non-empty array of tables ([[plate]])", path,
                           "plate")
    out, names = [], set()
    for q, tab in enumerate(tables):
        where = f"plate[{q}]"
        check_keys(tab, _KEYS, path, where, required=("name", "kind", "mesh", "mass_g",
                                                      "sample_offset_mm",
                                                      "stiffness_n_per_mm"))
        name = get_str(tab, "name", path, where)
        if name in names:
            raise BonesimError(f"plate name {name!r} is used twice", path, where)
        names.add(name)
        kind = get_str(tab, "kind", path, where, choices=PLATE_KINDS)
        mesh = path.parent / get_str(tab, "mesh", path, where)
        if not mesh.is_file():
            raise BonesimError(f"mesh file {mesh.name!r} not found beside the catalogue",
                               path, where)
        m = read_ply(mesh)
        if "nrm" not in m:
            raise BonesimError(f"mesh {mesh.name!r} has no vertex normals (nx ny nz)", path,
                               where)
        nrm = np.asarray(m["nrm"], np.float64)
        ln = np.linalg.norm(nrm, axis=1)
        if not (ln > 0.5).all():
            raise BonesimError(f"mesh {mesh.name!r} has zero vertex normals", path, where)
        axis = np.array(get_vector(tab, "axis", path, where, default=(1.0, 0.0, 0.0)), float)
        if not np.linalg.norm(axis) > 0:
            raise BonesimError("'axis' must be a non-zero direction", path, where)
        out.append(PlateSpec(
            name=name, kind=kind, description=get_str(tab, "description", path, where,
                                                      default=""),
            mesh=mesh, pos=np.asarray(m["pos"], np.float64),
            tris=np.asarray(m["tris"], np.int64), nrm=nrm / ln[:, None],
            mass_kg=get_number(tab, "mass_g", path, where, minimum=1e-6) * 1e-3,
            offset_mm=get_number(tab, "sample_offset_mm", path, where, minimum=0.0,
                                 maximum=2.0),
            stiffness_n_mm=get_number(tab, "stiffness_n_per_mm", path, where,
                                      minimum=1e-9),
            samples=get_number(tab, "samples", path, where, default=MAX_SAMPLES,
                               minimum=1, maximum=MAX_SAMPLES, integer=True),
            axis=axis / np.linalg.norm(axis)))
    return tuple(out)


@lru_cache(maxsize=1)
def default_plates() -> tuple:
    """The shipped catalogue, read once per process."""
    return load_plates()
