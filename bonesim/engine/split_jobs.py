"""Large fragment splits in bounded slices, one slice per world step.

The fragment finder's split (:class:`~bonesim.engine.world_commands.SplitPart`)
flood-fills one part of a body and moves it into a new body. Done at once, a
512,000-voxel part costs tens of milliseconds: dozens of haptic periods lost
in one. A part larger than the budget (``[split] voxels_per_step`` of
``bonesim/data/slicing.toml``, :func:`bonesim.engine.slicing.voxels_per_step`)
therefore becomes a **split job** queued in the :class:`~bonesim.engine.model.State`
(``state.split_jobs``), and every :func:`~bonesim.engine.world.world_step`
advances the queue by one **slice** (:func:`advance_splits`), after the
step's commands and before the rigid and haptic steps.

Determinism
-----------
A slice's size is a fixed number of voxels (never a time), so the slices
depend only on the state and on the commands and samples the run was given:
the same run gives the same slices at the same steps, in the haptic loop, in
``simulate`` and on every machine. Every slice is published as one block of
``SPLIT`` tissue events at its step's time (``body`` the new body, ``ijk``
the voxels moved in this slice in the order they were moved, ``n`` their
count, ``value[0]`` the source body), which is what a recording holds: replay
(:mod:`bonesim.session.replay`) re-applies each block as it was recorded
(:class:`~bonesim.engine.world_commands.SplitVoxels`, in the recorded order,
growing the body the first block created), so a recorded run with a large
split replays bit for bit, and replicas apply the blocks as they come.

A slice
-------
The job is a breadth-first flood fill (26-connected, inside the command's box,
through voxels of the source body holding material) whose queue is the list of
voxels moved so far. The first slice takes the lowest free body id, places it
at the source's pose and moves the seed; every slice then expands at most
``voxels_per_step`` queued voxels, moving each neighbour that still belongs to
the source and holds material into the new body at once (the moved voxels are
the fill's "seen" marks), until it has moved ``voxels_per_step`` voxels (at
most 26 more) or the queue is exhausted (the job is done). A queued voxel
that the burr removed in between is not expanded (no connection through
removed bone). Without drilling in between, the voxels moved are exactly those
of the one-shot fill (:func:`~bonesim.engine.fragments.component_voxels`;
the tests check it against it). A job stops at the command's ``n`` voxels
(the part cannot have grown since it was found: removal only shrinks parts).

Jobs run one after the other (first in, first out), sharing the budget of a
step; while any is queued, every further ``SplitPart`` (and ``ShedPart``) is
queued behind it, so that a part is never split twice while its first split
is half done. A :class:`~bonesim.engine.world_commands.Reset` drops the queue
(:func:`~bonesim.engine.model.reset_state`). A body being filled cannot be
woken as a rigid (:func:`filling`): its mass would be the part's so far.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from bonesim.engine.events import SPLIT
from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset
from bonesim.engine.haptics import push_event_kernel
from bonesim.engine.slicing import voxels_per_step

__all__ = ["SplitJob", "queue_split", "advance_splits",
           "filling", "run_split"]

class SplitJob:
    """One queued split (module docstring).

    Attributes
    ----------
    src : int
        The body split.
    seed, lo, hi : (3,) int64
        The part's voxel, and the box the fill stays in (body frame,
        inclusive, clipped to the grid).
    n_max : int
        The most voxels the part may hold.
    shed : bool
        A speck removed as dust (done at once when its turn comes).
    dst : int
        The new body (-1 until the first slice).
    queue : (n_max, 3) int32
        The voxels moved, in the order they were moved.
    cursor : (3,) int64
        Next voxel to expand, voxels moved, voxels published.
    """

    __slots__ = ("src", "seed", "lo", "hi", "n_max", "shed", "dst", "queue", "cursor")

    def __init__(self, src, seed, lo, hi, n_max, shed=False):
        self.src, self.n_max, self.shed = int(src), int(n_max), bool(shed)
        self.seed = np.asarray(seed, np.int64)
        self.lo, self.hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
        self.dst = -1
        self.queue = None
        self.cursor = np.zeros(3, np.int64)

    @property
    def moved(self) -> int:
        """Voxels moved so far."""
        return int(self.cursor[1])


def queue_split(state, src: int, seed, lo, hi, n_max: int, shed: bool = False) -> SplitJob:
    """Queue a split job on ``state`` (nothing of the tissue changes now: the
    next :func:`advance_splits` starts it). Arguments as
    :func:`~bonesim.engine.fragments.publish_part`'s.

    Raises
    ------
    ValueError
        ``n_max`` is not positive, ``seed`` is not three voxel indices, or
        no body id is free now (one taken before the job starts leaves the
        part where it is, as a split at once would refuse it).
    """
    n_max = int(n_max)
    if n_max < 1:
        raise ValueError(f"part: n_max must be positive, got {n_max}")
    seed = np.asarray(seed, np.int64)
    if seed.shape != (3,):
        raise ValueError(f"part: seed must be three voxel indices, got {seed.tolist()}")
    if not shed and not (state.alive == 0).any():
        raise ValueError(f"split: all {len(state.alive)} bodies are in use (max_bodies)")
    top = np.asarray(state.grid.shape, np.int64) - 1
    job = SplitJob(src, seed, np.clip(np.asarray(lo, np.int64), 0, top),
                   np.clip(np.asarray(hi, np.int64), 0, top), n_max, shed)
    state.split_jobs.append(job)
    return job


def filling(state, b: int) -> bool:
    """Whether a queued split job is still moving voxels into body ``b``."""
    return any(j.dst == b for j in state.split_jobs)


@njit(cache=True, nogil=True)
def _slice(keys, vals, density, body, src, dst, lo, hi, queue, cursor, budget, bounds, t,
           ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head):
    # expand queued voxels (breadth first) until the budget is spent; the
    # moved voxels are marked by their new body id; then publish this slice
    n_max = queue.shape[0]
    q, n, pub = cursor[0], cursor[1], cursor[2]
    pops = 0
    full = False
    while q < n and pops < budget and n - pub < budget and not full:
        ci, cj, ck = queue[q, 0], queue[q, 1], queue[q, 2]
        q += 1
        pops += 1
        br = find_brick(keys, vals, ci >> BRICK_SHIFT, cj >> BRICK_SHIFT, ck >> BRICK_SHIFT)
        if br < 0 or density[br, voxel_offset(ci, cj, ck)] <= 0.0:
            continue                        # drilled away since it moved: no bridge
        for di in range(-1, 2):
            x = ci + di
            if x < lo[0] or x > hi[0]:
                continue
            for dj in range(-1, 2):
                y = cj + dj
                if y < lo[1] or y > hi[1]:
                    continue
                for dk in range(-1, 2):
                    z = ck + dk
                    if z < lo[2] or z > hi[2]:
                        continue
                    b = find_brick(keys, vals, x >> BRICK_SHIFT, y >> BRICK_SHIFT,
                                   z >> BRICK_SHIFT)
                    if b < 0:
                        continue
                    off = voxel_offset(x, y, z)
                    if body[b, off] != src or density[b, off] <= 0.0:
                        continue
                    if n == n_max:
                        full = True
                        continue
                    body[b, off] = dst
                    queue[n, 0], queue[n, 1], queue[n, 2] = x, y, z
                    n += 1
                    bounds[dst, 0] = min(bounds[dst, 0], x)
                    bounds[dst, 1] = min(bounds[dst, 1], y)
                    bounds[dst, 2] = min(bounds[dst, 2], z)
                    bounds[dst, 3] = max(bounds[dst, 3], x)
                    bounds[dst, 4] = max(bounds[dst, 4], y)
                    bounds[dst, 5] = max(bounds[dst, 5], z)
    m = n - pub
    for r in range(pub, n):
        push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                          SPLIT, dst, 0, t, queue[r, 0], queue[r, 1], queue[r, 2], m,
                          float(src), 0.0, 0.0)
    cursor[0], cursor[1], cursor[2] = q, n, n
    if full:
        cursor[0] = n                       # the part outgrew n_max: the job ends
    return m, pops


def _start(state, job) -> bool:
    """The first slice's set-up: the new body and its seed. False: nothing to
    split (the source or the seed's material is gone, or no body id is free)."""
    alive = state.alive
    src = job.src
    if not 0 <= src < len(alive) or not alive[src]:
        return False
    s = job.seed
    if (s < job.lo).any() or (s > job.hi).any():
        return False
    g = state.grid
    br = find_brick(g.keys, g.vals, s[0] >> BRICK_SHIFT, s[1] >> BRICK_SHIFT,
                    s[2] >> BRICK_SHIFT)
    if br < 0:
        return False
    off = voxel_offset(s[0], s[1], s[2])
    if state.body[br, off] != src or not g.density[br, off] > 0.0:
        return False
    free = np.flatnonzero(alive == 0)
    if len(free) == 0:
        return False                        # as the one-shot split: no id, no split
    dst = int(free[0])
    job.dst = dst
    job.queue = np.empty((job.n_max, 3), np.int32)
    job.queue[0] = s
    job.cursor[:] = (0, 1, 0)
    state.body[br, off] = dst
    state.bounds[dst, :3] = s
    state.bounds[dst, 3:] = s
    state.pose[dst] = state.pose[src]
    state.pose_m[dst] = state.pose_m[src]
    alive[dst] = 1
    state._one_body = False
    return True


def advance_splits(state, t_s: float, budget: int | None = None) -> int:
    """One slice of the queued split jobs, published at ``t_s`` [s].

    Parameters
    ----------
    state : State
        ``split_jobs`` is advanced (finished jobs leave it); body arrays
        and the tissue ring change in place.
    t_s : float
        The step's time [s] (the ``SPLIT`` records' time).
    budget : int, optional
        Voxels expanded (and moved) this step; default
        :func:`~bonesim.engine.slicing.voxels_per_step`.

    Returns
    -------
    int
        Voxels moved (or shed) this step.
    """
    from bonesim.engine.fragments import publish_part

    budget = voxels_per_step() if budget is None else int(budget)
    jobs = state.split_jobs
    g = state.grid
    ev = state.tissue.fields
    done = 0
    while jobs and budget > 0:
        job = jobs[0]
        if job.shed:                        # a speck: at once (fewer than the speck size)
            jobs.pop(0)
            budget -= job.n_max
            try:
                done += publish_part(state, job.src, job.seed, job.lo, job.hi, job.n_max,
                                     t_s, shed=True)[1]
            except ValueError:              # larger than found: left as it is, as the
                pass                        # command at once refuses it
            continue
        if job.dst < 0 and not _start(state, job):
            jobs.pop(0)
            continue
        m, pops = _slice(g.keys, g.vals, g.density, state.body, np.uint8(job.src),
                         np.uint8(job.dst), job.lo, job.hi, job.queue, job.cursor,
                         budget, state.bounds, float(t_s), ev["kind"], ev["body"],
                         ev["label"], ev["t_s"], ev["ijk"], ev["n"], ev["value"],
                         state.tissue.head)
        done += int(m)
        budget -= max(int(pops), int(m), 1)
        if job.cursor[0] >= job.cursor[1]:
            jobs.pop(0)                     # the fill is complete
    return done


def run_split(state, src: int, seed, lo, hi, n_max: int, t_s: float,
              budget: int | None = None) -> tuple[int, int, int]:
    """Queue a split and run it to its end, slice after slice (all at
    ``t_s``; tests and tools).

    Returns
    -------
    dst, n, slices : int
        The new body (-1 when nothing moved), the voxels moved and the
        slices it took.
    """
    if state.split_jobs:
        raise ValueError("run_split: split jobs are already queued")
    job = queue_split(state, src, seed, lo, hi, n_max)
    slices = 0
    while state.split_jobs:
        advance_splits(state, t_s, budget)
        slices += 1
    return job.dst, job.moved, slices
