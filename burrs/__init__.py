"""Burr definitions shipped with bonesim.

Every ``*.toml`` file in this folder describes one *family* of burrs (for
example ``cutting.toml`` and ``diamond.toml``). :mod:`bonesim.io.burrs` reads
them; ``bonesim burrs`` lists them. A burr is named ``<family>-<d>mm`` where
``d`` is its diameter in millimetres written without trailing zeros
(``cutting-5mm``, ``diamond-2mm``, ``cutting-2.5mm``).

Family file
-----------
A ``[family]`` table holds the values its burrs share, and each ``[[burr]]``
entry gives a diameter plus any values that differ for that size. An entry's
value wins over the family's; every field must be set in one of the two::

    [family]
    name = "cutting"          # optional; defaults to the file name's stem
    kind = "cutting"          # "cutting" or "diamond"
    r_max = 4.0               # [1/(N*s)] removal rate per newton at the equator
    falloff = 2.0             # [1/rad]   rate lost per radian off the equator
    max_force_n = 3.3         # [N]
    # ... vibration, sound and speed fields (see bonesim.io.burrs.Burr) ...

    [[burr]]
    diameter_mm = 5.0
    k_low = 0.866             # [N/mm^3] override for this size
    k_high = 2.67
    n_t_fraction = 0.00265
    k_tan = 0.265

Single-burr file
----------------
A file with one ``[burr]`` table that carries every field itself, plus
``kind`` and, optionally, ``family`` (defaults to the kind)::

    [burr]
    family = "mine"
    kind = "diamond"
    diameter_mm = 2.5
    r_max = 2.0
    # ... every other field ...

Pass such a file (or a family file) to ``bonesim.io.burrs.load_burr`` by path.
A family file that defines several burrs needs the burr's name after a
``#``: ``load_burr("my_burrs.toml#mine-3mm")``.

The meaning and unit of each field is documented on
:class:`bonesim.io.burrs.Burr`.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["folder"]


def folder() -> Path:
    """Return the folder holding the shipped burr family files.

    Returns
    -------
    Path
        The directory of this package; it works from a source checkout and
        from an installed (non-editable) copy alike.
    """
    return Path(__file__).resolve().parent
