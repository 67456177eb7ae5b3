"""DICOM series: one CT series as a folder of single-slice files.

Reading orders slices by position along the slice normal and returns HU in
the LPS patient frame (DICOM's own); writing produces an axial series that
3D Slicer and other viewers read with the same anatomy.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.io.raw_volume import GRID_TOL_MM, OBLIQUE_TOL, RawVolume, snap_to_lps

__all__ = ["SLICE_GAP_RTOL", "DICOM_HU_OFFSET", "read_dicom_series",
           "write_dicom_series"]

SLICE_GAP_RTOL = 0.01
"""Largest relative deviation of one DICOM slice gap from the mean gap."""

DICOM_HU_OFFSET = 1024
"""Written DICOM pixels are ``HU + 1024`` (unsigned), intercept -1024."""


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
        ``data`` HU, axes along +x, +y, +z: int16 when every slice's rescale
        gives whole HU that fit it (the usual CT: slope 1, intercept -1024),
        else float32. Slices are decoded one at a time into the one volume
        (no list of planes, no float copy of an integer CT).
    """
    import pydicom
    from pydicom.errors import InvalidDicomError

    folder = Path(folder)
    files = _dicom_files(folder)
    slices = []
    for f in files:                    # headers only: the pixels are read one by one below
        try:
            ds = pydicom.dcmread(f, stop_before_pixels=True)
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

    rows, cols = sizes.popitem()[0]
    vol = np.empty((cols, rows, len(order)), dtype=_hu_dtype(slices))
    for k, idx in enumerate(order):
        f = files[idx]
        try:
            ds = pydicom.dcmread(f)
        except (InvalidDicomError, OSError, ValueError, EOFError) as exc:
            raise BonesimError(f"unreadable DICOM slice: {exc}", f) from None
        if "PixelData" not in ds:
            raise BonesimError("slice has no pixel data", f)
        try:
            px = ds.pixel_array
        except Exception as exc:  # pydicom raises many types for bad pixel data
            raise BonesimError(f"cannot decode pixel data: {exc}", f) from None
        if px.ndim != 2:
            raise BonesimError(f"expected a single-frame slice, got pixel array of "
                               f"shape {px.shape}", f)
        slope, icpt = _rescale(ds)
        if vol.dtype == np.int16:
            plane = px.astype(np.int64) * int(slope) + int(icpt)
            if plane.size and (plane.min() < -32768 or plane.max() > 32767):
                vol = vol.astype(np.float32)            # rare: HU beyond int16
        if vol.dtype != np.int16:
            plane = px.astype(np.float32) * np.float32(slope) + np.float32(icpt)
        vol[:, :, k] = plane.T                          # (cols, rows) of slice k
    affine = np.eye(4)
    affine[:3, 0] = row_dir * pix[0, 1]       # along a row: column index
    affine[:3, 1] = col_dir * pix[0, 0]       # down a column: row index
    affine[:3, 2] = (pos[order[-1]] - pos[order[0]]) / (len(order) - 1)
    affine[:3, 3] = pos[order[0]]
    src = f"{folder} (DICOM series, {len(order)} slices)"
    return snap_to_lps(vol, affine, folder, src)


def _rescale(ds) -> tuple[float, float]:
    """``(RescaleSlope, RescaleIntercept)`` of a slice (1, 0 when absent)."""
    return (float(getattr(ds, "RescaleSlope", 1.0) or 1.0),
            float(getattr(ds, "RescaleIntercept", 0.0) or 0.0))


def _hu_dtype(slices) -> np.dtype:
    """int16 when every slice's rescale is whole (its HU are whole numbers;
    a slice whose HU then do not fit int16 turns the volume to float32 as it
    is read), else float32."""
    for ds in slices:
        slope, icpt = _rescale(ds)
        if slope != round(slope) or icpt != round(icpt):
            return np.dtype(np.float32)
    return np.dtype(np.int16)


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
