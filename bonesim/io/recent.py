"""A process's most recently used values, kept for its later calls.

The phantom's generated volume (:func:`bonesim.io.phantom.phantom_volume`),
a phantom case's landmarks (:meth:`bonesim.io.case_records.Case.load_volume`)
and its plan (:func:`bonesim.io.mastoid_plan.plan_case`) are functions of
their arguments alone; a cohort, a plan and its runs ask for the same ones
again and again. :class:`Recent` keeps a few of them; the callers hand out
copies, so nobody changes what is kept.
"""
from __future__ import annotations

__all__ = ["Recent"]


class Recent:
    """At most ``size`` values by key, the least recently used dropped first.

    Parameters
    ----------
    size : int
        How many values are kept.
    max_bytes : int, optional
        With ``nbytes``: the most bytes the kept values may hold together
        [bytes]; a value larger than that is not kept.
    nbytes : callable, optional
        A value's size [bytes].
    """

    def __init__(self, size: int, max_bytes: int | None = None, nbytes=None):
        if (max_bytes is None) != (nbytes is None):
            raise ValueError("give max_bytes and nbytes together")
        self.size = int(size)
        self.max_bytes = max_bytes
        self._nbytes = nbytes
        self._values: dict = {}

    def get(self, key):
        """The value kept for ``key`` (now the most recently used), or None."""
        value = self._values.pop(key, None)
        if value is not None:
            self._values[key] = value
        return value

    def put(self, key, value) -> bool:
        """Keep ``value`` for ``key``, dropping the least recently used
        beyond :attr:`size` (and :attr:`max_bytes`). Returns whether it was
        kept (not when it alone is larger than :attr:`max_bytes`)."""
        self._values.pop(key, None)
        if self.max_bytes is not None and self._nbytes(value) > self.max_bytes:
            return False
        self._values[key] = value
        while len(self._values) > self.size or (
                self.max_bytes is not None and self.nbytes > self.max_bytes):
            del self._values[next(iter(self._values))]
        return key in self._values

    @property
    def nbytes(self) -> int:
        """Bytes the kept values hold (0 without ``nbytes``) [bytes]."""
        if self._nbytes is None:
            return 0
        return sum(self._nbytes(v) for v in self._values.values())

    def __len__(self) -> int:
        return len(self._values)
