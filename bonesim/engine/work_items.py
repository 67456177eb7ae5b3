"""Work items handed out one at a time to the threads of a parallel kernel.

numba's ``prange`` splits its iterations among the threads up front (with
the OpenMP threading layer, in equal contiguous blocks, whatever
``numba.parallel_chunksize`` says: the loop is statically scheduled), so a
thread that the OS holds back on a loaded machine holds the whole loop
back. A kernel that should not wait for it runs one ``prange`` iteration per
*worker* (:func:`workers`, one per thread) and lets each worker take the
next work item from a shared counter until none is left::

    for w in prange(n_workers):
        ...                                  # the worker's scratch
        while True:
            item = take_item(counter)        # counter: (1,) int64, 0 at start
            if item >= n_items:
                break
            ...                              # the item writes its own outputs

A held-back worker then delays the loop by at most the item it holds.
Each item must write only its own outputs, so that the result does not
depend on which worker ran it (nor on the number of workers).

:func:`take_item` is an atomic fetch-and-add on the counter (an LLVM
``atomicrmw``), the one primitive numba does not offer on the CPU.
"""
from __future__ import annotations

import numba
import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["take_item", "workers", "new_counter"]


@intrinsic
def take_item(typingctx, counter):
    """``counter[0]`` before adding 1 to it, atomically (``counter``: (1,)
    or longer int64 array, C-contiguous). Usable only in numba code."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64
            and counter.ndim == 1):
        return None
    sig = types.int64(counter)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary,
                                       [context.get_constant(types.intp, 0)])
        return builder.atomic_rmw("add", ptr, context.get_constant(types.int64, 1),
                                  "monotonic")

    return sig, codegen


def workers() -> int:
    """Number of workers a kernel should run: numba's current thread count."""
    return int(numba.get_num_threads())


def new_counter() -> np.ndarray:
    """A fresh (1,) int64 counter at 0 for one kernel call."""
    return np.zeros(1, dtype=np.int64)
