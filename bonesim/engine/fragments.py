"""Fragments: bone that removal has cut off, found by labelling the bodies.

After a burst of removals, the bodies the removed voxels belonged to may have
fallen apart. This module finds the parts (connected components, 26-connected,
of a body's voxels that still hold material: ``body == b`` and ``density > 0``)
and says which of them leave the body; the haptic loop's split commands
(:class:`bonesim.runtime.commands.SplitPart`, :class:`~bonesim.runtime.commands.ShedPart`)
then move or remove exactly one part each, and publish what they did as tissue
events, so that every replica and a replay apply the same voxels.

Which parts leave
-----------------
Only the parts that touch the burst count (**candidates**: a part holding a
voxel 26-adjacent to one of the burst's removed voxels of that body); parts
of a body that were apart before (an ossicle in the air of the middle ear)
stay as they are. Of the candidates, one keeps the body (the **keeper**, the
case's anchor): the largest candidate that touches the case boundary (the
outer voxel layer of the grid: bone beyond it is the rest of the skull),
else the largest candidate; ties go to the part whose first voxel (in
``(i, j, k)`` order) comes first. Every other candidate leaves: a part of
fewer than ``speck_voxels`` voxels (the case's ``[fragments] speck_voxels``,
default :data:`DEFAULT_SPECK_VOXELS`) is removed as dust (``shed``: removal
events marked :data:`~bonesim.engine.events.REMOVED_SHED`), a larger one
becomes a new body.

Local and global passes
-----------------------
:func:`find_parts_global` labels a body's whole voxel box. :func:`find_parts`
(the **local pass**) labels only a box around the burst's removals, grown by a
margin: a part that does not touch the box's open faces (faces not on the
body's box or the grid's edge) lies wholly inside it; a part that does is
open and may continue beyond. The local pass decides alone when every
candidate is closed, or when one candidate is open, no closed candidate
touches the case boundary, and the open one either touches the case
boundary or holds more voxels inside the box than any closed candidate has
in all (then it is the keeper, whatever lies beyond). Otherwise it doubles
its margin and labels again, until it decides or its box is the body's box
(the global pass). Both passes give the same parts (the tests check it).

Labelling is connected-components-3d (``cc3d``), checked in the tests
against :func:`scipy.ndimage.label`.

:func:`publish_part` carries a part out at once; a large part is carried out
in slices, one per world step, by :mod:`bonesim.engine.split_jobs`.
"""
from __future__ import annotations


import numpy as np
from numba import njit

from bonesim.engine.bodies import split_body
from bonesim.engine.events import REMOVED, REMOVED_SHED, SPLIT
from bonesim.engine.grid import BRICK, BRICK_SHIFT, find_brick, voxel_offset

__all__ = ["DEFAULT_SPECK_VOXELS", "DEFAULT_MARGIN_VOXELS", "CONNECTIVITY", "Part",
           "label_parts", "body_mask", "find_parts", "find_parts_global",
           "component_voxels", "publish_part", "shed_voxels"]

#: Parts smaller than this are removed as dust instead of becoming bodies [voxels].
DEFAULT_SPECK_VOXELS = 8
#: The local pass's box: the removals' box grown by this many voxels (first try).
DEFAULT_MARGIN_VOXELS = 3
#: Voxels that share a face, an edge or a corner are connected.
CONNECTIVITY = 26


class Part:
    """A part that leaves its body (see the module docstring).

    Attributes
    ----------
    body : int
        The body it leaves.
    seed : (3,) int64
        Its first voxel in ``(i, j, k)`` order (body frame).
    lo, hi : (3,) int64
        Its voxel box, inclusive (body frame).
    n : int
        Its voxels.
    shed : bool
        Fewer than the speck size: removed as dust, not a new body.
    """

    __slots__ = ("body", "seed", "lo", "hi", "n", "shed")

    def __init__(self, body, seed, lo, hi, n, shed):
        self.body, self.n, self.shed = int(body), int(n), bool(shed)
        self.seed = np.asarray(seed, np.int64)
        self.lo, self.hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)

    def key(self) -> tuple:
        """A hashable identity: ``(body, seed, lo, hi, n, shed)``."""
        return (self.body, tuple(self.seed.tolist()), tuple(self.lo.tolist()),
                tuple(self.hi.tolist()), self.n, self.shed)

    def __eq__(self, other):
        return isinstance(other, Part) and self.key() == other.key()

    def __hash__(self):
        return hash(self.key())

    def __repr__(self):
        return (f"Part(body={self.body}, seed={self.seed.tolist()}, lo={self.lo.tolist()}, "
                f"hi={self.hi.tolist()}, n={self.n}, shed={self.shed})")


def label_parts(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """26-connected components of a boolean volume.

    Parameters
    ----------
    mask : (nx, ny, nz) bool

    Returns
    -------
    labels : (nx, ny, nz) unsigned int
        0 outside ``mask``, 1 .. n per component.
    n : int
    """
    import cc3d

    lab, n = cc3d.connected_components(np.ascontiguousarray(mask), connectivity=CONNECTIVITY,
                                       return_N=True)
    return lab, int(n)


@njit(cache=True, nogil=True)
def _gather_mask(keys, vals, density, body, b, lo, hi, out):
    # brick by brick over the box: one hash lookup per brick
    for bi in range(lo[0] >> BRICK_SHIFT, (hi[0] >> BRICK_SHIFT) + 1):
        for bj in range(lo[1] >> BRICK_SHIFT, (hi[1] >> BRICK_SHIFT) + 1):
            for bk in range(lo[2] >> BRICK_SHIFT, (hi[2] >> BRICK_SHIFT) + 1):
                br = find_brick(keys, vals, bi, bj, bk)
                if br < 0:
                    continue
                i0, i1 = max(bi * BRICK, lo[0]), min(bi * BRICK + BRICK - 1, hi[0])
                j0, j1 = max(bj * BRICK, lo[1]), min(bj * BRICK + BRICK - 1, hi[1])
                k0, k1 = max(bk * BRICK, lo[2]), min(bk * BRICK + BRICK - 1, hi[2])
                for i in range(i0, i1 + 1):
                    for j in range(j0, j1 + 1):
                        for k in range(k0, k1 + 1):
                            off = voxel_offset(i, j, k)
                            out[i - lo[0], j - lo[1], k - lo[2]] = (
                                body[br, off] == b and density[br, off] > 0.0)


def body_mask(state, b: int, lo, hi) -> np.ndarray:
    """The voxels of body ``b`` that hold material, in a box.

    Parameters
    ----------
    state : State
        ``grid`` (density, brick table) and ``body`` are read.
    b : int
        Body id.
    lo, hi : (3,) int
        The box, voxel indices in the body's frame, inclusive, inside the grid.

    Returns
    -------
    (hi - lo + 1) bool, axes i, j, k.
    """
    lo = np.asarray(lo, np.int64)
    hi = np.asarray(hi, np.int64)
    g = state.grid
    if (lo < 0).any() or (hi >= np.asarray(g.shape)).any() or (hi < lo).any():
        raise ValueError(f"body mask: box {lo.tolist()}..{hi.tolist()} is not inside the "
                         f"grid {tuple(g.shape)}")
    out = np.zeros(tuple((hi - lo + 1).tolist()), np.bool_)
    _gather_mask(g.keys, g.vals, g.density, state.body, np.uint8(b), lo, hi, out)
    return out


def _limits(state, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Body ``b``'s box clipped to the grid."""
    bd = state.bounds[b].astype(np.int64)
    top = np.asarray(state.grid.shape, np.int64) - 1
    return np.clip(bd[:3], 0, top), np.clip(bd[3:], 0, top)


@njit(cache=True, nogil=True)
def _stats(lab, counts, boxes, seeds):
    # per label: voxels, box (i0, j0, k0, i1, j1, k1) and first voxel in
    # (i, j, k) order (the scan's order)
    nx, ny, nz = lab.shape
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                c = lab[i, j, k]
                if c == 0:
                    continue
                if counts[c] == 0:
                    seeds[c, 0], seeds[c, 1], seeds[c, 2] = i, j, k
                    boxes[c, 0], boxes[c, 1], boxes[c, 2] = i, j, k
                    boxes[c, 3], boxes[c, 4], boxes[c, 5] = i, j, k
                counts[c] += 1
                boxes[c, 1] = min(boxes[c, 1], j)
                boxes[c, 2] = min(boxes[c, 2], k)
                boxes[c, 3] = i
                boxes[c, 4] = max(boxes[c, 4], j)
                boxes[c, 5] = max(boxes[c, 5], k)


@njit(cache=True, nogil=True)
def _near(lab, dirty, near):
    # labels 26-adjacent to (or at) the removed voxels
    nx, ny, nz = lab.shape
    for q in range(dirty.shape[0]):
        for di in range(-1, 2):
            x = dirty[q, 0] + di
            if x < 0 or x >= nx:
                continue
            for dj in range(-1, 2):
                y = dirty[q, 1] + dj
                if y < 0 or y >= ny:
                    continue
                for dk in range(-1, 2):
                    z = dirty[q, 2] + dk
                    if 0 <= z < nz:
                        near[lab[x, y, z]] = True


def _faces(lab, sel) -> list:
    """Labels on each of the six faces of ``lab`` (only faces where ``sel``)."""
    out = []
    for a in range(3):
        for side in (0, -1):
            if sel[2 * a + (side != 0)]:
                sl = [slice(None)] * 3
                sl[a] = side
                out.append(np.unique(lab[tuple(sl)]))
    return out


def _decide(state, b, lo, hi, dirty, speck_voxels):
    """Label body ``b`` in the box ``lo .. hi``; the parts that leave, or
    None when the box cannot decide (see the module docstring)."""
    mask = body_mask(state, b, lo, hi)
    lab, n = label_parts(mask)
    if n <= 1:
        return []
    # candidates: labels 26-adjacent to a removed voxel (dirty: box-local ijk)
    near = np.zeros(n + 1, np.bool_)
    _near(lab, np.ascontiguousarray(dirty, np.int64), near)
    near[0] = False
    cand = np.flatnonzero(near)
    if len(cand) <= 1:
        return []
    lim_lo, lim_hi = _limits(state, b)
    top = np.asarray(state.grid.shape, np.int64) - 1
    open_sel = [lo[0] > lim_lo[0], hi[0] < lim_hi[0], lo[1] > lim_lo[1], hi[1] < lim_hi[1],
                lo[2] > lim_lo[2], hi[2] < lim_hi[2]]
    case_sel = [lo[0] == 0, hi[0] == top[0], lo[1] == 0, hi[1] == top[1],
                lo[2] == 0, hi[2] == top[2]]
    is_open = np.zeros(n + 1, np.bool_)
    for f in _faces(lab, open_sel):
        is_open[f] = True
    on_case = np.zeros(n + 1, np.bool_)
    for f in _faces(lab, case_sel):
        on_case[f] = True
    counts = np.zeros(n + 1, np.int64)
    boxes = np.zeros((n + 1, 6), np.int64)
    seeds = np.zeros((n + 1, 3), np.int64)
    _stats(lab, counts, boxes, seeds)
    opened = cand[is_open[cand]]
    closed = cand[~is_open[cand]]
    if len(opened) > 1:
        return None
    if len(opened) == 1:
        o = int(opened[0])
        if len(closed) and on_case[closed].any():
            return None
        if not (on_case[o] or counts[o] > counts[closed].max(initial=0)):
            return None
        keeper = o
    else:
        keeper = None
    parts = {}
    for c in closed:
        c = int(c)
        parts[c] = Part(b, seeds[c] + lo, boxes[c, :3] + lo, boxes[c, 3:] + lo, counts[c],
                        counts[c] < speck_voxels)
    if keeper is None:
        # the largest candidate on the case boundary, else the largest; ties:
        # the first seed in (i, j, k) order
        def rank(c):
            return (not on_case[c], -counts[c], tuple(parts[c].seed.tolist()))
        keeper = min(parts, key=rank)
    return sorted((p for c, p in parts.items() if c != keeper),
                  key=lambda p: tuple(p.seed.tolist()))


def _check(state, ijk, speck_voxels) -> np.ndarray:
    if int(speck_voxels) != speck_voxels or speck_voxels < 1:
        raise ValueError(f"fragments: speck_voxels must be a positive integer, got "
                         f"{speck_voxels!r}")
    ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
    shape = np.asarray(state.grid.shape)
    if len(ijk) and ((ijk < 0).any() or (ijk >= shape).any()):
        raise ValueError(f"fragments: removed voxels outside the grid {tuple(shape)}")
    return ijk


def find_parts_global(state, body: int, removed_ijk, speck_voxels: int = DEFAULT_SPECK_VOXELS
                      ) -> list:
    """The parts of body ``body`` that a burst cut off, labelling its whole box.

    Parameters
    ----------
    state : State
        The tissue after the burst (``grid``, ``body``, ``bounds``, ``alive``).
    body : int
    removed_ijk : (n, 3) int
        The burst's removed voxels of this body (body frame).
    speck_voxels : int
        Parts smaller than this are shed as dust.

    Returns
    -------
    list of Part
        In seed order; empty when nothing was cut off.
    """
    ijk = _check(state, removed_ijk, speck_voxels)
    if len(ijk) == 0 or not state.alive[body]:
        return []
    lo, hi = _limits(state, body)
    return _decide(state, body, lo, hi, ijk - lo, int(speck_voxels))


def find_parts(state, removed_ijk, removed_body, speck_voxels: int = DEFAULT_SPECK_VOXELS,
               margin: int = DEFAULT_MARGIN_VOXELS, stats: dict | None = None) -> list:
    """The parts a burst of removals cut off, by the local pass (module docstring).

    Parameters
    ----------
    state : State
        The tissue after the burst.
    removed_ijk : (n, 3) int
        The burst's removed voxels, each in its body's frame.
    removed_body : (n,) int
        The body each removed voxel belonged to.
    speck_voxels : int
        Parts smaller than this are shed as dust.
    margin : int
        The first box: the removals' box grown by this many voxels (>= 1).
    stats : dict, optional
        Counts ``boxes`` labelled and ``global`` passes (bodies whose box grew
        to their whole box) into it.

    Returns
    -------
    list of Part
        By body, then seed order.
    """
    ijk = _check(state, removed_ijk, speck_voxels)
    bod = np.asarray(removed_body, np.int64).reshape(-1)
    if len(bod) != len(ijk):
        raise ValueError(f"fragments: {len(bod)} bodies for {len(ijk)} removed voxels")
    if int(margin) != margin or margin < 1:
        raise ValueError(f"fragments: margin must be a positive integer, got {margin!r}")
    out = []
    for b in np.unique(bod):
        b = int(b)
        if not 0 <= b < len(state.alive) or not state.alive[b]:
            continue
        mine = ijk[bod == b]
        lim_lo, lim_hi = _limits(state, b)
        m = int(margin)
        while True:
            lo = np.maximum(mine.min(axis=0) - m, lim_lo)
            hi = np.minimum(mine.max(axis=0) + m, lim_hi)
            if (hi < lo).any():
                break
            got = _decide(state, b, lo, hi, mine - lo, int(speck_voxels))
            if stats is not None:
                stats["boxes"] = stats.get("boxes", 0) + 1
            if got is not None:
                if stats is not None and (lo == lim_lo).all() and (hi == lim_hi).all():
                    stats["global"] = stats.get("global", 0) + 1
                out += got
                break
            m *= 2
    return out


@njit(cache=True, nogil=True)
def _flood(keys, vals, density, body, src, seed, lo, hi, seen, out):
    n_max = out.shape[0]
    i, j, k = seed[0], seed[1], seed[2]
    br = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
    if br < 0:
        return 0
    off = voxel_offset(i, j, k)
    if body[br, off] != src or density[br, off] <= 0.0:
        return 0
    seen[i - lo[0], j - lo[1], k - lo[2]] = 2          # 2: a member, 1: looked at
    out[0, 0], out[0, 1], out[0, 2] = i, j, k
    n = 1
    q = 0
    while q < n:
        ci, cj, ck = out[q, 0], out[q, 1], out[q, 2]
        q += 1
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
                    if seen[x - lo[0], y - lo[1], z - lo[2]]:
                        continue
                    seen[x - lo[0], y - lo[1], z - lo[2]] = 1
                    br = find_brick(keys, vals, x >> BRICK_SHIFT, y >> BRICK_SHIFT,
                                    z >> BRICK_SHIFT)
                    if br < 0:
                        continue
                    off = voxel_offset(x, y, z)
                    if body[br, off] != src or density[br, off] <= 0.0:
                        continue
                    if n == n_max:
                        return -1
                    seen[x - lo[0], y - lo[1], z - lo[2]] = 2
                    out[n, 0], out[n, 1], out[n, 2] = x, y, z
                    n += 1
    # the members again, in (i, j, k) order
    m = 0
    for x in range(seen.shape[0]):
        for y in range(seen.shape[1]):
            for z in range(seen.shape[2]):
                if seen[x, y, z] == 2:
                    out[m, 0], out[m, 1], out[m, 2] = x + lo[0], y + lo[1], z + lo[2]
                    m += 1
    return n


def component_voxels(state, src: int, seed, lo, hi, n_max: int) -> np.ndarray:
    """The part of body ``src`` holding voxel ``seed``, flood-filled
    (26-connected, voxels of ``src`` with material) inside the box ``lo .. hi``.

    Parameters
    ----------
    state : State
    src : int
    seed : (3,) int
        A voxel of the part (body frame).
    lo, hi : (3,) int
        The box the fill stays in (inclusive; clipped to the grid).
    n_max : int
        The most voxels the part may hold.

    Returns
    -------
    (n, 3) int32
        Its voxels in ``(i, j, k)`` order; empty when ``seed`` holds no
        material of ``src``.

    Raises
    ------
    ValueError
        The part holds more than ``n_max`` voxels (it is not the part that
        was found: the tissue changed in a way removal cannot).
    """
    g = state.grid
    top = np.asarray(g.shape, np.int64) - 1
    lo = np.clip(np.asarray(lo, np.int64), 0, top)
    hi = np.clip(np.asarray(hi, np.int64), 0, top)
    seed = np.asarray(seed, np.int64)
    if seed.shape != (3,) or (seed < lo).any() or (seed > hi).any():
        return np.zeros((0, 3), np.int32)
    n_max = int(n_max)
    if n_max < 1:
        raise ValueError(f"part: n_max must be positive, got {n_max}")
    seen = np.zeros(tuple((hi - lo + 1).tolist()), np.uint8)
    out = np.empty((n_max, 3), np.int32)
    n = _flood(g.keys, g.vals, g.density, state.body, np.uint8(src), seed, lo, hi, seen, out)
    if n < 0:
        raise ValueError(f"part of body {src} at {seed.tolist()} holds more than {n_max} "
                         "voxels: the tissue is not the one it was found in")
    return out[:n]


def shed_voxels(state, src: int, ijk, t_s: float) -> int:
    """Remove voxels of body ``src`` as dust, published as ``REMOVED`` events
    whose ``n`` is :data:`~bonesim.engine.events.REMOVED_SHED` (not drilled).

    Voxels are taken in ``(i, j, k)`` order, each once; those that are not
    ``src``'s or hold no material are skipped. Every record carries the
    voxel's label, so dust, replicas and per-label totals see a removal.

    Returns
    -------
    int
        Voxels removed.
    """
    ijk = np.unique(np.asarray(ijk, np.int64).reshape(-1, 3), axis=0)
    g = state.grid
    if len(ijk) == 0:
        return 0
    bi = ijk >> BRICK_SHIFT
    br = np.array([find_brick(g.keys, g.vals, *v) for v in bi.tolist()], np.int64)
    off = ((ijk[:, 0] & 7) << 6) | ((ijk[:, 1] & 7) << 3) | (ijk[:, 2] & 7)
    ok = br >= 0
    ok[ok] = (state.body[br[ok], off[ok]] == src) & (g.density[br[ok], off[ok]] > 0.0)
    br, off, ijk = br[ok], off[ok], ijk[ok]
    n = len(ijk)
    if n == 0:
        return 0
    lab = g.label[br, off]
    g.density[br, off] = 0.0
    np.add.at(state.removed_by_label, lab.astype(np.int64), 1)
    state.tissue.append(kind=np.full(n, REMOVED, np.uint8), body=np.full(n, src, np.uint8),
                        label=lab, t_s=np.full(n, float(t_s)), ijk=ijk.astype(np.int32),
                        n=np.full(n, REMOVED_SHED, np.int32), value=np.zeros((n, 7)))
    return n


def publish_part(state, src: int, seed, lo, hi, n_max: int, t_s: float,
                 shed: bool = False) -> tuple[int, int]:
    """Carry out one :class:`Part` on a live state: the part of ``src``
    holding ``seed`` (:func:`component_voxels`) becomes a new body
    (:func:`~bonesim.engine.bodies.publish_split`, ``SPLIT`` events) or, with
    ``shed``, is removed as dust (:func:`shed_voxels`).

    Returns
    -------
    dst, n : int
        The new body (-1 when shed or nothing moved) and the voxels moved or removed.
    """
    if not 0 <= src < len(state.alive) or not state.alive[src]:
        return -1, 0                      # the body is gone (a reset in between)
    ijk = component_voxels(state, src, seed, lo, hi, n_max)
    if len(ijk) == 0:
        return -1, 0
    if shed:
        return -1, shed_voxels(state, src, ijk, t_s)
    # the records publish_split gives for these voxels (sorted, each once, all
    # of src with material), without its checks of that
    dst, n = split_body(state, src, ijk)
    if n != len(ijk):
        raise RuntimeError(f"part of body {src}: {n} of {len(ijk)} voxels moved")
    state.tissue.append(kind=np.full(n, SPLIT, np.uint8), body=np.full(n, dst, np.uint8),
                        label=np.zeros(n, np.uint8), t_s=np.full(n, float(t_s)), ijk=ijk,
                        n=np.full(n, n, np.int32),
                        value=np.pad(np.full((n, 1), float(src)), ((0, 0), (0, 6))))
    return dst, n
