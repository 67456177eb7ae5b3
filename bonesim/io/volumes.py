"""CT volumes and label maps: one entry point from any format to the engine's grid.

Frame and layout
----------------
Every volume handed to the engine is a :class:`CaseVolume`: arrays indexed
``[i, j, k]`` along the case-frame axes ``(x, y, z)``, isotropic spacing
``spacing_mm`` and the centre of voxel ``(0, 0, 0)`` at ``origin_mm``. The case
frame is anatomical LPS, as in DICOM: ``+x`` toward the patient's left, ``+y``
posterior, ``+z`` superior.

Reading is split in two steps:

1. a reader turns one file or folder into a
   :class:`~bonesim.io.raw_volume.RawVolume` whose array is already reordered
   (flips / axis permutations only, never interpolated) so that its axes run
   along ``+x, +y, +z``; spacing may still differ per axis. The readers live
   with their formats: :mod:`bonesim.io.dicom`, :mod:`bonesim.io.images`
   (NRRD, NIfTI), :mod:`bonesim.io.label_stack`, :mod:`bonesim.io.segmentation`
   (3D Slicer ``.seg.nrrd``), and are re-exported here;
2. :func:`load_volume` turns intensities into structure labels (threshold plus
   an optional label map), then resamples to isotropic voxels
   (:mod:`bonesim.io.resample`) of the case's ``voxel_mm``, or keeps the
   source's own spacing for ``voxel_mm = "native"`` (:func:`engine_voxel_mm`).

Memory
------
At a source's resolution a volume is big (512³ voxels: 134 MB of uint8
labels), so nothing here makes a whole-volume temporary of another type:
thresholding, label-map lookup, counting and resampling go slab by slab
(:data:`bonesim.io.resample.SLAB_VOXELS`), intensities are kept in the
source's type, and when the engine's grid is the source's grid the labels
are held once (:attr:`CaseVolume.native` is None).

Labels
------
``labels`` values are 1-based indices into the case's structure list, 0 for
empty (air, background). For intensity volumes, voxels ``>= bone_threshold_hu``
become the first structure of kind ``"bone"``; a label map, if given, then
overrides: a voxel whose map value equals a structure's ``label`` integer gets
that structure's index. Map value 0 never overrides. A map value that no
structure claims is an error. A Slicer segmentation as the label map
overrides with its segments (see :mod:`bonesim.io.segmentation`).

Every problem with the input is raised as one
:class:`~bonesim.errors.BonesimError` naming the file or folder.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from bonesim.io.dicom import (DICOM_HU_OFFSET, SLICE_GAP_RTOL,  # noqa: F401 (re-exported)
                              read_dicom_series, write_dicom_series)
from bonesim.errors import BonesimError
from bonesim.io.limits import check, check_grid
from bonesim.io.images import (NRRD_GZIP_LEVEL, read_nifti, read_nrrd,  # noqa: F401
                               write_nifti, write_nrrd)
from bonesim.io.label_stack import (UNKNOWN_COLOR_MODES, natural_key,  # noqa: F401
                                    read_label_stack, write_label_stack)
from bonesim.io.orientation import PATIENT_FRAME
from bonesim.io.raw_volume import (GRID_TOL_MM, MAX_LISTED, MAX_STRUCTURES,  # noqa: F401
                                   OBLIQUE_TOL, SPACING_RTOL, ObliqueWarning, RawVolume)
from bonesim.io.resample import (SLAB_VOXELS, label_counts, nearest_indices,  # noqa: F401
                                 resample_isotropic, slabs)
from bonesim.io.segmentation import (SEG_SUFFIX, embed_on_grid, read_segmentation,  # noqa: F401
                                     write_seg_nrrd)

__all__ = ["FORMATS", "NATIVE", "NativeLabels", "CaseVolume", "engine_voxel_mm",
           "labels_from_intensity", "nearest_indices", "resample_isotropic", "load_volume",
           "label_counts", "SLAB_VOXELS", "DICOM_HU_OFFSET",
           "SLICE_GAP_RTOL", "read_dicom_series", "write_dicom_series", "BonesimError",
           "NRRD_GZIP_LEVEL", "read_nifti", "read_nrrd", "write_nifti", "write_nrrd",
           "UNKNOWN_COLOR_MODES", "natural_key", "read_label_stack",
           "write_label_stack", "PATIENT_FRAME", "GRID_TOL_MM", "MAX_LISTED",
           "MAX_STRUCTURES", "OBLIQUE_TOL", "SPACING_RTOL", "ObliqueWarning",
           "RawVolume", "SEG_SUFFIX", "embed_on_grid", "read_segmentation",
           "write_seg_nrrd"]

FORMATS = ("phantom", "dicom", "nrrd", "nifti", "label-stack", "seg-nrrd")
"""Volume formats a case manifest may name."""

NATIVE = "native"
"""``voxel_mm`` asking for the source's own spacing (:func:`engine_voxel_mm`)."""


def engine_voxel_mm(voxel_mm: float | str, spacing_mm) -> float:
    """The engine's isotropic voxel edge [mm] for a source of ``spacing_mm``.

    Parameters
    ----------
    voxel_mm : float or "native"
        The case's ``voxel_mm``. :data:`NATIVE` keeps the source's spacing;
        with an anisotropic source (e.g. 0.19 x 0.19 mm pixels, 0.5 mm
        slices) that is its **finest** spacing, so no axis loses detail
        (the coarser axes are resampled to it, nearest neighbour for labels).
    spacing_mm : (3,) float
        The source's voxel edges along x, y, z [mm].

    Returns
    -------
    float
    """
    if isinstance(voxel_mm, str):
        if voxel_mm != NATIVE:
            raise ValueError(f"voxel_mm must be a number or {NATIVE!r}, got {voxel_mm!r}")
        return float(np.min(np.asarray(spacing_mm, dtype=np.float64)))
    return float(voxel_mm)


# ----------------------------------------------------------------- containers
@dataclass
class NativeLabels:
    """The label map at the source's own resolution, already in the case frame.

    Distances that must hold at every resampling (planning margins, guidance,
    the nerve monitor) are measured on this map, not on the engine's grid.

    Attributes
    ----------
    labels : (n0, n1, n2) uint8
        Structure index per source voxel (same indices as
        :attr:`CaseVolume.labels`), axes along ``+x, +y, +z`` (LPS).
    spacing_mm : (3,) float64
        Source voxel edge along x, y, z [mm] (may be anisotropic).
    origin_mm : (3,) float64
        Case-frame centre of source voxel ``(0, 0, 0)`` [mm].
    """

    labels: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray

    def __post_init__(self):
        self.labels = np.asarray(self.labels)
        if self.labels.ndim != 3 or self.labels.dtype != np.uint8:
            raise ValueError("labels must be a 3-D uint8 array, got "
                             f"{self.labels.dtype} {self.labels.shape}")
        self.spacing_mm = np.asarray(self.spacing_mm, dtype=np.float64).reshape(3)
        if not np.all(self.spacing_mm > 0):
            raise ValueError(f"spacing_mm must be positive, got {self.spacing_mm}")
        self.origin_mm = np.asarray(self.origin_mm, dtype=np.float64).reshape(3)


@dataclass
class CaseVolume:
    """A case's volume on an isotropic grid in the case frame.

    Attributes
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel (1-based into the case's ``structures``,
        0 = empty). Axis order ``(x, y, z)`` of the LPS case frame.
    spacing_mm : float
        Isotropic voxel edge [mm].
    origin_mm : (3,) float64
        Case-frame position of the centre of voxel ``(0, 0, 0)`` [mm].
    source : str
        What was read (file or folder, format), for messages and reports.
    hu : (nx, ny, nz) float32, or the source's integer type, or None
        Intensities [HU] where the format has them (kept in the source's
        type: no float copy of an integer CT).
    native : NativeLabels or None
        The labels at the source's resolution; None when the source is this
        grid (``voxel_mm = "native"`` of an isotropic source, or a
        ``voxel_mm`` equal to its spacing): the labels are then held once,
        see :attr:`native_labels`.
    """

    labels: np.ndarray
    spacing_mm: float
    origin_mm: np.ndarray
    source: str
    hu: np.ndarray | None = None
    native: NativeLabels | None = None

    def __post_init__(self):
        self.labels = np.asarray(self.labels)
        if self.labels.ndim != 3 or self.labels.dtype != np.uint8:
            raise ValueError("labels must be a 3-D uint8 array, got "
                             f"{self.labels.dtype} {self.labels.shape}")
        self.spacing_mm = float(self.spacing_mm)
        if not self.spacing_mm > 0:
            raise ValueError(f"spacing_mm must be positive, got {self.spacing_mm}")
        self.origin_mm = np.asarray(self.origin_mm, dtype=np.float64).reshape(3)
        if self.hu is not None:
            self.hu = np.asarray(self.hu)
            kind, size = self.hu.dtype.kind, self.hu.dtype.itemsize
            if kind not in "iuf" or (kind == "f" and size < 4):
                self.hu = self.hu.astype(np.float32)
            if self.hu.shape != self.labels.shape:
                raise ValueError("hu and labels differ in shape")

    @property
    def shape(self) -> tuple[int, int, int]:
        """Grid size ``(nx, ny, nz)`` [voxels]."""
        return tuple(int(n) for n in self.labels.shape)

    @property
    def extent_mm(self) -> np.ndarray:
        """Physical size of the grid, voxel edge to voxel edge, (3,) [mm]."""
        return np.asarray(self.shape, dtype=np.float64) * self.spacing_mm

    @property
    def native_labels(self) -> NativeLabels:
        """The source-resolution label map (this grid when none was kept)."""
        if self.native is not None:
            return self.native
        return NativeLabels(self.labels, np.full(3, self.spacing_mm), self.origin_mm)

    def counts(self, n_structures: int) -> np.ndarray:
        """Voxel count per index ``0 .. n_structures`` (index 0 = empty),
        counted slab by slab."""
        return label_counts(self.labels, n_structures + 1)

    def index_to_mm(self, ijk) -> np.ndarray:
        """Case-frame centres [mm] of voxel indices ``ijk`` (shape (..., 3))."""
        return self.origin_mm + self.spacing_mm * np.asarray(ijk, dtype=np.float64)


# ------------------------------------------------------------- label assembly
def labels_from_intensity(hu: np.ndarray | None, label_map: np.ndarray | None,
                          kinds: Sequence[str], label_values: Sequence[int | None],
                          bone_threshold_hu: float, source: Path,
                          labels_source: Path | None = None) -> np.ndarray:
    """Structure indices from intensities and an optional label map.

    Works slab by slab along x (:func:`bonesim.io.resample.slabs`): the
    threshold's mask and the label map's lookup (a table over values
    ``0 .. 65535``; others are sorted out per slab) are slab-sized, and the
    result is the only whole-volume array.

    Parameters
    ----------
    hu : (nx, ny, nz) real or None
        Intensities [HU], any real type (an int16 CT is not copied to
        float); voxels ``>= bone_threshold_hu`` become the first structure
        of kind ``"bone"``.
    label_map : (nx, ny, nz) int, bool or whole-valued float, or None
        Overrides: value ``v == label_values[s - 1]`` gives index ``s``; 0 does
        not override.
    kinds : sequence of str
        Kind of each structure, in manifest order.
    label_values : sequence of int or None
        Label-map integer of each structure (``None``: not in the map).
    bone_threshold_hu : float
        Bone threshold [HU].
    source, labels_source : Path
        Volume and label-map files, for messages.

    Returns
    -------
    (nx, ny, nz) uint8
    """
    bone = 1 + list(kinds).index("bone")
    shape = (hu if hu is not None else label_map).shape
    out = np.zeros(shape, dtype=np.uint8)
    where = labels_source or source
    table = {int(v): s for s, v in enumerate(label_values, start=1) if v is not None}
    lut = None
    if label_map is not None:
        lut = np.full(_LUT_SIZE, _UNCLAIMED, dtype=np.uint16)
        lut[0] = 0
        for v, s in table.items():
            if 0 <= v < _LUT_SIZE:
                lut[v] = s
    strays: dict[int, int] = {}
    counts = np.zeros(256, dtype=np.int64)
    for a, b in slabs(shape[0], shape[1] * shape[2]):
        o = out[a:b]
        if hu is not None:
            o[hu[a:b] >= bone_threshold_hu] = bone
        if lut is not None:
            idx = _map_label_slab(np.asarray(label_map[a:b]), lut, table, strays, where)
            np.copyto(o, idx, where=idx > 0, casting="unsafe")
        counts += np.bincount(o.ravel(), minlength=256)
    if strays:
        bad = sorted(strays.items())
        listed = ", ".join(f"{v} ({c} voxels)" for v, c in bad[:MAX_LISTED])
        more = f" and {len(bad) - MAX_LISTED} more" if len(bad) > MAX_LISTED else ""
        raise BonesimError(
            f"label map has {len(bad)} value(s) no structure claims: {listed}"
            f"{more}; known labels: {sorted(table)}", where)
    bone_idx = [s for s, k in enumerate(kinds, start=1) if k == "bone"]
    if not counts[bone_idx].any():
        what = ""
        if hu is not None and hu.size:
            what = (f"no voxel reaches bone_threshold_hu = {bone_threshold_hu:g} "
                    f"(intensities range {float(hu.min()):g} to {float(hu.max()):g})")
        if label_map is not None:
            what += ("; " if what else "") + "the label map marks no bone structure"
        raise BonesimError(f"no bone after thresholding: {what}", source)
    return out


_LUT_SIZE = 1 << 16                  # label-map values looked up in a table
_UNCLAIMED = np.uint16(0xFFFF)       # the table's mark of a value no structure claims


def _map_label_slab(m: np.ndarray, lut: np.ndarray, table: dict, strays: dict,
                    where) -> np.ndarray:
    """Structure index (uint16, 0 = no override) of each voxel of a slab of a
    label map; values no structure claims are counted into ``strays`` (and
    left 0)."""
    if m.dtype == np.bool_:
        m = m.view(np.uint8)
    elif not np.issubdtype(m.dtype, np.integer):
        if m.dtype.kind != "f" or not np.all(np.isfinite(m)) or np.any(m != np.round(m)):
            raise BonesimError("label map has non-integer values", where)
        m = m.astype(np.int64)
    if m.size and int(m.min()) >= 0 and int(m.max()) < _LUT_SIZE:
        idx = lut[m]
        bad = idx == _UNCLAIMED
        if bad.any():
            values, n = np.unique(m[bad], return_counts=True)
            for v, c in zip(values.tolist(), n.tolist()):
                strays[int(v)] = strays.get(int(v), 0) + int(c)
            idx[bad] = 0
        return idx
    idx = np.zeros(m.shape, dtype=np.uint16)
    values, inverse, n = np.unique(m, return_inverse=True, return_counts=True)
    known = np.array([table.get(int(v), 0) for v in values.tolist()], dtype=np.uint16)
    for v, c, s in zip(values.tolist(), n.tolist(), known.tolist()):
        if v != 0 and s == 0:
            strays[int(v)] = strays.get(int(v), 0) + int(c)
    idx.ravel()[:] = known[inverse.ravel()]
    return idx


# ------------------------------------------------------------------- loading
def _same_grid(a: RawVolume, b: RawVolume) -> bool:
    return (a.data.shape == b.data.shape
            and np.allclose(a.spacing_mm, b.spacing_mm, atol=GRID_TOL_MM)
            and np.allclose(a.origin_mm, b.origin_mm, atol=GRID_TOL_MM))


def _check_source(raw: RawVolume, voxel_mm: float, path) -> None:
    """The source's origin and extent within the physical bounds, and the
    engine grid it resamples to within them and the machine's memory
    (:mod:`bonesim.io.limits`), before the grid is allocated."""
    for v in np.asarray(raw.origin_mm, dtype=np.float64).reshape(-1):
        check("coordinate_mm", v, path, "origin", what="the volume's origin")
    extent = np.asarray(raw.data.shape[:3], np.float64) * np.asarray(raw.spacing_mm,
                                                                       np.float64)
    check_grid(extent, voxel_mm, path, "voxel_mm")


def _check_bone(labels: np.ndarray, kinds, path, what: str) -> None:
    bone_idx = [s for s, k in enumerate(kinds, start=1) if k == "bone"]
    if not label_counts(labels, MAX_STRUCTURES + 1)[bone_idx].any():
        raise BonesimError(f"no bone: {what}", path)


def load_volume(fmt: str, path: Path | None, *, kinds: Sequence[str],
                label_values: Sequence[int | None] = (),
                colors: Sequence = (), voxel_mm: float | str = 0.5,
                bone_threshold_hu: float = 300.0, labels_path: Path | None = None,
                pattern: str = "*.png", size_mm=None, unknown_colors: str = "error",
                origin_mm=None, orientation: str = PATIENT_FRAME,
                segment_names: Sequence[str] | None = None,
                progress=None) -> CaseVolume:
    """Read a CT / label volume of any file format into a :class:`CaseVolume`.

    Parameters
    ----------
    fmt : {"dicom", "nrrd", "nifti", "label-stack", "seg-nrrd"}
        File format (the phantom is generated by :mod:`bonesim.io.phantom`).
    path : Path or None
        Intensity volume (file, or folder for DICOM / label stacks), or the
        ``.seg.nrrd`` of a ``"seg-nrrd"`` case. For NRRD and NIfTI it may be
        ``None`` when ``labels_path`` alone gives the structures.
    kinds : sequence of str
        Kind of each structure in manifest order (``"bone"``, ...).
    label_values : sequence of int or None
        Label-map integer per structure.
    colors : sequence of (3,) int or None
        Label-stack colour per structure.
    voxel_mm : float or "native"
        Isotropic output voxel edge [mm], or :data:`NATIVE` for the source's
        own spacing (its finest axis, see :func:`engine_voxel_mm`).
    bone_threshold_hu : float
        Bone threshold for intensity formats [HU].
    labels_path : Path, optional
        Label map (NRRD or NIfTI, chosen by file name) on the volume's grid,
        or a 3D Slicer ``.seg.nrrd`` on the volume's voxel lattice (it may be
        cropped, as Slicer writes it).
    pattern, size_mm, unknown_colors, origin_mm, orientation
        Label-stack options, see :func:`read_label_stack`.
    segment_names : sequence of str, optional
        Segment per structure of a Slicer segmentation (``"seg-nrrd"``, or a
        ``.seg.nrrd`` label map), see :func:`read_segmentation`.
    progress : callable, optional
        ``progress(done, total, what)`` while slices decode or segments are
        painted.

    Returns
    -------
    CaseVolume
        On the engine's grid; ``native`` holds the source-resolution labels
        only when they differ from it (else None: one array, not two).
    """
    if len(kinds) > MAX_STRUCTURES:
        raise ValueError(f"at most {MAX_STRUCTURES} structures")
    if fmt in ("label-stack", "seg-nrrd"):
        if fmt == "label-stack":
            raw = read_label_stack(path, pattern, size_mm, colors, unknown_colors,
                                   origin_mm, orientation, progress=progress)
            what = "no pixel has the colour of a bone structure"
        else:
            if segment_names is None:
                raise ValueError("a seg-nrrd volume needs segment_names")
            raw = read_segmentation(path, segment_names, kinds, progress)
            what = "no voxel of the segmentation is in a bone segment"
        voxel = engine_voxel_mm(voxel_mm, raw.spacing_mm)
        _check_source(raw, voxel, path)
        labels, origin = resample_isotropic(raw.data, raw.spacing_mm, raw.origin_mm,
                                            voxel, order=0)
        _check_bone(labels, kinds, path, what)
        return CaseVolume(labels, voxel, origin, raw.source,
                          native=_native_or_none(labels, raw))

    readers = {"dicom": read_dicom_series, "nrrd": read_nrrd, "nifti": read_nifti}
    if fmt not in readers:
        raise ValueError(f"unknown volume format {fmt!r}")
    raw = readers[fmt](path) if path is not None else None
    lmap = None
    if labels_path is not None:
        name = Path(labels_path).name.lower()
        if name.endswith(SEG_SUFFIX) and segment_names is not None:
            lmap = read_segmentation(labels_path, segment_names, kinds, progress)
            if raw is not None:
                lmap = RawVolume(embed_on_grid(lmap, raw.data.shape, raw.spacing_mm,
                                               raw.origin_mm, Path(labels_path)),
                                 raw.spacing_mm, raw.origin_mm, lmap.source)
            label_values = range(1, len(kinds) + 1)
        elif name.endswith((".nii", ".nii.gz")):
            lmap = read_nifti(labels_path, scaled=False)
        else:
            lmap = read_nrrd(labels_path)
        if raw is not None and not _same_grid(raw, lmap):
            raise BonesimError(
                "label map grid differs from the volume's: shape "
                f"{lmap.data.shape} vs {raw.data.shape}, spacing "
                f"{np.round(lmap.spacing_mm, 4).tolist()} vs "
                f"{np.round(raw.spacing_mm, 4).tolist()} mm, origin "
                f"{np.round(lmap.origin_mm, 3).tolist()} vs "
                f"{np.round(raw.origin_mm, 3).tolist()} mm", labels_path)
    if raw is None and lmap is None:
        raise ValueError("need a volume path or a label map")
    grid = raw if raw is not None else lmap
    source = grid.source if lmap is None or raw is None else \
        f"{raw.source} + labels {lmap.source}"
    hu = None if raw is None else raw.data             # the source's type, no copy
    src = RawVolume(labels_from_intensity(hu, None if lmap is None else lmap.data, kinds,
                                          label_values, bone_threshold_hu,
                                          Path(path if path is not None else labels_path),
                                          labels_path),
                    grid.spacing_mm, grid.origin_mm, grid.source)
    grid = lmap = raw = None                           # the map is done with: freed
    voxel = engine_voxel_mm(voxel_mm, src.spacing_mm)
    _check_source(src, voxel, path if path is not None else labels_path)
    labels, origin = resample_isotropic(src.data, src.spacing_mm, src.origin_mm, voxel,
                                        order=0)
    if hu is not None:
        hu, _ = resample_isotropic(hu, src.spacing_mm, src.origin_mm, voxel, order=1)
    return CaseVolume(labels, voxel, origin, source, hu, native=_native_or_none(labels, src))


def _native_or_none(labels: np.ndarray, raw: RawVolume) -> NativeLabels | None:
    """The source's labels to keep beside the engine's ``labels``: None when
    they are the same array (no resampling happened)."""
    if labels is raw.data:
        return None
    return NativeLabels(raw.data, raw.spacing_mm, raw.origin_mm)
