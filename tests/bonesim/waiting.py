"""Waiting in tests for another process or thread to get somewhere."""
from __future__ import annotations

import time

#: How often the condition is polled [s].
POLL_S = 0.005


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
