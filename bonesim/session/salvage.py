"""Opening session files that are damaged: cut short, zeroed, or left open.

A session file can be damaged in ways HDF5 handles badly:

* **cut short** (a full disk, a copy that stopped): a plain open refuses it at
  once (``truncated file: eof = ..., stored_eof = ...``); an open in SWMR mode
  skips that check and then blocks for a long time retrying metadata that is
  not there;
* **left open** by a writer that died (kill, power loss): the superblock still
  says a writer holds the file, so a plain open refuses it;
* **zeroed or corrupt blocks**: chunks that no longer decompress.

:func:`open_session_file` never waits on a file that no writer holds: it
opens a file plainly; only a file whose lock a live writer holds is opened in
SWMR mode. A cut-short or left-open file is read through
:class:`RepairedView`, a read-only view of the file as HDF5 would see it
whole: zeros past the real end and the superblock's "open for writing" flags
cleared (with its checksum recomputed), the byte-level equivalent of
``h5clear``. Nothing is written to the file itself.

:func:`read_prefix` then reads the leading rows of a dataset that really lie
in the file and decode.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.session.disk_guard import HDF5_SIGNATURE, lookup3

__all__ = ["Superblock", "read_superblock", "RepairedView",
           "open_session_file", "read_prefix", "read_prefix_why"]


class Superblock:
    """The fields of an HDF5 superblock (versions 0 to 3) needed here.

    Attributes
    ----------
    version : int
    eof : int
        End-of-file address the file should reach [bytes].
    flags : int
        File consistency flags (versions 2, 3: bit 0 open for writing, bit 2
        open for SWMR writing).
    raw : bytes
        The superblock's bytes (with the checksum for versions 2, 3).
    """

    def __init__(self, version: int, eof: int, flags: int, raw: bytes):
        self.version, self.eof, self.flags, self.raw = version, eof, flags, raw

    def cleared(self) -> bytes:
        """The superblock with its open-for-writing flags cleared (version 2, 3:
        checksum recomputed); unchanged for older versions."""
        if self.version < 2:
            return self.raw
        body = bytearray(self.raw[:-4])
        body[11] = 0
        return bytes(body) + lookup3(bytes(body)).to_bytes(4, "little")


def read_superblock(path: Path) -> Superblock | None:
    """The superblock at the start of ``path`` (None: no HDF5 signature there,
    or a layout not understood)."""
    with open(path, "rb") as f:
        head = f.read(96)
    if head[:8] != HDF5_SIGNATURE or len(head) < 12:
        return None
    version = head[8]
    if version in (2, 3):
        off = head[9]
        end = 12 + 4 * off + 4
        if len(head) < end or off not in (4, 8):
            return None
        eof = int.from_bytes(head[12 + 2 * off:12 + 3 * off], "little")
        return Superblock(version, eof, head[11], head[:end])
    if version in (0, 1):
        off = head[13]
        start = 24 + (4 if version == 1 else 0)
        if off not in (4, 8) or len(head) < start + 3 * off:
            return None
        eof = int.from_bytes(head[start + 2 * off:start + 3 * off], "little")
        return Superblock(version, eof, 0, head[:start + 4 * off])
    return None


class RepairedView(io.RawIOBase):
    """A read-only view of a damaged HDF5 file as HDF5 would see it whole.

    Parameters
    ----------
    path : Path
    length : int
        Size the view reports [bytes] (the superblock's end of file): reads
        past the file's real end give zeros.
    superblock : bytes
        Replaces the file's first ``len(superblock)`` bytes.
    """

    def __init__(self, path: Path, length: int, superblock: bytes):
        super().__init__()
        self._f = open(path, "rb")
        self._size = Path(path).stat().st_size
        self._length = max(int(length), self._size)
        self._sb = superblock
        self._pos = 0

    @property
    def real_size(self) -> int:
        """Bytes the file really holds."""
        return self._size

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._length}[whence]
        self._pos = max(0, base + int(offset))
        return self._pos

    def readinto(self, buf) -> int:
        view = memoryview(buf).cast("B")
        n = max(0, min(len(view), self._length - self._pos))
        if n == 0:
            return 0
        self._f.seek(self._pos)
        got = self._f.readinto(view[:n]) or 0
        view[got:n] = bytes(n - got)                     # past the real end: zeros
        lo, hi = self._pos, self._pos + n
        if lo < len(self._sb):
            k = min(hi, len(self._sb))
            view[:k - lo] = self._sb[lo:k]
        self._pos = hi
        return n

    def close(self) -> None:
        if not self.closed:
            self._f.close()
        super().close()


def open_session_file(path: Path, h5py):
    """Open a session file for reading without ever waiting on it.

    Returns
    -------
    file : h5py.File
    damage : str or None
        What is wrong with the file, in words (None: nothing).
    real_size : int or None
        Bytes the file holds when it is read through a :class:`RepairedView`
        (None otherwise).
    view : RepairedView or None
        The view read; close it after the file.

    Raises
    ------
    BonesimError
        Missing, empty, not HDF5, or damaged beyond reading.
    """
    if not path.exists():
        raise BonesimError(f"{path}: no such session file")
    if not path.is_file():
        raise BonesimError(f"{path}: not a file")
    size = path.stat().st_size
    if size == 0:
        raise BonesimError(f"{path}: empty file (0 bytes): nothing was recorded in it")
    with open(path, "rb") as f:
        if f.read(8) != HDF5_SIGNATURE:
            raise BonesimError(f"{path}: not an HDF5 file (no HDF5 signature at its start)")
    try:
        return h5py.File(path, "r"), None, None, None
    except OSError as exc:
        msg = str(exc)
    low = msg.lower()
    if "unable to lock" in low or "locking flag" in low:   # a live writer holds it
        try:
            return h5py.File(path, "r", swmr=True, locking=False), None, None, None
        except OSError as exc:
            raise BonesimError(f"{path}: cannot read the file a writer holds ({exc})") \
                from None
    sb = read_superblock(path)
    if sb is None or ("truncated" not in low and "already open for write" not in low):
        raise BonesimError(f"{path}: not a readable HDF5 session file ({msg})")
    damage = []
    if size < sb.eof:
        damage.append(f"cut short: it ends at byte {size:,} of {sb.eof:,}")
    if sb.flags:
        damage.append("left open by a writer that did not close it")
    view = RepairedView(path, sb.eof, sb.cleared())
    try:
        f = h5py.File(view, "r")
    except OSError as exc:
        view.close()
        raise BonesimError(f"{path}: damaged beyond reading ({'; '.join(damage)}): "
                           f"{exc}") from None
    return f, "; ".join(damage) or None, size, view


def read_prefix(ds, real_size: int | None = None) -> np.ndarray:
    """The leading rows of a dataset whose data are in the file and decode
    (:func:`read_prefix_why` without the reason)."""
    return read_prefix_why(ds, real_size)[0]


def read_prefix_why(ds, real_size: int | None = None,
                    holes: bool = False) -> tuple[np.ndarray, str | None]:
    """The leading rows of a dataset whose data are in the file and decode,
    and why the rest do not.

    Parameters
    ----------
    ds : h5py.Dataset
        Rows along axis 0.
    real_size : int or None
        Bytes the file really holds when it is read through a
        :class:`RepairedView` (None: the whole file is there).
    holes : bool
        A chunk that fails to decode or fails its checksum does not end the
        rows: its rows read as NaN (floats) or 0 and reading goes on (for
        columns a replay does not need).

    Returns
    -------
    rows : ndarray
        All rows when every row reads; else the rows up to the first chunk
        that lies past the file's end, was never written (a session file
        writes every row of every column, so a chunk the index lacks within
        the declared rows was lost: it would read as zeros), whose index
        entry can no longer be read, or that fails to decode or fails its
        checksum (Fletcher32).
    why : str or None
        That first bad chunk, in words (``rows 4,096-8,191 fail their
        checksum``); None when every row reads.
    """
    rows = int(ds.shape[0])
    step = ds.chunks[0] if ds.chunks else max(rows, 1)
    why = None
    if rows and ds.chunks:
        # chunk by chunk through the index (a cut-short index still finds its
        # early chunks; a walk over all of them would fail at once)
        r = 0
        while r < rows:
            try:
                info = ds.id.get_chunk_info_by_coord((r,) + (0,) * (ds.ndim - 1))
            except (OSError, RuntimeError, ValueError, KeyError):
                why = f"the index of rows from {r:,} is unreadable"
                break
            if info.byte_offset is None:
                why = f"rows from {r:,} were never written"
                break
            if real_size is not None and info.byte_offset + info.size > real_size:
                why = f"rows from {r:,} lie past the file's end"
                break
            r += step
        rows = min(rows, r)
    elif rows and real_size is not None:
        off = ds.id.get_offset()
        if off is None or off + ds.id.get_storage_size() > real_size:
            rows, why = 0, "its data lie past the file's end"
    try:
        return ds[:rows], why
    except (OSError, ValueError, RuntimeError):
        pass
    parts, r, bad = [], 0, []                    # up to the first chunk that fails
    while r < rows:
        e = min(r + step, rows)
        try:
            parts.append(ds[r:e])
        except (OSError, ValueError, RuntimeError) as exc:
            low = str(exc).lower()
            # with Fletcher32 the checksum is the first filter undone on reading
            checked = "fletcher" in low or "checksum" in low or (
                bool(getattr(ds, "fletcher32", False)) and "filter" in low)
            what = "fail their checksum" if checked else "do not decode"
            if not holes:
                why = f"rows {r:,}-{e - 1:,} {what}"
                break
            bad.append(f"rows {r:,}-{e - 1:,} {what}")
            parts.append(np.full((e - r,) + ds.shape[1:],
                                 np.nan if ds.dtype.kind == "f" else 0, ds.dtype))
        r += step
    if bad:
        fill = "NaN" if ds.dtype.kind == "f" else "0"
        why = "; ".join(bad) + f" ({fill} there)" + (f"; {why}" if why else "")
    out = np.concatenate(parts) if parts else np.zeros((0,) + ds.shape[1:], ds.dtype)
    return out, why
