"""Waiting in tests for another process or thread to get somewhere."""
from __future__ import annotations

import time

#: How often the condition is polled [s].
POLL_S = 0.005
#: Loop steps a dropped plate or fragment is given to fall and come to rest
#: (it sleeps after :data:`bonesim.engine.rigid.SLEEP_STEPS` calm steps):
#: 1.5 s of physics at 1 kHz.
SETTLE_STEPS = 1500


def wait_until(cond, timeout_s: float = 20.0, poll=None) -> bool:
    """Call ``cond()`` until it is true or ``timeout_s`` [s] have passed;
    returns its last value. ``poll()``, if given, runs between tries (e.g.
    to pump a consumer)."""
    end = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < end:
        if poll is not None:
            poll()
        time.sleep(POLL_S)
    return bool(cond())


def wait_steps(loop, n: int, timeout_s: float = 60.0) -> bool:
    """Wait until a running haptic loop has taken ``n`` more steps (its
    ``status["steps"]``): the physics' own time, which a fixed sleep only
    stands in for (a loaded machine runs fewer steps in the same seconds).
    Returns True when it has."""
    s0 = int(loop.status["steps"])
    return wait_until(lambda: int(loop.status["steps"]) >= s0 + n, timeout_s)


def wait_tool_at(loop, pos_mm, tol_mm: float = 0.05, timeout_s: float = 20.0) -> bool:
    """Wait until the loop's tool is within ``tol_mm`` [mm] of ``pos_mm`` [mm]
    (case frame), e.g. after :meth:`HapticLoop.set_target`."""
    import numpy as np

    goal = np.asarray(pos_mm, float)
    return wait_until(lambda: float(np.linalg.norm(np.asarray(loop.status["pos_mm"]) - goal))
                      <= tol_mm, timeout_s)


def wait_drill_off(loop, timeout_s: float = 20.0) -> bool:
    """Wait until the loop has taken a step with the drill off (after
    ``set_drill(False)``): every removal it made is published by then."""
    return wait_until(lambda: int(loop.status["drill"]) == 0, timeout_s)
