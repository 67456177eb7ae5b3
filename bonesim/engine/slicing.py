"""How much large work a world step may do: the slice sizes.

Large tissue changes are done in bounded slices, one per world step: a
fragment split (:mod:`bonesim.engine.split_jobs`), a cut-plane stroke
(:mod:`bonesim.engine.cut_plane`) and a fragment's first measurement
(:mod:`bonesim.engine.rigid_measure`). Each slice's size is a number of
voxels, read from ``bonesim/data/slicing.toml`` (:data:`SLICING_FILE`), never a
time, so that what a step does depends only on the run's inputs.
"""
from __future__ import annotations

from functools import lru_cache

__all__ = ["SLICING_FILE", "TABLES", "voxels_per_step"]

#: The data file of the slice sizes (``bonesim/data``).
SLICING_FILE = "slicing.toml"
#: Its tables, one per kind of sliced work.
TABLES = ("split", "cut_plane", "rigid")


@lru_cache(maxsize=None)
def voxels_per_step(table: str = "split", path=None) -> int:
    """The budget of one world step [voxels]: ``voxels_per_step`` of table
    ``table`` (``split``: voxels a split moves; ``cut_plane``: voxels a
    stroke's rays walk; ``rigid``: voxels of a fragment measured,
    :mod:`bonesim.engine.rigid_measure`) of :data:`SLICING_FILE` (or of the
    file ``path``). A bad file is one :class:`~bonesim.errors.BonesimError`
    line naming the file and field."""
    from pathlib import Path

    from bonesim.resources import data_path
    from bonesim.tomlfile import check_keys, get_number, read_toml

    path = data_path(SLICING_FILE) if path is None else Path(path)
    doc = read_toml(path)
    check_keys(doc, TABLES, path, "top level", required=TABLES)
    tab = doc[table]
    check_keys(tab, ("voxels_per_step",), path, table, required=("voxels_per_step",))
    return int(get_number(tab, "voxels_per_step", path, table, minimum=1,
                          maximum=1 << 24, integer=True))
