"""One base for every child process: shared status, start-up, errors, quit.

The haptic loop, the audio synthesizer, the session recorder, the nerve
monitor, the tutoring server and the trainee's servo each run in a spawned
child process of their own (see :mod:`bonesim.runtime.haptic_loop` for why). They all
follow one protocol, written once here:

Shared memory
    Each process object owns one :class:`~bonesim.runtime.shared.SharedArrays` block
    with

    ``status`` (child -> parent)
        one record of a numpy structured dtype: the base's fields
        (:data:`BASE_STATUS`: ``ready``, ``done``, ``failed``, ``error``)
        plus the fields the class declares in :attr:`ChildProcess.STATUS`.
        Read a field by name: ``proc.status["t_s"]``.
    ``control`` (parent -> child)
        the same for the parent's side: ``quit`` (:data:`BASE_CONTROL`) plus
        :attr:`ChildProcess.CONTROL` (e.g. the haptic loop's target pose).
    rings
        the rings named in :attr:`ChildProcess.RINGS`, laid out as
        :data:`bonesim.engine.events.RINGS` / :data:`~bonesim.engine.events.OTHER_RINGS`
        declare them, plus any arrays :meth:`ChildProcess.shared_spec` adds.

    Each field has one writer; the other side polls.

Start-up
    :meth:`ChildProcess.start` spawns the child, which attaches to the block
    and runs the class's :meth:`ChildProcess.run`. ``run`` prepares (loads,
    compiles, opens devices), calls :meth:`Child.ready` and then works until
    :attr:`Child.quit`. ``start`` returns once the child is ready. An
    exception in the child before it is ready is written into the shared
    ``error`` field (at most :data:`ERROR_BYTES` bytes); ``start`` then
    raises :class:`~bonesim.errors.ProcessFailed` with the process's name and
    that message. A child that dies silently, or is not ready within the
    timeout, raises the same error type, saying so.

Quit
    :meth:`ChildProcess.stop` sets ``control["quit"]``, waits for the child
    to end (terminating it after ``timeout_s``), and collects the messages
    the child sent the parent (:meth:`Child.send`: final statistics, a model
    too large for shared memory). :meth:`ChildProcess.close` also frees the
    shared memory; the context manager starts and closes.

A new kind of child process is one small subclass: declare ``NAME``,
``STATUS`` (and ``CONTROL`` / ``RINGS`` if it needs them), give
:meth:`ChildProcess.child_args` the picklable arguments and write
:meth:`ChildProcess.run`. ``tests/bonesim/runtime/test_child.py`` shows one.
"""
from __future__ import annotations

import multiprocessing as mp
import time
import traceback

import numpy as np

from bonesim.engine import events
from bonesim.errors import BonesimError, ProcessFailed
from bonesim.runtime.shared import SharedArrays, die_with_parent, end_process

__all__ = ["ERROR_BYTES", "BASE_STATUS", "BASE_CONTROL", "START_TIMEOUT_S",
           "STOP_TIMEOUT_S", "READY_POLL_S", "STOP_POLL_S", "record_dtype", "Child", "ChildProcess"]

#: Size of the shared field a child writes its start-up error into [bytes].
ERROR_BYTES = 512
#: Fields every status record starts with (written by the child).
BASE_STATUS = (("ready", np.uint8), ("done", np.uint8), ("failed", np.uint8),
               ("error", f"S{ERROR_BYTES}"))
#: Fields every control record starts with (written by the parent).
BASE_CONTROL = (("quit", np.uint8),)
#: Default time :meth:`ChildProcess.start` waits for the child to be ready [s].
START_TIMEOUT_S = 60.0
#: Default time :meth:`ChildProcess.stop` waits before terminating the child [s].
STOP_TIMEOUT_S = 5.0
#: How often the parent polls a starting child [s].
READY_POLL_S = 0.01
#: How often a stopping parent looks for the child's last messages [s].
STOP_POLL_S = 0.05


def record_dtype(base, fields) -> np.dtype:
    """An aligned structured dtype of ``base`` followed by ``fields``.

    Parameters
    ----------
    base, fields : sequence of tuple
        ``(name, dtype)`` or ``(name, dtype, shape)`` items.

    Raises
    ------
    ValueError
        If a name repeats (naming it).
    """
    items = [tuple(f) for f in base] + [tuple(f) for f in fields]
    names = [f[0] for f in items]
    for n in names:
        if names.count(n) > 1:
            raise ValueError(f"status/control field {n!r} is declared twice")
    return np.dtype(items, align=True)


def _message(exc: BaseException) -> str:
    """One line for the parent: a user-facing error as it is, else its type too."""
    if isinstance(exc, BonesimError):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


def _encode_error(text: str) -> bytes:
    raw = text.encode("utf-8", errors="replace")[:ERROR_BYTES]
    return raw.decode("utf-8", errors="ignore").encode()          # no cut character


class Child:
    """The child's side of the protocol, handed to :meth:`ChildProcess.run`.

    Attributes
    ----------
    name : str
        The process's name.
    arrays : dict of str -> ndarray
        Every array of the block.
    status, control : ndarray
        The 0-d structured records (``status["t_s"]``); the child writes
        ``status`` and reads ``control``.
    rings : dict of str -> events.Ring
        The rings the class declared.
    """

    def __init__(self, name: str, shared: SharedArrays, ring_names, conn):
        self.name = name
        self.shared = shared
        self.arrays = shared.arrays
        self.status = shared["status"]
        self.control = shared["control"]
        self.rings = {r: events.ring_from_arrays(r, self.arrays) for r in ring_names}
        self._conn = conn
        self._terminated = False

    @property
    def quit(self) -> bool:
        """True once the parent asked the child to end (or SIGTERM did, for
        a class with :attr:`ChildProcess.TERM_QUITS`)."""
        return bool(self.control["quit"]) or self._terminated

    def terminate_softly(self) -> None:
        """SIGTERM handler of :attr:`ChildProcess.TERM_QUITS` classes."""
        self._terminated = True

    def ready(self) -> None:
        """Say the child is ready: :meth:`ChildProcess.start` returns."""
        self.status["ready"] = 1

    def fail(self, message: str) -> None:
        """Report an error for the parent to raise (before :meth:`ready`)."""
        self.status["error"] = _encode_error(message)
        self.status["failed"] = 1

    def send(self, obj) -> None:
        """Send a picklable object to the parent (it reads it in
        :meth:`ChildProcess.receive` or when it stops the child); large
        objects block until the parent reads, so send them after
        :meth:`ready`."""
        try:
            self._conn.send(obj)
        except (OSError, ValueError):          # the parent went away
            pass


def _child_main(cls, handle, name: str, conn, kwargs: dict) -> None:
    """Body of every child process: attach, run the class's :meth:`run`."""
    die_with_parent()
    sh = SharedArrays.attach(handle)
    child = Child(name, sh, cls.RINGS, conn)
    if cls.TERM_QUITS:
        die_with_parent(child.terminate_softly)
    try:
        cls.run(child, **kwargs)
    except Exception as exc:
        child.fail(_message(exc))
        if not isinstance(exc, BonesimError):
            traceback.print_exc()
        raise SystemExit(1) from None
    finally:
        child.status["done"] = 1
        conn.close()
        sh.close()


class ChildProcess:
    """Base of every process object (parent side); see the module docstring.

    Subclasses declare class attributes and implement :meth:`child_args`
    and :meth:`run`, and call ``super().__init__()`` once what
    :meth:`shared_spec` needs is set.

    Attributes
    ----------
    status, control : ndarray
        0-d structured records in shared memory (see :data:`BASE_STATUS`).
    rings : dict of str -> events.Ring
        The class's :attr:`RINGS`, in shared memory.
    arrays : dict of str -> ndarray
        The whole block.
    messages : list
        Objects the child sent (:meth:`Child.send`), collected so far.
    """

    #: Process name (``ps``, error messages).
    NAME = "bonesim-child"
    #: ``(name, dtype[, shape])`` fields the child writes, after :data:`BASE_STATUS`.
    STATUS: tuple = ()
    #: ``(name, dtype[, shape])`` fields the parent writes, after :data:`BASE_CONTROL`.
    CONTROL: tuple = ()
    #: Ring names (:data:`bonesim.engine.events.RINGS` / ``OTHER_RINGS``) in the block.
    RINGS: tuple = ()
    #: SIGTERM sets :attr:`Child.quit` instead of raising SystemExit (a child
    #: that must end its own way, as the recorder closing its file).
    TERM_QUITS = False
    #: Default start-up timeout [s].
    START_TIMEOUT_S = START_TIMEOUT_S
    #: False: a child still starting at the timeout is left to finish (the
    #: audio: the drill is silent until then); errors still raise.
    START_REQUIRED = True

    def __init__(self):
        status_dt = record_dtype(BASE_STATUS, self.STATUS)
        control_dt = record_dtype(BASE_CONTROL, self.CONTROL)
        spec = [("status", (), status_dt), ("control", (), control_dt)]
        for r in self.RINGS:
            spec += events.ring_arrays_spec(r)
        spec += list(self.shared_spec())
        self._sh = SharedArrays.create(spec)
        self.arrays = self._sh.arrays
        self.status = self._sh["status"]
        self.control = self._sh["control"]
        self.rings = {r: events.ring_from_arrays(r, self.arrays) for r in self.RINGS}
        self.messages: list = []
        self._proc = None
        self._conn = None

    # ------------------------------------------------------- subclass parts
    def shared_spec(self) -> list:
        """Further ``(name, shape, dtype)`` arrays of the block (default none)."""
        return []

    def child_args(self) -> dict:
        """Picklable keyword arguments of :meth:`run` (default none)."""
        return {}

    @classmethod
    def run(cls, child: Child, **kwargs) -> None:
        """The child's work (runs in the child): prepare, ``child.ready()``,
        work until ``child.quit``. Raise to report a start-up error."""
        raise NotImplementedError(f"{cls.__name__} must implement run()")

    # ----------------------------------------------------------- lifecycle
    @property
    def handle(self) -> tuple:
        """Shared-memory handle, for other processes that attach to the block."""
        return self._sh.handle

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def error(self) -> str:
        """The child's reported error ("" if none)."""
        if self._sh is None:
            return ""
        return bytes(self.status["error"].item()).decode("utf-8", errors="replace")

    def launch(self) -> "ChildProcess":
        """Spawn the child without waiting (then :meth:`wait_ready`)."""
        if self._proc is not None:
            raise RuntimeError(f"{self.NAME} is already started")
        ctx = mp.get_context("spawn")
        mine, theirs = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_child_main, name=self.NAME, daemon=True,
                           args=(type(self), self._sh.handle, self.NAME, theirs,
                                 self.child_args()))
        try:
            proc.start()                    # pickles the arguments: may raise
        except BaseException:
            mine.close()
            raise
        finally:
            theirs.close()
        self._proc = proc
        self._conn = mine
        return self

    def wait_ready(self, timeout_s: float | None = None) -> "ChildProcess":
        """Wait until the launched child is ready.

        Raises
        ------
        ProcessFailed
            The child reported an error, died, or was not ready within
            ``timeout_s`` [s]. The child is stopped and the shared memory
            freed then (a late child of a class with :attr:`START_REQUIRED`
            False is left to finish starting instead).
        """
        timeout_s = self.START_TIMEOUT_S if timeout_s is None else timeout_s
        end = time.monotonic() + timeout_s
        while not self.status["ready"]:
            if self.status["failed"] or not self._proc.is_alive():
                self._proc.join(STOP_TIMEOUT_S)
                msg = self.error or ("exited during start-up "
                                     f"(exit code {self._proc.exitcode})")
                self.close()
                raise ProcessFailed(self.NAME, msg)
            if time.monotonic() > end:
                if not self.START_REQUIRED:
                    return self                # it goes on starting; fine for this class
                self.close()
                raise ProcessFailed(self.NAME, f"did not start within {timeout_s:g} s")
            time.sleep(READY_POLL_S)
        return self

    def start(self, timeout_s: float | None = None) -> "ChildProcess":
        """Spawn the child and wait until it is ready (see :meth:`wait_ready`)."""
        return self.launch().wait_ready(timeout_s)

    def _recv(self, timeout_s: float) -> tuple:
        """``(True, obj)`` for a message, ``(False, None)`` for none yet;
        closes the pipe at its end (the child is gone)."""
        c = self._conn
        if c is None or not c.poll(timeout_s):
            return False, None
        try:
            obj = c.recv()
        except (EOFError, OSError):
            c.close()
            self._conn = None
            return False, None
        self.messages.append(obj)
        return True, obj

    def receive(self, timeout_s: float = 0.0):
        """The next object the child sent, or None if none came within
        ``timeout_s`` [s] (or the child ended)."""
        return self._recv(timeout_s)[1]

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for a child that ends by itself; True if it has ended."""
        if self._proc is None:
            return True
        self._proc.join(timeout_s)
        return not self._proc.is_alive()

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Ask the child to quit, collect what it sends (:attr:`messages`)
        and wait for it, terminating it after ``timeout_s`` [s]. Idempotent."""
        if self._sh is not None:
            self.control["quit"] = 1
        if self._proc is None:
            return
        end = time.monotonic() + timeout_s
        while self._conn is not None and time.monotonic() < end:
            got, _ = self._recv(min(end - time.monotonic(), STOP_POLL_S))
            if not got and not self._proc.is_alive() and self._conn is not None \
                    and not self._conn.poll(0):
                break
        end_process(self._proc, max(end - time.monotonic(), READY_POLL_S))
        self._proc = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def close(self) -> None:
        """Stop the child and free the shared memory; idempotent. The
        status keeps its final values (a private copy: reading a view of the
        freed memory would crash the process)."""
        self.stop()
        if self._sh is not None:
            self.rings = {}
            self.status = self.status.copy()
            self._sh.close()
            self._sh = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()
