"""Compile the numba kernels ahead of time (``bonesim warmup``).

Kernels are compiled on first use and cached on disk next to their modules
(``@njit(cache=True)``). A cold first run of the simulator therefore spends
about a minute compiling in its processes (haptic loop, sound, nerve
monitor, window) at once. :func:`warmup_all` compiles them all in one
process instead; ``scripts/setup.sh`` runs it after installing, so the first
``bonesim run`` (and the test suite) starts warm.
"""
from __future__ import annotations

import time

__all__ = ["warmup_all"]


def _monitor() -> None:
    import numpy as np

    from .monitor import NerveField

    mask = np.zeros((6, 6, 6), bool)
    mask[3, 3, 1:5] = True
    NerveField(mask, 0.5, (0.0, 0.0, 0.0), 1.0).distance([[0.5, 0.5, 0.5], [9.0, 9.0, 9.0]])


def _parts():
    from . import clicks, dust, model, sound, surface, thickness, tutor, vibration

    return [("haptic step", model.warmup), ("surface", surface.warmup), ("dust", dust.warmup),
            ("vibration", vibration.warmup), ("sound", sound.warmup),
            ("thickness", thickness.warmup), ("clicks", clicks.warmup),
            ("nerve monitor", _monitor), ("tutoring", tutor.warmup)]


def warmup_all(report=None) -> dict:
    """Compile (or load from the cache) every kernel the simulator's
    processes use at start-up.

    Parameters
    ----------
    report : callable, optional
        Called with ``(name, seconds)`` after each part.

    Returns
    -------
    dict
        Seconds per part [s].
    """
    out = {}
    for name, fn in _parts():
        t0 = time.perf_counter()
        fn()
        out[name] = round(time.perf_counter() - t0, 3)
        if report is not None:
            report(name, out[name])
    return out
