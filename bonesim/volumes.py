"""CT volumes and label maps: reading, labelling, resampling, writing.

Frame and layout
----------------
Every volume handed to the engine is a :class:`CaseVolume`: arrays indexed
``[i, j, k]`` along the case-frame axes ``(x, y, z)``, isotropic spacing
``spacing_mm`` and the centre of voxel ``(0, 0, 0)`` at ``origin_mm``. The case
frame is anatomical LPS, as in DICOM: ``+x`` toward the patient's left, ``+y``
posterior, ``+z`` superior.

Reading is split in two steps:

1. a reader turns one file or folder into a :class:`RawVolume` whose array is
   already reordered (flips / axis permutations only, never interpolated) so
   that its axes run along ``+x, +y, +z``; spacing may still differ per axis;
2. :func:`load_volume` turns intensities into structure labels (threshold plus
   an optional label map), then resamples to isotropic voxels.

Orientation
-----------
NIfTI affines are RAS (``x`` toward the right, ``y`` anterior): the ``x`` and
``y`` rows are negated to get LPS. NRRD ``space`` may be LPS, RAS or LAS; DICOM
is LPS by definition. An **oblique** volume (direction cosines not aligned with
the case axes) is reordered onto the nearest axes and its residual rotation is
dropped; an :class:`ObliqueWarning` says so and by how many degrees. The voxel
data are never rotated, so a slightly tilted gantry gives a slightly tilted
anatomy rather than an interpolated one.

Labels
------
``labels`` values are 1-based indices into the case's structure list, 0 for
empty (air, background). For intensity volumes, voxels ``>= bone_threshold_hu``
become the first structure of kind ``"bone"``; a label map, if given, then
overrides: a voxel whose map value equals a structure's ``label`` integer gets
that structure's index. Map value 0 never overrides. A map value that no
structure claims is an error.

Every problem with the input is raised as one
:class:`~bonesim.errors.BonesimError` naming the file or folder.
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import BonesimError
from .orientation import (PATIENT_FRAME, from_lps, lps_geometry, parse_orientation,
                          to_lps)

FORMATS = ("phantom", "dicom", "nrrd", "nifti", "label-stack")
"""Volume formats a case manifest may name."""

UNKNOWN_COLOR_MODES = ("error", "nearest", "background")
"""What to do with label-stack colours that match no structure."""

MAX_STRUCTURES = 255
"""Structure indices are stored as uint8 (0 is empty)."""

SPACING_RTOL = 1e-6
"""Relative tolerance under which a spacing counts as equal to ``voxel_mm``."""

SLICE_GAP_RTOL = 0.01
"""Largest relative deviation of one DICOM slice gap from the mean gap."""

OBLIQUE_TOL = 1e-4
"""Largest direction-cosine deviation still treated as axis-aligned."""

GRID_TOL_MM = 1e-3
"""Tolerance when checking that a label map shares its volume's grid [mm]."""

MAX_LISTED = 8
"""How many offending items (colours, values, files) an error message lists."""

DICOM_HU_OFFSET = 1024
"""Written DICOM pixels are ``HU + 1024`` (unsigned), intercept -1024."""

NRRD_GZIP_LEVEL = 1
"""gzip level for written NRRD files (fast; the data compress well anyway)."""

_LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0])
_LPS_FROM_SPACE = {
    "left-posterior-superior": np.eye(3),
    "lps": np.eye(3),
    "right-anterior-superior": _LPS_FROM_RAS,
    "ras": _LPS_FROM_RAS,
    "left-anterior-superior": np.diag([1.0, -1.0, 1.0]),
    "las": np.diag([1.0, -1.0, 1.0]),
}


class ObliqueWarning(UserWarning):
    """A volume's axes were snapped to the nearest case-frame axes."""


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


@dataclass
class RawVolume:
    """One file's data, axes already along ``+x, +y, +z`` of the case frame.

    Attributes
    ----------
    data : (nx, ny, nz) array
        Intensities (readers of CT formats) or structure indices (label stack).
    spacing_mm : (3,) float64
        Voxel edge along x, y, z [mm]; may be anisotropic.
    origin_mm : (3,) float64
        Case-frame centre of voxel ``(0, 0, 0)`` [mm].
    source : str
        The file or folder read, with its format.
    """

    data: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    source: str


# ---------------------------------------------------------------- orientation
def _snap_to_lps(data: np.ndarray, affine: np.ndarray, path: Path, source: str
                 ) -> RawVolume:
    """Reorder ``data`` so its axes run along +x, +y, +z (LPS).

    Parameters
    ----------
    data : (n0, n1, n2) array
        Voxel data in file index order.
    affine : (4, 4) float
        Index -> case-frame (LPS) position [mm] of voxel centres.
    path : Path
        File or folder, for messages.
    source : str
        Description kept in the result.
    """
    from nibabel.orientations import (apply_orientation, inv_ornt_aff,
                                      io_orientation, ornt_transform)

    affine = np.asarray(affine, dtype=np.float64)
    cols = affine[:3, :3]
    norms = np.linalg.norm(cols, axis=0)
    if not np.all(np.isfinite(affine)) or np.any(norms <= 0):
        raise BonesimError("missing or invalid voxel spacing / orientation "
                           f"(axis lengths {np.round(norms, 6).tolist()} mm)", path)
    ornt = io_orientation(affine)
    if np.isnan(ornt).any():
        raise BonesimError("degenerate orientation: two axes point the same way", path)
    to_lps = ornt_transform(ornt, np.array([[0, 1], [1, 1], [2, 1]]))
    out = apply_orientation(data, to_lps)
    aff = affine @ inv_ornt_aff(to_lps, data.shape)
    spacing = np.linalg.norm(aff[:3, :3], axis=0)
    dirs = aff[:3, :3] / spacing
    dev = np.abs(dirs - np.eye(3)).max()
    if dev > OBLIQUE_TOL:
        angle = np.degrees(np.arccos(np.clip(np.diag(dirs).min(), -1.0, 1.0)))
        warnings.warn(f"{path}: volume is oblique (up to {angle:.1f} deg off the "
                      "case axes); its axes were snapped to the nearest case axes "
                      "without resampling", ObliqueWarning, stacklevel=3)
    return RawVolume(np.ascontiguousarray(out), spacing, aff[:3, 3].copy(), source)


# --------------------------------------------------------------------- DICOM
def _dicom_files(folder: Path) -> list[Path]:
    if not folder.exists():
        raise BonesimError("DICOM folder not found", folder)
    if not folder.is_dir():
        raise BonesimError("expected a folder of DICOM slices, got a file", folder)
    files = sorted(p for p in folder.iterdir()
                   if p.is_file() and not p.name.startswith(".")
                   and p.name.upper() != "DICOMDIR")
    if not files:
        raise BonesimError("no DICOM files in folder", folder)
    return files


def read_dicom_series(folder: str | Path) -> RawVolume:
    """Read one DICOM series (a folder of single-slice files) as HU.

    Slices are ordered by ``ImagePositionPatient`` projected on the slice
    normal (never by file name or ``InstanceNumber``). In-plane spacing comes
    from ``PixelSpacing``, slice spacing from the position differences, which
    must be uniform. ``RescaleSlope`` / ``RescaleIntercept`` give HU.

    Parameters
    ----------
    folder : str or Path
        Folder holding the slices (hidden files and ``DICOMDIR`` skipped).

    Returns
    -------
    RawVolume
        ``data`` float32 HU, axes along +x, +y, +z.
    """
    import pydicom
    from pydicom.errors import InvalidDicomError

    folder = Path(folder)
    files = _dicom_files(folder)
    slices = []
    for f in files:
        try:
            ds = pydicom.dcmread(f)
        except (InvalidDicomError, OSError, ValueError, EOFError) as exc:
            raise BonesimError(f"unreadable DICOM slice: {exc}", f) from None
        slices.append(ds)

    series = {str(getattr(ds, "SeriesInstanceUID", "")) for ds in slices}
    if len(series) > 1:
        raise BonesimError(f"folder mixes {len(series)} DICOM series; keep one "
                           "series per folder", folder)
    sizes: dict[tuple, list[Path]] = {}
    for f, ds in zip(files, slices):
        for key in ("Rows", "Columns", "ImagePositionPatient",
                    "ImageOrientationPatient"):
            if key not in ds:
                raise BonesimError(f"slice lacks {key}", f)
        if "PixelSpacing" not in ds:
            raise BonesimError("missing spacing: slice lacks PixelSpacing", f)
        if "PixelData" not in ds:
            raise BonesimError("slice has no pixel data", f)
        sizes.setdefault((int(ds.Rows), int(ds.Columns)), []).append(f)
    if len(sizes) > 1:
        parts = [f"{r}x{c} ({len(fs)} file(s), e.g. {fs[0].name})"
                 for (r, c), fs in sorted(sizes.items(), key=lambda kv: -len(kv[1]))]
        raise BonesimError("mixed slice sizes (rows x columns): " + ", ".join(parts),
                           folder)
    if len(slices) < 2:
        raise BonesimError("missing spacing: a single slice gives no slice spacing; "
                           "need at least 2 slices", folder)

    iop = np.array([np.asarray(ds.ImageOrientationPatient, float) for ds in slices])
    if np.abs(iop - iop[0]).max() > OBLIQUE_TOL:
        raise BonesimError("slices have different ImageOrientationPatient", folder)
    row_dir, col_dir = iop[0, :3], iop[0, 3:]
    normal = np.cross(row_dir, col_dir)
    if not np.isclose(np.linalg.norm(normal), 1.0, atol=1e-3):
        raise BonesimError("invalid ImageOrientationPatient (not two unit "
                           "perpendicular vectors)", files[0])
    pix = np.array([np.asarray(ds.PixelSpacing, float) for ds in slices])
    if pix.shape[1] != 2 or np.any(pix <= 0):
        raise BonesimError("missing spacing: invalid PixelSpacing", folder)
    if np.abs(pix - pix[0]).max() > GRID_TOL_MM:
        raise BonesimError("slices have different PixelSpacing", folder)
    pos = np.array([np.asarray(ds.ImagePositionPatient, float) for ds in slices])
    depth = pos @ normal
    order = np.argsort(depth, kind="stable")
    depth = depth[order]
    gaps = np.diff(depth)
    if np.any(gaps < GRID_TOL_MM):
        k = int(np.argmin(gaps))
        raise BonesimError(
            "two slices at the same position: "
            f"{files[order[k]].name} and {files[order[k + 1]].name}", folder)
    mean_gap = float(gaps.mean())
    if np.abs(gaps - mean_gap).max() > SLICE_GAP_RTOL * mean_gap:
        raise BonesimError(
            f"inconsistent slice spacing: gaps between slice positions range from "
            f"{gaps.min():.4g} to {gaps.max():.4g} mm (missing slices?)", folder)

    planes = []
    for idx in order:
        ds, f = slices[idx], files[idx]
        try:
            px = ds.pixel_array
        except Exception as exc:  # pydicom raises many types for bad pixel data
            raise BonesimError(f"cannot decode pixel data: {exc}", f) from None
        if px.ndim != 2:
            raise BonesimError(f"expected a single-frame slice, got pixel array of "
                               f"shape {px.shape}", f)
        slope = float(getattr(ds, "RescaleSlope", 1.0) or 1.0)
        icpt = float(getattr(ds, "RescaleIntercept", 0.0) or 0.0)
        planes.append(px.astype(np.float32) * np.float32(slope) + np.float32(icpt))
    vol = np.stack(planes, axis=0).transpose(2, 1, 0)     # (cols, rows, slices)
    affine = np.eye(4)
    affine[:3, 0] = row_dir * pix[0, 1]       # along a row: column index
    affine[:3, 1] = col_dir * pix[0, 0]       # down a column: row index
    affine[:3, 2] = (pos[order[-1]] - pos[order[0]]) / (len(order) - 1)
    affine[:3, 3] = pos[order[0]]
    src = f"{folder} (DICOM series, {len(order)} slices)"
    return _snap_to_lps(vol, affine, folder, src)


def write_dicom_series(folder: str | Path, hu: np.ndarray, spacing_mm: float,
                       origin_mm, description: str = "bonesim export") -> list[Path]:
    """Write an axial CT series, one file per ``z`` slice.

    Parameters
    ----------
    folder : str or Path
        Created if needed; files ``slice0001.dcm, ...``.
    hu : (nx, ny, nz) float
        Intensities [HU], axis order ``(x, y, z)``; rounded to integers and
        stored as unsigned ``HU + 1024``.
    spacing_mm : float
        Isotropic voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel ``(0, 0, 0)`` [mm].
    description : str
        ``SeriesDescription``.

    Returns
    -------
    list of Path
        The files written, in slice order.
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    hu = np.asarray(hu)
    stored = np.rint(hu.astype(np.float64) + DICOM_HU_OFFSET)
    if stored.min() < 0 or stored.max() > np.iinfo(np.uint16).max:
        raise ValueError("HU out of the range a 16-bit DICOM slice can hold")
    stored = stored.astype(np.uint16)
    origin = np.asarray(origin_mm, dtype=np.float64)
    study, series, frame = generate_uid(), generate_uid(), generate_uid()
    nx, ny, nz = hu.shape
    width = max(4, len(str(nz)))
    paths = []
    for k in range(nz):
        uid = generate_uid()
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = uid
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = uid
        ds.StudyInstanceUID = study
        ds.SeriesInstanceUID = series
        ds.FrameOfReferenceUID = frame
        ds.Modality = "CT"
        ds.PatientName = "bonesim^phantom"
        ds.PatientID = "bonesim"
        ds.SeriesDescription = description[:64]
        ds.SeriesNumber = 1
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [float(v) for v in origin + (0.0, 0.0, k * spacing_mm)]
        ds.ImageOrientationPatient = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        ds.PixelSpacing = [float(spacing_mm), float(spacing_mm)]
        ds.SliceThickness = float(spacing_mm)
        ds.Rows, ds.Columns = ny, nx
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated = 16
        ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 0
        ds.RescaleSlope = 1
        ds.RescaleIntercept = -DICOM_HU_OFFSET
        ds.RescaleType = "HU"
        ds.PixelData = np.ascontiguousarray(stored[:, :, k].T).tobytes()
        path = folder / f"slice{k + 1:0{width}d}.dcm"
        ds.save_as(path, enforce_file_format=True)
        paths.append(path)
    return paths


# ---------------------------------------------------------------- NRRD, NIfTI
def _check_file(path: Path, what: str) -> None:
    if not path.exists():
        raise BonesimError(f"{what} file not found", path)
    if not path.is_file():
        raise BonesimError(f"expected a {what} file, got a folder", path)


def _squeeze3(data: np.ndarray, path: Path) -> np.ndarray:
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise BonesimError(f"expected a 3-D volume, got shape {data.shape}", path)
    return data


def read_nrrd(path: str | Path) -> RawVolume:
    """Read a 3-D NRRD volume (intensities or a label map).

    Orientation comes from ``space``, ``space directions`` and
    ``space origin``; a file with only ``spacings`` (no ``space``) is taken as
    axis-aligned with the case frame, origin 0.

    Returns
    -------
    RawVolume
        Data in their stored dtype, axes along +x, +y, +z.
    """
    import nrrd

    path = Path(path)
    _check_file(path, "NRRD")
    try:
        data, hdr = nrrd.read(str(path), index_order="F")
    except Exception as exc:  # pynrrd raises NRRDError, ValueError, OSError...
        raise BonesimError(f"unreadable NRRD file: {exc}", path) from None
    data = _squeeze3(np.asarray(data), path)
    affine = np.eye(4)
    dirs = hdr.get("space directions")
    if dirs is not None:
        dirs = np.array([np.full(3, np.nan) if d is None else np.asarray(d, float)
                         for d in dirs], dtype=float)
        dirs = dirs[~np.isnan(dirs).any(axis=1)]
        if dirs.shape != (3, 3):
            raise BonesimError("missing spacing: 'space directions' does not give "
                               "three spatial axes", path)
        space = str(hdr.get("space", "left-posterior-superior")).lower()
        if space not in _LPS_FROM_SPACE:
            raise BonesimError(f"unsupported NRRD space {space!r}; use one of "
                               f"{sorted(k for k in _LPS_FROM_SPACE if '-' in k)}",
                               path)
        to_lps = _LPS_FROM_SPACE[space]
        affine[:3, :3] = to_lps @ dirs.T
        origin = np.asarray(hdr.get("space origin", np.zeros(3)), float)
        affine[:3, 3] = to_lps @ origin
    else:
        sp = hdr.get("spacings")
        sp = None if sp is None else np.asarray(sp, dtype=float)
        if sp is None or sp.shape != (3,) or np.any(~np.isfinite(sp)) or np.any(sp <= 0):
            raise BonesimError("missing spacing: the header has neither 'space "
                               "directions' nor three positive 'spacings'", path)
        affine[:3, :3] = np.diag(sp)
    return _snap_to_lps(data, affine, path, f"{path} (NRRD)")


def read_nifti(path: str | Path, scaled: bool = True) -> RawVolume:
    """Read a 3-D NIfTI volume; its RAS affine is converted to LPS.

    Parameters
    ----------
    path : str or Path
        ``.nii`` or ``.nii.gz``.
    scaled : bool
        Apply ``scl_slope`` / ``scl_inter`` (intensities: yes; label maps: no).
    """
    import nibabel as nib

    path = Path(path)
    _check_file(path, "NIfTI")
    try:
        img = nib.load(str(path))
        data = (np.asarray(img.dataobj, dtype=np.float32) if scaled
                else np.asarray(img.dataobj.get_unscaled()))
    except Exception as exc:  # nibabel raises ImageFileError, OSError, EOFError...
        raise BonesimError(f"unreadable NIfTI file: {exc}", path) from None
    data = _squeeze3(data, path)
    zooms = np.asarray(img.header.get_zooms()[:3], dtype=float)
    if np.any(~np.isfinite(zooms)) or np.any(zooms <= 0):
        raise BonesimError(f"missing spacing: pixdim is {zooms.tolist()}", path)
    affine = np.eye(4)
    affine[:3, :] = _LPS_FROM_RAS @ np.asarray(img.affine, float)[:3, :]
    return _snap_to_lps(data, affine, path, f"{path} (NIfTI)")


def _lps_affine(spacing_mm: float, origin_mm) -> np.ndarray:
    aff = np.diag([spacing_mm] * 3 + [1.0])
    aff[:3, 3] = np.asarray(origin_mm, dtype=float)
    return aff


def write_nrrd(path: str | Path, data: np.ndarray, spacing_mm: float, origin_mm) -> Path:
    """Write ``data`` (axes x, y, z) as a gzip NRRD in LPS space."""
    import nrrd

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    hdr = {
        "space": "left-posterior-superior",
        "space directions": np.eye(3) * float(spacing_mm),
        "space origin": np.asarray(origin_mm, dtype=float),
        "kinds": ["domain"] * 3,
        "encoding": "gzip",
    }
    nrrd.write(str(path), np.asarray(data), hdr, index_order="F",
               compression_level=NRRD_GZIP_LEVEL)
    return path


def write_nifti(path: str | Path, data: np.ndarray, spacing_mm: float, origin_mm) -> Path:
    """Write ``data`` (axes x, y, z) as NIfTI-1 with the equivalent RAS affine."""
    import nibabel as nib

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ras = _lps_affine(spacing_mm, origin_mm)
    ras[:3, :] = _LPS_FROM_RAS @ ras[:3, :]
    img = nib.Nifti1Image(np.asarray(data), ras)
    img.header.set_xyzt_units("mm")
    img.set_qform(ras, code=1)
    img.set_sform(ras, code=1)
    nib.save(img, str(path))
    return path


# --------------------------------------------------------------- label stacks
def natural_key(name: str) -> tuple:
    """Sort key that orders embedded numbers numerically (plane2 < plane10)."""
    parts = re.split(r"(\d+)", name)
    key = tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts)
    return key, name


def _pack_rgb(rgb) -> np.ndarray:
    rgb = np.asarray(rgb, dtype=np.uint32)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


def _unpack_rgb(code: int) -> tuple[int, int, int]:
    code = int(code)
    return (code >> 16) & 255, (code >> 8) & 255, code & 255


def read_label_stack(folder: str | Path, pattern: str, size_mm, colors,
                     unknown_colors: str = "error", origin_mm=None,
                     orientation: str = PATIENT_FRAME) -> RawVolume:
    """Read a folder of RGB(A) slices where each colour marks one structure.

    Parameters
    ----------
    folder : str or Path
        Folder of images.
    pattern : str
        Glob selecting the slices (e.g. ``"*.png"``); matches are sorted
        naturally (``plane2`` before ``plane10``). Slice ``k`` is ``z`` index k.
    size_mm : (3,) float
        Physical extent of the stack along image columns, image rows (top row
        first) and slices, in that order [mm].
    colors : sequence of (3,) int or None
        RGB of structure ``s`` at position ``s - 1``; ``None`` for a structure
        not drawn in the stack.
    unknown_colors : {"error", "nearest", "background"}
        Colours matching no structure: raise (naming each colour and its voxel
        count), map to the nearest structure colour (RGB distance), or drop.
        Black and fully transparent pixels are always background.
    origin_mm : (3,) float, optional
        Case-frame (LPS) centre of the first slice's top-left pixel [mm];
        default centres the stack on 0.
    orientation : str
        The stack's axis code (:mod:`bonesim.orientation`): the directions
        in which image columns, rows and slices increase. ``"LPS"`` (the
        default) reads columns as ``+x``, rows as ``+y``, slices as ``+z``.

    Returns
    -------
    RawVolume
        ``data`` uint8 structure indices, axes along +x, +y, +z (LPS).
    """
    from PIL import Image, UnidentifiedImageError

    folder = Path(folder)
    if not folder.exists():
        raise BonesimError("label-stack folder not found", folder)
    if not folder.is_dir():
        raise BonesimError("expected a folder of label images, got a file", folder)
    if unknown_colors not in UNKNOWN_COLOR_MODES:
        raise ValueError(f"unknown_colors must be one of {UNKNOWN_COLOR_MODES}")
    files = sorted((p for p in folder.glob(pattern) if p.is_file()),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise BonesimError(f"no images match pattern {pattern!r}", folder)
    planes = []
    sizes: dict[tuple, list[Path]] = {}
    for f in files:
        try:
            with Image.open(f) as im:
                im.load()
                rgba = np.asarray(im.convert("RGBA"))
        except (UnidentifiedImageError, OSError, ValueError) as exc:
            raise BonesimError(f"unreadable slice image: {exc}", f) from None
        sizes.setdefault(rgba.shape[:2], []).append(f)
        planes.append(rgba)
    if len(sizes) > 1:
        parts = [f"{w}x{h} px ({len(fs)} file(s), e.g. {fs[0].name})"
                 for (h, w), fs in sorted(sizes.items(), key=lambda kv: -len(kv[1]))]
        raise BonesimError("mixed slice sizes (width x height): " + ", ".join(parts),
                           folder)
    stack = np.stack(planes, axis=0)                       # (nz, ny, nx, 4)
    code = _pack_rgb(stack[..., :3])
    code[stack[..., 3] == 0] = 0                           # transparent = background
    code = code.transpose(2, 1, 0)                         # -> (nx, ny, nz)
    labels = np.zeros(code.shape, dtype=np.uint8)
    known = {}
    for s, rgb in enumerate(colors, start=1):
        if rgb is None:
            continue
        key = int(_pack_rgb(rgb))
        known[key] = s
        labels[code == key] = s
    stray = (labels == 0) & (code != 0)
    if stray.any():
        values, counts = np.unique(code[stray], return_counts=True)
        if unknown_colors == "error":
            order = np.argsort(-counts)
            listed = ", ".join(f"RGB{_unpack_rgb(values[i])} x {counts[i]} voxels"
                               for i in order[:MAX_LISTED])
            more = (f" and {len(values) - MAX_LISTED} more"
                    if len(values) > MAX_LISTED else "")
            raise BonesimError(
                f"{len(values)} colour(s) match no structure ({int(counts.sum())} "
                f"voxels): {listed}{more}; add them to [[structures]] or set "
                "unknown_colors = \"nearest\" or \"background\"", folder)
        if unknown_colors == "nearest" and known:
            ref_codes = np.array(sorted(known), dtype=np.uint32)
            ref = np.array([_unpack_rgb(c) for c in ref_codes], dtype=float)
            got = np.array([_unpack_rgb(c) for c in values], dtype=float)
            near = np.argmin(((got[:, None, :] - ref[None]) ** 2).sum(-1), axis=1)
            lut_idx = np.array([known[int(ref_codes[n])] for n in near], dtype=np.uint8)
            pos = np.searchsorted(values, code[stray])
            labels[stray] = lut_idx[pos]
    shape_img = np.array(labels.shape, dtype=float)
    size = np.asarray(size_mm, dtype=float).reshape(3)
    if np.any(~np.isfinite(size)) or np.any(size <= 0):
        raise BonesimError(f"missing spacing: size_mm must be three positive "
                           f"numbers, got {size.tolist()}", folder)
    code = parse_orientation(orientation, folder, "orientation")
    labels = np.ascontiguousarray(to_lps(labels, code))
    spacing, origin = lps_geometry(code, shape_img, size / shape_img,
                                   np.zeros(3) if origin_mm is None else origin_mm)
    if origin_mm is None:                   # centred on the frame's origin
        origin = -(np.array(labels.shape) - 1) * spacing / 2
    src = f"{folder} (label stack '{pattern}', {len(files)} slices, {code})"
    return RawVolume(labels, spacing, origin, src)


def write_label_stack(folder: str | Path, labels: np.ndarray, colors,
                      stem: str = "plane", orientation: str = PATIENT_FRAME) -> list[Path]:
    """Write structure indices as RGB PNG slices ``plane1.png, plane2.png, ...``.

    Parameters
    ----------
    folder : str or Path
        Created if needed.
    labels : (nx, ny, nz) uint8
        Structure index per voxel, axis order ``(x, y, z)`` of the LPS frame.
    colors : sequence of (3,) int
        RGB of structure ``s`` at position ``s - 1``; must be unique and not
        black (black is background).
    stem : str
        File-name stem.
    orientation : str
        Axis code of the written stack (:mod:`bonesim.orientation`): with
        ``"LPS"`` slice ``k`` is ``labels[:, :, k]``, columns along x and
        rows along y. Reading the files back with the same code gives
        ``labels`` exactly.
    """
    from PIL import Image

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    code = parse_orientation(orientation)
    lut = np.zeros((MAX_STRUCTURES + 1, 3), dtype=np.uint8)
    for s, rgb in enumerate(colors, start=1):
        lut[s] = rgb
    rgb = lut[from_lps(np.asarray(labels), code)]        # image order, + RGB
    paths = []
    for k in range(rgb.shape[2]):
        path = folder / f"{stem}{k + 1}.png"
        Image.fromarray(np.ascontiguousarray(rgb[:, :, k].transpose(1, 0, 2)),
                        mode="RGB").save(path, compress_level=1)
        paths.append(path)
    return paths


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


def resample_isotropic(data: np.ndarray, spacing_mm, origin_mm, voxel_mm: float,
                       order: int) -> tuple[np.ndarray, np.ndarray]:
    """Resample onto isotropic voxels of edge ``voxel_mm`` covering the same box.

    The physical box (voxel edge to voxel edge) is kept; the new voxel count
    per axis is ``round(n * spacing / voxel_mm)``. When every spacing already
    equals ``voxel_mm`` the data are returned untouched (no interpolation).

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
    from scipy import ndimage

    shape = np.maximum(1, np.round(np.asarray(data.shape) * spacing / voxel_mm))
    scale = voxel_mm / spacing
    out = ndimage.affine_transform(data, scale, offset=0.5 * scale - 0.5,
                                   output_shape=tuple(int(n) for n in shape),
                                   order=order, mode="nearest", prefilter=False)
    return out, origin - spacing / 2 + voxel_mm / 2


# ------------------------------------------------------------------- loading
def _same_grid(a: RawVolume, b: RawVolume) -> bool:
    return (a.data.shape == b.data.shape
            and np.allclose(a.spacing_mm, b.spacing_mm, atol=GRID_TOL_MM)
            and np.allclose(a.origin_mm, b.origin_mm, atol=GRID_TOL_MM))


def load_volume(fmt: str, path: Path | None, *, kinds: Sequence[str],
                label_values: Sequence[int | None] = (),
                colors: Sequence = (), voxel_mm: float = 0.5,
                bone_threshold_hu: float = 300.0, labels_path: Path | None = None,
                pattern: str = "*.png", size_mm=None, unknown_colors: str = "error",
                origin_mm=None, orientation: str = PATIENT_FRAME) -> CaseVolume:
    """Read a CT / label volume of any file format into a :class:`CaseVolume`.

    Parameters
    ----------
    fmt : {"dicom", "nrrd", "nifti", "label-stack"}
        File format (the phantom is generated by :mod:`bonesim.phantom`).
    path : Path or None
        Intensity volume (file, or folder for DICOM / label stacks). For NRRD
        and NIfTI it may be ``None`` when ``labels_path`` alone gives the
        structures.
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
        Label map (NRRD or NIfTI, chosen by file name) on the volume's grid.
    pattern, size_mm, unknown_colors, origin_mm, orientation
        Label-stack options, see :func:`read_label_stack`.
    """
    if len(kinds) > MAX_STRUCTURES:
        raise ValueError(f"at most {MAX_STRUCTURES} structures")
    if fmt == "label-stack":
        raw = read_label_stack(path, pattern, size_mm, colors, unknown_colors,
                               origin_mm, orientation)
        native = NativeLabels(raw.data, raw.spacing_mm, raw.origin_mm)
        labels, origin = resample_isotropic(raw.data, raw.spacing_mm, raw.origin_mm,
                                            voxel_mm, order=0)
        bone_idx = [s for s, k in enumerate(kinds, start=1) if k == "bone"]
        if not np.isin(labels, bone_idx).any():
            raise BonesimError("no bone: no pixel has the colour of a bone structure",
                               path)
        return CaseVolume(labels, voxel_mm, origin, raw.source, native=native)

    readers = {"dicom": read_dicom_series, "nrrd": read_nrrd, "nifti": read_nifti}
    if fmt not in readers:
        raise ValueError(f"unknown volume format {fmt!r}")
    raw = readers[fmt](path) if path is not None else None
    lmap = None
    if labels_path is not None:
        name = Path(labels_path).name.lower()
        if name.endswith((".nii", ".nii.gz")):
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
