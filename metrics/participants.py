"""The participants table of a cohort: who is in which group, with sessions.

A CSV with a header row naming at least ``id``, ``group`` (``expert`` or
``novice``, any case) and ``instructor_score`` (a number, or empty), and
optionally:

``session``
    The session: an index (1, 2, ...) or an ISO date (``2026-03-14``; a
    participant's dates are numbered 1, 2, ... in date order). A participant
    may then have many rows, one per session, all of one group.
``file``
    The session file (its name, or a path; matched by name) the row scores.

How a run finds its row (:func:`assign_sessions`): by its file name when the
table names files; else, for a participant with one row and no session,
each of their runs is a session, numbered by the run's start time; else the
participant's runs in start-time order take their rows in session order (the
counts must agree).
"""
from __future__ import annotations

import csv
import datetime as _dt
import io
import math
from pathlib import Path

__all__ = ["COLUMNS", "read_participants", "assign_sessions"]

#: The columns every participants table has.
COLUMNS = ("id", "group", "instructor_score")


def _session(text: str):
    """A session cell as a number or a date (None if neither)."""
    try:
        v = float(text)
        return v if math.isfinite(v) else None
    except ValueError:
        pass
    try:
        return _dt.date.fromisoformat(text)
    except ValueError:
        return None


def read_participants(path) -> dict:
    """Read and check a participants table (module docstring).

    Returns
    -------
    dict
        ``id -> {"group": str, "instructor_score": float, "sessions": list}``
        in file order; ``instructor_score`` is the mean of the participant's
        scored rows (NaN if none); each session is ``{"session": float (1, 2,
        ... or NaN when the table has none), "date": str, "file": str,
        "instructor_score": float, "line": int}``, sorted by session.

    Raises
    ------
    BonesimError
        Naming the file, line and column: a missing file or column, an empty
        id, a group other than expert/novice or one that differs between a
        participant's rows, a score that is not a number, a session that is
        neither a number nor a date, a participant listed twice for one
        session (or twice without sessions), a file named twice.
    """
    from bonesim.errors import BonesimError

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise BonesimError(f"{path}: cannot read the participants table "
                           f"({getattr(exc, 'strerror', None) or exc})") from None
    rd = csv.reader(io.StringIO(text, newline=""))
    head = next(rd, None)
    if head is None:
        raise BonesimError(f"{path}: line 1: empty file; expected the columns "
                           f"{', '.join(COLUMNS)}")
    head = [h.strip().lower() for h in head]
    for c in COLUMNS:
        if c not in head:
            raise BonesimError(f"{path}: line 1: column {c!r} is missing (the header "
                               f"names {', '.join(repr(h) for h in head)})")
    col = {c: head.index(c) for c in (*COLUMNS, "session", "file") if c in head}
    out, files = {}, {}
    for row in rd:
        line = rd.line_num
        if not any(x.strip() for x in row):
            continue
        cell = {c: (row[k].strip() if k < len(row) else "") for c, k in col.items()}
        pid = cell["id"]
        if not pid:
            raise BonesimError(f"{path}: line {line}, column 'id': empty participant id")
        g = cell["group"].lower()
        if g not in ("expert", "novice"):
            raise BonesimError(f"{path}: line {line}, column 'group': {cell['group']!r} "
                               "is not 'expert' or 'novice'")
        s = cell["instructor_score"]
        try:
            score = float(s) if s else math.nan
        except ValueError:
            score = None
        if score is None or math.isinf(score):
            raise BonesimError(f"{path}: line {line}, column 'instructor_score': "
                               f"{s!r} is not a number")
        sess = cell.get("session", "")
        key = _session(sess) if sess else None
        if sess and key is None:
            raise BonesimError(f"{path}: line {line}, column 'session': {sess!r} is "
                               "neither a session number nor an ISO date (YYYY-MM-DD)")
        f = cell.get("file", "")
        if f:
            name = Path(f).name
            if name in files:
                raise BonesimError(f"{path}: line {line}, column 'file': {f!r} is "
                                   f"already listed on line {files[name]}")
            files[name] = line
        p = out.get(pid)
        if p is None:
            p = out[pid] = {"group": g, "sessions": [], "_lines": {}}
        elif p["group"] != g:
            raise BonesimError(f"{path}: line {line}, column 'group': participant {pid!r} "
                               f"is {g!r} here but {p['group']!r} above")
        if repr(key) in p["_lines"]:
            what = f"session {sess!r}" if sess else "without a session"
            raise BonesimError(f"{path}: line {line}, column 'id': participant {pid!r} is "
                               f"listed twice {what} (line {p['_lines'][repr(key)]})")
        p["_lines"][repr(key)] = line
        p["sessions"].append({"key": key, "date": sess if isinstance(key, _dt.date) else "",
                              "file": Path(f).name if f else "", "instructor_score": score,
                              "line": line})
    for pid, p in out.items():
        keys = [s["key"] for s in p["sessions"]]
        kinds = {type(k) for k in keys}
        if len(kinds) > 1:
            raise BonesimError(f"{path}: column 'session': participant {pid!r} mixes "
                               "numbers, dates and blanks")
        if keys[0] is None:
            idx = [math.nan] * len(keys) if len(keys) == 1 else list(range(1, len(keys) + 1))
        elif isinstance(keys[0], _dt.date):
            order = sorted(range(len(keys)), key=lambda q: keys[q])
            idx = [0.0] * len(keys)
            for rank, q in enumerate(order, start=1):
                idx[q] = float(rank)
        else:
            idx = [float(k) for k in keys]
        for s, i in zip(p["sessions"], idx):
            s["session"] = i
            del s["key"]
        p["sessions"].sort(key=lambda s: (s["session"], s["line"]))
        scores = [s["instructor_score"] for s in p["sessions"]
                  if not math.isnan(s["instructor_score"])]
        p["instructor_score"] = sum(scores) / len(scores) if scores else math.nan
        del p["_lines"]
    return out


def assign_sessions(people: dict, runs: list, source="the participants table") -> tuple:
    """Give each run of a listed participant its session and score.

    Parameters
    ----------
    people : dict
        :func:`read_participants`.
    runs : list of dict
        Each with ``file``, ``participant`` and ``start_time`` (ISO text or
        "") ; runs that failed (``error``) are skipped.
    source : str
        Named in the messages.

    Returns
    -------
    (dict, list of str)
        ``file -> {"session": float, "instructor_score": float}`` and one line
        per problem (a run whose file the table does not list while it lists
        files, a count of runs that differs from the participant's sessions).
    """
    out, errors = {}, []
    by_person = {}
    for r in runs:
        if "error" in r or r.get("participant") not in people:
            continue
        by_person.setdefault(r["participant"], []).append(r)
    for pid, mine in by_person.items():
        rows = people[pid]["sessions"]
        mine.sort(key=lambda r: (str(r.get("start_time", "")), Path(r["file"]).name))
        named = {s["file"]: s for s in rows if s["file"]}
        if named:
            for r in mine:
                s = named.get(Path(r["file"]).name)
                if s is None:
                    errors.append(f"{r['file']}: {source} lists files for participant "
                                  f"{pid!r} but not this one; scored without a session")
                    out[r["file"]] = {"session": math.nan,
                                      "instructor_score": people[pid]["instructor_score"]}
                else:
                    out[r["file"]] = {"session": s["session"],
                                      "instructor_score": s["instructor_score"]}
        elif len(rows) == 1 and math.isnan(rows[0]["session"]):
            for k, r in enumerate(mine, start=1):
                out[r["file"]] = {"session": float(k),
                                  "instructor_score": rows[0]["instructor_score"]}
        elif len(rows) == len(mine):
            for s, r in zip(rows, mine):
                out[r["file"]] = {"session": s["session"],
                                  "instructor_score": s["instructor_score"]}
        else:
            errors.append(f"{source}: participant {pid!r} has {len(rows)} session(s) but "
                          f"{len(mine)} run(s); add a 'file' column to say which is which; "
                          "scored without sessions")
            for r in mine:
                out[r["file"]] = {"session": math.nan,
                                  "instructor_score": people[pid]["instructor_score"]}
    return out, errors
