"""Writing a case in another format: its volume plus a ``case.toml`` that
reloads voxel-identical, with the same colours, monitor flags and camera.

Used through :func:`bonesim.io.case.export_case` (``bonesim case-export``).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.io.orientation import PATIENT_FRAME, image_geometry, parse_orientation

__all__ = ["EXPORT_FORMATS", "export_case", "export_labels"]

EXPORT_FORMATS = ("dicom", "nrrd", "nifti", "label-stack", "seg-nrrd")
"""Formats :func:`export_case` writes."""
EXPORT_HU_BY_KIND = {"bone": 1500.0, "critical": 40.0, "soft": 40.0}
"""HU written for label-only volumes exported to an intensity format."""
EMPTY_HU = -1000.0
SEG_FILE = "segmentation.seg.nrrd"
"""File name of an exported 3D Slicer segmentation."""
_SETTLE_ROUNDS = 3     # re-reads of the written manifest to pin colours down


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if not math.isfinite(v):
            raise ValueError("TOML export of a non-finite number")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)          # JSON string escapes are valid TOML
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_table(header: str, table: dict) -> str:
    lines = [header]
    lines += [f"{k} = {_toml_value(v)}" for k, v in table.items() if v is not None]
    return "\n".join(lines) + "\n"


def _export_labels(structures) -> list[int]:
    """Label-map integer per structure: its own, else the smallest free one."""
    used = {s.label for s in structures if s.label is not None}
    out, nxt = [], 1
    for s in structures:
        if s.label is not None:
            out.append(s.label)
            continue
        while nxt in used:
            nxt += 1
        used.add(nxt)
        out.append(nxt)
    return out


def _export_colors(structures) -> list[tuple[int, int, int]]:
    """Label-stack colour per structure: unique, non-black (its stack colour,
    else its display colour, else a free one)."""
    from bonesim.io.anatomy import load_table

    spare = tuple(load_table().fallback) + tuple((r, 255 - r, 128) for r in range(256))
    taken: set = set()
    out = []
    for s in structures:
        c = tuple(s.color or s.display_color)
        if c in taken or c == (0, 0, 0):
            c = next(p for p in spare if p not in taken and p != (0, 0, 0))
        taken.add(c)
        out.append(tuple(int(v) for v in c))
    return out


def _default_monitor(s, table) -> bool:
    cls = table.classes.get(s.anatomy)
    return s.kind != "bone" and cls is not None and cls.monitor


def _write_volume(case, vol, structs, fmt: str, out: Path, code: str) -> tuple[dict, list]:
    """Write the data files; returns the ``[volume]`` table and the per-structure
    data keys (``label`` / ``color``)."""
    from bonesim.io.volumes import write_dicom_series, write_label_stack, write_nifti, write_nrrd

    volume: dict = {"format": fmt, "voxel_mm": vol.spacing_mm}
    keys: list[dict] = [{} for _ in structs]
    if fmt == "label-stack":
        colors = _export_colors(structs)
        write_label_stack(out / "planes", vol.labels, colors, orientation=code)
        spacing_img, first = image_geometry(code, vol.shape, np.full(3, vol.spacing_mm),
                                            vol.origin_mm)
        shape_img = np.array(vol.shape)[list(code_axes(code))]
        volume.update(path="planes", pattern="plane*.png", orientation=code,
                      size_mm=[float(v) for v in spacing_img * shape_img],
                      origin_mm=[float(v) for v in first])
        for k, c in zip(keys, colors):
            k["color"] = list(c)
        return volume, keys
    if fmt == "seg-nrrd":
        from bonesim.io.volumes import write_seg_nrrd

        write_seg_nrrd(out / SEG_FILE, vol.labels, [s.name for s in structs],
                       [tuple(s.display_color) for s in structs], vol.spacing_mm,
                       vol.origin_mm)
        volume.update(path=SEG_FILE)
        return volume, keys
    thr = case.volume.bone_threshold_hu
    label_ints = _export_labels(structs)
    if vol.hu is not None:
        hu = vol.hu.copy()
    else:
        lut = np.array([EMPTY_HU] + [EXPORT_HU_BY_KIND[s.kind] for s in structs],
                       dtype=np.float32)
        hu = lut[vol.labels]
    below = np.float32(math.floor(thr) - 1)
    hu[(vol.labels == 0) & (hu > below)] = below
    lut = np.zeros(len(structs) + 1, dtype=np.uint16)
    lut[1:] = label_ints
    lmap = lut[vol.labels]
    if max(label_ints) <= np.iinfo(np.uint8).max:
        lmap = lmap.astype(np.uint8)
    if fmt == "dicom":
        write_dicom_series(out / "ct", hu, vol.spacing_mm, vol.origin_mm,
                           f"bonesim {case.name}")
        write_nrrd(out / "labels.nrrd", lmap, vol.spacing_mm, vol.origin_mm)
        volume.update(path="ct", labels="labels.nrrd")
    elif fmt == "nrrd":
        write_nrrd(out / "ct.nrrd", np.rint(hu).astype(np.int16), vol.spacing_mm,
                   vol.origin_mm)
        write_nrrd(out / "labels.nrrd", lmap, vol.spacing_mm, vol.origin_mm)
        volume.update(path="ct.nrrd", labels="labels.nrrd")
    else:
        write_nifti(out / "ct.nii.gz", np.rint(hu).astype(np.int16),
                    vol.spacing_mm, vol.origin_mm)
        write_nifti(out / "labels.nii.gz", lmap, vol.spacing_mm, vol.origin_mm)
        volume.update(path="ct.nii.gz", labels="labels.nii.gz")
    volume["bone_threshold_hu"] = thr
    for k, lab in zip(keys, label_ints):
        k["label"] = lab
    return volume, keys


def code_axes(code: str) -> tuple[int, int, int]:
    """LPS axis each image axis (columns, rows, slices) of ``code`` runs along."""
    from bonesim.io.orientation import LETTERS

    return tuple(LETTERS[ch][0] for ch in parse_orientation(code))


def _manifest_text(case, fmt, volume, structs, keys, explicit, monitor_explicit,
                   note=None) -> str:
    from bonesim.io.anatomy import classify

    note = note or f"exported as {fmt} from {case.manifest}"
    parts = [f"# bonesim case, {note}\n"]
    if fmt != "label-stack":
        parts.append("# orientation: read from the file's header (patient frame LPS)\n")
    parts += [_toml_table("[case]", {"name": case.name,
                                     "description": case.description or note,
                                     "side": case.side}),
              _toml_table("[volume]", volume)]
    for i, (s, k) in enumerate(zip(structs, keys)):
        cls = classify(s.name)
        anatomy = s.anatomy if s.anatomy != (cls.id if cls is not None else "") else None
        parts.append(_toml_table("[[structures]]", {
            "name": s.name, "kind": s.kind, **k, "anatomy": anatomy,
            "display_color": list(s.display_color) if i in explicit else None,
            "monitor": s.monitor if i in monitor_explicit else None}))
    if case.declared_camera is not None:
        cam = case.declared_camera
        parts.append(_toml_table("[camera]", {"eye_mm": cam.eye_mm,
                                              "focal_mm": cam.focal_mm, "up": cam.up}))
    if case.target is not None:
        t = case.target
        box = None if t.box_min_mm is None else [list(t.box_min_mm), list(t.box_max_mm)]
        parts.append(_toml_table("[target]", {"description": t.description,
                                              "structures": list(t.structures),
                                              "box_mm": box}))
    return "\n".join(parts)


def export_case(case, fmt: str, out_dir: str | Path, overwrite: bool = False,
                orientation: str | None = None, progress=None) -> Path:
    """Write the case's volume in another format plus a ``case.toml``.

    The written case loads back to the same labels (same grid, same counts per
    structure), display colours, monitor flags and camera: ``display_color``
    is written only where the reloaded default would differ, ``monitor``
    only where it differs from the name's default, ``[camera]`` only when
    the source declares one (a derived view derives again from the same
    anatomy).

    Parameters
    ----------
    case : Case
    fmt : {"dicom", "nrrd", "nifti", "label-stack", "seg-nrrd"}
        ``dicom``: folder ``ct/`` of slices + ``labels.nrrd``; ``nrrd``:
        ``ct.nrrd`` + ``labels.nrrd``; ``nifti``: ``ct.nii.gz`` +
        ``labels.nii.gz``; ``label-stack``: ``planes/plane1.png ...`` with one
        RGB colour per structure; ``seg-nrrd``: ``segmentation.seg.nrrd``, a
        3D Slicer segmentation with the structures' names and display colours.
        Intensity formats hold HU (synthesised from the structure kinds when
        the source has none); in voxels labelled empty the HU are kept below
        the bone threshold so the labels reload exactly.
    out_dir : str or Path
        Created if needed.
    overwrite : bool
        Replace an existing ``case.toml`` in ``out_dir``.
    orientation : str, optional
        Label stacks only: the axis code to write the slices in (default
        ``"LPS"``); the manifest states it.
    progress : callable, optional
        ``progress(done, total, what)`` while the source volume loads.

    Returns
    -------
    Path
        The written ``case.toml``.
    """
    code = _check_orientation(fmt, orientation)
    manifest = _manifest_path(out_dir, overwrite)
    vol = case.load_volume(progress=progress)
    return _write_case(case.resolved(vol), vol, fmt, Path(out_dir), code, manifest)


def _check_orientation(fmt: str, orientation) -> str:
    if fmt not in EXPORT_FORMATS:
        raise BonesimError(f"cannot export to {fmt!r}; formats: {list(EXPORT_FORMATS)}")
    if orientation is not None and fmt != "label-stack":
        raise BonesimError(f"an orientation applies to label stacks only; {fmt} files "
                           "store theirs in the header (always LPS here)")
    return PATIENT_FRAME if orientation is None else parse_orientation(
        orientation, None, "orientation")


def _manifest_path(out_dir, overwrite: bool) -> Path:
    from bonesim.io.case_records import CASE_FILE

    manifest = Path(out_dir) / CASE_FILE
    if manifest.exists() and not overwrite:
        raise BonesimError("already exists (choose another folder or overwrite)",
                           manifest)
    return manifest


def _write_case(rc, vol, fmt: str, out: Path, code: str, manifest: Path,
                note: str | None = None) -> Path:
    """Write ``vol`` with the structures of ``rc`` (a resolved case) and the
    manifest that reloads it with the same colours, monitor flags and camera."""
    from bonesim.io.anatomy import load_table
    from bonesim.io.case_manifest import parse_manifest as parse_case

    structs = rc.structures
    table = load_table()
    out.mkdir(parents=True, exist_ok=True)
    volume, keys = _write_volume(rc, vol, structs, fmt, out, code)
    explicit = {i for i, s in enumerate(structs) if s.color_source == "manifest"}
    if fmt == "label-stack":
        explicit |= {i for i, (s, k) in enumerate(zip(structs, keys))
                     if tuple(k["color"]) != tuple(s.display_color)}
    monitor_explicit = {i for i, s in enumerate(structs)
                        if s.monitor != _default_monitor(s, table)}
    for _ in range(_SETTLE_ROUNDS):
        manifest.write_text(_manifest_text(rc, fmt, volume, structs, keys, explicit,
                                           monitor_explicit, note), encoding="utf-8")
        back = parse_case(manifest).resolved(vol)
        wrong = {i for i, (a, b) in enumerate(zip(back.structures, structs))
                 if a.display_color != b.display_color}
        if not wrong:
            return manifest
        explicit |= wrong
    manifest.write_text(_manifest_text(rc, fmt, volume, structs, keys, set(range(
        len(structs))), monitor_explicit, note), encoding="utf-8")
    return manifest


def export_labels(case, labels, spacing_mm: float, origin_mm, fmt: str, out_dir,
                  *, overwrite: bool = False, orientation: str | None = None,
                  camera=None, note: str | None = None) -> Path:
    """Write a label volume on a case's structures as a case of its own (e.g.
    the bone as drilled at some moment, :mod:`bonesim.session.bone_export`).

    Parameters
    ----------
    case : Case
        The case the labels index (its structures, resolved: colours as
        shown; its side, name, target).
    labels : (nx, ny, nz) uint8
        Structure index per voxel (0 empty), axes x, y, z of the patient
        frame (LPS).
    spacing_mm : float
        Isotropic voxel edge [mm]; the manifest's ``voxel_mm``, so the case
        reloads on this very grid.
    origin_mm : (3,) float
        Centre of voxel ``(0, 0, 0)`` [mm].
    fmt, overwrite, orientation
        As :func:`export_case`.
    camera : Camera, optional
        Written as the manifest's ``[camera]`` (default: the case's declared
        one, if any).
    note : str, optional
        The manifest's description and first comment.

    Returns
    -------
    Path
        The written ``case.toml``.
    """
    import dataclasses

    from bonesim.io.volumes import CaseVolume

    code = _check_orientation(fmt, orientation)
    manifest = _manifest_path(out_dir, overwrite)
    vol = CaseVolume(np.ascontiguousarray(labels, dtype=np.uint8), float(spacing_mm),
                     np.asarray(origin_mm, dtype=np.float64), f"{fmt} export")
    rc = case if camera is None else dataclasses.replace(case, declared_camera=camera)
    if note:
        rc = dataclasses.replace(rc, description=note)
    rc._derived.update(getattr(case, "_derived", {}))
    return _write_case(rc, vol, fmt, Path(out_dir), code, manifest, note)
