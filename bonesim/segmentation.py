"""3D Slicer segmentation files (``.seg.nrrd``): the segment table.

A Slicer segmentation is an NRRD file whose header lists its segments as
``Segment<i>_<Field>`` keys (``i`` = 0, 1, ...): ``ID``, ``Name``, ``Color``
(three floats in 0-1), ``LabelValue`` (the voxel value of the segment in its
layer, default 1) and ``Layer`` (default 0). Segments that overlap are stored
in separate layers: the data then have a fourth, leading ``list`` axis, one
3-D layer per entry.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from .errors import BonesimError

__all__ = ["SEG_SUFFIX", "Segment", "read_seg_segments"]

#: File-name ending of a Slicer segmentation.
SEG_SUFFIX = ".seg.nrrd"

_KEY = re.compile(r"^Segment(\d+)_(\w+)$")


@dataclass(frozen=True)
class Segment:
    """One segment of a Slicer segmentation.

    Attributes
    ----------
    id : str
        Slicer's segment ID (``Segment_1``, ...).
    name : str
        Display name (the ID when the file gives none).
    color : (3,) int
        RGB 0-255.
    layer : int
        Layer holding its voxels (0 for a 3-D file).
    label_value : int
        Voxel value of the segment within its layer.
    """

    id: str
    name: str
    color: tuple[int, int, int]
    layer: int
    label_value: int


def _int(fields: dict, key: str, default: int, path: Path, i: int) -> int:
    raw = fields.get(key)
    if raw is None:
        return default
    try:
        return int(str(raw).strip())
    except ValueError:
        raise BonesimError(f"Segment{i}_{key} must be an integer, got {raw!r}",
                           path, f"Segment{i}_{key}") from None


def read_seg_segments(path: str | Path) -> list[Segment]:
    """Read the segment table of a ``.seg.nrrd`` file (header only).

    Raises
    ------
    BonesimError
        The file is missing or not NRRD, has no segments, or a segment field
        is malformed.
    """
    import nrrd

    path = Path(path)
    if not path.is_file():
        raise BonesimError("segmentation file not found", path)
    try:
        hdr = nrrd.read_header(str(path))
    except Exception as exc:  # pynrrd raises NRRDError, ValueError, OSError...
        raise BonesimError(f"unreadable NRRD header: {exc}", path) from None
    by_index: dict[int, dict] = {}
    for key, value in hdr.items():
        m = _KEY.match(str(key))
        if m:
            by_index.setdefault(int(m.group(1)), {})[m.group(2)] = value
    if not by_index:
        raise BonesimError("no segments: not a 3D Slicer segmentation (no "
                           "Segment<i>_ID keys in the header)", path)
    out = []
    for i in sorted(by_index):
        f = by_index[i]
        sid = str(f.get("ID", f"Segment_{i}")).strip()
        name = str(f.get("Name", sid)).strip() or sid
        raw = f.get("Color", "0.5 0.5 0.5")
        try:
            rgb = [float(v) for v in str(raw).split()]
        except ValueError:
            rgb = []
        if len(rgb) != 3 or any(not 0.0 <= v <= 1.0 for v in rgb):
            raise BonesimError(f"Segment{i}_Color must be three numbers in 0-1, got "
                               f"{raw!r}", path, f"Segment{i}_Color")
        color = tuple(int(round(255 * v)) for v in rgb)
        out.append(Segment(sid, name, color, _int(f, "Layer", 0, path, i),
                           _int(f, "LabelValue", 1, path, i)))
    return out
