"""The session file's layout: its identity attributes, groups and columns.

A session file (``docs/session_schema.md``) is an HDF5 file whose root
attributes say what it is (:data:`FORMAT`, :data:`SCHEMA_VERSION`, the
header) and whose groups hold the recorded streams, one dataset a column.
This module is the one place the layout is named: the writer
(:mod:`bonesim.session.writer`) creates it, the reader
(:mod:`bonesim.session.reader`) checks it, and the recorder process
(:mod:`bonesim.runtime.record`) fills it.
"""
from __future__ import annotations

import numpy as np

from bonesim.engine import events
from bonesim.errors import BonesimError

__all__ = ["SCHEMA_VERSION", "FORMAT", "GROUPS", "OPTIONAL_GROUPS", "HEADER_KEYS",
           "require_h5py"]

#: Version of the file layout written here (``docs/session_schema.md``).
SCHEMA_VERSION = 4
#: Value of the root attribute ``format``.
FORMAT = "bonesim-session"
#: Columns of each group: name -> (dtype, trailing shape). ``samples``,
#: ``camera`` and ``events`` are the rings of the same names
#: (:data:`bonesim.engine.events.OTHER_RINGS`); ``tissue`` is the tissue-event
#: record (:data:`bonesim.engine.events.TISSUE_FIELDS`) plus ``visible`` (removals:
#: 1 visible from the eye, 0 hidden, -1 unknown; -1 for other kinds).
GROUPS = {
    "samples": events.OTHER_RINGS["samples"][1],
    "tissue": {**events.TISSUE_FIELDS, "visible": (np.int8, ())},
    "camera": events.OTHER_RINGS["camera"][1],
    "events": events.OTHER_RINGS["ui"][1],
}
#: Optional groups (a file may lack them;
#: :func:`bonesim.session.reader.read_session` then gives them no rows):
#: ``handle``, an instrumented handle's readings
#: (:mod:`bonesim.runtime.handle_stream`).
GROUPS["handle"] = events.OTHER_RINGS["handle"][1]
OPTIONAL_GROUPS = ("handle",)
#: Header keys every file must carry.
HEADER_KEYS = ("bonesim_version", "case", "burrs", "oversample", "voxel_mm", "structures",
               "device", "rate_hz", "start_time", "participant", "group", "notes",
               "model_sha256", "machine")


def require_h5py():
    """The ``h5py`` module, or one line saying it is missing (:class:`BonesimError`)."""
    try:
        import h5py
    except ImportError as exc:                                  # pragma: no cover
        raise BonesimError("session files need h5py (pip install h5py)") from exc
    return h5py
