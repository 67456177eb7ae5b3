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
    """

    def __init__(self, size: int):
        self.size = int(size)
        self._values: dict = {}

    def get(self, key):
        """The value kept for ``key`` (now the most recently used), or None."""
        value = self._values.pop(key, None)
        if value is not None:
            self._values[key] = value
        return value

    def put(self, key, value) -> None:
        """Keep ``value`` for ``key``, dropping the least recently used
        beyond :attr:`size`."""
        self._values.pop(key, None)
        self._values[key] = value
        while len(self._values) > self.size:
            del self._values[next(iter(self._values))]

    def __len__(self) -> int:
        return len(self._values)
