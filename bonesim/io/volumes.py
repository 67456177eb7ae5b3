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
   an optional label map), then resamples to isotropic voxels.

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
from bonesim.io.images import (NRRD_GZIP_LEVEL, read_nifti, read_nrrd,  # noqa: F401
                               write_nifti, write_nrrd)
from bonesim.io.label_stack import (UNKNOWN_COLOR_MODES, natural_key,  # noqa: F401
                                    read_label_stack, write_label_stack)
from bonesim.io.orientation import PATIENT_FRAME
from bonesim.io.raw_volume import (GRID_TOL_MM, MAX_LISTED, MAX_STRUCTURES,  # noqa: F401
                                   OBLIQUE_TOL, SPACING_RTOL, ObliqueWarning, RawVolume)
from bonesim.io.segmentation import (SEG_SUFFIX, embed_on_grid, read_segmentation,  # noqa: F401
                                     write_seg_nrrd)

__all__ = ["FORMATS", "NativeLabels", "CaseVolume", "labels_from_intensity",
           "nearest_indices", "resample_isotropic", "load_volume", "DICOM_HU_OFFSET",
           "SLICE_GAP_RTOL", "read_dicom_series", "write_dicom_series", "BonesimError",
           "NRRD_GZIP_LEVEL", "read_nifti", "read_nrrd", "write_nifti", "write_nrrd",
           "UNKNOWN_COLOR_MODES", "natural_key", "read_label_stack",
           "write_label_stack", "PATIENT_FRAME", "GRID_TOL_MM", "MAX_LISTED",
           "MAX_STRUCTURES", "OBLIQUE_TOL", "SPACING_RTOL", "ObliqueWarning",
           "RawVolume", "SEG_SUFFIX", "embed_on_grid", "read_segmentation",
           "write_seg_nrrd"]

FORMATS = ("phantom", "dicom", "nrrd", "nifti", "label-stack", "seg-nrrd")
"""Volume formats a case manifest may name."""


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
    hu : (nx, ny, nz) float32 or None
        Intensities [HU] where the format has them.
    native : NativeLabels or None
        The labels at the source's resolution (None: the source is this grid;
        see :attr:`native_labels`).
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
            self.hu = np.asarray(self.hu, dtype=np.float32)
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
        """Voxel count per index ``0 .. n_structures`` (index 0 = empty)."""
        return np.bincount(self.labels.ravel(), minlength=n_structures + 1)

    def index_to_mm(self, ijk) -> np.ndarray:
        """Case-frame centres [mm] of voxel indices ``ijk`` (shape (..., 3))."""
        return self.origin_mm + self.spacing_mm * np.asarray(ijk, dtype=np.float64)


# ------------------------------------------------------------- label assembly
def labels_from_intensity(hu: np.ndarray | None, label_map: np.ndarray | None,
                          kinds: Sequence[str], label_values: Sequence[int | None],
                          bone_threshold_hu: float, source: Path,
                          labels_source: Path | None = None) -> np.ndarray:
    """Structure indices from intensities and an optional label map.

    Parameters
    ----------
    hu : (nx, ny, nz) float or None
        Intensities [HU]; voxels ``>= bone_threshold_hu`` become the first
        structure of kind ``"bone"``.
    label_map : (nx, ny, nz) int or None
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
    if hu is not None:
        out[hu >= bone_threshold_hu] = bone
    if label_map is not None:
        lm = np.asarray(label_map)
        where = labels_source or source
        if not np.issubdtype(lm.dtype, np.integer):
            if not np.all(np.isfinite(lm)) or np.any(lm != np.round(lm)):
                raise BonesimError("label map has non-integer values", where)
            lm = lm.astype(np.int64)
        values, counts = np.unique(lm, return_counts=True)
        table = {int(v): s for s, v in enumerate(label_values, start=1) if v is not None}
        bad = [(int(v), int(c)) for v, c in zip(values, counts)
               if v != 0 and int(v) not in table]
        if bad:
            listed = ", ".join(f"{v} ({c} voxels)" for v, c in bad[:MAX_LISTED])
            more = f" and {len(bad) - MAX_LISTED} more" if len(bad) > MAX_LISTED else ""
            raise BonesimError(
                f"label map has {len(bad)} value(s) no structure claims: {listed}"
                f"{more}; known labels: {sorted(table)}", where)
        idx = np.zeros(lm.shape, dtype=np.uint8)
        for v, s in table.items():
            idx[lm == v] = s
        np.copyto(out, idx, where=idx > 0)
    bone_idx = [s for s, k in enumerate(kinds, start=1) if k == "bone"]
    if not np.isin(out, bone_idx).any():
        what = ""
        if hu is not None and hu.size:
            what = (f"no voxel reaches bone_threshold_hu = {bone_threshold_hu:g} "
                    f"(intensities range {float(hu.min()):g} to {float(hu.max()):g})")
        if label_map is not None:
            what += ("; " if what else "") + "the label map marks no bone structure"
        raise BonesimError(f"no bone after thresholding: {what}", source)
    return out


def nearest_indices(n_in: int, spacing_mm: float, voxel_mm: float, n_out: int
                    ) -> np.ndarray:
    """Source index of each output voxel's centre along one axis (nearest).

    Output voxel ``o`` (edge ``voxel_mm``) is centred at
    ``(o + 0.5) * voxel_mm`` from the box's low edge, which falls in source
    voxel ``floor(c + 0.5)`` with ``c = (o + 0.5) * voxel_mm / spacing_mm - 0.5``,
    clipped to the source (the box's edges repeat the edge voxels). ``c`` is
    evaluated in the floating-point order ``scipy.ndimage.affine_transform``
    uses for a diagonal matrix, so ties (a centre exactly on a voxel
    boundary) fall the same way.

    Returns
    -------
    (n_out,) intp
    """
    scale = voxel_mm / spacing_mm
    shift = (0.5 * scale - 0.5) / scale
    c = (np.arange(n_out, dtype=np.float64) + shift) * scale
    return np.clip(np.floor(c + 0.5), 0, n_in - 1).astype(np.intp)


def resample_isotropic(data: np.ndarray, spacing_mm, origin_mm, voxel_mm: float,
                       order: int) -> tuple[np.ndarray, np.ndarray]:
    """Resample onto isotropic voxels of edge ``voxel_mm`` covering the same box.

    The physical box (voxel edge to voxel edge) is kept; the new voxel count
    per axis is ``round(n * spacing / voxel_mm)``. When every spacing already
    equals ``voxel_mm`` the data are returned untouched (no interpolation).
    Nearest-neighbour resampling picks source voxels axis by axis
    (:func:`nearest_indices`): it reads only the voxels it keeps and gives the
    same result as a full ``scipy.ndimage.affine_transform`` of order 0.

    Parameters
    ----------
    data : (nx, ny, nz) array
        Axes along x, y, z.
    spacing_mm : (3,) float
        Current voxel edges [mm].
    origin_mm : (3,) float
        Current centre of voxel (0, 0, 0) [mm].
    voxel_mm : float
        Target edge [mm].
    order : int
        0 nearest neighbour (labels), 1 linear (intensities).

    Returns
    -------
    data : (mx, my, mz) array
    origin_mm : (3,) float64
    """
    spacing = np.asarray(spacing_mm, dtype=np.float64).reshape(3)
    origin = np.asarray(origin_mm, dtype=np.float64).reshape(3)
    if np.allclose(spacing, voxel_mm, rtol=SPACING_RTOL, atol=0.0):
        return data, origin
    shape = [int(n) for n in
             np.maximum(1, np.round(np.asarray(data.shape) * spacing / voxel_mm))]
    new_origin = origin - spacing / 2 + voxel_mm / 2
    if order == 0:
        out = data
        for a in range(3):                     # shrinking axes first keeps it small
            idx = nearest_indices(data.shape[a], spacing[a], voxel_mm, shape[a])
            out = np.take(out, idx, axis=a)
        return np.ascontiguousarray(out), new_origin
    from scipy import ndimage

    scale = voxel_mm / spacing
    out = ndimage.affine_transform(data, scale, offset=0.5 * scale - 0.5,
                                   output_shape=tuple(shape), order=order,
                                   mode="nearest", prefilter=False)
    return out, new_origin


# ------------------------------------------------------------------- loading
def _same_grid(a: RawVolume, b: RawVolume) -> bool:
    return (a.data.shape == b.data.shape
            and np.allclose(a.spacing_mm, b.spacing_mm, atol=GRID_TOL_MM)
            and np.allclose(a.origin_mm, b.origin_mm, atol=GRID_TOL_MM))


def _check_bone(labels: np.ndarray, kinds, path, what: str) -> None:
    bone_idx = [s for s, k in enumerate(kinds, start=1) if k == "bone"]
    if not np.isin(labels, bone_idx).any():
        raise BonesimError(f"no bone: {what}", path)


def load_volume(fmt: str, path: Path | None, *, kinds: Sequence[str],
                label_values: Sequence[int | None] = (),
                colors: Sequence = (), voxel_mm: float = 0.5,
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
    voxel_mm : float
        Isotropic output voxel edge [mm].
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
        native = NativeLabels(raw.data, raw.spacing_mm, raw.origin_mm)
        labels, origin = resample_isotropic(raw.data, raw.spacing_mm, raw.origin_mm,
                                            voxel_mm, order=0)
        _check_bone(labels, kinds, path, what)
        return CaseVolume(labels, voxel_mm, origin, raw.source, native=native)

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
    hu = None if raw is None else raw.data.astype(np.float32, copy=False)
    labels = labels_from_intensity(hu, None if lmap is None else lmap.data, kinds,
                                   label_values, bone_threshold_hu,
                                   Path(path if path is not None else labels_path),
                                   labels_path)
    native = NativeLabels(labels, grid.spacing_mm, grid.origin_mm)
    labels, origin = resample_isotropic(labels, grid.spacing_mm, grid.origin_mm,
                                        voxel_mm, order=0)
    if hu is not None:
        hu, _ = resample_isotropic(hu, grid.spacing_mm, grid.origin_mm, voxel_mm,
                                   order=1)
    source = grid.source if lmap is None or raw is None else \
        f"{raw.source} + labels {lmap.source}"
    return CaseVolume(labels, voxel_mm, origin, source, hu, native=native)
