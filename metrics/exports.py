"""Research outputs a paper can use and trace, each with its provenance.

Per run (:func:`export_run`, ``bonesim metrics export``)
    ``<stem>_visibility.nrrd``: per-voxel visibility on the case grid (the
    session header's ``shape``, ``voxel_mm`` and ``origin_mm``: the
    voxel ``(i, j, k)`` centre lies at ``origin_mm + voxel_mm * (i, j, k)``
    in the case frame, LPS [mm], as the case's own volumes), so it opens in
    3D Slicer over the case. Values (:data:`VISIBILITY_VALUES`): 0 not
    removed, 1 removed while visible, 2 removed while hidden (undercut);
    removals of every epoch, the last one wins; shed specks are not drilled
    and stay 0. ``<stem>_removals.parquet``: one row per drilled removal
    (:func:`removal_rows`). Both carry the provenance (NRRD key-value field
    ``bonesim_provenance``, Parquet schema metadata ``bonesim_provenance``),
    JSON text.
Per cohort (:func:`export_cohort`)
    ``stats.csv`` (the statistics table), ``runs.csv`` (the per-run table),
    and ``provenance.json`` (the provenance, the design and the metrics left
    out of the tests with their reasons: a CSV has no place for them).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = ["VISIBILITY_VALUES", "visibility_volume", "removal_rows", "export_run",
           "export_cohort", "PROVENANCE_KEY"]

#: Voxel values of the visibility volume.
VISIBILITY_VALUES = {0: "not removed", 1: "removed, visible", 2: "removed, hidden"}
#: Key of the provenance in the NRRD header and the Parquet metadata.
PROVENANCE_KEY = "bonesim_provenance"


def visibility_volume(session, models=None) -> np.ndarray:
    """Per-voxel visibility (module docstring) as ``(nx, ny, nz)`` uint8 on
    the case grid (axes x, y, z)."""
    from bonesim.engine import events
    from metrics.visibility import visibility

    h = session.header
    shape = tuple(int(x) for x in h["shape"])
    vol = np.zeros(shape, np.uint8)
    res = visibility(session, models=models)
    kinds = np.asarray(session.tissue["kind"])
    drilled = events.drilled(session.tissue)[kinds == events.REMOVED]
    ijk = np.asarray(session.removals["ijk"], np.int64).reshape(-1, 3)
    ok = drilled & (res.visible >= 0)
    vol[tuple(ijk[ok].T)] = np.where(res.visible[ok] == 1, 1, 2).astype(np.uint8)
    return vol


def removal_rows(session, models=None):
    """One row per drilled removal.

    Returns
    -------
    pandas.DataFrame
        ``t_s`` [s], ``epoch``, ``i, j, k`` (voxel), ``x_mm, y_mm, z_mm``
        (its centre, case frame), ``label``, ``visible`` (1, 0; -1 unknown),
        ``force_n`` (applied, :data:`metrics.forces.DEFAULT_FORCE`) [N],
        ``speed_rpm`` [rpm], ``tool_mm_s`` [mm/s], and ``dist_<structure>_mm``
        per non-bone structure of the case [mm].
    """
    import pandas as pd

    from bonesim.engine import events
    from bonesim.physics.force_limits import force_magnitude
    from metrics.forces import DEFAULT_FORCE, tool_speed
    from metrics.visibility import visibility

    if models is None:
        models = session.burr_models()
    model = models[0]
    h = session.header
    res = visibility(session, models=models)
    kinds = np.asarray(session.tissue["kind"])
    drilled = events.drilled(session.tissue)[kinds == events.REMOVED]
    rem = session.removals
    ijk = np.asarray(rem["ijk"], np.int64).reshape(-1, 3)[drilled]
    t = np.asarray(rem["t_s"], np.float64)[drilled]
    s = session.samples
    idx = np.clip(np.searchsorted(s["t_s"], t), 0, max(len(s["t_s"]) - 1, 0))
    centre = np.asarray(h["origin_mm"], float) + float(h["voxel_mm"]) * ijk
    out = {"t_s": t, "epoch": np.asarray(rem["epoch"])[drilled],
           "i": ijk[:, 0], "j": ijk[:, 1], "k": ijk[:, 2],
           "x_mm": centre[:, 0], "y_mm": centre[:, 1], "z_mm": centre[:, 2],
           "label": np.asarray(rem["label"])[drilled], "visible": res.visible[drilled],
           "force_n": force_magnitude(s, DEFAULT_FORCE)[idx] if len(t) else np.zeros(0),
           "speed_rpm": np.asarray(s["speed_rpm"])[idx] if len(t) else np.zeros(0),
           "tool_mm_s": tool_speed(s)[idx] if len(t) else np.zeros(0)}
    cl = model.clearance
    for lab, st in enumerate(model.structures, start=1):
        if st.kind == "bone" or cl is None or lab not in cl.structures:
            continue
        out[f"dist_{st.name}_mm"] = cl.distance(centre, [lab]) if len(t) else np.zeros(0)
    return pd.DataFrame(out)


def _json(x) -> str:
    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {str(k): clean(w) for k, w in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(w) for w in v]
        if isinstance(v, np.generic):
            return clean(v.item())
        return v
    return json.dumps(clean(x), sort_keys=True)


def export_run(path, out_dir, *, command: str | None = None, participants=None) -> dict:
    """Write a run's visibility NRRD and removals Parquet (module docstring).

    Returns
    -------
    dict
        ``visibility``, ``removals`` (paths) and ``provenance``.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from bonesim.io.images import write_nrrd
    from bonesim.session.reader import read_session
    from metrics.provenance import provenance

    s = read_session(path)
    h = s.header
    models = s.burr_models()
    prov = provenance([h], participants, command=command)
    prov["session_file"] = str(path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = Path(path).stem
    vol = visibility_volume(s, models)
    nrrd_path = write_nrrd(out / f"{stem}_visibility.nrrd", vol, float(h["voxel_mm"]),
                           h["origin_mm"],
                           {PROVENANCE_KEY: _json(prov),
                            "bonesim_values": _json(VISIBILITY_VALUES)})
    rows = removal_rows(s, models)
    tab = pa.Table.from_pandas(rows, preserve_index=False)
    tab = tab.replace_schema_metadata({**(tab.schema.metadata or {}),
                                       PROVENANCE_KEY.encode(): _json(prov).encode()})
    pq_path = out / f"{stem}_removals.parquet"
    pq.write_table(tab, pq_path)
    return {"visibility": str(nrrd_path), "removals": str(pq_path), "provenance": prov}


def _agreement_record(ins: dict) -> dict:
    """The instructor agreement without the Bland-Altman points (the numbers)."""
    out = {k: v for k, v in ins.items() if k != "against"}
    if "against" in ins:
        a = dict(ins["against"])
        if "bland_altman" in a:
            a["bland_altman"] = {k: v for k, v in a["bland_altman"].items()
                                 if k not in ("mean", "diff")}
        out["against"] = a
    return out


def export_cohort(result, out_dir) -> dict:
    """Write a scored cohort's ``stats.csv``, ``runs.csv`` and
    ``provenance.json`` into ``out_dir`` (module docstring)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result.stats.to_csv(out / "stats.csv", index=False)
    result.table.to_csv(out / "runs.csv", index=False)
    meta = {"provenance": result.provenance, "design": result.design,
            "excluded": result.excluded,
            "classifiers": {k: {q: v[q] for q in ("auc", "auc_ci", "se", "n_pos", "n_neg",
                                                  "ci_method", "validation", "note")
                                if q in v}
                            for k, v in result.classifiers.items()},
            "instructors": _agreement_record(getattr(result, "instructors", None) or {}),
            "files": {"stats": "stats.csv", "runs": "runs.csv"}}
    (out / "provenance.json").write_text(_json(meta) + "\n")
    return {"stats": str(out / "stats.csv"), "runs": str(out / "runs.csv"),
            "provenance": str(out / "provenance.json")}
