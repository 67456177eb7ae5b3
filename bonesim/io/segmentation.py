"""3D Slicer segmentation files (``.seg.nrrd``): the segment table.

A Slicer segmentation is an NRRD file whose header lists its segments as
``Segment<i>_<Field>`` keys (``i`` = 0, 1, ...): ``ID``, ``Name``, ``Color``
(three floats in 0-1), ``LabelValue`` (the voxel value of the segment in its
layer, default 1) and ``Layer`` (default 0). Segments that overlap are stored
in separate layers: the data then have a fourth, leading ``list`` axis, one
3-D layer per entry.

Reading a segmentation's voxels (:func:`read_segmentation`) turns the chosen
segments into structure indices in the LPS patient frame. Where segments
overlap, a voxel takes the structure that matters most for safety:
``critical`` over ``soft`` over ``bone``; between structures of one kind, the
later one in the case's structure order. Segments no structure names are left
out. Slicer stores a segmentation cropped to its segments' extent; on a CT's
grid it is placed by its origin (see :func:`embed_on_grid`).

:func:`write_seg_nrrd` writes structure indices as a one-layer segmentation
that 3D Slicer opens with the same names, colours and anatomy.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.io.raw_volume import GRID_TOL_MM, MAX_STRUCTURES, RawVolume, check_file, snap_to_lps
from bonesim.io.resample import slabs

__all__ = ["SEG_SUFFIX", "KIND_PRIORITY", "Segment", "read_seg_segments", "segment_keys",
           "read_segmentation", "embed_on_grid", "write_seg_nrrd"]

#: Overlapping segments: a voxel takes the structure of the higher kind.
KIND_PRIORITY = {"bone": 0, "soft": 1, "critical": 2}

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


def segment_keys(segments: list[Segment]) -> dict[str, str]:
    """Segment ID -> the key a case names it by: its name, or its ID when
    two segments share the name."""
    counts: dict[str, int] = {}
    for g in segments:
        counts[g.name] = counts.get(g.name, 0) + 1
    return {g.id: (g.name if counts[g.name] == 1 else g.id) for g in segments}


def read_segmentation(path: str | Path, segment_names, kinds, progress=None
                      ) -> RawVolume:
    """Structure indices from a 3D Slicer segmentation's voxels.

    Parameters
    ----------
    path : str or Path
        The ``.seg.nrrd`` file (3-D, or 4-D with a leading layer axis).
    segment_names : sequence of str or None
        Per structure, in index order: the segment it comes from, as
        :func:`segment_keys` names it (or a segment ID); None for a structure
        that is not in the segmentation (bone thresholded from a CT).
    kinds : sequence of str
        Per structure: its kind, which settles overlaps (:data:`KIND_PRIORITY`).
    progress : callable, optional
        ``progress(done, total, what)`` once per structure painted.

    Returns
    -------
    RawVolume
        ``data`` uint8 structure indices (0 empty), axes along +x, +y, +z.
    """
    import nrrd

    from bonesim.io.images import nrrd_affine

    path = Path(path)
    check_file(path, "segmentation")
    if len(segment_names) != len(kinds):
        raise ValueError("one kind per segment name")
    if len(kinds) > MAX_STRUCTURES:
        raise ValueError(f"at most {MAX_STRUCTURES} structures")
    segments = read_seg_segments(path)
    keys = segment_keys(segments)
    by_key = {}
    for g in segments:
        by_key.setdefault(keys[g.id], g)
        by_key.setdefault(g.id, g)
    try:
        data, hdr = nrrd.read(str(path), index_order="F")
    except Exception as exc:  # pynrrd raises NRRDError, ValueError, OSError...
        raise BonesimError(f"unreadable NRRD file: {exc}", path) from None
    affine, spatial = nrrd_affine(hdr, path)
    data = np.asarray(data)
    extra = [a for a in range(data.ndim) if a not in spatial]
    if len(extra) > 1 or data.ndim not in (3, 4):
        raise BonesimError(f"expected 3 spatial axes and at most one layer axis, got "
                           f"shape {data.shape}", path, "sizes")
    layers = np.moveaxis(data, extra[0], 0) if extra else data[None]
    if not np.issubdtype(layers.dtype, np.integer):
        raise BonesimError(f"segmentation voxels must be integers, got {layers.dtype}",
                           path, "type")
    out = np.zeros(layers.shape[1:], dtype=np.uint8)
    order = sorted(range(len(kinds)), key=lambda s: (KIND_PRIORITY[kinds[s]], s))
    for done, s in enumerate(order, start=1):
        if segment_names[s] is None:
            continue
        g = by_key.get(segment_names[s])
        if g is None:
            listed = ", ".join(repr(keys[x.id]) for x in segments)
            raise BonesimError(f"no segment {segment_names[s]!r}; its segments: "
                               f"{listed}", path)
        if not 0 <= g.layer < layers.shape[0]:
            raise BonesimError(f"segment {g.name!r} is in layer {g.layer}, but the file "
                               f"has {layers.shape[0]} layer(s)", path,
                               f"Segment{segments.index(g)}_Layer")
        layer = layers[g.layer]
        for a, b in slabs(out.shape[0], out.shape[1] * out.shape[2]):   # small masks
            out[a:b][layer[a:b] == g.label_value] = s + 1
        if progress is not None:
            progress(done, len(order), "painting segments")
    return snap_to_lps(out, affine, path, f"{path} (3D Slicer segmentation, "
                       f"{len(segments)} segments)")


def embed_on_grid(seg: RawVolume, shape, spacing_mm, origin_mm, path: Path
                  ) -> np.ndarray:
    """Place a (cropped) segmentation on a volume's grid.

    Slicer writes a segmentation only over its segments' extent, on the
    reference CT's voxel lattice. The segmentation must share that lattice
    (same spacing, origin offset a whole number of voxels) and lie inside it.

    Parameters
    ----------
    seg : RawVolume
        Structure indices, axes along +x, +y, +z.
    shape : (3,) int
        The volume's grid size.
    spacing_mm, origin_mm : (3,) float
        The volume's voxel edges and centre of voxel ``(0, 0, 0)`` [mm].
    path : Path
        The segmentation, for messages.

    Returns
    -------
    (nx, ny, nz) uint8
        Structure indices on the volume's grid (0 outside the segmentation).
    """
    spacing = np.asarray(spacing_mm, float).reshape(3)
    offset = (np.asarray(seg.origin_mm, float) - np.asarray(origin_mm, float)) / spacing
    start = np.rint(offset).astype(int)
    stop = start + np.array(seg.data.shape)
    if (not np.allclose(seg.spacing_mm, spacing, atol=GRID_TOL_MM)
            or np.abs(offset - start).max() * spacing.max() > GRID_TOL_MM
            or np.any(start < 0) or np.any(stop > np.asarray(shape))):
        raise BonesimError(
            "segmentation does not lie on the volume's grid: spacing "
            f"{np.round(seg.spacing_mm, 4).tolist()} vs {np.round(spacing, 4).tolist()} "
            f"mm, voxels {start.tolist()} to {(stop - 1).tolist()} of a "
            f"{list(map(int, shape))} grid (offset {np.round(offset, 3).tolist()})", path)
    out = np.zeros(tuple(int(n) for n in shape), dtype=np.uint8)
    out[start[0]:stop[0], start[1]:stop[1], start[2]:stop[2]] = seg.data
    return out


def write_seg_nrrd(path: str | Path, labels: np.ndarray, names, colors, spacing_mm,
                   origin_mm) -> Path:
    """Write structure indices as a one-layer 3D Slicer segmentation.

    Parameters
    ----------
    path : str or Path
        Output ``.seg.nrrd``.
    labels : (nx, ny, nz) uint8
        Structure index per voxel (0 empty), axes along x, y, z of LPS.
    names : sequence of str
        Segment name per structure, in index order.
    colors : sequence of (3,) int
        Display RGB 0-255 per structure.
    spacing_mm : float
        Isotropic voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel ``(0, 0, 0)`` [mm].

    Segment ``s`` has ID ``Segment_s``, label value ``s`` in layer 0 and its
    own extent; the file is gzip NRRD in LPS space.
    """
    from bonesim.io.images import write_nrrd

    labels = np.asarray(labels, dtype=np.uint8)
    if len(names) != len(colors):
        raise ValueError("one colour per name")
    fields = {
        "Segmentation_MasterRepresentation": "Binary labelmap",
        "Segmentation_ContainedRepresentationNames": "Binary labelmap|",
        "Segmentation_ReferenceImageExtentOffset": "0 0 0",
    }
    from scipy.ndimage import find_objects

    boxes = find_objects(labels, max_label=len(names))      # one pass for all
    for i, (name, rgb) in enumerate(zip(names, colors)):
        box = boxes[i]
        ext = [(0, -1)] * 3 if box is None else [(b.start, b.stop - 1) for b in box]
        fields.update({
            f"Segment{i}_ID": f"Segment_{i + 1}",
            f"Segment{i}_Name": str(name),
            f"Segment{i}_Color": " ".join(f"{c / 255:.6g}" for c in rgb),
            f"Segment{i}_LabelValue": str(i + 1),
            f"Segment{i}_Layer": "0",
            f"Segment{i}_Extent": " ".join(str(v) for e in ext for v in e),
            f"Segment{i}_Tags": "|",
        })
    return write_nrrd(path, labels, spacing_mm, origin_mm, fields)
