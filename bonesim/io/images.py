"""NRRD and NIfTI volumes (intensities or label maps) in the LPS patient frame.

NIfTI affines are RAS (``x`` toward the right, ``y`` anterior): the ``x`` and
``y`` rows are negated to get LPS. NRRD ``space`` may be LPS, RAS or LAS.
Exports write LPS NRRD and the equivalent RAS NIfTI affine, so 3D Slicer
shows the same anatomy as bonesim.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.io.raw_volume import LPS_FROM_RAS, RawVolume, check_file, snap_to_lps, squeeze3

__all__ = ["NRRD_GZIP_LEVEL", "nrrd_affine", "read_nrrd", "read_nifti", "write_nrrd",
           "write_nifti", "lps_affine"]

NRRD_GZIP_LEVEL = 1
"""gzip level for written NRRD files (fast; the data compress well anyway)."""

_LPS_FROM_SPACE = {
    "left-posterior-superior": np.eye(3),
    "lps": np.eye(3),
    "right-anterior-superior": LPS_FROM_RAS,
    "ras": LPS_FROM_RAS,
    "left-anterior-superior": np.diag([1.0, -1.0, 1.0]),
    "las": np.diag([1.0, -1.0, 1.0]),
}


def nrrd_affine(hdr: dict, path: Path) -> tuple[np.ndarray, list[int]]:
    """Index -> LPS position [mm] of a NRRD header's spatial axes.

    Orientation comes from ``space``, ``space directions`` and
    ``space origin``; a header with only ``spacings`` (no ``space``) is taken
    as axis-aligned with the case frame, origin 0. Axes whose direction is
    ``none`` (a Slicer segmentation's layer axis, a vector axis) are not
    spatial.

    Parameters
    ----------
    hdr : dict
        Header as :func:`nrrd.read_header` returns it.
    path : Path
        File, for messages.

    Returns
    -------
    affine : (4, 4) float64
        Maps the spatial axes' indices (in file order) to LPS voxel centres.
    spatial : list of int
        File axes that are spatial (three of them).
    """
    dim = int(hdr.get("dimension", len(hdr.get("sizes", ()))))
    affine = np.eye(4)
    dirs = hdr.get("space directions")
    if dirs is not None:
        rows = [np.full(3, np.nan) if d is None else np.asarray(d, float).reshape(-1)
                for d in dirs]
        spatial = [a for a, r in enumerate(rows) if r.shape == (3,)
                   and not np.isnan(r).any()]
        if len(spatial) != 3:
            raise BonesimError("missing spacing: 'space directions' does not give "
                               "three spatial axes", path, "space directions")
        space = str(hdr.get("space", "left-posterior-superior")).lower()
        if space not in _LPS_FROM_SPACE:
            raise BonesimError(f"unsupported NRRD space {space!r}; use one of "
                               f"{sorted(k for k in _LPS_FROM_SPACE if '-' in k)}",
                               path, "space")
        to_lps = _LPS_FROM_SPACE[space]
        affine[:3, :3] = to_lps @ np.array([rows[a] for a in spatial]).T
        origin = np.asarray(hdr.get("space origin", np.zeros(3)), float).reshape(-1)
        if origin.shape != (3,) or not np.isfinite(origin).all():
            raise BonesimError(f"'space origin' must be three numbers, got {origin}",
                               path, "space origin")
        affine[:3, 3] = to_lps @ origin
        return affine, spatial
    sp = hdr.get("spacings")
    sp = None if sp is None else np.asarray(sp, dtype=float)
    if sp is None or sp.shape != (dim,) or dim < 3:
        raise BonesimError("missing spacing: the header has neither 'space "
                           "directions' nor a positive spacing per axis", path)
    spatial = [a for a in range(dim) if np.isfinite(sp[a])]
    if len(spatial) != 3 or np.any(sp[spatial] <= 0):
        raise BonesimError("missing spacing: the header has neither 'space "
                           "directions' nor three positive 'spacings'", path, "spacings")
    affine[:3, :3] = np.diag(sp[spatial])
    return affine, spatial


def read_nrrd(path: str | Path) -> RawVolume:
    """Read a 3-D NRRD volume (intensities or a label map).

    Orientation: see :func:`nrrd_affine`.

    Returns
    -------
    RawVolume
        Data in their stored dtype, axes along +x, +y, +z.
    """
    import nrrd

    path = Path(path)
    check_file(path, "NRRD")
    try:
        data, hdr = nrrd.read(str(path), index_order="F")
    except Exception as exc:  # pynrrd raises NRRDError, ValueError, OSError...
        raise BonesimError(f"unreadable NRRD file: {exc}", path) from None
    data = squeeze3(np.asarray(data), path)
    affine, _ = nrrd_affine(hdr, path)
    return snap_to_lps(data, affine, path, f"{path} (NRRD)")


def read_nifti(path: str | Path, scaled: bool = True) -> RawVolume:
    """Read a 3-D NIfTI volume; its RAS affine is converted to LPS.

    Parameters
    ----------
    path : str or Path
        ``.nii`` or ``.nii.gz``.
    scaled : bool
        Apply ``scl_slope`` / ``scl_inter`` (intensities: yes; label maps: no).

    Returns
    -------
    RawVolume
        Scaled intensities as float32; without scaling to apply (or with
        ``scaled`` False) the stored type (an int16 CT stays int16).
    """
    import nibabel as nib

    path = Path(path)
    check_file(path, "NIfTI")
    try:
        img = nib.load(str(path))
        proxy = img.dataobj
        identity = (float(getattr(proxy, "slope", 1.0)) == 1.0
                    and float(getattr(proxy, "inter", 0.0)) == 0.0)
        if scaled and not identity:
            data = np.asarray(proxy, dtype=np.float32)
        else:                          # no scaling to apply: the stored type, no copy
            data = np.asarray(proxy.get_unscaled())
            if scaled and data.dtype.kind == "f" and data.dtype != np.float32:
                data = data.astype(np.float32)
    except Exception as exc:  # nibabel raises ImageFileError, OSError, EOFError...
        raise BonesimError(f"unreadable NIfTI file: {exc}", path) from None
    data = squeeze3(data, path)
    zooms = np.asarray(img.header.get_zooms()[:3], dtype=float)
    if np.any(~np.isfinite(zooms)) or np.any(zooms <= 0):
        raise BonesimError(f"missing spacing: pixdim is {zooms.tolist()}", path)
    affine = np.eye(4)
    affine[:3, :] = LPS_FROM_RAS @ np.asarray(img.affine, float)[:3, :]
    return snap_to_lps(data, affine, path, f"{path} (NIfTI)")


def lps_affine(spacing_mm: float, origin_mm) -> np.ndarray:
    """(4, 4) LPS affine of an isotropic grid: edge ``spacing_mm`` [mm], voxel
    ``(0, 0, 0)`` centred at ``origin_mm`` [mm]."""
    aff = np.diag([spacing_mm] * 3 + [1.0])
    aff[:3, 3] = np.asarray(origin_mm, dtype=float)
    return aff


def write_nrrd(path: str | Path, data: np.ndarray, spacing_mm: float, origin_mm,
               fields: dict | None = None) -> Path:
    """Write ``data`` (axes x, y, z) as a gzip NRRD in LPS space.

    Parameters
    ----------
    path : str or Path
        Output file (its folder is created).
    data : (nx, ny, nz) array
        Voxels along x, y, z of LPS.
    spacing_mm : float
        Isotropic voxel edge [mm].
    origin_mm : (3,) float
        Centre of voxel ``(0, 0, 0)`` [mm].
    fields : dict, optional
        Extra header fields (key-value pairs such as a segmentation's table).
    """
    import nrrd

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    hdr = {
        "space": "left-posterior-superior",
        "space directions": np.eye(3) * float(spacing_mm),
        "space origin": np.asarray(origin_mm, dtype=float),
        "kinds": ["domain"] * 3,
        "encoding": "gzip",
        **(fields or {}),
    }
    nrrd.write(str(path), np.asarray(data), hdr, index_order="F",
               compression_level=NRRD_GZIP_LEVEL)
    return path


def write_nifti(path: str | Path, data: np.ndarray, spacing_mm: float, origin_mm) -> Path:
    """Write ``data`` (axes x, y, z) as NIfTI-1 with the equivalent RAS affine."""
    import nibabel as nib

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ras = lps_affine(spacing_mm, origin_mm)
    ras[:3, :] = LPS_FROM_RAS @ ras[:3, :]
    img = nib.Nifti1Image(np.asarray(data), ras)
    img.header.set_xyzt_units("mm")
    img.set_qform(ras, code=1)
    img.set_sform(ras, code=1)
    nib.save(img, str(path))
    return path
