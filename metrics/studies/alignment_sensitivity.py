"""Sensitivity of the force-trajectory alignment to its weights and penalty.

Run ``python -m metrics.studies.alignment_sensitivity [--trials N]``: it
prints, per setting of ``w_slope`` [s^2] (with ``w_force = 1``) and
``penalty`` [N^2], how well :func:`metrics.alignment.align` recovers known
time warps of synthetic drilling force curves. The defaults of
:mod:`metrics.alignment` come from this table.

Synthetic trials
----------------
* **Pattern** (:func:`drilling_pattern`): plateaus of 0.4 to 1.5 s at levels
  of 0.5 to 3.3 N (the device maximum of ``burrs/*.toml``), a quarter of them
  at 0 N (tool lifted), joined by ramps of 0.1 to 0.6 s; consecutive levels
  differ by at least 0.5 N; 10 s long.
* **Warp** (:func:`smooth_warp`): the trainee's time ``u`` maps to the
  pattern's time ``w(u) = s u + sum_k A_k sin(pi k u / T)`` (k = 1..3), which
  keeps both ends, stretches or shrinks the run by ``s`` (the trainee's run
  is 10 s +- 10 %) and moves events by up to :data:`WARP_S`, always
  forward in time (``w' >= MIN_WARP_RATE``).
* **Trainee** (:func:`make_trial`): the pattern at ``w(u)``, each plateau's
  level off by up to +-:data:`LEVEL_ERROR`, plus white noise of
  :data:`NOISE_N` at 1 kHz, clipped to ``[0, 3.3]`` N.
* **Target**: the clean pattern (scenario ``pattern``, the thesis' setting) or
  a noisy recording of it (scenario ``recorded``: same noise, and the target
  box-filtered too, as :func:`metrics.alignment.align_sessions` does).
* **Control**: the trainee's curve without warp and level error (noise
  only): any offset found there is spurious.

Figures
-------
``ramp_ms``: RMS error of the recovered time offset on the target's ramps
(where the warp is identifiable; on a plateau any pairing fits) [ms];
``all_ms``: the same over every sample; ``rms_N``: residual after alignment
[N] (unaligned beside it in the header); ``dist``: fraction of non-diagonal
moves; ``ctrl_ms``: RMS offset found on the control [ms] (0 is right).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from metrics.alignment import DEFAULT_RATE_HZ, align

__all__ = ["RAW_RATE_HZ", "DURATION_S", "MAX_FORCE_N", "PLATEAU_S", "RAMP_S", "MIN_STEP_N",
           "ZERO_SHARE", "NOISE_N", "LEVEL_ERROR", "WARP_S", "STRETCH", "MIN_WARP_RATE",
           "W_SLOPES", "PENALTIES", "drilling_pattern", "smooth_warp", "make_trial",
           "score_trial", "run_study", "main"]

#: Rate of the synthetic recordings [Hz] (the haptic rate).
RAW_RATE_HZ = 1000.0
#: Length of a synthetic pattern [s] (1000 samples at 100 Hz, as in the thesis).
DURATION_S = 10.0
#: Highest force [N] (device maximum in ``burrs/*.toml``).
MAX_FORCE_N = 3.3
#: Plateau and ramp durations [s].
PLATEAU_S = (0.4, 1.5)
RAMP_S = (0.1, 0.6)
#: Smallest level change between consecutive plateaus [N].
MIN_STEP_N = 0.5
#: Share of plateaus at 0 N (tool lifted).
ZERO_SHARE = 0.25
#: White noise on a recorded curve [N] (standard deviation at 1 kHz).
NOISE_N = 0.1
#: Largest relative error of a trainee's plateau level.
LEVEL_ERROR = 0.15
#: Largest shift of an event by the warp [s].
WARP_S = 0.6
#: Largest relative change of the trainee's run length.
STRETCH = 0.1
#: Slowest local rate of the warp (``dw/du``).
MIN_WARP_RATE = 0.4
#: The grid studied: ``w_slope`` [s^2] and ``penalty`` [N^2] (``w_force = 1``).
W_SLOPES = (0.0, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 3e-1)
PENALTIES = (0.0, 1e-3, 1e-2, 3e-2, 1e-1, 3e-1, 1.0)


def drilling_pattern(rng, duration_s: float = DURATION_S):
    """Knots ``(t [s], f [N])`` of a piecewise-linear plateau-and-ramp force
    pattern ending at ``duration_s`` (see the module docstring)."""
    t, f = [0.0], []
    level = 0.0 if rng.random() < ZERO_SHARE else rng.uniform(MIN_STEP_N, MAX_FORCE_N)
    f.append(level)
    while t[-1] < duration_s:
        t.append(t[-1] + rng.uniform(*PLATEAU_S))
        f.append(level)
        while True:
            new = 0.0 if rng.random() < ZERO_SHARE else rng.uniform(MIN_STEP_N, MAX_FORCE_N)
            if abs(new - level) >= MIN_STEP_N:
                break
        level = new
        t.append(t[-1] + rng.uniform(*RAMP_S))
        f.append(level)
    t, f = np.array(t), np.array(f)
    keep = t < duration_s
    end = np.interp(duration_s, t, f)
    return np.append(t[keep], duration_s), np.append(f[keep], end)


def smooth_warp(rng, applied_s: float, target_s: float, shift_s: float = WARP_S):
    """``w`` mapping the trainee's time [s] on ``[0, applied_s]`` to the
    pattern's time on ``[0, target_s]``: monotone, ends fixed, events moved by
    up to ``shift_s`` (see the module docstring)."""
    s = target_s / applied_s
    k = np.arange(1, 4)
    a = rng.normal(size=3) / k
    u = np.linspace(0.0, applied_s, 4001)
    bump = np.sin(np.pi * k[:, None] * u[None, :] / applied_s)
    d_bump = (np.pi * k[:, None] / applied_s) * np.cos(np.pi * k[:, None] * u[None, :]
                                                       / applied_s)
    scale = shift_s / max(np.abs(a @ bump).max(), 1e-12)
    slowest = (a @ d_bump).min()
    if slowest < 0:                        # keep w' >= MIN_WARP_RATE
        scale = min(scale, (s - MIN_WARP_RATE) / -slowest)
    a = a * scale
    return lambda x: s * x + a @ np.sin(np.pi * k[:, None] * np.atleast_1d(x)[None, :]
                                        / applied_s)


def make_trial(rng, *, warp: bool = True, level_error: float = LEVEL_ERROR,
               noisy_target: bool = False):
    """One synthetic trial: target and trainee curves (1 kHz) and the true
    offset [s] and ramp mask as functions of target time [s]."""
    kt, kf = drilling_pattern(rng)
    applied_s = DURATION_S * (1.0 + rng.uniform(-STRETCH, STRETCH)) if warp else DURATION_S
    w = smooth_warp(rng, applied_s, DURATION_S) if warp else (lambda x: np.atleast_1d(x) * 1.0)
    # level error: one factor per plateau (knots 2p, 2p+1 hold plateau p)
    factor = 1.0 + rng.uniform(-level_error, level_error, size=(len(kf) + 1) // 2)
    kf_applied = np.clip(kf * np.repeat(factor, 2)[:len(kf)], 0.0, MAX_FORCE_N)
    ta = np.arange(int(DURATION_S * RAW_RATE_HZ) + 1) / RAW_RATE_HZ
    tb = np.arange(int(applied_s * RAW_RATE_HZ) + 1) / RAW_RATE_HZ
    target = np.interp(ta, kt, kf)
    if noisy_target:
        target = np.clip(target + rng.normal(0, NOISE_N, len(ta)), 0.0, MAX_FORCE_N)
    applied = np.clip(np.interp(w(tb), kt, kf_applied) + rng.normal(0, NOISE_N, len(tb)),
                      0.0, MAX_FORCE_N)
    u = np.linspace(0.0, tb[-1], 20001)
    wu = w(u)

    def true_offset(t):
        return np.interp(t, wu, u) - t

    def on_ramp(t):
        d = np.diff(kf) != 0
        seg = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, len(d) - 1)
        return d[seg]

    return dict(target_t=ta, target_f=target, applied_t=tb, applied_f=applied,
                true_offset=true_offset, on_ramp=on_ramp, filter_target=noisy_target)


def score_trial(trial: dict, **kw) -> dict:
    """Align one trial; errors of the recovered offset [ms] and residuals [N]."""
    al = align(trial["target_t"], trial["target_f"], trial["applied_t"], trial["applied_f"],
               filter_target=trial["filter_target"], **kw)
    err = (al.offset_s - trial["true_offset"](al.t_s)) * 1e3
    ramp = trial["on_ramp"](al.t_s)
    return {"ramp_ms": float(np.sqrt(np.mean(err[ramp] ** 2))),
            "all_ms": float(np.sqrt(np.mean(err ** 2))), "rms_N": al.rms_n,
            "unaligned_N": al.unaligned_rms_n, "dist": al.distortion}


def run_study(trials: int = 12, seed: int = 0, w_slopes=W_SLOPES, penalties=PENALTIES,
              rate_hz: float = DEFAULT_RATE_HZ) -> dict:
    """Mean figures per scenario and setting: ``{scenario: {(w_slope,
    penalty): figures}}``, with the control's ``ctrl_ms`` in each."""
    rng = np.random.default_rng(seed)
    sets = {"pattern": [make_trial(rng) for _ in range(trials)],
            "recorded": [make_trial(rng, noisy_target=True) for _ in range(trials)]}
    controls = {"pattern": [make_trial(rng, warp=False, level_error=0.0)
                            for _ in range(trials)],
                "recorded": [make_trial(rng, warp=False, level_error=0.0, noisy_target=True)
                             for _ in range(trials)]}
    out = {}
    for name, group in sets.items():
        table = {}
        for ws in w_slopes:
            for pen in penalties:
                kw = dict(rate_hz=rate_hz, w_slope=ws, penalty=pen)
                rows = [score_trial(tr, **kw) for tr in group]
                fig = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
                fig["ramp_ms_worst"] = float(np.max([r["ramp_ms"] for r in rows]))
                fig["ctrl_ms"] = float(np.mean([score_trial(tr, **kw)["all_ms"]
                                                for tr in controls[name]]))
                table[(ws, pen)] = fig
        out[name] = table
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=12, help="synthetic trials per scenario")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    res = run_study(args.trials, args.seed)
    for name, table in res.items():
        first = next(iter(table.values()))
        print(f"\nscenario {name}: {args.trials} trials, unaligned RMS "
              f"{first['unaligned_N']:.3f} N (mean)")
        print(f"{'w_slope':>8} {'penalty':>8} {'ramp_ms':>8} {'worst':>7} {'all_ms':>7} "
              f"{'rms_N':>6} {'dist':>5} {'ctrl_ms':>7}")
        for (ws, pen), f in table.items():
            print(f"{ws:8.0e} {pen:8.0e} {f['ramp_ms']:8.1f} {f['ramp_ms_worst']:7.1f} "
                  f"{f['all_ms']:7.1f} {f['rms_N']:6.3f} {f['dist']:5.2f} {f['ctrl_ms']:7.1f}")
        best = min(table, key=lambda k: table[k]["ramp_ms"])
        print(f"lowest ramp error: w_slope={best[0]:g} s^2, penalty={best[1]:g} N^2")
    print(f"\n({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main()
