"""Tool trajectories: reading, writing and resampling CSV pose tracks.

A trajectory file is a CSV table in the case frame, one row per sample, with
a header naming exactly these columns (any order, surrounding spaces
ignored)::

    t_s, x_mm, y_mm, z_mm, axis_x, axis_y, axis_z, drill, speed_rpm

plus, optionally, ``direction``, ``suction``, ``irrigation`` and ``burr``:

``t_s``
    Time [s], strictly increasing (it may start anywhere).
``x_mm, y_mm, z_mm``
    Burr centre [mm].
``axis_x, axis_y, axis_z``
    Drill axis, from the handle toward the burr tip; any non-zero length (it
    is normalized on reading).
``drill``
    ``1`` while the drill runs, ``0`` otherwise.
``speed_rpm``
    Spindle speed [rpm], >= 0.
``direction``
    ``1`` (or ``+1``) forward, ``-1`` reverse; ``1`` when the column is absent.
``suction``
    ``1`` while the suction is on, else ``0``; ``0`` when the column is absent.
``irrigation``
    ``1`` while the irrigation runs, else ``0``; ``0`` when the column is absent.
``burr``
    Index of the burr in use in the run's burr table (0: the run's first
    burr; ``bonesim simulate --burr A --burr B`` makes ``A`` 0 and ``B`` 1);
    ``0`` when the column is absent. In ``bonesim simulate`` (and the
    synthetic cohorts) a change is a burr change in the recording, as a key
    press is in the window; the live window's scripted device does not
    change burrs (the keys do).

Suction and irrigation: on a sample with either set, the tool position
stands for the tip of the suction (irrigation) cannula, and the drill must be
off (``drill`` 0): a scripted surgeon rinses between passes, the drill
resting (the demo plan, :mod:`bonesim.io.toolpath`, sweeps the tip over the
cavity just above the cut surface, never touching bone). Both may be on at
once (a suction-irrigator). Consumers (the dust model, the headless run) read
the suction / irrigation tip from the tool position of those samples.

Blank lines are skipped. Every problem is raised as a
:class:`~bonesim.errors.BonesimError` naming the file, the line (1-based, as
an editor shows it) and the column.

Between samples, :meth:`Trajectory.sample_at` interpolates the position
linearly and the axis by normalized linear interpolation, and holds the
previous sample's drill state, speed, direction, suction, irrigation and burr.
"""
from __future__ import annotations

import difflib
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple

import numpy as np

from bonesim.errors import BonesimError
from bonesim.engine.model import Sample
from bonesim.io.limits import LIMITS_FILE, bound, check, check_memory, setting

__all__ = ["COLUMNS", "OPTIONAL_COLUMNS", "Trajectory", "TrajectorySample",
           "read_trajectory", "write_trajectory"]

#: Columns every trajectory file has.
COLUMNS = ("t_s", "x_mm", "y_mm", "z_mm", "axis_x", "axis_y", "axis_z", "drill",
           "speed_rpm")
#: Columns a trajectory file may add.
OPTIONAL_COLUMNS = ("direction", "suction", "irrigation", "burr")
_ALL_COLUMNS = COLUMNS + OPTIONAL_COLUMNS
_AXIS_COLUMNS = ("axis_x", "axis_y", "axis_z")
_POS_COLUMNS = ("x_mm", "y_mm", "z_mm")
_DELIMITER = ","
_FORWARD, _REVERSE = 1, -1
_DRILL_VALUES = (0.0, 1.0)
#: Largest burr index (the recording stores it as uint8).
_MAX_BURR = 255
#: Columns holding 0/1 states.
_FLAG_COLUMNS = ("drill", "suction", "irrigation")

# Relative slack when counting fixed-rate steps in a time span, so that a
# span that is an exact multiple of the step (up to rounding) keeps its end.
_STEP_SLACK = 1e-9


class TrajectorySample(NamedTuple):
    """One sample of a trajectory: a device :class:`~bonesim.engine.model.Sample`
    (the same leading fields, so :func:`bonesim.engine.model.step` takes it) plus
    the rinse states.

    Attributes
    ----------
    t_s : float
        Time [s].
    pos_mm : (3,) float64
        Burr centre, or the suction / irrigation tip while either is on,
        case frame [mm].
    axis : (3,) float64
        Drill axis (unit vector, from the handle toward the burr tip).
    drill : bool
        Drill running.
    speed_rpm : float
        Spindle speed [rpm].
    direction : int
        +1 forward, -1 reverse.
    suction : bool
        Suction on (the position is the suction tip).
    irrigation : bool
        Irrigation running (the position is the irrigation tip).
    burr : int
        Index of the burr in use in the run's burr table.
    """

    t_s: float
    pos_mm: np.ndarray
    axis: np.ndarray
    drill: bool
    speed_rpm: float
    direction: int = 1
    suction: bool = False
    irrigation: bool = False
    burr: int = 0

    def device_sample(self) -> Sample:
        """The device sample alone (without the rinse states)."""
        return Sample(*self[:6])


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A tool trajectory: ``n`` samples as numpy arrays.

    Parameters
    ----------
    t_s : (n,) array_like
        Times [s], finite and strictly increasing.
    pos_mm : (n, 3) array_like
        Burr centre positions, case frame [mm].
    axis : (n, 3) array_like
        Drill axes, any non-zero length (stored normalized).
    drill : (n,) array_like of bool
        Drill running.
    speed_rpm : (n,) array_like
        Spindle speeds [rpm], >= 0.
    direction : (n,) array_like of int, optional
        +1 forward / -1 reverse; all forward by default.
    suction, irrigation : (n,) array_like of bool, optional
        Suction on / irrigation running (the position is then that tip and
        the drill must be off); all off by default.
    burr : (n,) array_like of int, optional
        Index of the burr in use in the run's burr table, >= 0; all 0 by
        default.

    Raises
    ------
    ValueError
        On inconsistent shapes or values (files are checked, with line
        numbers, by :func:`read_trajectory` before they get here).

    Notes
    -----
    The arrays are copies and read-only.
    """

    t_s: np.ndarray
    pos_mm: np.ndarray
    axis: np.ndarray
    drill: np.ndarray
    speed_rpm: np.ndarray
    direction: np.ndarray = field(default=None)
    suction: np.ndarray = field(default=None)
    irrigation: np.ndarray = field(default=None)
    burr: np.ndarray = field(default=None)

    def __post_init__(self):
        t = np.array(self.t_s, dtype=np.float64).reshape(-1)
        n = t.shape[0]
        if n == 0:
            raise ValueError("a trajectory needs at least one sample")
        pos = np.array(self.pos_mm, dtype=np.float64)
        axis = np.array(self.axis, dtype=np.float64)
        drill = np.array(self.drill)
        speed = np.array(self.speed_rpm, dtype=np.float64).reshape(-1)
        if self.direction is None:
            direction = np.full(n, _FORWARD, dtype=np.int8)
        else:
            direction = np.array(self.direction)
        suction, irrigation = (np.zeros(n, dtype=bool) if v is None else np.array(v)
                               for v in (self.suction, self.irrigation))
        burr = np.zeros(n, np.int64) if self.burr is None else np.array(self.burr)
        for label, arr, shape in (("pos_mm", pos, (n, 3)), ("axis", axis, (n, 3)),
                                  ("drill", drill, (n,)), ("speed_rpm", speed, (n,)),
                                  ("direction", direction, (n,)),
                                  ("suction", suction, (n,)),
                                  ("irrigation", irrigation, (n,)), ("burr", burr, (n,))):
            if arr.shape != shape:
                raise ValueError(f"{label} has shape {arr.shape}, expected {shape}")
        for label, arr in (("t_s", t), ("pos_mm", pos), ("axis", axis),
                           ("speed_rpm", speed)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{label} holds non-finite values")
        if np.any(np.diff(t) <= 0):
            raise ValueError("t_s must increase strictly")
        if np.any(speed < 0):
            raise ValueError("speed_rpm must be >= 0")
        for label, arr in (("drill", drill), ("suction", suction),
                           ("irrigation", irrigation)):
            if not np.all(np.isin(arr, (False, True))):
                raise ValueError(f"{label} must hold only 0/1 or False/True")
        if np.any(drill.astype(bool) & (suction.astype(bool) | irrigation.astype(bool))):
            raise ValueError("suction and irrigation need the drill off (the tool "
                             "position is then their tip)")
        if not np.all(np.isin(direction, (_FORWARD, _REVERSE))):
            raise ValueError("direction must hold only +1 or -1")
        if burr.size and not (np.all(np.isfinite(burr)) and np.all(burr == np.round(burr))
                              and burr.min() >= 0 and burr.max() <= _MAX_BURR):
            raise ValueError(f"burr must hold burr indices 0..{_MAX_BURR}")
        norm = np.linalg.norm(axis, axis=1)
        if np.any(norm == 0) or not np.all(np.isfinite(axis / norm[:, None])):
            raise ValueError("axis holds a zero (or unnormalizable) vector")
        set_ = object.__setattr__
        set_(self, "t_s", _frozen(t))
        set_(self, "pos_mm", _frozen(pos))
        set_(self, "axis", _frozen(axis / norm[:, None]))
        set_(self, "drill", _frozen(drill.astype(bool)))
        set_(self, "speed_rpm", _frozen(speed))
        set_(self, "direction", _frozen(direction.astype(np.int8)))
        set_(self, "suction", _frozen(suction.astype(bool)))
        set_(self, "irrigation", _frozen(irrigation.astype(bool)))
        set_(self, "burr", _frozen(burr.astype(np.uint8)))

    def __len__(self) -> int:
        return self.t_s.shape[0]

    @property
    def start_s(self) -> float:
        """Time of the first sample [s]."""
        return float(self.t_s[0])

    @property
    def end_s(self) -> float:
        """Time of the last sample [s]."""
        return float(self.t_s[-1])

    @property
    def duration_s(self) -> float:
        """Time from the first to the last sample [s]."""
        return self.end_s - self.start_s

    def sample(self, i: int) -> TrajectorySample:
        """The ``i``-th stored sample as a :class:`TrajectorySample`."""
        return TrajectorySample(float(self.t_s[i]), self.pos_mm[i].copy(),
                                self.axis[i].copy(), bool(self.drill[i]),
                                float(self.speed_rpm[i]), int(self.direction[i]),
                                bool(self.suction[i]), bool(self.irrigation[i]),
                                int(self.burr[i]))

    def samples(self) -> Iterator[TrajectorySample]:
        """Iterate over the stored samples, in time order."""
        for i in range(len(self)):
            yield self.sample(i)

    def _interpolate(self, times: np.ndarray):
        """Interpolated arrays at ``times`` (clamped to the stored span)."""
        t = self.t_s
        tq = np.clip(times, t[0], t[-1])
        i = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 1)
        j = np.minimum(i + 1, len(t) - 1)
        span = t[j] - t[i]
        w = np.divide(tq - t[i], span, out=np.zeros_like(tq), where=span > 0)
        pos = self.pos_mm[i] + w[:, None] * (self.pos_mm[j] - self.pos_mm[i])
        blend = (1.0 - w)[:, None] * self.axis[i] + w[:, None] * self.axis[j]
        norm = np.linalg.norm(blend, axis=1)
        # Opposite axes half-way through cancel: hold the earlier axis there.
        degenerate = norm == 0
        axis = np.where(degenerate[:, None], self.axis[i],
                        blend / np.where(degenerate, 1.0, norm)[:, None])
        return (tq, pos, axis, self.drill[i], self.speed_rpm[i], self.direction[i],
                self.suction[i], self.irrigation[i], self.burr[i])

    def sample_at(self, t_s: float) -> TrajectorySample:
        """The tool state at time ``t_s``.

        Parameters
        ----------
        t_s : float
            Time [s]. Times before the first sample give the first sample,
            times after the last give the last.

        Returns
        -------
        TrajectorySample
            Position linearly interpolated, axis normalized-lerped, drill,
            speed, direction, suction, irrigation and burr held from the last
            sample at or before ``t_s``. The returned ``t_s`` is the clamped
            time.
        """
        t = self.t_s
        tq = float(t_s)
        if not math.isfinite(tq):              # as the arrays' path does it
            tq, pos, axis, drill, speed, direction, suction, irrigation, burr = \
                self._interpolate(np.array([t_s], dtype=np.float64))
            return TrajectorySample(float(tq[0]), pos[0], axis[0], bool(drill[0]),
                                    float(speed[0]), int(direction[0]), bool(suction[0]),
                                    bool(irrigation[0]), int(burr[0]))
        # one time: the arithmetic of _interpolate on scalars and rows, a
        # few microseconds instead of tens (a scripted device reads one a step)
        last = t.shape[0] - 1
        tq = min(max(tq, float(t[0])), float(t[last]))
        i = min(max(int(np.searchsorted(t, tq, side="right")) - 1, 0), last)
        j = min(i + 1, last)
        span = t[j] - t[i]
        w = (tq - t[i]) / span if span > 0 else np.float64(0.0)
        p0, a0 = self.pos_mm[i], self.axis[i]
        pos = p0 + w * (self.pos_mm[j] - p0)
        blend = (1.0 - w) * a0 + w * self.axis[j]
        norm = np.sqrt(np.add.reduce(blend * blend))
        axis = a0.copy() if norm == 0 else blend / norm
        return TrajectorySample(tq, pos, axis, bool(self.drill[i]), float(self.speed_rpm[i]),
                                int(self.direction[i]), bool(self.suction[i]),
                                bool(self.irrigation[i]), int(self.burr[i]))

    def at_times(self, times_s) -> "Trajectory":
        """The trajectory sampled at given times.

        Parameters
        ----------
        times_s : (m,) array_like
            Strictly increasing times [s] (clamped to the stored span, so
            they must stay strictly increasing after clamping).

        Returns
        -------
        Trajectory
            As :meth:`sample_at`, for every time.
        """
        times = np.asarray(times_s, dtype=np.float64).reshape(-1)
        return Trajectory(*self._interpolate(times))

    def resample(self, rate_hz: float, start_s: float | None = None,
                 end_s: float | None = None) -> "Trajectory":
        """The trajectory at a fixed rate (e.g. the haptic rate).

        Parameters
        ----------
        rate_hz : float
            Samples per second [Hz], > 0.
        start_s, end_s : float, optional
            Span to cover [s]; default: the stored span. Samples fall at
            ``start_s + k / rate_hz`` up to ``end_s``.

        Returns
        -------
        Trajectory

        Raises
        ------
        BonesimError
            If the rate is not a positive number or the span is empty.
        """
        if (isinstance(rate_hz, bool) or not isinstance(rate_hz, (int, float, np.number))
                or not math.isfinite(rate_hz) or rate_hz <= 0):
            raise BonesimError(f"the rate must be a positive number [Hz], got {rate_hz!r}",
                               field="rate_hz")
        start = self.start_s if start_s is None else float(start_s)
        end = self.end_s if end_s is None else float(end_s)
        if not (math.isfinite(start) and math.isfinite(end)) or end < start:
            raise BonesimError(f"the span [{start}, {end}] s is empty or not finite",
                               field="start_s/end_s")
        count = math.floor((end - start) * rate_hz * (1.0 + _STEP_SLACK)) + 1
        check_memory(count * setting("memory", "sample_bytes"),
                     f"resampling the trajectory ({end - start:g} s) at {rate_hz:g} Hz "
                     f"({count:.3g} samples)", field="rate_hz")
        return self.at_times(start + np.arange(count) / rate_hz)


# --------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------

def _where(line: int, column: str | None = None) -> str:
    return f"line {line}" + (f", column '{column}'" if column else "")


def _read_header(path: Path, lines: list[str]) -> tuple[int, list[str]]:
    """Locate the header; return its index in ``lines`` and the column order."""
    head = next((k for k, text in enumerate(lines) if text.strip()), None)
    if head is None:
        raise BonesimError("empty file: expected a header line with the columns "
                           + ", ".join(COLUMNS), path)
    names = [c.strip() for c in lines[head].split(_DELIMITER)]
    line = head + 1
    seen = set()
    for name in names:
        if not name:
            raise BonesimError("empty column name (a stray comma in the header?)",
                               path, _where(line))
        if name in seen:
            raise BonesimError(f"column '{name}' appears twice", path, _where(line))
        seen.add(name)
        if name not in _ALL_COLUMNS:
            close = difflib.get_close_matches(name, _ALL_COLUMNS, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise BonesimError(
                f"unknown column '{name}'{hint}; the columns are "
                f"{', '.join(COLUMNS)} and optionally {', '.join(OPTIONAL_COLUMNS)}",
                path, _where(line))
    missing = [c for c in COLUMNS if c not in seen]
    if missing:
        raise BonesimError(f"missing column(s) {', '.join(missing)}", path, _where(line))
    return head, names


def _parse_slowly(path: Path, rows: list[tuple[int, str]], names: list[str]) -> np.ndarray:
    """Parse cell by cell, raising at the first bad cell (line and column)."""
    data = np.empty((len(rows), len(names)))
    for r, (line, text) in enumerate(rows):
        cells = text.split(_DELIMITER)
        if len(cells) != len(names):
            raise BonesimError(f"expected {len(names)} cells ({', '.join(names)}), "
                               f"got {len(cells)}", path, _where(line))
        for c, (cell, name) in enumerate(zip(cells, names)):
            cell = cell.strip()
            if not cell:
                raise BonesimError("empty cell", path, _where(line, name))
            try:
                data[r, c] = float(cell)
            except ValueError:
                raise BonesimError(f"not a number: {cell!r}", path,
                                   _where(line, name)) from None
    return data


def _first_failure(path: Path, rows, names, checks) -> None:
    """Raise for the earliest row failing any check.

    ``checks`` holds ``(bad_mask, column, message)``; ``message`` may use
    ``{cell}`` (the cell's text) and ``{prev}`` (the same column's cell on the
    previous data row).
    """
    first = None
    for mask, column, message in checks:
        bad = np.flatnonzero(mask)
        if bad.size and (first is None or bad[0] < first[0]):
            first = (int(bad[0]), column, message)
    if first is None:
        return
    r, column, message = first
    col = names.index(column)
    line, text = rows[r]
    cell = text.split(_DELIMITER)[col].strip()
    prev = rows[r - 1][1].split(_DELIMITER)[col].strip() if r else ""
    raise BonesimError(message.format(cell=repr(cell), prev=repr(prev)), path,
                       _where(line, column))


def _chunks(path: Path, fh, chunk_rows: int, max_rows, progress):
    """Yield ``(line numbers, data)`` of the data rows after the header, at
    most ``chunk_rows`` rows at a time; the header's column names come first
    (``names`` then the chunks). Only one chunk's text is in memory at once."""
    line = 0
    names = None
    done_bytes = 0                              # characters read (bytes in ASCII)
    for text in fh:
        line += 1
        done_bytes += len(text)
        if text.strip():
            names = _read_header(path, [text])[1]
            break
    if names is None:
        _read_header(path, [])                  # raises: empty file
    yield names
    rows_seen = 0
    while True:
        numbers, texts = [], []
        try:
            for text in fh:
                line += 1
                done_bytes += len(text)
                if text.strip():
                    numbers.append(line)
                    texts.append(text)
                    if len(texts) >= chunk_rows:
                        break
        except UnicodeDecodeError:
            raise BonesimError(f"not a UTF-8 text (CSV) file (a byte that is not "
                               f"UTF-8 after line {line})", path) from None
        if not texts:
            return
        rows_seen += len(texts)
        if rows_seen > max_rows.max:
            raise BonesimError(f"the number of rows ({rows_seen} so far) is outside the "
                               f"physical bounds {max_rows.text()} ({max_rows.why}; "
                               f"bonesim/data/{LIMITS_FILE})", path, f"line {line}")
        if progress is not None:
            progress(done_bytes)
        rows = list(zip(numbers, (t.rstrip("\r\n") for t in texts)))
        try:
            data = np.loadtxt(io.StringIO("".join(texts)), dtype=np.float64,
                              delimiter=_DELIMITER, comments=None, ndmin=2)
            if data.shape != (len(rows), len(names)):
                raise ValueError("shape")
        except ValueError:
            data = _parse_slowly(path, rows, names)
        yield np.asarray(numbers, dtype=np.int64), data


class _Rows:
    """Row ``r``'s ``(line number, text)`` of a file read in chunks, read
    back from the file only when a message needs a cell's text."""

    def __init__(self, path: Path, lines: np.ndarray):
        self.path, self.lines = path, lines

    def __len__(self) -> int:
        return len(self.lines)

    def __getitem__(self, r: int) -> tuple[int, str]:
        want = int(self.lines[r])
        with open(self.path, encoding="utf-8-sig", newline=None) as fh:
            for k, text in enumerate(fh, start=1):
                if k == want:
                    return want, text.rstrip("\r\n")
        return want, ""


def read_trajectory(path: str | Path, progress=None) -> Trajectory:
    """Read and check a trajectory CSV file, in chunks.

    Parameters
    ----------
    path : str or Path
        The file (format in the module docstring).
    progress : callable or "auto", optional
        ``progress(done_bytes, total_bytes)`` after every chunk; ``"auto"``
        draws a bar on stderr for files of at least ``[reading]
        progress_bytes`` (``bonesim/data/limits.toml``).

    Returns
    -------
    Trajectory

    Raises
    ------
    BonesimError
        Naming the file, line and column: missing or unreadable file, empty
        file, missing, unknown or repeated columns, a row with the wrong
        number of cells, a non-numeric or non-finite cell, time not strictly
        increasing, a zero axis, drill, suction or irrigation not 0/1, a burr
        that is not an index 0..255, suction
        or irrigation with the drill running, a negative speed, a direction
        not +1/-1, or a header without samples; and values outside the
        physical bounds of ``bonesim/data/limits.toml`` (positions, speeds,
        duration, row count) or more memory than the machine has.

    Notes
    -----
    The file is parsed ``[reading] trajectory_chunk_rows`` rows at a time,
    so only one chunk's text is in memory beside the parsed numbers; the
    row count is checked against its bound as the chunks come in, and the
    parsed numbers' memory (estimated from the file size) against the
    machine's before the first chunk.
    """
    path = Path(path)
    if not path.is_file():
        raise BonesimError("file not found", path)
    try:
        size = path.stat().st_size
        fh = open(path, encoding="utf-8-sig", newline=None)
    except OSError as exc:
        raise BonesimError(f"cannot read: {exc.strerror}", path) from None
    shortest_row = 2 * len(COLUMNS)          # "0," per cell
    check_memory(min(size / shortest_row, bound("trajectory_rows").max)
                 * setting("memory", "trajectory_row_bytes"), "reading this trajectory",
                 path)
    bar = None
    if progress == "auto":
        progress = None
        if size >= setting("reading", "progress_bytes"):
            from bonesim.progress import ProgressBar

            bar = ProgressBar(size, label=f"reading {path.name}")
            progress = lambda done: bar.update(done)        # noqa: E731
    elif progress is not None:
        report = progress
        progress = lambda done: report(done, size)           # noqa: E731
    try:
        with fh:
            chunks = _chunks(path, fh, int(setting("reading", "trajectory_chunk_rows")),
                             bound("trajectory_rows"), progress)
            try:
                names = next(chunks)
                parts = list(chunks)
            except UnicodeDecodeError:
                raise BonesimError("not a UTF-8 text (CSV) file", path) from None
    finally:
        if bar is not None:
            bar.close()
    if not parts:
        raise BonesimError("no samples: the file has a header but no data rows", path)
    rows = _Rows(path, np.concatenate([p[0] for p in parts]))
    data = parts[0][1] if len(parts) == 1 else np.concatenate([p[1] for p in parts])
    del parts

    col = {name: data[:, names.index(name)] for name in names}
    checks = [(~np.isfinite(col[name]), name, "must be finite, got {cell}")
              for name in names]
    t = col["t_s"]
    later = np.zeros(len(rows), dtype=bool)
    later[1:] = ~(t[1:] > t[:-1])
    checks.append((later, "t_s", "time must increase strictly: {cell} follows {prev}"))
    axis = np.column_stack([col[c] for c in _AXIS_COLUMNS])
    checks.append((np.all(axis == 0, axis=1), "axis_x",
                   "the axis (axis_x, axis_y, axis_z) is the zero vector"))
    for name in _FLAG_COLUMNS:
        if name in col:
            checks.append((~np.isin(col[name], _DRILL_VALUES), name,
                           name + " must be 0 or 1, got {cell}"))
    running = col["drill"] == _DRILL_VALUES[1]
    for name in ("suction", "irrigation"):
        if name in col:
            checks.append((running & (col[name] == _DRILL_VALUES[1]), name,
                           name + " needs the drill off (the tool position is then "
                           "its tip), got 1 with drill 1"))
    checks.append((col["speed_rpm"] < 0, "speed_rpm", "speed_rpm must be >= 0, got {cell}"))
    speed = bound("speed_rpm")
    checks.append((col["speed_rpm"] > speed.max, "speed_rpm",
                   f"speed_rpm {{cell}} is outside the physical bounds {speed.text()} "
                   f"({speed.why}; bonesim/data/{LIMITS_FILE})"))
    place = bound("coordinate_mm")
    for name in _POS_COLUMNS:
        checks.append(((col[name] < place.min) | (col[name] > place.max), name,
                       f"{name} {{cell}} is outside the physical bounds {place.text()} "
                       f"({place.why}; bonesim/data/{LIMITS_FILE})"))
    if "direction" in col:
        checks.append((~np.isin(col["direction"], (_FORWARD, _REVERSE)), "direction",
                       "direction must be +1 or -1, got {cell}"))
    if "burr" in col:
        b = col["burr"]
        checks.append(((b != np.round(b)) | (b < 0) | (b > _MAX_BURR), "burr",
                       f"burr must be a burr index 0..{_MAX_BURR}, got {{cell}}"))
    _first_failure(path, rows, names, checks)
    check("trajectory_duration_s", float(t[-1] - t[0]), path,
          f"lines {rows.lines[0]}-{rows.lines[-1]}, column 't_s'",
          what="the duration (last t_s - first t_s)")

    pos = np.column_stack([col[c] for c in _POS_COLUMNS])
    direction = col["direction"] if "direction" in col else None
    flags = [col[name] == _DRILL_VALUES[1] if name in col else None
             for name in ("suction", "irrigation")]
    try:
        return Trajectory(t, pos, axis, running, col["speed_rpm"], direction, *flags,
                          col.get("burr"))
    except ValueError as exc:  # e.g. an axis too small to normalize
        raise BonesimError(str(exc), path) from None


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------

def write_trajectory(path: str | Path, traj: Trajectory) -> None:
    """Write a trajectory as CSV, with every column including the optional ones.

    Numbers are written in their shortest exact form, so reading the file
    back gives the same values (axes are re-normalized, which may move them
    by a rounding error).

    Parameters
    ----------
    path : str or Path
        Destination file (overwritten).
    traj : Trajectory

    Raises
    ------
    BonesimError
        If the file cannot be written.
    """
    path = Path(path)
    out = io.StringIO()
    out.write(_DELIMITER.join(_ALL_COLUMNS) + "\n")
    for i in range(len(traj)):
        cells = [repr(float(traj.t_s[i])),
                 *(repr(float(v)) for v in traj.pos_mm[i]),
                 *(repr(float(v)) for v in traj.axis[i]),
                 "1" if traj.drill[i] else "0",
                 repr(float(traj.speed_rpm[i])),
                 str(int(traj.direction[i])),
                 "1" if traj.suction[i] else "0",
                 "1" if traj.irrigation[i] else "0",
                 str(int(traj.burr[i]))]
        out.write(_DELIMITER.join(cells) + "\n")
    try:
        path.write_text(out.getvalue(), encoding="utf-8")
    except OSError as exc:
        raise BonesimError(f"cannot write: {exc.strerror}", path) from None
