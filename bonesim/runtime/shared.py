"""Numpy arrays in shared memory, for state shared between processes.

The haptic loop runs in its own process (so that neither rendering nor Python's
global interpreter lock can delay it); the window, sound and recorder read the
state it writes. :class:`SharedArrays` lays out named numpy arrays in one
:class:`multiprocessing.shared_memory.SharedMemory` block; its picklable
:attr:`~SharedArrays.handle` lets another process attach to the same memory.

Each array has a single writer; readers poll. Ring heads are written after
the records they publish (see :mod:`bonesim.engine.events`).
"""
from __future__ import annotations

from multiprocessing import shared_memory

import numpy as np

__all__ = ["SharedArrays", "end_process", "die_with_parent"]

_ALIGN = 64


def _layout(spec):
    out, off = [], 0
    for name, shape, dtype in spec:
        dt = np.dtype(dtype)
        shape = tuple(int(s) for s in shape)
        n = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
        out.append((name, shape, dt, off))       # the dtype itself: structured ones too
        off += (n + _ALIGN - 1) // _ALIGN * _ALIGN
    return out, max(off, _ALIGN)


class SharedArrays:
    """Named arrays in one shared-memory block.

    Parameters
    ----------
    spec : list of (name, shape, dtype)
        The arrays, created zero-filled. ``dtype`` may be structured (a
        process's named status fields, :mod:`bonesim.runtime.child`); shape ``()``
        is one record.
    """

    def __init__(self, shm, layout, owner: bool):
        self._shm = shm
        self._layout = layout
        self.owner = owner
        self.arrays = {name: np.ndarray(shape, dtype=dt, buffer=shm.buf, offset=off)
                       for name, shape, dt, off in layout}

    @classmethod
    def create(cls, spec) -> "SharedArrays":
        layout, size = _layout(spec)
        shm = shared_memory.SharedMemory(create=True, size=size)
        arr = cls(shm, layout, owner=True)
        for a in arr.arrays.values():
            a.reshape(-1).view(np.uint8).fill(0)     # bytes: structured fields too
        return arr

    @property
    def handle(self) -> tuple:
        """Picklable ``(block name, layout)`` for :meth:`attach`."""
        return self._shm.name, self._layout

    @classmethod
    def attach(cls, handle) -> "SharedArrays":
        name, layout = handle
        # The creating process owns (and unlinks) the block. Processes it
        # spawns share its resource tracker, which unlinks only what is left
        # when all of them are gone, so attaching needs no unregistering.
        try:
            shm = shared_memory.SharedMemory(name=name, track=False)
        except TypeError:                       # Python < 3.13: no 'track'
            shm = shared_memory.SharedMemory(name=name)
        return cls(shm, layout, owner=False)

    def __getitem__(self, name) -> np.ndarray:
        return self.arrays[name]

    def close(self) -> None:
        """Drop this process's mapping (and free the block if we created it)."""
        self.arrays = {}
        try:
            self._shm.close()
        except BufferError:
            pass                       # views still alive: the mapping goes at exit
        if self.owner:
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass


def end_process(proc, timeout_s: float = 5.0) -> None:
    """Wait up to ``timeout_s`` [s] for a child that was asked to quit; if
    it is still alive then, terminate it (SIGTERM: its ``finally`` blocks
    run, see :func:`die_with_parent`) and wait again."""
    proc.join(timeout_s)
    if proc.is_alive():
        proc.terminate()
        proc.join(timeout_s)


def die_with_parent(on_term=None) -> None:
    """End this child process when its parent dies.

    Call first thing in a child process's main function. On Linux the kernel
    then sends it SIGTERM when the parent goes, however it goes (a crash, a
    SIGKILL), so that no haptic loop keeps spinning at real-time priority and
    no server keeps its port after the program is gone. SIGTERM (also what
    ``Process.terminate`` sends) raises :class:`SystemExit`, so the child's
    ``finally`` blocks run. Elsewhere it only installs the SIGTERM handler.

    Parameters
    ----------
    on_term : callable, optional
        Called (in the signal handler) instead of raising SystemExit: a
        process with a main loop sets its quit flag, so it ends the way it
        ends when asked (the recorder's writer drains the rings and closes
        its file). Calling again replaces the handler.
    """
    import ctypes
    import os
    import signal

    def _term(signum, frame):
        if on_term is None:
            raise SystemExit(128 + signum)
        on_term()

    signal.signal(signal.SIGTERM, _term)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)          # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() == 1:                      # the parent died before prctl
        raise SystemExit(0)
