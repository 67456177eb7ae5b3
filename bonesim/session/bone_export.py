"""The bone of a recording at any moment, written as a case to go on drilling.

``bonesim sessions export RUN.h5 --at S --format seg-nrrd OUT/`` replays the
recorded tissue events up to playback time ``S``
(:class:`~bonesim.session.playback.Player`, no surface) and writes the
remaining voxels, each with its structure, as a case in the patient frame
(:func:`bonesim.io.case_export.export_labels`): a 3D Slicer segmentation
(``seg-nrrd``), ``nrrd``, ``nifti`` or a ``label-stack``, on the recording's
own grid (same voxel size and origin: ``voxel_mm`` is the grid's, so the
case reloads voxel for voxel) with a ``case.toml`` that keeps the
structures' names, kinds, colours and monitor flags, and the camera of that
moment (the recorded one, else the case's), so a run started from it
(``bonesim run --case OUT/``) opens on the view the recording stopped at
with the cavity as it was. ``export.json`` beside it says where it came
from (the run's SHA-256, the moment, the tool's pose and burr then).

What is kept
------------
* Every voxel of every body whose density is above 0 at that moment, with
  its label: exactly the recording's remaining voxels. Partly drilled
  voxels are not recorded (their density loss is not in the file), so they
  are whole again in the export, as in playback.
* A fragment that was moved (a body at a pose other than the identity) is
  placed where it then lay: each of its voxels goes to the case-frame voxel
  nearest its centre, unless that voxel is taken (``overlapping`` counts
  those); ``moved_bodies`` lists them. Plates are not tissue and are not
  written.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError

__all__ = ["EXPORT_JSON", "bone_at", "export_bone"]

#: Provenance written beside the exported case.
EXPORT_JSON = "export.json"


def bone_at(player, t: float) -> tuple[np.ndarray, dict]:
    """The remaining voxels at playback time ``t`` as a label volume.

    Parameters
    ----------
    player : bonesim.session.playback.Player
    t : float
        Playback time [s] (clamped to the recording).

    Returns
    -------
    labels : (nx, ny, nz) uint8
        Structure per voxel of the case grid, 0 where nothing is left.
    info : dict
        ``remaining_voxels``, ``moved_bodies``, ``overlapping``, ``epoch``, ``t_s``.
    """
    from bonesim.engine.bodies import is_identity
    from bonesim.engine.grid import gather_box

    player.seek(t)
    g = player.grid
    st = player.replica.state
    dens, lab = g.to_dense()
    body = np.zeros(g.shape, np.uint8)
    gather_box(g.keys, g.vals, st.body, body, 0, 0, 0)
    occ = dens > 0
    labels = np.where(occ, lab, 0).astype(np.uint8)
    moved = [int(b) for b in np.flatnonzero(st.alive)
             if not is_identity(st.pose[b])]
    overlapping = 0
    if moved:
        pending = []
        for b in moved:
            m = occ & (body == b)
            ijk = np.argwhere(m)
            labels[m] = 0
            pending.append((b, ijk, lab[m]))
        shape = np.asarray(g.shape)
        for b, ijk, labs in pending:
            pm = st.pose_m[b]
            centres = g.origin_mm + g.spacing_mm * ijk
            case = centres @ pm[:, :3].T + pm[:, 3]
            tgt = np.rint((case - g.origin_mm) / g.spacing_mm).astype(np.int64)
            inside = np.all((tgt >= 0) & (tgt < shape), axis=1)
            for (i, j, k), v in zip(tgt[inside], labs[inside]):
                if labels[i, j, k]:
                    overlapping += 1
                else:
                    labels[i, j, k] = v
            overlapping += int((~inside).sum())
    info = {"t_s": float(player.t), "epoch": int(player.timeline.epoch_at(player.t)),
            "remaining_voxels": int(occ.sum()), "moved_bodies": moved,
            "overlapping": int(overlapping)}
    return labels, info


def export_bone(session, at: float | None, fmt: str, out_dir, *, overwrite: bool = False,
                orientation: str | None = None, player=None) -> dict:
    """Write the bone of ``session`` at playback time ``at`` as a case.

    Parameters
    ----------
    session : Session
        As :func:`bonesim.session.reader.read_session` returns it.
    at : float or None
        Playback time [s]; None: the recording's last moment.
    fmt : {"seg-nrrd", "nrrd", "nifti", "label-stack", "dicom"}
    out_dir : path
        Created if needed; must not hold a ``case.toml`` unless ``overwrite``.
    orientation : str, optional
        Label stacks: the axis code to write the slices in.
    player : Player, optional
        Default: a new one (no surface).

    Returns
    -------
    dict
        ``case`` (the manifest), ``at_s``, ``remaining_voxels``,
        ``removed_voxels`` (this epoch), the tool's pose, and what
        :func:`bone_at` says.
    """
    from bonesim.io.case_export import export_labels
    from bonesim.io.case_records import Camera
    from bonesim.session.dataset_spec import file_sha256
    from bonesim.session.playback import Player

    p = Player(session, surface=False) if player is None else player
    tl = p.timeline
    t = tl.duration if at is None else float(at)
    if not np.isfinite(t) or t < 0 or t > tl.duration + 1e-9:
        raise BonesimError(f"--at {t:g} s lies outside the recording (0 .. "
                           f"{tl.duration:.3f} s)", getattr(session, "path", None), "--at")
    labels, info = bone_at(p, t)
    f = p.frame()
    model = p.model
    case = getattr(model, "case", None)
    if case is None:
        raise BonesimError("the recording's model has no case to export",
                           getattr(session, "path", None))
    cam = f.camera if f.camera is not None else (case.camera.eye_mm, case.camera.focal_mm,
                                                  case.camera.up)
    camera = Camera(*(tuple(float(x) for x in v) for v in cam))
    src = getattr(session, "path", None)
    name = Path(src).name if src is not None else "the recording"
    note = (f"the bone of {name} at {t:.3f} s (bonesim sessions export); case "
            f"{model.name}")
    g = model.grid
    manifest = export_labels(case, labels, g.spacing_mm, g.origin_mm, fmt, out_dir,
                             overwrite=overwrite, orientation=orientation, camera=camera,
                             note=note)
    record = {"run": name, "run_sha256": file_sha256(src) if src is not None else "",
              "case": model.name, "at_s": round(t, 6),
              "session_t_s": round(tl.t0 + t, 6), "format": fmt,
              "voxel_mm": float(g.spacing_mm), "origin_mm": [float(v) for v in g.origin_mm],
              "shape": [int(v) for v in g.shape],
              "removed_voxels": int(f.voxels_removed),
              "tool": {"pos_mm": [float(v) for v in f.pos_mm],
                       "axis": [float(v) for v in f.axis],
                       "burr": str(getattr(f.burr, "name", "?")), "drill": bool(f.drill)},
              "camera": {"eye_mm": list(camera.eye_mm), "focal_mm": list(camera.focal_mm),
                         "up": list(camera.up)}, **info}
    from bonesim import __version__

    record["bonesim_version"] = __version__
    (Path(out_dir) / EXPORT_JSON).write_text(json.dumps(record, indent=1, sort_keys=True)
                                             + "\n", encoding="utf-8")
    record["case"] = str(manifest)
    return record
