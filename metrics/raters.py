"""Instructor scores: between-rater agreement and the simulator against them.

A study's instructors score the runs (each participant's sessions) on the
final-product scale the simulator's assessment uses (:mod:`metrics.assessment`,
``assess_total``), one or several raters per run. The researcher gives those
scores as a CSV file (``bonesim metrics cohort --ratings CSV``); this module
reads it and measures:

Between raters (:func:`instructor_agreement`, ``between_raters``)
    With two raters or more: ICC(2,1) (two-way random effects, absolute
    agreement, single rater; :func:`metrics.agreement.icc`) over the runs
    every rater scored (a run missing a rater's score is left out and
    counted), the raters as the columns.
Simulator against the instructors (``against``)
    Per run scored by an instructor: the mean of its raters' scores against
    the simulator's own score of that run (default ``assess_total``, on the
    same scale): ICC(2,1) of the two columns and the Bland-Altman bias and
    limits of agreement of simulator minus instructors
    (:func:`metrics.agreement.bland_altman`). The runs are the targets (a
    participant's sessions are several targets: agreement of two
    measurements of the same performance, not a group comparison).

File format (``participant,session,rater,score``)
-------------------------------------------------
A header line naming exactly these four columns (any order, other columns
are refused so that a typo is not ignored), then one line per score:
``participant`` an id of the participants table; ``session`` the session
number as in the participants table (a number); ``rater`` any non-empty
name; ``score`` a finite number. A (participant, session, rater) appears
once. Anything else is refused with one line naming the file, the line and
the column.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

__all__ = ["RATING_COLUMNS", "DEFAULT_AGAINST", "read_ratings", "instructor_agreement"]

#: The columns of a ratings file.
RATING_COLUMNS = ("participant", "session", "rater", "score")
#: The simulator's score compared with the instructors' by default.
DEFAULT_AGAINST = "assess_total"


def read_ratings(path, participants: dict | None = None):
    """Read an instructor ratings file (module notes).

    Parameters
    ----------
    path : path
    participants : dict, optional
        :func:`metrics.participants.read_participants`; a participant not in
        it is refused.

    Returns
    -------
    pandas.DataFrame
        ``participant`` (str), ``session`` (float), ``rater`` (str),
        ``score`` (float), in file order.

    Raises
    ------
    BonesimError
        One line naming the file, the line and the column.
    """
    import pandas as pd

    from bonesim.errors import BonesimError

    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except OSError as exc:
        raise BonesimError(f"{path}: cannot read the ratings ({exc.strerror or exc})") \
            from None
    except UnicodeDecodeError:
        raise BonesimError(f"{path}: the ratings are not UTF-8 text (a CSV file with the "
                           f"columns {', '.join(RATING_COLUMNS)})") from None
    rows = list(csv.reader(text.splitlines()))
    if not rows or not any(c.strip() for c in rows[0]):
        raise BonesimError(f"{path}: empty; expected a header line "
                           f"{','.join(RATING_COLUMNS)}")
    head = [c.strip().lower() for c in rows[0]]
    if sorted(head) != sorted(RATING_COLUMNS):
        raise BonesimError(f"{path}: line 1: the columns must be "
                           f"{','.join(RATING_COLUMNS)} (got {','.join(head)})")
    col = {c: head.index(c) for c in RATING_COLUMNS}
    out, seen = [], {}
    for line, r in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in r):
            continue
        if len(r) != len(head):
            raise BonesimError(f"{path}: line {line}: {len(r)} fields, the header has "
                               f"{len(head)}")
        cell = {c: r[col[c]].strip() for c in RATING_COLUMNS}
        if not cell["participant"]:
            raise BonesimError(f"{path}: line {line}, column 'participant': empty")
        if participants is not None and cell["participant"] not in participants:
            raise BonesimError(f"{path}: line {line}, column 'participant': "
                               f"{cell['participant']!r} is not in the participants table")
        if not cell["rater"]:
            raise BonesimError(f"{path}: line {line}, column 'rater': empty")
        num = {}
        for c in ("session", "score"):
            try:
                num[c] = float(cell[c])
            except ValueError:
                num[c] = math.nan
            if not math.isfinite(num[c]):
                raise BonesimError(f"{path}: line {line}, column {c!r}: {cell[c]!r} is not "
                                   "a finite number")
        key = (cell["participant"], num["session"], cell["rater"])
        if key in seen:
            raise BonesimError(f"{path}: line {line}: rater {cell['rater']!r} scored "
                               f"participant {cell['participant']!r} session "
                               f"{num['session']:g} already on line {seen[key]}")
        seen[key] = line
        out.append((cell["participant"], num["session"], cell["rater"], num["score"]))
    if not out:
        raise BonesimError(f"{path}: no scores after the header")
    return pd.DataFrame(out, columns=list(RATING_COLUMNS))


def _between_raters(ratings) -> dict:
    from metrics.agreement import icc

    raters = sorted(ratings["rater"].unique())
    wide = ratings.pivot(index=["participant", "session"], columns="rater", values="score")
    full = wide.dropna()
    rec = {"raters": raters, "runs": int(len(full)), "runs_left_out": int(len(wide) -
                                                                           len(full))}
    if len(raters) < 2:
        rec["note"] = "one rater: no between-rater agreement"
        return rec
    if len(full) < 2:
        rec["note"] = "fewer than two runs scored by every rater"
        return rec
    try:
        rec["icc"] = icc(full[raters].to_numpy(float))
    except ValueError as exc:
        rec["note"] = str(exc)
    return rec


def instructor_agreement(ratings, table, against: str = DEFAULT_AGAINST) -> dict:
    """Agreement between the raters, and of the simulator with them.

    Parameters
    ----------
    ratings : pandas.DataFrame
        From :func:`read_ratings`.
    table : pandas.DataFrame
        The cohort table (``participant``, ``session``, the ``against`` column).
    against : str
        The simulator's column on the instructors' scale.

    Returns
    -------
    dict
        ``between_raters`` (``raters``, ``runs``, ``runs_left_out``, ``icc``
        or ``note``) and ``against`` (``metric``, ``runs``, ``unmatched``
        (ratings of runs not in the table), ``icc``, ``bland_altman``
        (simulator minus instructors' mean) or ``note``).
    """
    from metrics.agreement import bland_altman, icc

    out = {"between_raters": _between_raters(ratings)}
    mean = ratings.groupby(["participant", "session"])["score"].mean()
    rec = {"metric": against, "runs": 0, "unmatched": []}
    if against not in table:
        rec["note"] = f"the cohort table has no column {against!r}"
        out["against"] = rec
        return out
    t = table[["participant", "session", against]].dropna()
    t = t.assign(session=t["session"].astype(float)).groupby(
        ["participant", "session"])[against].mean()
    both = mean.to_frame("instructors").join(t.rename("simulator"), how="left")
    rec["unmatched"] = [f"{p} session {s:g}" for (p, s) in
                        both.index[both["simulator"].isna()]]
    both = both.dropna()
    rec["runs"] = int(len(both))
    if len(both) < 3:
        rec["note"] = "fewer than three scored runs with the simulator's score"
    else:
        a, b = both["simulator"].to_numpy(float), both["instructors"].to_numpy(float)
        try:
            rec["icc"] = icc(np.column_stack([a, b]))
        except ValueError as exc:
            rec["note"] = str(exc)
        rec["bland_altman"] = bland_altman(a, b)
    out["against"] = rec
    return out
