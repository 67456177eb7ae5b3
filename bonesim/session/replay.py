"""Replaying a recorded session through the engine, and verifying it bit for bit.

A session's samples, stepped again from the case's initial tissue with the
recorded burrs, must give the recorded tissue events and forces exactly
(``bonesim replay --verify``). Replay has no step of its own: it calls the
same :func:`bonesim.engine.world.world_step` as the haptic loop and
``simulate``, with the world commands (:mod:`bonesim.engine.world_commands`)
rebuilt from the file (:func:`recorded_commands`), each handed to the step
of its time:

* a :class:`~bonesim.engine.world_commands.Reset` where the samples' epoch
  changes and a :class:`~bonesim.engine.world_commands.SetBurr` where their
  burr does;
* the recorded body records, in their recorded order: splits
  (:class:`~bonesim.engine.world_commands.SplitVoxels`), specks shed as dust
  (removals marked ``REMOVED_SHED``, :class:`~bonesim.engine.world_commands.ShedVoxels`),
  cut-plane strokes (``CUT``, :class:`~bonesim.engine.world_commands.CutStroke`),
  body poses (``POSE``, :class:`~bonesim.engine.world_commands.MoveBody`)
  and plate poses (``PLATE``, :class:`~bonesim.engine.world_commands.PlateRecord`).

**Recorded poses and the rigid step.** A recording's ``POSE`` and
``PLATE`` records are what the run's rigid step (and its grab, release,
place, affix and distract commands) produced; the session file does not
hold those user commands, only their outcome. Replay therefore applies the
recorded poses as commands, before the step of their time, and runs with
the rigid step off (its state has no rigid set, ``state.rigid`` None):
the bodies stand exactly where they stood in the run, whatever the rigid
physics of today's code would make of the same inputs, so every file,
of every schema, replays bit for bit the same way.

A damaged file is replayed over its readable part
(:func:`bonesim.session.reader.read_session` cuts every stream at the same
moment).
"""
from __future__ import annotations

import numpy as np

from bonesim.engine import events
from bonesim.session.reader import Session

__all__ = ["replay", "recorded_commands", "verify", "coverage"]


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
    from bonesim.engine.haptics import O_MAG, O_TX, O_TZ
    from bonesim.engine.model import Sample, make_state
    from bonesim.engine.world import world_step
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
    state = make_state(model, rigid=False)   # the recorded poses stand in for it
    mag = np.zeros(n)
    tang = np.zeros((n, 3))
    ring = state.tissue
    cur = events.Cursor(ring, 0)
    chunks = []
    t_col, pos, axis = s["t_s"], s["pos_mm"], s["axis"]
    drill, speed, direc, burr = s["drill"], s["speed_rpm"], s["direction"], s["burr"]
    per_step = recorded_commands(session)
    for q in range(n):
        step_cmds = per_step.get(q, ())
        world_step(model, state, Sample(float(t_col[q]), pos[q], axis[q], bool(drill[q]),
                                        float(speed[q]), int(direc[q]), int(burr[q])),
                   step_cmds)
        mag[q] = state.out[O_MAG]
        tang[q] = state.out[O_TX:O_TZ + 1]
        if ring.count - cur.pos > ring.capacity // 2:
            chunks.append(cur.drain())
        if progress is not None and q % 20000 == 0:
            progress(q / max(n, 1))
    chunks.append(cur.drain())
    return {"tissue": events.concat(chunks), "mag_n": mag, "tangential_n": tang,
            "state": state}


def recorded_commands(session: Session) -> dict:
    """The world commands a recording stands for, per step.

    Parameters
    ----------
    session : Session

    Returns
    -------
    dict of int -> list of WorldCommand
        Sample index -> the commands to hand to that sample's world step, in
        order: a reset where the epoch changes, a burr change where the burr
        does, then the body records of times up to the sample's (see the
        module docstring). Steps without commands are absent.
    """
    from bonesim.engine.world_commands import Reset, SetBurr

    s = session.samples
    t_col, ep, burr = s["t_s"], s["epoch"], s["burr"]
    n = len(t_col)
    body = _body_commands(session.tissue)
    out = {}
    epoch, cur_burr, c = 0, 0, 0
    for q in range(n):
        cmds = []
        if int(ep[q]) != epoch:
            epoch = int(ep[q])
            cmds.append(Reset(epoch))
        if int(burr[q]) != cur_burr:
            cur_burr = int(burr[q])
            cmds.append(SetBurr(cur_burr))
        t = float(t_col[q])
        while c < len(body) and body[c][0] <= t:
            cmds.append(body[c][1])
            c += 1
        if cmds:
            out[q] = cmds
    return out


def _body_commands(tissue: dict) -> list:
    """The recorded splits, poses, plates, shed specks and cut-plane strokes
    as ``(t_s, WorldCommand)``, in recorded order."""
    from bonesim.engine.world_commands import (CutStroke, MoveBody, PlateRecord, ShedVoxels,
                                               SplitVoxels)

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
            out.append((t, ShedVoxels(body, tissue["ijk"][idx[q:e]].copy())))
            q = e
            continue
        if kind[i] == events.CUT:
            # n >= 0: done at once; n = -k: in slices of k rays per step
            k = int(tissue["n"][i])
            out.append((t, CutStroke(tissue["value"][i].copy(), tissue["ijk"][i].copy(),
                                     rays_per_step=-k if k < 0 else 0)))
            q += 1
            continue
        if kind[i] == events.PLATE:
            # a plate's pose touches no tissue: the record again, as it was
            out.append((t, PlateRecord({f: tissue[f][i:i + 1].copy()
                                        for f in events.TISSUE_FIELDS})))
            q += 1
            continue
        if kind[i] == events.POSE:
            out.append((t, MoveBody(body, tissue["value"][i].copy())))
            q += 1
            continue
        # one split (or one slice of a large one, bonesim.engine.split_jobs):
        # consecutive records of one new body and one time, in recorded order
        e = q
        while e < len(idx) and idx[e] == i + (e - q) and kind[idx[e]] == events.SPLIT \
                and int(tissue["body"][idx[e]]) == body and tissue["t_s"][idx[e]] == t:
            e += 1
        src = int(tissue["value"][i, 0])
        out.append((t, SplitVoxels(src, tissue["ijk"][idx[q:e]].copy(), body, ordered=True)))
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


def verify(session: Session, progress=None, models=None) -> dict:
    """Replay ``session`` and compare with the recording bit for bit.

    Parameters
    ----------
    models : list of Model, optional
        As :func:`replay`'s (a run on a model built in memory, whose case no
        file names); default the session's own.

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
    out = replay(session, models=models, progress=progress)
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
