"""Numpy arrays in shared memory, for state shared between processes.

The haptic loop runs in its own process (so that neither rendering nor Python's
global interpreter lock can delay it); the window, sound and recorder read the
state it writes. :class:`SharedArrays` lays out named numpy arrays in one
:class:`multiprocessing.shared_memory.SharedMemory` block; its picklable
:attr:`~SharedArrays.handle` lets another process attach to the same memory.

Each array has a single writer; readers poll. Ring heads are written after
the records they publish (see :mod:`bonesim.engine.events`).

Nothing is left behind: every block is named ``bonesim_<owner pid>_<random>``.
Whichever process survives frees it: the owner when it closes, an attached
process (a child) when it closes after its owner died (a SIGKILL of the
parent sends the child SIGTERM, :func:`die_with_parent`). A block whose owner
and children were all killed at once (``kill -9`` of the process group, the
resource tracker too) is reclaimed when the next block is created: a block of
the prefix whose owner pid is no longer alive is unlinked, with one line on
stderr saying how much was freed (:func:`reclaim_leftovers`).
"""
from __future__ import annotations

import os
import re
import secrets
import sys
from multiprocessing import shared_memory
from pathlib import Path

import numpy as np

__all__ = ["read_seqlocked", "PREFIX", "SHM_DIR", "SharedArrays", "block_name", "owner_pid", "pid_alive",
           "reclaim_leftovers", "end_process", "die_with_parent"]

_ALIGN = 64
#: Prefix of every block's name (``bonesim_<owner pid>_<random hex>``).
PREFIX = "bonesim_"
#: Where POSIX shared memory shows as files (Linux).
SHM_DIR = Path("/dev/shm")
_NAME = re.compile(rf"^{PREFIX}(\d+)_[0-9a-f]+$")
_reclaimed = False


def block_name(pid: int | None = None) -> str:
    """A new block name owned by ``pid`` (default this process)."""
    return f"{PREFIX}{os.getpid() if pid is None else int(pid)}_{secrets.token_hex(6)}"


def owner_pid(name: str) -> int | None:
    """The owner pid a block name carries (None: not one of ours)."""
    m = _NAME.match(name.lstrip("/"))
    return int(m.group(1)) if m else None


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, dead but not yet reaped, is not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True                       # someone else's process: alive
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def reclaim_leftovers(shm_dir: Path = SHM_DIR, quiet: bool = False) -> list[tuple[str, int]]:
    """Unlink blocks left by dead runs: named with :data:`PREFIX` and an
    owner pid that is no longer alive.

    Parameters
    ----------
    shm_dir : Path
        Where the blocks show as files (``/dev/shm``; nothing is done where
        it does not exist).
    quiet : bool
        Do not print the line on stderr.

    Returns
    -------
    list of (name, bytes)
        What was freed.
    """
    freed = []
    try:
        entries = list(shm_dir.iterdir())
    except OSError:
        return freed
    for entry in entries:
        pid = owner_pid(entry.name)
        if pid is None or pid == os.getpid() or pid_alive(pid):
            continue
        try:
            size = entry.stat().st_size
            entry.unlink()
        except OSError:
            continue                      # another process got it first, or not ours
        freed.append((entry.name, size))
    if freed and not quiet:
        pids = sorted({owner_pid(n) for n, _ in freed})
        print(f"bonesim: reclaimed {sum(b for _, b in freed) / 1e6:.1f} MB of shared "
              f"memory in {len(freed)} block(s) left by dead run(s) (pid "
              f"{', '.join(map(str, pids))})", file=sys.stderr)
    return freed


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
        #: the process that started this one when it attached (the block's
        #: owner, for a child process)
        self._parent = os.getppid()
        self.arrays = {name: np.ndarray(shape, dtype=dt, buffer=shm.buf, offset=off)
                       for name, shape, dt, off in layout}

    @classmethod
    def create(cls, spec) -> "SharedArrays":
        global _reclaimed
        if not _reclaimed:                  # once per process: a dead run's blocks
            _reclaimed = True
            reclaim_leftovers()
        layout, size = _layout(spec)
        shm = None
        while shm is None:
            try:
                shm = shared_memory.SharedMemory(name=block_name(), create=True, size=size)
            except FileExistsError:         # a random name taken: draw again
                pass
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
        """Drop this process's mapping and free the block if we created it,
        or if its owner is dead (we are the survivor)."""
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
        else:
            pid = owner_pid(self._shm.name)
            # the owner is gone, or it was the parent that started us and we
            # have been handed to another (the kernel does that as the parent
            # dies, before any state of its own says so)
            orphaned = pid == self._parent and os.getppid() != pid
            if pid is not None and (orphaned or not pid_alive(pid)):
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


def read_seqlocked(status, fields, tries: int = 1000):
    """Copy ``fields`` of shared status arrays as written in one go.

    A writer that updates several fields between two increments of the
    ``seq`` field (a sequence lock: odd while writing; the haptic loop's
    per-step status, :data:`bonesim.runtime.haptic_loop.STATUS`) is read
    consistently: the copy is kept when ``seq`` was even and unchanged
    across it, else taken again.

    Parameters
    ----------
    status : mapping of str -> ndarray
        Shared arrays holding ``seq`` (int64) and ``fields``.
    fields : sequence of str
        Names of fields the writer updates under the lock.
    tries : int
        Copies attempted before giving up.

    Returns
    -------
    dict of str -> ndarray or None
        Copies of the fields, or None when no consistent copy was had (the
        caller skips this reading).
    """
    seq = status["seq"]
    for _ in range(tries):
        s0 = int(seq)
        if s0 & 1:
            continue
        out = {k: np.array(status[k], copy=True) for k in fields}
        if int(seq) == s0:
            return out
    return None
