"""One form per kernel argument: arrays handed to numba kernels with one
layout and one writeable flag, whatever the caller passed.

numba compiles a kernel once per distinct argument type, and a read-only
array is a different type from a writeable one (as a broadcast view is
from a contiguous array). A model's grid is read-only and a state's is
not; a caller's array may be a view or a copy. Wrappers pass their
read-only inputs through :func:`read_only` and build per-sample columns
with :func:`filled`, so each kernel is compiled (and cached) once.
"""
from __future__ import annotations

import numpy as np

__all__ = ["read_only", "filled"]


def read_only(a: np.ndarray) -> np.ndarray:
    """``a`` if it is read-only, else a read-only view of it (same memory:
    later writes through ``a`` show)."""
    if not a.flags.writeable:
        return a
    v = a.view()
    v.flags.writeable = False
    return v


def filled(x, shape, dtype) -> np.ndarray:
    """A new writeable C-ordered ``dtype`` array of ``x`` broadcast to
    ``shape`` (a scalar, a row or the whole array alike)."""
    return np.array(np.broadcast_to(np.asarray(x, dtype=dtype), shape), dtype=dtype,
                    order="C")
