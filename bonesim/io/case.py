"""Cases: a manifest (``case.toml``) naming a volume, its structures, the camera
start and the procedure's target.

Manifest
--------
.. code-block:: toml

    [case]
    name = "phantom"                  # required
    description = "..."               # optional
    side = "left"                     # "left" | "right"

    [volume]
    format = "nrrd"                   # phantom | dicom | nrrd | nifti |
                                      # label-stack | seg-nrrd
    path = "ct.nrrd"                  # relative to this manifest (not for phantom)
    voxel_mm = 0.5                    # isotropic output voxel edge [mm], default 0.5;
                                      # "native": the source's own spacing (its
                                      # finest axis if anisotropic; the phantom:
                                      # the generator's 0.5 mm)
    bone_threshold_hu = 300           # dicom / nrrd / nifti, default 300
    labels = "labels.nrrd"            # dicom / nrrd / nifti: optional label map
                                      # (a .seg.nrrd alone makes a seg-nrrd case)
    # label-stack only:
    #   pattern = "*.png"  size_mm = [columns, rows, slices]
    #   orientation = "LPS"  (axis code; default LPS, "assumed")
    #   origin_mm = [x, y, z]  (LPS centre of the first slice's top-left pixel;
    #                           default centred)   unknown_colors = "error"
    # phantom only:
    #   seed = 0  size_mm = [52, 52, 52]

    [[structures]]                    # order = label index 1, 2, ...
    name = "bone"
    kind = "bone"                     # bone | critical | soft (seg-nrrd: optional)
    label = 1                         # label-map integer (intensity formats)
    color = [230, 220, 200]           # label-stack colour (label-stack: required)
    segment = "Bone"                  # seg-nrrd: segment name or ID (default: name)
    anatomy = "bone"                  # optional: class of bonesim/data/anatomy.toml
    display_color = [230, 220, 200]   # rendering colour (default: from the data)
    monitor = false                   # nerve monitor (default: true for the facial
                                      # nerve and the chorda tympani)

    [camera]                          # optional; case frame (LPS), mm
    eye_mm = [120, 0, 0]
    focal_mm = [15, 0, 0]
    up = [0, 0, 1]

    [physics]                         # optional
    gravity = [-1, 0, 0]              # direction fragments and plates fall
                                      # (default: the camera's view direction)

    [target]                          # optional
    description = "cortical mastoidectomy"
    structures = ["sigmoid_sinus"]    # structures the procedure should expose
    box_mm = [[5, -8, -14], [20, 14, 11]]   # region expected to be drilled

    [fragments]                       # optional
    speck_voxels = 8                  # bone cut off in parts of fewer voxels
                                      # becomes dust, not a body (default 8)

For NRRD and NIfTI, ``path`` may be left out when ``labels`` alone gives all
structures (a label-only case). For the phantom, structure names must be
phantom parts (:data:`bonesim.io.phantom.PARTS`); parts not listed stay empty.
For a seg-nrrd case ``[[structures]]`` is optional: without it the
structures are the file's segments, with their names and colours and a kind
read from the name.

Defaults read from the anatomy (:mod:`bonesim.io.anatomy`, ``docs/cases.md``):
``display_color`` is the label stack's colour, the segment's colour, or a
conventional palette colour for the structure's name and kind, changed where
it would look like a neighbour's (:meth:`Case.resolved`); ``monitor`` is on
for the facial nerve and the chorda tympani (other nerves are listed by
``case-info`` as available, off); without ``[camera]`` the camera is the
surgeon's lateral view of the mastoid (:mod:`bonesim.io.surgical_view`).

Every problem is raised as a :class:`~bonesim.errors.BonesimError` naming the
manifest and the offending key.
"""
from __future__ import annotations

from pathlib import Path

from bonesim.io import anatomy as _anatomy
from bonesim.io.case_export import EXPORT_FORMATS, export_case
from bonesim.io.case_manifest import parse_manifest
from bonesim.io.case_records import (CASE_FILE, CASE_FORMATS, DEFAULT_BONE_THRESHOLD_HU,  # noqa: F401
                                     DEFAULT_PATTERN, DEFAULT_VOXEL_MM, KINDS, MAX_LABEL,
                                     MAX_VOXEL_MM, MIN_VOXEL_MM, NATIVE, ORIENTATION_SOURCES,
                                     SEG_FORMAT, SIDES, Camera, Case, Structure, Target,
                                     VolumeSpec, check_voxel_mm)
from bonesim.errors import BonesimError
from bonesim.io.orientation import PATIENT_FRAME
from bonesim.io.volumes import CaseVolume

__all__ = ["CASE_FILE", "SIDES", "KINDS", "CASE_FORMATS", "EXPORT_FORMATS",
           "Structure", "VolumeSpec", "Camera", "Target", "Case", "parse_case",
           "cases_dir", "load_case", "case_versions", "list_cases", "case_info",
           "export_case"]


def parse_case(path: str | Path) -> Case:
    """Parse and check one ``case.toml`` (no volume is read; a segmentation's
    header is, for its segment table). See :mod:`bonesim.io.case_manifest`."""
    return parse_manifest(path)


# ------------------------------------------------------------------ lookup
def cases_dir() -> Path:
    """Folder of the bundled cases (the ``ct_cases`` package)."""
    import ct_cases

    return Path(ct_cases.__file__).resolve().parent


def _bundled(versions: bool = False) -> dict[str, Path]:
    """Bundled case name -> manifest; with ``versions``, also the kept older
    versions of each (``ct_cases/NAME/versions/vK/case.toml`` as ``NAME@K``)."""
    root = cases_dir()
    out = {p.parent.name: p for p in sorted(root.glob(f"*/{CASE_FILE}"))}
    if versions:
        for p in sorted(root.glob(f"*/versions/v*/{CASE_FILE}")):
            k = p.parent.name[1:]
            if k.isdigit():
                out[f"{p.parent.parent.parent.name}@{int(k)}"] = p
    return out


def case_versions(name: str) -> list[str]:
    """The kept older versions of a bundled case, newest first
    (``["phantom@2"]``)."""
    pre = f"{name}@"
    found = [k for k in _bundled(versions=True) if k.startswith(pre)]
    return sorted(found, key=lambda k: -int(k[len(pre):]))


def load_case(name_or_path: str | Path | Case = "phantom",
              voxel_mm: float | str | None = None) -> Case:
    """Load a bundled case by name, or any case by manifest or folder path.

    Parameters
    ----------
    name_or_path : str, Path or Case
        A bundled case name (a folder of the ``ct_cases`` package, e.g.
        ``"phantom"``), or the path of a ``case.toml`` or of a folder holding
        one. A bare name that matches a bundled case wins over a same-named
        folder in the working directory. A :class:`Case` is taken as it is
        (so callers may pass either).
    voxel_mm : float or "native", optional
        Overrides the manifest's ``[volume] voxel_mm`` (``--voxel-mm``; see
        :meth:`Case.with_voxel_mm`).
    """
    if voxel_mm is not None:
        return load_case(name_or_path).with_voxel_mm(voxel_mm)
    if isinstance(name_or_path, Case):
        return name_or_path
    text = str(name_or_path)
    bundled = _bundled(versions=True)
    bare = isinstance(name_or_path, str) and "/" not in text and "\\" not in text \
        and not text.endswith(".toml")
    if bare and text in bundled:
        return parse_case(bundled[text])
    path = Path(name_or_path).expanduser()
    if path.is_dir():
        manifest = path / CASE_FILE
        if not manifest.is_file():
            raise BonesimError(f"folder has no {CASE_FILE}", path)
        return parse_case(manifest)
    if path.is_file():
        return parse_case(path)
    if bare:
        raise BonesimError(f"no bundled case named {text!r} and no such file or "
                           f"folder; bundled cases: {sorted(bundled)}", path)
    raise BonesimError("case manifest or folder not found", path)


def list_cases() -> list[Case]:
    """All bundled cases, sorted by folder name."""
    return [parse_case(p) for _, p in sorted(_bundled().items())]


def _color_warnings(case: Case, vol: CaseVolume) -> list[str]:
    """Neighbours whose manifest colours look alike (never changed)."""
    table = _anatomy.load_table()
    fixed = [i for i, s in enumerate(case.structures) if s.color_source == "manifest"]
    if len(fixed) < 2:
        return []
    adj = case.neighbours(vol)
    out = []
    for a in fixed:
        for b in fixed:
            if a < b and adj[a, b]:
                sa, sb = case.structures[a], case.structures[b]
                d = float(_anatomy.delta_e(sa.display_color, sb.display_color))
                if d < table.warn_delta_e:
                    out.append(f"neighbours {sa.name!r} and {sb.name!r} have near-"
                               f"identical display colours {list(sa.display_color)} "
                               f"and {list(sb.display_color)} (CIEDE2000 difference "
                               f"{d:.0f}); both set in the manifest, so kept")
    return out


def case_info(case: Case, progress=None) -> dict:
    """Summary of a case and its loaded volume (for ``bonesim case-info``).

    Parameters
    ----------
    case : Case
    progress : callable, optional
        ``progress(done, total, what)`` while the volume loads.

    Returns
    -------
    dict
        ``name, description, side, manifest, format, source, frame``
        (the patient frame's name and axes), ``orientation`` (``code`` or
        None, ``source``), ``grid`` (nx, ny, nz), ``voxel_mm, origin_mm,
        extent_mm, counts`` (voxels per structure name), ``kinds`` (kind per
        structure name), ``colors`` (per name: ``rgb``, ``source``),
        ``display_names`` (per name: the clinical name shown on screen,
        :func:`bonesim.io.anatomy.clinical_name`), ``monitored`` (names the
        nerve monitor watches), ``monitor_available`` (nerves it could watch
        but leaves off by default; ``monitor = true`` turns one on), ``camera``
        (``eye_mm, focal_mm, up, source`` and, when derived, ``notes``),
        ``landmarks`` (:meth:`bonesim.io.landmarks.Landmarks.as_dict`: each
        landmark's point, source and confidence, what is missing, how merged
        labels were split), ``warnings`` (anatomy against the declared side
        and orientation, look-alike colours),
        ``total`` (non-empty voxels).
    """
    vol = case.load_volume(progress=progress)
    rc = case.resolved(vol)
    counts = vol.counts(len(case.structures))
    cam = rc.camera
    camera = {"eye_mm": [round(c, 3) for c in cam.eye_mm],
              "focal_mm": [round(c, 3) for c in cam.focal_mm],
              "up": [round(c, 4) for c in cam.up], "source": rc.camera_source}
    if rc.declared_camera is None:
        camera["notes"] = list(rc.surgical_view.notes)
    code, how = case.orientation
    lm = case.landmarks
    problem = case.orientation_problem()
    warnings = [problem] if problem else []
    fc = case.frame_check
    if fc.unchecked:
        warnings.append("no labelled structures tell the " + ", ".join(fc.unchecked)
                        + " direction: the orientation is not checked along it")
    warnings += _color_warnings(rc, vol)
    return {
        "name": case.name,
        "description": case.description,
        "side": case.side,
        "manifest": str(case.manifest),
        "format": case.volume.format,
        "source": vol.source,
        "frame": {"name": PATIENT_FRAME, "x": "patient left", "y": "posterior",
                  "z": "superior", "units": "mm"},
        "orientation": {"code": code, "source": how},
        "grid": list(vol.shape),
        "voxel_mm": vol.spacing_mm,
        "origin_mm": [float(v) for v in vol.origin_mm],
        "extent_mm": [float(v) for v in vol.extent_mm],
        "counts": {s.name: int(counts[i]) for i, s in enumerate(case.structures, 1)},
        "kinds": {s.name: s.kind for s in case.structures},
        "colors": {s.name: {"rgb": list(s.display_color), "source": s.color_source}
                   for s in rc.structures},
        "display_names": {s.name: s.display_name for s in case.structures},
        "monitored": [s.name for s in case.structures if s.monitor],
        "monitor_available": [s.name for s in case.structures
                              if s.monitor_available and not s.monitor],
        "camera": camera,
        "landmarks": lm.as_dict(),
        "warnings": warnings,
        "total": int(counts[1:].sum()),
    }
