"""Replaying a recorded session through the engine, and verifying it bit for bit.

A session's samples, stepped again from the case's initial tissue with the
recorded burrs, must give the recorded tissue events and forces exactly
(``bonesim replay --verify``). The recorded body splits and poses, the
specks shed as dust with a fragment (removals marked ``REMOVED_SHED``) and the
plates' poses are inputs too (commands the haptic loop applied between two
steps): the replay applies
them again before the step of their time. A damaged file is replayed over its readable
part (:func:`bonesim.session.reader.read_session` cuts every stream at the
same moment).
"""
from __future__ import annotations

import numpy as np

from bonesim.engine import events
from bonesim.session.reader import Session

__all__ = ["replay", "verify", "coverage"]


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
        ``tissue`` (the tissue-event stream the run publishes: resets and
        burr changes where the samples' epoch and burr change, the recorded
        splits and poses, then each step's removals, contacts and injuries),
        ``mag_n`` and ``tangential_n`` per sample, and the final ``state``.
    """
    from bonesim.engine.model import Sample, make_state, reset_state, step

    from bonesim.errors import BonesimError
    from bonesim.session.reader import REPLAY_COLUMNS

    gone = [c for c in session.lost if c.startswith("/samples/")
            and c.split("/")[-1] in REPLAY_COLUMNS]
    if gone:
        raise BonesimError(f"{session.path}: cannot replay: {', '.join(gone)} "
                           f"{'is' if len(gone) == 1 else 'are'} lost")
    models = session.burr_models() if models is None else models
    s = session.samples
    n = len(s["t_s"])
    model = models[0].with_burrs([m.burr for m in models[1:]])
    state = make_state(model)
    from bonesim.engine.haptics import O_MAG, O_TX, O_TZ

    mag = np.zeros(n)
    tang = np.zeros((n, 3))
    ring = state.tissue
    cur = events.Cursor(ring, 0)
    chunks = []
    epoch, cur_burr = 0, 0
    t_col, pos, axis = s["t_s"], s["pos_mm"], s["axis"]
    drill, speed, direc = s["drill"], s["speed_rpm"], s["direction"]
    burr, ep = s["burr"], s["epoch"]
    commands = _body_commands(session.tissue, model.injury)
    c = 0
    for q in range(n):
        t = float(t_col[q])
        if int(ep[q]) != epoch:
            reset_state(model, state, rings=False)
            epoch = int(ep[q])
            events.push_event(ring, events.RESET, t, n=epoch)
        if int(burr[q]) != cur_burr:
            cur_burr = int(burr[q])
            events.push_event(ring, events.BURR, t, n=cur_burr)
        while c < len(commands) and commands[c][0] <= t:
            commands[c][1](state)
            c += 1
        step(model, state, Sample(t, pos[q], axis[q], bool(drill[q]), float(speed[q]),
                                  int(direc[q]), cur_burr))
        mag[q] = state.out[O_MAG]
        tang[q] = state.out[O_TX:O_TZ + 1]
        if ring.count - cur.pos > ring.capacity // 2:
            chunks.append(cur.drain())
        if progress is not None and q % 20000 == 0:
            progress(q / max(n, 1))
    chunks.append(cur.drain())
    return {"tissue": events.concat(chunks), "mag_n": mag, "tangential_n": tang,
            "state": state}


def _body_commands(tissue: dict, injury=None) -> list:
    """The recorded splits, poses, shed specks and cut-plane strokes (``CUT``
    records, :mod:`bonesim.engine.cut_plane`; ``injury`` the model's) as
    ``(t_s, apply(state))``, in order."""
    from bonesim.engine.bodies import publish_pose, publish_split
    from bonesim.engine.cut_plane import publish_cut_record
    from bonesim.engine.fragments import shed_voxels

    kind = tissue["kind"]
    shed = (kind == events.REMOVED) & (tissue["n"] == events.REMOVED_SHED)
    idx = np.flatnonzero((kind == events.SPLIT) | (kind == events.POSE) | (kind == events.CUT)
                         | (kind == events.PLATE) | shed)
    out = []
    q = 0
    while q < len(idx):
        i = idx[q]
        t = float(tissue["t_s"][i])
        body = int(tissue["body"][i])
        if shed[i]:
            # specks shed as dust with a fragment (bonesim.engine.fragments):
            # consecutive records of one body and time, in (i, j, k) order
            # (each speck is published sorted; a step down starts the next)
            e = q + 1
            while e < len(idx) and idx[e] == i + (e - q) and shed[idx[e]] \
                    and int(tissue["body"][idx[e]]) == body and tissue["t_s"][idx[e]] == t \
                    and tuple(tissue["ijk"][idx[e]]) > tuple(tissue["ijk"][idx[e - 1]]):
                e += 1
            ijk = tissue["ijk"][idx[q:e]].copy()
            out.append((t, lambda st, b=body, v=ijk, t=t: shed_voxels(st, b, v, t)))
            q = e
            continue
        if kind[i] == events.CUT:
            out.append((t, lambda st, v=tissue["ijk"][i].copy(), p=tissue["value"][i].copy(),
                        t=t: publish_cut_record(st, injury, v, p, t)))
            q += 1
            continue
        if kind[i] == events.PLATE:
            # a plate's pose touches no tissue: the record again, as it was
            rec = {f: tissue[f][i:i + 1].copy() for f in events.TISSUE_FIELDS}
            out.append((t, lambda st, r=rec: st.tissue.append(**r)))
            q += 1
            continue
        if kind[i] == events.POSE:
            pose = tissue["value"][i].copy()
            out.append((t, lambda st, b=body, p=pose, t=t: publish_pose(st, b, p, t)))
            q += 1
            continue
        # one split: consecutive records of one new body
        e = q
        while e < len(idx) and idx[e] == i + (e - q) and kind[idx[e]] == events.SPLIT \
                and int(tissue["body"][idx[e]]) == body:
            e += 1
        ijk = tissue["ijk"][idx[q:e]].copy()
        src = int(tissue["value"][i, 0])
        out.append((t, lambda st, s=src, v=ijk, b=body, t=t: publish_split(st, s, v, t, b)))
        q = e
    return out


def coverage(session: Session) -> dict:
    """How much of a recorded run a replay can check.

    Returns
    -------
    dict
        ``samples_checked`` (rows readable), ``samples_declared`` (rows the
        file declares), ``seconds_checked`` [s], ``tissue_checked`` and
        ``tissue_declared``, and ``short``: why less than the declared run
        can be checked (None when all of it can).
    """
    s = session.samples
    n = int(len(s["t_s"]))
    ns = session.readable.get("samples", (n, n))[1]
    nt = int(len(session.tissue["t_s"]))
    nt_declared = session.readable.get("tissue", (nt, nt))[1]
    why = []
    if not session.header_ok:
        why.append("the header is corrupt")
    if n == 0:
        why.append("the file holds no samples: nothing to verify")
    elif n < ns:
        why.append(f"only {n:,} of the {ns:,} samples the file declares are readable")
    if nt < nt_declared:
        why.append(f"only {nt:,} of the {nt_declared:,} tissue events are readable")
    lost = [c for c in session.lost if c.startswith(("/samples/", "/tissue/"))]
    if lost:
        why.append(f"{', '.join(lost)} lost")
    if session.holes:
        why.append(f"{', '.join(session.holes)} with rows that fail their checksum")
    if session.stopped:
        why.append(f"the recording stopped early ({session.stopped})")
    return {"samples_checked": n, "samples_declared": int(ns),
            "seconds_checked": round(session.duration_s, 3),
            "tissue_checked": nt, "tissue_declared": int(nt_declared),
            "short": "; ".join(why) or None}


def verify(session: Session, progress=None) -> dict:
    """Replay ``session`` and compare with the recording bit for bit.

    Returns
    -------
    dict
        ``ok`` (everything the file declares was checked and matched),
        ``identical`` (what could be checked matched), :func:`coverage`'s
        figures and, per stream, whether it matched and the first mismatch.
        A file with nothing to check, or less than it declares, is not ok.
    """
    cov = coverage(session)
    if cov["samples_checked"] == 0:
        return {"file": str(session.path), "samples": 0, **cov, "identical": False,
                "tissue_match": False, "forces_match": False, "first_mismatch": None,
                "removals_recorded": 0, "removals_replayed": 0, "events_recorded": 0,
                "events_replayed": 0, "ok": False}
    out = replay(session, progress=progress)
    rec = {k: a for k, a in session.tissue.items() if k != "visible"}
    s = session.samples
    if not session.complete and len(s["t_s"]):
        # a file cut by a crash may hold events of steps whose samples had
        # not been flushed yet: compare what the samples cover
        keep = rec["t_s"] <= s["t_s"][-1]
        rec = {k: v[keep] for k, v in rec.items()}
    got = out["tissue"]
    is_rem = rec["kind"] == events.REMOVED
    report = {"file": str(session.path), "samples": int(len(session.samples["t_s"])),
              "removals_recorded": int(is_rem.sum()),
              "removals_replayed": int((got["kind"] == events.REMOVED).sum()),
              "events_recorded": int(len(rec["t_s"])),
              "events_replayed": int(len(got["t_s"]))}
    n = min(len(rec["t_s"]), len(got["t_s"]))
    first = None
    for k in events.TISSUE_FIELDS:
        a, b = rec[k][:n], got[k][:n]
        bad = np.flatnonzero((a != b).reshape(n, -1).any(axis=1)) if n else []
        if len(bad) and (first is None or bad[0] < first["index"]):
            first = {"index": int(bad[0]), "field": k,
                     "kind": events.KIND_NAMES[int(rec["kind"][bad[0]])],
                     "recorded": np.asarray(a[bad[0]]).tolist(),
                     "replayed": np.asarray(b[bad[0]]).tolist()}
    if first is None and len(rec["t_s"]) != len(got["t_s"]):
        first = {"index": n, "field": "count", "recorded": int(len(rec["t_s"])),
                 "replayed": int(len(got["t_s"]))}
    report["tissue_match"] = first is None
    report["first_mismatch"] = first
    # rows of a column with holes read as NaN (their chunk failed its
    # checksum; coverage names them): they cannot be compared, the rest can
    ok_rows = np.isfinite(s["mag_n"]) & np.isfinite(s["tangential_n"]).all(axis=1)
    report["forces_match"] = bool(
        np.array_equal(s["mag_n"][ok_rows], out["mag_n"][ok_rows])
        and np.array_equal(s["tangential_n"][ok_rows], out["tangential_n"][ok_rows]))
    report.update(cov)
    report["identical"] = report["tissue_match"] and report["forces_match"]
    report["ok"] = report["identical"] and cov["short"] is None
    return report
