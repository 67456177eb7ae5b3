"""Force-trajectory alignment: how well an applied force curve recalls a target.

A plain RMS difference between a target force curve and the force a user
applied punishes a well-recalled pattern with small timing errors more than
one that is wrong altogether. Following the thesis' section 4 (the
force-recall study), the applied curve is first aligned to the target by
dynamic programming (DP), then scored.

Method
------
1. **Common time base.** Both curves (times [s], possibly irregular, and
   force magnitudes [N]) are resampled at ``rate_hz`` (default
   :data:`DEFAULT_RATE_HZ`), each from its own first sample: sample ``k`` is
   at ``t0 + k / rate_hz``. Times are compared relative to each curve's start.
2. **Box filter.** The applied curve is averaged over a centred window of
   ``window_s`` (the thesis' 100 ms, :data:`DEFAULT_WINDOW_S`). The mean is
   taken exactly over the piecewise-linear curve through the raw samples
   (by its running integral), so the 1 kHz haptic samples are filtered
   before they are decimated; near the ends the window is cut to the data.
   ``filter_target`` filters the target likewise (for a *recorded* target:
   :func:`align_sessions` does; the thesis' target was a clean pattern).
3. **Cost.** ``cost(i, j) = w_force * (a_i - b_j)^2 + w_slope * (a'_i - b'_j)^2``
   [N^2], with ``a`` the target, ``b`` the applied curve and ``'`` the slope
   ``df/dt`` [N/s] (central differences on the time base), so ``w_force``
   has no unit and ``w_slope`` is in s^2.
4. **DP.** A monotone path from ``(0, 0)`` to ``(n-1, m-1)`` through the
   ``n x m`` cost matrix, moving diagonally ``(i-1, j-1) -> (i, j)``,
   vertically ``(i-1, j)`` (the target advances, the applied curve holds) or
   horizontally ``(i, j-1)``; every vertical or horizontal move adds
   ``penalty`` [N^2] (the time-distortion penalty). The path minimises the
   sum of the costs of its cells plus its penalties. **Ties** prefer the
   diagonal, then the vertical, then the horizontal move. An optional
   ``band_s`` keeps the path within that many seconds of the straight line
   from ``(0, 0)`` to ``(n-1, m-1)`` (time and memory then grow with
   ``n * band`` instead of ``n * m``).
5. **Warp and score.** The applied curve is warped onto the target's time
   base: target sample ``i`` takes the mean of the applied samples the path
   pairs with it, and its time offset is the mean of their times minus its
   own (positive: the user was late). The score is the RMS residual [N]
   between the target and the warped curve; the RMS difference without
   alignment (over the samples both curves have) is reported beside it.

Defaults and the evidence for them
----------------------------------
The thesis leaves the weights and the penalty open. They were chosen with
``python -m metrics.studies.alignment_sensitivity`` on synthetic drilling
force curves at 100 Hz: 10 s of plateaus (0 to 3.3 N) joined by 0.1 to
0.6 s ramps, warped by known smooth monotone time warps that move events by
up to 0.6 s and stretch the run by up to 10 %, the trainee's plateau levels
off by up to 15 %, white noise of 0.1 N at 1 kHz; 12 trials per setting, a
clean target (``pattern``, the thesis' setting) and a noisy recorded one
(``recorded``, both filtered). Figures: RMS error of the recovered time
offset on the target's ramps (where a warp is identifiable) [ms], mean and
worst trial, and the RMS offset found on an unwarped control (spurious
distortion) [ms]. Ramp columns: mean over the trials with seed 0 (seed 1
in brackets), then the worst trial of seed 0; control: pattern, recorded.

====================  =============  ===============  =========
w_slope, penalty      pattern ramp   recorded ramp    control
====================  =============  ===============  =========
0, 0.1 (force only)   49 (55), 84    65 (46), 171     0.2, 0
0.01, 0.03            26 (37), 56    53 (31), 155     6.9, 1.1
**0.03, 0.1**         26 (31), 51    47 (25), 109     6.9, 0.9
0.1, 0.3              26 (30), 48    46 (24), 111     7.9, 1.0
0.1, 0.03             26 (30), 45    53 (32), 155     15.6, 30
0.03, 0 (no penalty)  28, 56         60, 187          38, 81
====================  =============  ===============  =========

* The slope term matters: with the force alone the best penalty still
  leaves about twice the ramp error, and its worst trial misses by 0.17 s.
* The penalty matters: without it noise alone warps an unwarped curve by
  tens of milliseconds; too high a penalty (1 N^2) stops the path from
  following real warps (ramp errors of 64 and 95 ms at ``w_slope`` 0.03).
* Good settings lie on a ridge where ``penalty`` is about three times
  ``w_slope`` (in N^2 and s^2; at one time the control picks up 10 ms); ``w_slope = 0.03 s^2`` with
  ``penalty = 0.1 N^2`` (:data:`DEFAULT_W_SLOPE`, :data:`DEFAULT_PENALTY`)
  sits in its middle: ramp errors of 25 to 50 ms (2.5 to 5 samples) against
  true offsets of up to about 1 s, under 1 ms of spurious offset on a recorded target
  and under one sample on a clean one, and the residual after alignment
  falls from 0.6 to 0.9 N (unaligned) to about 0.12 N (the noise and the
  level errors).

The penalty and the summed cell costs both count samples, so the defaults
hold for the default rate; at another ``rate_hz`` rerun the study.

Public API
----------
:func:`align` (two curves), :func:`align_sessions` (two recorded runs),
:func:`resample`, :func:`box_filter` and the result :class:`Alignment`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

__all__ = ["DEFAULT_RATE_HZ", "DEFAULT_WINDOW_S", "DEFAULT_W_FORCE", "DEFAULT_W_SLOPE",
           "DEFAULT_PENALTY", "MAX_CELLS", "ACTIVE_FORCE_N", "SESSION_COLUMNS",
           "MOVE_START", "MOVE_DIAGONAL", "MOVE_VERTICAL", "MOVE_HORIZONTAL",
           "Alignment", "resample", "box_filter", "slope", "band_limits", "dp_align",
           "align", "align_sessions"]

#: Common time base [Hz]: 10 ms steps, so a 10 s trial has the thesis' 1000
#: samples and the 100 ms box spans 10 of them.
DEFAULT_RATE_HZ = 100.0
#: Box-filter width applied to the applied curve [s] (the thesis' 100 ms).
DEFAULT_WINDOW_S = 0.1
#: Weight of the squared force difference [1].
DEFAULT_W_FORCE = 1.0
#: Weight of the squared slope difference [s^2] (from the sensitivity study
#: in the module docstring).
DEFAULT_W_SLOPE = 0.03
#: Cost of one vertical or horizontal DP move [N^2] (from the sensitivity
#: study in the module docstring).
DEFAULT_PENALTY = 0.1
#: Largest DP table allowed (cells of the path-direction table, one byte
#: each); lower ``rate_hz`` or set ``band_s`` for longer curves.
MAX_CELLS = 64_000_000
#: Force above which a session is drilling [N] (:func:`align_sessions` trims
#: each run to its first and last sample above it).
ACTIVE_FORCE_N = 0.05
#: Session columns :func:`align_sessions` can align: ``mag_n`` (the normal
#: force magnitude the haptic step computed) or ``force_n`` (the norm of the
#: force sent to the device: vibration and tangential drag included).
SESSION_COLUMNS = ("mag_n", "force_n")

#: Path-direction codes of the DP table.
MOVE_START = 0
MOVE_DIAGONAL = 1
MOVE_VERTICAL = 2
MOVE_HORIZONTAL = 3

#: Rounding tolerance: a duration this close to a whole number of samples
#: counts as whole, and times this close to a curve's ends [s] as inside.
_ROUNDING_S = 1e-9


# ------------------------------------------------------------------ kernel
@njit(cache=True, nogil=True)
def _dp_kernel(fa, sa, fb, sb, w_force, w_slope, penalty, lo, hi, prev, cur, move, path):
    """Fill the DP over the band ``lo[i] <= j <= hi[i]`` and backtrack.

    ``prev``/``cur`` (m,) float64 are row scratch, ``move`` (n, width) uint8
    the directions (column ``j - lo[i]``), ``path`` (n + m - 1, 2) int64 the
    output. Returns ``(total cost, path length)``.
    """
    n = fa.shape[0]
    inf = np.inf
    pl = 0
    ph = -1
    for i in range(n):
        lo_i = lo[i]
        hi_i = hi[i]
        for j in range(lo_i, hi_i + 1):
            df = fa[i] - fb[j]
            ds = sa[i] - sb[j]
            c = w_force * (df * df) + w_slope * (ds * ds)
            if i == 0 and j == 0:
                best = 0.0
                mv = MOVE_START
            else:
                best = inf
                mv = MOVE_START
                if i > 0 and pl <= j - 1 <= ph:
                    d = prev[j - 1]
                    if d < best:
                        best = d
                        mv = MOVE_DIAGONAL
                if i > 0 and pl <= j <= ph:
                    d = prev[j] + penalty
                    if d < best:
                        best = d
                        mv = MOVE_VERTICAL
                if j > lo_i:
                    d = cur[j - 1] + penalty
                    if d < best:
                        best = d
                        mv = MOVE_HORIZONTAL
            cur[j] = c + best
            move[i, j - lo_i] = mv
        prev, cur = cur, prev
        pl = lo_i
        ph = hi_i
    m = fb.shape[0]
    total = prev[m - 1]
    i = n - 1
    j = m - 1
    k = 0
    while True:
        path[k, 0] = i
        path[k, 1] = j
        k += 1
        mv = move[i, j - lo[i]]
        if mv == MOVE_DIAGONAL:
            i -= 1
            j -= 1
        elif mv == MOVE_VERTICAL:
            i -= 1
        elif mv == MOVE_HORIZONTAL:
            j -= 1
        else:
            break
    for q in range(k // 2):                      # reverse in place: start first
        a0 = path[q, 0]
        a1 = path[q, 1]
        path[q, 0] = path[k - 1 - q, 0]
        path[q, 1] = path[k - 1 - q, 1]
        path[k - 1 - q, 0] = a0
        path[k - 1 - q, 1] = a1
    return total, k


# ----------------------------------------------------------------- helpers
def _finite(name: str, x: float, *, positive: bool = False) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {x!r}") from None
    if not math.isfinite(v) or v < 0 or (positive and v == 0):
        raise ValueError(f"{name} must be a finite number {'> 0' if positive else '>= 0'}, "
                         f"got {x!r}")
    return v


def _curve(name_t: str, name_f: str, t, f) -> tuple[np.ndarray, np.ndarray]:
    """Checked float64 copies of a curve's times [s] and forces [N]."""
    t = np.asarray(t, dtype=np.float64)
    f = np.asarray(f, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"{name_t} must be one-dimensional, got shape {t.shape}")
    if f.shape != t.shape:
        raise ValueError(f"{name_f} must have the shape of {name_t} {t.shape}, got {f.shape}")
    if len(t) < 2:
        raise ValueError(f"{name_t} needs at least 2 samples, got {len(t)}")
    if not np.isfinite(t).all():
        raise ValueError(f"{name_t} holds non-finite times")
    if not np.isfinite(f).all():
        raise ValueError(f"{name_f} holds non-finite forces")
    if not (np.diff(t) > 0).all():
        raise ValueError(f"{name_t} must be strictly increasing")
    return t, f


def _time_base(t: np.ndarray, rate_hz: float) -> np.ndarray:
    n = int(math.floor((t[-1] - t[0]) * rate_hz + _ROUNDING_S)) + 1
    return t[0] + np.arange(n) / rate_hz


def resample(t, f, rate_hz: float = DEFAULT_RATE_HZ) -> tuple[np.ndarray, np.ndarray]:
    """A curve linearly interpolated on a regular time base.

    Parameters
    ----------
    t : (k,) float
        Sample times [s], strictly increasing.
    f : (k,) float
        Forces [N].
    rate_hz : float
        Rate of the time base [Hz].

    Returns
    -------
    tb : (n,) float64
        ``t[0] + arange(n) / rate_hz`` up to ``t[-1]`` [s].
    fb : (n,) float64
        The curve at ``tb`` [N].
    """
    t, f = _curve("t", "f", t, f)
    rate_hz = _finite("rate_hz", rate_hz, positive=True)
    tb = _time_base(t, rate_hz)
    return tb, np.interp(tb, t, f)


def _integral_at(t: np.ndarray, f: np.ndarray, cum: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Integral of the piecewise-linear curve from ``t[0]`` to ``x`` (inside)."""
    k = np.clip(np.searchsorted(t, x, side="right") - 1, 0, len(t) - 2)
    dx = x - t[k]
    fx = f[k] + (f[k + 1] - f[k]) * (dx / (t[k + 1] - t[k]))
    return cum[k] + 0.5 * dx * (f[k] + fx)


def box_filter(t, f, at, window_s: float = DEFAULT_WINDOW_S) -> np.ndarray:
    """Centred moving average of a curve, evaluated at given times.

    The mean is exact over the piecewise-linear curve through the samples;
    the window is cut to ``[t[0], t[-1]]`` near the ends.

    Parameters
    ----------
    t : (k,) float
        Sample times [s], strictly increasing (may be irregular).
    f : (k,) float
        Forces [N].
    at : (n,) float
        Times to evaluate at [s], within ``[t[0], t[-1]]``.
    window_s : float
        Window width [s]; 0 interpolates linearly.

    Returns
    -------
    (n,) float64
        Mean force over ``[at - window_s / 2, at + window_s / 2]`` [N].
    """
    t, f = _curve("t", "f", t, f)
    window_s = _finite("window_s", window_s)
    at = np.asarray(at, dtype=np.float64)
    if at.ndim != 1 or not np.isfinite(at).all():
        raise ValueError("at must be a one-dimensional array of finite times")
    if len(at) and (at.min() < t[0] - _ROUNDING_S or at.max() > t[-1] + _ROUNDING_S):
        raise ValueError(f"at must lie within [{t[0]}, {t[-1]}] s")
    if window_s == 0:
        return np.interp(at, t, f)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * np.diff(t) * (f[1:] + f[:-1]))])
    a = np.clip(at - 0.5 * window_s, t[0], t[-1])
    b = np.clip(at + 0.5 * window_s, t[0], t[-1])
    return (_integral_at(t, f, cum, b) - _integral_at(t, f, cum, a)) / (b - a)


def slope(f, rate_hz: float) -> np.ndarray:
    """Slope ``df/dt`` [N/s] of a curve on a regular time base (central
    differences inside, one-sided at the ends); ``f`` (n,) [N], n >= 2."""
    return np.gradient(np.asarray(f, dtype=np.float64), 1.0 / rate_hz)


def band_limits(n: int, m: int, band: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Per target sample ``i`` the applied samples ``lo[i] <= j <= hi[i]`` the
    path may visit.

    Parameters
    ----------
    n, m : int
        Samples of the target and the applied curve.
    band : float or None
        Half-width in samples around the line from ``(0, 0)`` to
        ``(n-1, m-1)``; None for the whole table. The band is widened where
        needed so that a path always exists.

    Returns
    -------
    lo, hi : (n,) int64
    """
    if band is None:
        return np.zeros(n, np.int64), np.full(n, m - 1, np.int64)
    c = np.arange(n) * ((m - 1) / (n - 1)) if n > 1 else np.zeros(1)
    lo = np.clip(np.ceil(c - band), 0, m - 1).astype(np.int64)
    hi = np.clip(np.floor(c + band), 0, m - 1).astype(np.int64)
    lo[0] = 0
    hi[-1] = m - 1
    # connected: row i must reach back to row i-1 (lo and hi never decrease)
    lo[1:] = np.minimum(lo[1:], hi[:-1] + 1)
    hi = np.maximum(hi, lo)
    return lo, hi


def dp_align(target, applied, target_slope, applied_slope, *, w_force: float = DEFAULT_W_FORCE,
             w_slope: float = DEFAULT_W_SLOPE, penalty: float = DEFAULT_PENALTY,
             band: float | None = None) -> tuple[float, np.ndarray]:
    """The minimum-cost monotone pairing of two sampled curves (step 4 of the
    module docstring).

    Parameters
    ----------
    target, applied : (n,), (m,) float
        Forces on a common time base [N].
    target_slope, applied_slope : (n,), (m,) float
        Their slopes [N/s].
    w_force : float
        Weight of the squared force difference [1].
    w_slope : float
        Weight of the squared slope difference [s^2].
    penalty : float
        Cost of each vertical or horizontal move [N^2].
    band : float, optional
        Half-width of the allowed band [samples] (:func:`band_limits`).

    Returns
    -------
    cost : float
        Sum of the path's cell costs and penalties [N^2].
    path : (k, 2) int64
        ``(i, j)`` pairs from ``(0, 0)`` to ``(n-1, m-1)``.
    """
    arrays = []
    for name, a in (("target", target), ("applied", applied), ("target_slope", target_slope),
                    ("applied_slope", applied_slope)):
        a = np.ascontiguousarray(a, dtype=np.float64)
        if a.ndim != 1 or len(a) < 1:
            raise ValueError(f"{name} must be a non-empty one-dimensional array")
        if not np.isfinite(a).all():
            raise ValueError(f"{name} holds non-finite values")
        arrays.append(a)
    fa, fb, sa, sb = arrays
    n, m = len(fa), len(fb)
    if len(sa) != n:
        raise ValueError(f"target_slope must have {n} samples like target, got {len(sa)}")
    if len(sb) != m:
        raise ValueError(f"applied_slope must have {m} samples like applied, got {len(sb)}")
    w_force = _finite("w_force", w_force)
    w_slope = _finite("w_slope", w_slope)
    penalty = _finite("penalty", penalty)
    if band is not None:
        band = _finite("band", band)
    lo, hi = band_limits(n, m, band)
    width = int((hi - lo).max()) + 1
    if n * width > MAX_CELLS:
        raise ValueError(f"the DP table of {n} x {width} cells exceeds MAX_CELLS={MAX_CELLS}: "
                         "lower rate_hz or set a band")
    move = np.empty((n, width), np.uint8)
    path = np.empty((n + m - 1, 2), np.int64)
    total, k = _dp_kernel(fa, sa, fb, sb, w_force, w_slope, penalty, lo, hi,
                          np.empty(m), np.empty(m), move, path)
    return float(total), path[:k].copy()


# ------------------------------------------------------------------ result
@dataclass(frozen=True, eq=False)
class Alignment:
    """A force-trajectory alignment (:func:`align`).

    Attributes
    ----------
    rms_n : float
        RMS residual between the target and the warped applied curve [N]:
        the score (lower is better).
    unaligned_rms_n : float
        RMS difference without alignment, over the first ``min(n, m)``
        samples of the time base [N].
    cost : float
        DP cost of the path [N^2].
    distortion : float
        Fraction of the path's moves that are not diagonal (0 for the
        diagonal of equal-length curves).
    path : (k, 2) int64
        Paired samples ``(i, j)``, target index first.
    t_s : (n,) float64
        The target's time base, relative to its first sample [s].
    target_n : (n,) float64
        Target on the time base (filtered if ``filter_target``) [N].
    applied_n : (m,) float64
        Box-filtered applied curve on its own time base (same rate) [N].
    warped_n : (n,) float64
        Applied curve warped onto the target's time base [N].
    offset_s : (n,) float64
        Per target sample, the (mean) time of its paired applied samples
        minus its own, both relative to their curve's start [s].
    rate_hz, window_s, w_force, w_slope, penalty : float
        The settings used.
    band_s : float or None
    """

    rms_n: float
    unaligned_rms_n: float
    cost: float
    distortion: float
    path: np.ndarray
    t_s: np.ndarray
    target_n: np.ndarray
    applied_n: np.ndarray
    warped_n: np.ndarray
    offset_s: np.ndarray
    rate_hz: float
    window_s: float
    w_force: float
    w_slope: float
    penalty: float
    band_s: float | None

    def summary(self) -> dict:
        """JSON-ready scalar figures."""
        return {"rms_n": self.rms_n, "unaligned_rms_n": self.unaligned_rms_n,
                "cost": self.cost, "distortion": self.distortion,
                "max_abs_offset_s": float(np.abs(self.offset_s).max()),
                "target_s": float(self.t_s[-1]),
                "applied_s": float((len(self.applied_n) - 1) / self.rate_hz),
                "rate_hz": self.rate_hz, "window_s": self.window_s, "w_force": self.w_force,
                "w_slope": self.w_slope, "penalty": self.penalty, "band_s": self.band_s}


def align(target_t, target_f, applied_t, applied_f, *, rate_hz: float = DEFAULT_RATE_HZ,
          window_s: float = DEFAULT_WINDOW_S, w_force: float = DEFAULT_W_FORCE,
          w_slope: float = DEFAULT_W_SLOPE, penalty: float = DEFAULT_PENALTY,
          band_s: float | None = None, filter_target: bool = False) -> Alignment:
    """Align an applied force curve to a target one and score it.

    Parameters
    ----------
    target_t : (k,) float
        Target sample times [s], strictly increasing (may be irregular).
    target_f : (k,) float
        Target force magnitudes [N].
    applied_t : (l,) float
        Applied sample times [s], strictly increasing.
    applied_f : (l,) float
        Applied force magnitudes [N].
    rate_hz : float
        Rate of the common time base [Hz].
    window_s : float
        Width of the applied curve's box filter [s] (0: none).
    w_force : float
        Weight of the squared force difference [1].
    w_slope : float
        Weight of the squared slope difference [s^2].
    penalty : float
        Cost of each vertical or horizontal DP move [N^2].
    band_s : float, optional
        Keep the path within this many seconds of the straight line between
        the curves' ends (None: no limit).
    filter_target : bool
        Box-filter the target too (for a recorded target).

    Returns
    -------
    Alignment

    Raises
    ------
    ValueError
        Naming the argument that is wrong (shapes, non-finite values, times
        not increasing, negative weights, a DP table over :data:`MAX_CELLS`).
    """
    target_t, target_f = _curve("target_t", "target_f", target_t, target_f)
    applied_t, applied_f = _curve("applied_t", "applied_f", applied_t, applied_f)
    rate_hz = _finite("rate_hz", rate_hz, positive=True)
    window_s = _finite("window_s", window_s)
    w_force = _finite("w_force", w_force)
    w_slope = _finite("w_slope", w_slope)
    penalty = _finite("penalty", penalty)
    if w_force == 0 and w_slope == 0:
        raise ValueError("w_force and w_slope are both 0: every pairing would cost nothing")
    if band_s is not None:
        band_s = _finite("band_s", band_s, positive=True)
    ta = _time_base(target_t, rate_hz)
    tb = _time_base(applied_t, rate_hz)
    if len(ta) < 2:
        raise ValueError(f"target_t spans less than one sample at rate_hz={rate_hz}")
    if len(tb) < 2:
        raise ValueError(f"applied_t spans less than one sample at rate_hz={rate_hz}")
    fa = (box_filter(target_t, target_f, ta, window_s) if filter_target
          else np.interp(ta, target_t, target_f))
    fb = box_filter(applied_t, applied_f, tb, window_s)
    band = None if band_s is None else band_s * rate_hz
    n, m = len(fa), len(fb)
    if band is None and n * m > MAX_CELLS:
        raise ValueError(f"rate_hz={rate_hz} gives a {n} x {m} DP table, over "
                         f"MAX_CELLS={MAX_CELLS}: lower rate_hz or set band_s")
    cost, path = dp_align(fa, fb, slope(fa, rate_hz), slope(fb, rate_hz), w_force=w_force,
                          w_slope=w_slope, penalty=penalty, band=band)
    i, j = path[:, 0], path[:, 1]
    count = np.bincount(i, minlength=n)
    warped = np.bincount(i, weights=fb[j], minlength=n) / count
    offset = (np.bincount(i, weights=j.astype(np.float64), minlength=n) / count
              - np.arange(n)) / rate_hz
    steps = np.diff(path, axis=0)
    moves = len(steps)
    diagonal = int(np.count_nonzero((steps[:, 0] == 1) & (steps[:, 1] == 1)))
    k = min(n, m)
    return Alignment(
        rms_n=float(np.sqrt(np.mean((fa - warped) ** 2))),
        unaligned_rms_n=float(np.sqrt(np.mean((fa[:k] - fb[:k]) ** 2))),
        cost=cost, distortion=(moves - diagonal) / moves if moves else 0.0,
        path=path, t_s=ta - ta[0], target_n=fa, applied_n=fb, warped_n=warped,
        offset_s=offset, rate_hz=rate_hz, window_s=window_s, w_force=w_force,
        w_slope=w_slope, penalty=penalty, band_s=band_s)


# ---------------------------------------------------------------- sessions
def _session_curve(name: str, session, column: str, trim: bool):
    """Times [s] and force magnitudes [N] of a recorded run (a Session or a
    session file's path), trimmed to its drilling if ``trim``."""
    if isinstance(session, (str, Path)):
        from bonesim.session.reader import read_session

        session = read_session(session)
    samples = getattr(session, "samples", None)
    if not isinstance(samples, dict) or "t_s" not in samples or column not in samples:
        raise ValueError(f"{name} has no samples with columns 't_s' and {column!r}")
    t = np.asarray(samples["t_s"], dtype=np.float64)
    f = np.asarray(samples[column], dtype=np.float64)
    if column == "force_n":
        if f.ndim != 2 or f.shape[1:] != (3,):
            raise ValueError(f"{name}'s force_n column must be (n, 3), got {f.shape}")
        f = np.sqrt((f * f).sum(axis=1))
    if trim:
        active = np.flatnonzero(f > ACTIVE_FORCE_N)
        if len(active) < 2:
            raise ValueError(f"{name} never applies more than ACTIVE_FORCE_N="
                             f"{ACTIVE_FORCE_N} N on two samples: nothing to align")
        t, f = t[active[0]:active[-1] + 1], f[active[0]:active[-1] + 1]
    if len(t) < 2:
        raise ValueError(f"{name} has {len(t)} samples; at least 2 are needed")
    return t, f


def align_sessions(expert_session, trainee_session, *, column: str = "mag_n",
                   trim: bool = True, rate_hz: float = DEFAULT_RATE_HZ,
                   window_s: float = DEFAULT_WINDOW_S, w_force: float = DEFAULT_W_FORCE,
                   w_slope: float = DEFAULT_W_SLOPE, penalty: float = DEFAULT_PENALTY,
                   band_s: float | None = None) -> Alignment:
    """Align a trainee's recorded force to an expert's (the target profile).

    Parameters
    ----------
    expert_session, trainee_session : Session or path
        Recorded runs (:func:`bonesim.session.reader.read_session`'s result,
        or a session file to read); their ``samples`` give ``t_s`` [s] and
        the force.
    column : {"mag_n", "force_n"}
        The force compared (:data:`SESSION_COLUMNS`): ``mag_n`` [N], the
        normal force magnitude, or the norm of ``force_n`` (n, 3) [N].
    trim : bool
        Cut each run to the span from its first to its last sample above
        :data:`ACTIVE_FORCE_N` (idle time before and after drilling is not
        part of the pattern).
    rate_hz, window_s, w_force, w_slope, penalty, band_s
        As for :func:`align`. Both curves are box-filtered (the expert's is
        recorded, not a clean pattern).

    Returns
    -------
    Alignment
        Times relative to each run's (trimmed) start.

    Raises
    ------
    ValueError
        Naming the argument that is wrong (an unknown ``column``, a session
        without samples or without force).
    """
    if column not in SESSION_COLUMNS:
        raise ValueError(f"column must be one of {SESSION_COLUMNS}, got {column!r}")
    te, fe = _session_curve("expert_session", expert_session, column, trim)
    tt, ft = _session_curve("trainee_session", trainee_session, column, trim)
    return align(te, fe, tt, ft, rate_hz=rate_hz, window_s=window_s, w_force=w_force,
                 w_slope=w_slope, penalty=penalty, band_s=band_s, filter_target=True)
