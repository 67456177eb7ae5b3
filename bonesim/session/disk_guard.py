"""Writing session files on a disk that may fill: space checks and a file
whose failed writes HDF5 never sees.

HDF5 handles a failed write badly: the error surfaces as a stack of
tracebacks, the library retries the write at every later flush and at close,
and a process that closes (or merely exits with) such a file can crash
(a segmentation fault at exit was seen with a full disk). Session files are
therefore written through :class:`GuardedFile`, an ordinary Python file that
HDF5 uses through its ``fileobj`` driver: the first write that fails (ENOSPC,
EFBIG from a file-size limit, EIO) is kept as :attr:`GuardedFile.error` and
from then on writes are dropped, so HDF5 carries on and closes normally,
while the file on disk stays exactly what it was before the failure: a
file cut at that moment, which :mod:`bonesim.session.salvage` reads up to its
last complete flush. The writer looks at :attr:`GuardedFile.error` after
every flush and stops recording, saying so.

The file holds an exclusive ``flock`` while it is open, as HDF5's own driver
would: a reader then knows a live writer holds it (and reads it in SWMR mode),
and a second writer is refused.

Space is checked before a run (:func:`check_space`) and while it goes
(:func:`headroom_bytes`): the space left is the smaller of the filesystem's
free space and what the process's file-size limit (``RLIMIT_FSIZE``) still
allows. The figures are in ``bonesim/data/recording.toml``.
"""
from __future__ import annotations

import errno
import fcntl
import io
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from bonesim.errors import BonesimError

__all__ = ["HDF5_SIGNATURE", "lookup3", "SpaceLimits", "load_space_limits", "GuardedFile", "headroom_bytes",
           "estimate_bytes", "check_space", "warn_space", "describe_error"]

_MB = 1 << 20
#: First eight bytes of an HDF5 file.
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_M32 = 0xFFFFFFFF


def _rot(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _M32


def lookup3(data: bytes, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 ``hashlittle``, the checksum of HDF5 metadata.

    Parameters
    ----------
    data : bytes
    initval : int

    Returns
    -------
    int
        The 32-bit hash.
    """
    n = len(data)
    a = b = c = (0xDEADBEEF + n + initval) & _M32
    i = 0
    while n > 12:
        a = (a + int.from_bytes(data[i:i + 4], "little")) & _M32
        b = (b + int.from_bytes(data[i + 4:i + 8], "little")) & _M32
        c = (c + int.from_bytes(data[i + 8:i + 12], "little")) & _M32
        a = (a - c) & _M32
        a ^= _rot(c, 4)
        c = (c + b) & _M32
        b = (b - a) & _M32
        b ^= _rot(a, 6)
        a = (a + c) & _M32
        c = (c - b) & _M32
        c ^= _rot(b, 8)
        b = (b + a) & _M32
        a = (a - c) & _M32
        a ^= _rot(c, 16)
        c = (c + b) & _M32
        b = (b - a) & _M32
        b ^= _rot(a, 19)
        a = (a + c) & _M32
        c = (c - b) & _M32
        c ^= _rot(b, 4)
        b = (b + a) & _M32
        n -= 12
        i += 12
    if n == 0:
        return c
    tail = data[i:i + n] + bytes(12 - n)
    a = (a + int.from_bytes(tail[0:4], "little")) & _M32
    b = (b + int.from_bytes(tail[4:8], "little")) & _M32
    c = (c + int.from_bytes(tail[8:12], "little")) & _M32
    c ^= b
    c = (c - _rot(b, 14)) & _M32
    a ^= c
    a = (a - _rot(c, 11)) & _M32
    b ^= a
    b = (b - _rot(a, 25)) & _M32
    c ^= b
    c = (c - _rot(b, 16)) & _M32
    a ^= c
    a = (a - _rot(c, 4)) & _M32
    b ^= a
    b = (b - _rot(a, 14)) & _M32
    c ^= b
    c = (c - _rot(b, 24)) & _M32
    return c


def _mark_open_for_writing(buf: bytearray) -> None:
    """Set the "open for writing" flag beside the "open for SWMR writing" one in
    a superblock (version 2, 3) at the start of ``buf``, checksum recomputed.

    HDF5's ``fileobj`` driver sets only the SWMR bit; readers then refuse to
    open the live file in SWMR mode ("not already open for SWMR writing").
    With both bits set (as HDF5's own driver writes them) readers follow the
    file while it grows; a clean close writes the flags as 0."""
    if len(buf) < 12 or bytes(buf[:8]) != HDF5_SIGNATURE or buf[8] not in (2, 3):
        return
    size = 12 + 4 * buf[9] + 4
    if len(buf) < size or buf[11] != 4:
        return
    buf[11] = 5
    buf[size - 4:size] = lookup3(bytes(buf[:size - 4])).to_bytes(4, "little")




@dataclass(frozen=True)
class SpaceLimits:
    """The figures of ``bonesim/data/recording.toml`` (see its comments).

    Attributes
    ----------
    reserve_mb : float
        Space kept free for closing and compacting [MB].
    check_every_s : float
        Period of the writer's space check [s].
    warn_minutes : float
        An interactive run warns when less than this much recording fits [min].
    tissue_rows_per_s, camera_rows_per_s : float
        Rows per second assumed by :func:`estimate_bytes` [1/s].
    overhead_fraction : float
        Metadata and chunk rounding, as a fraction of the rows' bytes.
    fixed_mb : float
        Size of a file of no rows [MB].
    """

    reserve_mb: float = 8.0
    check_every_s: float = 1.0
    warn_minutes: float = 10.0
    tissue_rows_per_s: float = 500.0
    camera_rows_per_s: float = 60.0
    overhead_fraction: float = 0.25
    fixed_mb: float = 2.0


def load_space_limits(path=None) -> SpaceLimits:
    """Read :class:`SpaceLimits` (default the shipped ``recording.toml``)."""
    from bonesim.resources import data_path
    from bonesim.tomlfile import check_keys, get_number, read_toml

    path = Path(path) if path is not None else data_path("recording.toml")
    doc = read_toml(path)
    check_keys(doc, ("space", "estimate"), path, "top level")
    space, est = doc.get("space", {}), doc.get("estimate", {})
    check_keys(space, ("reserve_mb", "check_every_s", "warn_minutes"), path, "space")
    check_keys(est, ("tissue_rows_per_s", "camera_rows_per_s", "overhead_fraction",
                     "fixed_mb"), path, "estimate")
    d = SpaceLimits()
    return SpaceLimits(
        reserve_mb=float(get_number(space, "reserve_mb", path, "space", d.reserve_mb, 0.0)),
        check_every_s=float(get_number(space, "check_every_s", path, "space",
                                       d.check_every_s, 0.01)),
        warn_minutes=float(get_number(space, "warn_minutes", path, "space", d.warn_minutes,
                                      0.0)),
        tissue_rows_per_s=float(get_number(est, "tissue_rows_per_s", path, "estimate",
                                           d.tissue_rows_per_s, 0.0)),
        camera_rows_per_s=float(get_number(est, "camera_rows_per_s", path, "estimate",
                                           d.camera_rows_per_s, 0.0)),
        overhead_fraction=float(get_number(est, "overhead_fraction", path, "estimate",
                                           d.overhead_fraction, 0.0)),
        fixed_mb=float(get_number(est, "fixed_mb", path, "estimate", d.fixed_mb, 0.0)))


def describe_error(exc: BaseException) -> str:
    """A failed write in words: the disk full, a file-size limit, or the OS message."""
    code = getattr(exc, "errno", None)
    if code == errno.ENOSPC:
        return "the disk is full (no space left on device)"
    if code == errno.EFBIG:
        return "the file reached the largest size allowed (file too large)"
    if code == errno.EDQUOT:
        return "the disk quota is used up"
    text = getattr(exc, "strerror", None) or str(exc)
    return f"a write failed ({text})"


class GuardedFile(io.RawIOBase):
    """A file for HDF5's ``fileobj`` driver whose writes never raise.

    Parameters
    ----------
    path : path
        Created (or truncated with ``overwrite``) and locked exclusively.
    overwrite : bool
        Replace an existing file (else an existing file is an error).

    Attributes
    ----------
    error : OSError or None
        The first write that failed; from then on every write is dropped.
    written : int
        Bytes written so far (the furthest offset reached) [bytes].
    """

    def __init__(self, path, overwrite: bool = False):
        super().__init__()
        self.path = Path(path)
        flags = os.O_RDWR | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
        fd = os.open(self.path, flags, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise BonesimError(f"{self.path}: another process is writing this file") \
                from None
        self._fd = fd
        self._pos = 0
        self.error: OSError | None = None
        self.written = 0

    # --- the parts HDF5's fileobj driver uses
    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def fileno(self) -> int:
        return self._fd

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        if whence == io.SEEK_END:
            base = max(os.fstat(self._fd).st_size, self.written)
        else:
            base = self._pos if whence == io.SEEK_CUR else 0
        self._pos = max(0, base + int(offset))
        return self._pos

    def readinto(self, buf) -> int:
        view = memoryview(buf).cast("B")
        got = os.preadv(self._fd, [view], self._pos) if len(view) else 0
        if got < len(view):                 # past the end (or dropped writes): zeros
            view[got:] = bytes(len(view) - got)
        self._pos += len(view)
        return len(view)

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        n = len(view)
        if self._pos == 0 and n >= 12:          # the superblock: see _mark_open_for_writing
            buf = bytearray(view)
            _mark_open_for_writing(buf)
            view = memoryview(buf)
        if self.error is None:
            try:
                done = 0
                while done < n:
                    done += os.pwrite(self._fd, view[done:], self._pos + done)
            except OSError as exc:
                self.error = exc
        self._pos += n
        self.written = max(self.written, self._pos)
        return n

    def truncate(self, size=None) -> int:
        size = self._pos if size is None else int(size)
        if self.error is None:
            try:
                os.ftruncate(self._fd, size)
            except OSError as exc:
                self.error = exc
        return size

    def flush(self) -> None:
        pass

    def sync(self) -> None:
        """Make what was written durable (fsync; a failure is an :attr:`error`)."""
        if self.error is None:
            try:
                os.fsync(self._fd)
            except OSError as exc:
                self.error = exc

    def close(self) -> None:
        if not self.closed:
            try:
                os.close(self._fd)          # releases the lock
            finally:
                super().close()


def headroom_bytes(path) -> int:
    """Bytes that may still be written to ``path``: the filesystem's free space,
    or less when the process's file-size limit (``RLIMIT_FSIZE``) is nearer."""
    path = Path(path)
    folder = path.parent if path.parent.exists() else Path.cwd()
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        free = 1 << 62
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        if soft != resource.RLIM_INFINITY:
            size = path.stat().st_size if path.exists() else 0
            free = min(free, max(0, soft - size))
    except (ImportError, OSError, ValueError):
        pass
    return int(free)


def estimate_bytes(duration_s: float, rate_hz: float, limits: SpaceLimits | None = None) -> int:
    """Estimated size of an uncompressed session file [bytes].

    Parameters
    ----------
    duration_s : float
        Length of the run [s].
    rate_hz : float
        Haptic rate [Hz] (one ``samples`` row per step).
    limits : SpaceLimits, optional
        Default :func:`load_space_limits`.
    """
    import numpy as np

    from bonesim.engine import events

    lim = load_space_limits() if limits is None else limits

    def row(cols):
        return sum(np.dtype(dt).itemsize * int(np.prod(shape)) for dt, shape in cols.values())

    # the recorder's groups (bonesim.session.schema.GROUPS): the rings' records,
    # the tissue rows with their one-byte ``visible``
    per_s = (row(events.OTHER_RINGS["samples"][1]) * rate_hz
             + (row(events.TISSUE_FIELDS) + 1) * lim.tissue_rows_per_s
             + row(events.OTHER_RINGS["camera"][1]) * lim.camera_rows_per_s)
    return int(lim.fixed_mb * _MB + per_s * max(duration_s, 0.0) * (1 + lim.overhead_fraction))


def check_space(path, duration_s: float | None, rate_hz: float,
                limits: SpaceLimits | None = None) -> str | None:
    """Check there is room to record before a run starts.

    Parameters
    ----------
    path : path
        The session file to be written.
    duration_s : float or None
        Length of a scripted run [s]; None for an interactive run.
    rate_hz : float
        Haptic rate [Hz].
    limits : SpaceLimits, optional

    Returns
    -------
    str or None
        A warning for an interactive run with room for less than
        ``warn_minutes`` of recording (None: enough room).

    Raises
    ------
    BonesimError
        A run of known length whose estimated file does not fit (with the
        estimate and the space left), or no room even for an empty file.
    """
    lim = load_space_limits() if limits is None else limits
    room = headroom_bytes(path)
    reserve = int(lim.reserve_mb * _MB)
    empty = estimate_bytes(0.0, rate_hz, lim)
    if room < empty + reserve:
        raise BonesimError(f"only {room / _MB:.1f} MB can be written there; a recording "
                           f"needs at least {(empty + reserve) / _MB:.1f} MB",
                           path=path, field="--record")
    if duration_s is not None:
        need = estimate_bytes(duration_s, rate_hz, lim) + reserve
        if room < need:
            raise BonesimError(f"not enough space to record the {duration_s:.1f} s run: about "
                               f"{need / _MB:.1f} MB needed, {room / _MB:.1f} MB can be "
                               "written there", path=path, field="--record")
        return None
    per_min = estimate_bytes(60.0, rate_hz, lim) - empty
    minutes = (room - reserve - empty) / max(per_min, 1)
    if minutes < lim.warn_minutes:
        return (f"{path}: room for only about {minutes:.1f} min of recording "
                f"({room / _MB:.0f} MB can be written there); recording stops, saying so, "
                "when the space runs out")
    return None


def warn_space(path, rate_hz: float | None = None) -> None:
    """Before an interactive run: print :func:`check_space`'s warning (if any)
    on stderr as one line (a file that cannot be written at all raises)."""
    import sys

    from bonesim.engine.model import HAPTIC_RATE_HZ

    warn = check_space(path, None, HAPTIC_RATE_HZ if rate_hz is None else rate_hz)
    if warn:
        print(f"bonesim: {warn}", file=sys.stderr, flush=True)
