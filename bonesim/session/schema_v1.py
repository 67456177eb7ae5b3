"""Session schema 1, read by migration to the tissue-event stream of schema 2.

Schema 1 (bonesim up to the core redesign) stored tissue changes in two
groups, ``removals`` (``ijk``, ``label``, ``t_s``, ``visible``) and
``injuries`` (``label``, ``kind`` 0 contact / 1 removal, ``t_s``,
``pos_mm``, ``voxels``), and case resets and burr changes as ``reset`` /
``burr`` rows of the ``events`` group. Schema 2 carries all of them as one
stream of tissue events (:mod:`bonesim.engine.events`). :func:`migrate` turns the
first into the second, in the order the haptic loop would have published
them: at one step time, a reset or burr change first, then the step's
removals, then its contacts and injuries (each kind keeps its recorded
order). Every voxel of a schema-1 file belongs to body 0.
"""
from __future__ import annotations

import numpy as np

from bonesim.engine import events

__all__ = ["GROUPS_V1", "migrate"]

#: Columns of the schema-1 groups that differ from schema 2.
GROUPS_V1 = {
    "removals": {"ijk": (np.int32, (3,)), "label": (np.uint8, ()), "t_s": (np.float64, ()),
                 "visible": (np.int8, ())},
    "injuries": {"label": (np.uint8, ()), "kind": (np.uint8, ()), "t_s": (np.float64, ()),
                 "pos_mm": (np.float64, (3,)), "voxels": (np.int32, ())},
}
# order of kinds within one step time, as the haptic loop publishes them
_RESET, _BURR, _STEP_REMOVALS, _STEP_INJURIES = 0, 1, 2, 3


def migrate(removals: dict, injuries: dict, ui_events: list) -> tuple[dict, list]:
    """Schema-1 groups as schema-2 tissue events.

    Parameters
    ----------
    removals, injuries : dict of str -> ndarray
        The schema-1 groups' columns.
    ui_events : list of (t_s, name, value)
        The ``events`` group; its ``reset`` and ``burr`` rows become tissue
        events.

    Returns
    -------
    tissue : dict of str -> ndarray
        Tissue-event columns plus ``visible``, in stream order.
    ui_events : list
        The other ``events`` rows.
    """
    nr, ni = len(removals["t_s"]), len(injuries["t_s"])
    changes = [(t, name, value) for t, name, value in ui_events
               if name in ("reset", "burr")]
    rest = [e for e in ui_events if e[1] not in ("reset", "burr")]
    nc = len(changes)
    ev = events.empty_events(nc + nr + ni)
    visible = np.full(nc + nr + ni, -1, np.int8)
    for q, (t, name, value) in enumerate(changes):
        ev["kind"][q] = events.RESET if name == "reset" else events.BURR
        ev["t_s"][q] = t
        try:
            ev["n"][q] = int(value)
        except ValueError:
            ev["n"][q] = -1
    r = slice(nc, nc + nr)
    ev["kind"][r] = events.REMOVED
    ev["t_s"][r] = removals["t_s"]
    ev["ijk"][r] = removals["ijk"]
    ev["label"][r] = removals["label"]
    visible[r] = removals["visible"]
    i = slice(nc + nr, nc + nr + ni)
    ev["kind"][i] = np.where(injuries["kind"] == events.INJURY_CONTACT, events.CONTACT,
                             events.INJURY)
    ev["t_s"][i] = injuries["t_s"]
    ev["label"][i] = injuries["label"]
    ev["n"][i] = injuries["voxels"]
    ev["value"][i, :3] = injuries["pos_mm"]
    first = np.where(ev["kind"][:nc] == events.RESET, _RESET, _BURR)
    rank = np.concatenate([first, np.full(nr, _STEP_REMOVALS), np.full(ni, _STEP_INJURIES)])
    order = np.lexsort((np.arange(len(rank)), rank, ev["t_s"]))
    tissue = {k: a[order] for k, a in ev.items()}
    tissue["visible"] = visible[order]
    return tissue, rest
