"""Replaying a recorded session through the engine, and verifying it bit for bit.

A session's samples, stepped again from the case's initial tissue with the
recorded burrs, must give the recorded removals and forces exactly
(``bonesim replay --verify``). A damaged file is replayed over its readable
part (:func:`bonesim.session_reader.read_session` cuts every stream at the
same moment).
"""
from __future__ import annotations

import numpy as np

from . import events
from .session_reader import Session

__all__ = ["replay", "verify"]


def replay(session: Session, models=None, progress=None) -> dict:
    """Re-run the recorded samples through the engine.

    Parameters
    ----------
    session : Session
    models : list of Model, optional
        Default :meth:`Session.burr_models` (hash-checked).
    progress : callable, optional
        Called with the fraction done now and then.

    Returns
    -------
    dict
        ``removals`` (``t_s``, ``ijk``, ``label``), ``mag_n`` and
        ``tangential_n`` per sample, and the final ``state``.
    """
    from .model import Sample, make_state, reset_state, step

    models = session.burr_models() if models is None else models
    s = session.samples
    n = len(s["t_s"])
    state = make_state(models[0])
    for m in models:
        state.fit_scratch(m)
    from .haptics import O_MAG, O_TX, O_TZ

    mag = np.zeros(n)
    tang = np.zeros((n, 3))
    cur = events.Cursor(state.removed, 0)
    chunks = []
    epoch = 0
    t_col, pos, axis = s["t_s"], s["pos_mm"], s["axis"]
    drill, speed, direc = s["drill"], s["speed_rpm"], s["direction"]
    burr, ep = s["burr"], s["epoch"]
    for q in range(n):
        if int(ep[q]) != epoch:
            reset_state(models[int(burr[q])], state, rings=False)
            epoch = int(ep[q])
        step(models[int(burr[q])], state,
             Sample(float(t_col[q]), pos[q], axis[q], bool(drill[q]), float(speed[q]),
                    int(direc[q])))
        mag[q] = state.out[O_MAG]
        tang[q] = state.out[O_TX:O_TZ + 1]
        if state.removed.count - cur.pos > state.removed.capacity // 2:
            chunks.append(cur.drain())
        if progress is not None and q % 20000 == 0:
            progress(q / max(n, 1))
    chunks.append(cur.drain())
    rem = {k: np.concatenate([c[k] for c in chunks]) for k in ("t_s", "ijk", "label")}
    return {"removals": rem, "mag_n": mag, "tangential_n": tang, "state": state}


def verify(session: Session, progress=None) -> dict:
    """Replay ``session`` and compare with the recording bit for bit.

    Returns
    -------
    dict
        ``ok`` and, per stream, whether it matched and the first mismatch.
    """
    out = replay(session, progress=progress)
    rec = session.removals
    s = session.samples
    if not session.complete and len(s["t_s"]):
        # a file cut by a crash may hold removals of steps whose samples had
        # not been flushed yet: compare what the samples cover
        keep = rec["t_s"] <= s["t_s"][-1]
        rec = {k: v[keep] for k, v in rec.items()}
    got = out["removals"]
    report = {"file": str(session.path), "samples": int(len(session.samples["t_s"])),
              "removals_recorded": int(len(rec["t_s"])),
              "removals_replayed": int(len(got["t_s"]))}
    n = min(len(rec["t_s"]), len(got["t_s"]))
    first = None
    for k in ("t_s", "ijk", "label"):
        a, b = rec[k][:n], got[k][:n]
        bad = np.flatnonzero((a != b).reshape(n, -1).any(axis=1)) if n else []
        if len(bad) and (first is None or bad[0] < first["index"]):
            first = {"index": int(bad[0]), "field": k,
                     "recorded": np.asarray(a[bad[0]]).tolist(),
                     "replayed": np.asarray(b[bad[0]]).tolist()}
    if first is None and len(rec["t_s"]) != len(got["t_s"]):
        first = {"index": n, "field": "count", "recorded": int(len(rec["t_s"])),
                 "replayed": int(len(got["t_s"]))}
    report["removals_match"] = first is None
    report["first_mismatch"] = first
    report["forces_match"] = bool(np.array_equal(s["mag_n"], out["mag_n"])
                                  and np.array_equal(s["tangential_n"], out["tangential_n"]))
    report["ok"] = report["removals_match"] and report["forces_match"]
    return report
