"""Clearance: distances [mm] to structures, measured on the source-resolution label map.

Margins that must hold whatever grid the engine drills on (the demo plan's
margin, the nerve monitor's distances) are measured here, on the case's label
map at the resolution the data came in (:class:`bonesim.io.volumes.NativeLabels`:
possibly anisotropic voxels, already in the LPS case frame), never on the
engine's resampled grid.

Geometry
--------
Source voxel ``(i, j, k)`` is the closed box of its spacing ``(sx, sy, sz)``
[mm] centred on ``origin + (i sx, j sy, k sz)``. The distance from a point to
a set of structures is the Euclidean distance to the union of their voxels'
boxes [mm]: zero inside (and on) a box, exact and sub-voxel everywhere else,
rounded to neither grid.

What is kept
------------
Nothing of the volume, only what answers that distance exactly (a few MB for
a real temporal bone, so a :class:`~bonesim.engine.model.Model` carrying one pickles
cheaply into the haptic, monitor and recorder processes):

* the **surface voxels** of each structure: its voxels with at least one of
  their 6 face neighbours outside the structure (or beyond the volume). From a
  point outside a structure the nearest point of its boxes lies on an exposed
  face, and every exposed face belongs to a surface voxel, so these give the
  exact distance;
* per structure, a **bounding-volume hierarchy** over its surface voxels: a
  balanced binary tree in heap order (node ``n`` has children ``2n + 1`` and
  ``2n + 2``; at most :data:`LEAF_SIZE` voxels per leaf), each node with the
  index bounds of its voxels. A branch-and-bound search, with the node's
  bounds widened by half a voxel as the lower bound, returns the exact
  nearest box; structures are searched nearest first and share the bound.
  Points come in batches along paths (the planner's segments and floors, a
  run's samples), so each search starts from a bound: the previous point's
  distance plus the step between them (distance is 1-Lipschitz), widened by
  :data:`_BOUND_RTOL` and :data:`_BOUND_ATOL` past rounding. The nearest box
  lies within it, so the search returns the same box and the same bits as a
  search from infinity, only pruning sooner (a search that finds nothing
  under the bound, which the bound rules out, is run again from infinity);
* the structures' voxels as **runs along z**, column ``(i, j)`` by column:
  whether a point lies inside one (distance 0).

Queries (:meth:`Clearance.distance`, :meth:`Clearance.distances`) run in one
numba kernel over any number of points and any number of structure groups
(the nerve monitor asks for each nerve at once, the planner for the union of
everything that is not bone).
"""
from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np
from numba import njit

from bonesim.engine.kernel_args import read_only

__all__ = ["Clearance", "LEAF_SIZE", "MAX_LABEL"]

#: Most surface voxels in one leaf of a structure's hierarchy.
LEAF_SIZE = 16
#: Largest structure index (labels are uint8).
MAX_LABEL = 255
#: Largest voxel count along an axis (indices are stored as int16).
_MAX_AXIS = np.iinfo(np.int16).max
#: Depth of the search stack (two entries per tree level; 2**60 leaves).
_STACK = 128
#: Relative and absolute widening of a search's starting bound [mm]: far
#: above the rounding of a distance of a few hundred mm in float64.
_BOUND_RTOL = 1e-9
_BOUND_ATOL = 1e-9
# Columns of a node row: voxel index bounds lo (3), hi (3), first and end
# (exclusive) surface voxel of its range.
_N_LO, _N_HI, _N_START, _N_END = 0, 3, 6, 7


# ------------------------------------------------------------------ building
@njit(cache=True, nogil=True)
def _is_surface(labels, i, j, k, s):
    n0, n1, n2 = labels.shape
    return (i == 0 or labels[i - 1, j, k] != s or i == n0 - 1 or labels[i + 1, j, k] != s
            or j == 0 or labels[i, j - 1, k] != s or j == n1 - 1
            or labels[i, j + 1, k] != s
            or k == 0 or labels[i, j, k - 1] != s or k == n2 - 1
            or labels[i, j, k + 1] != s)


@njit(cache=True, nogil=True)
def _count(labels, held, n_surface, col_runs):
    """Surface voxels per label and runs (of one held label) per column."""
    n0, n1, n2 = labels.shape
    for i in range(n0):
        for j in range(n1):
            runs = 0
            prev = 0
            for k in range(n2):
                s = labels[i, j, k]
                if held[s]:
                    if s != prev:
                        runs += 1
                    if _is_surface(labels, i, j, k, s):
                        n_surface[s] += 1
                    prev = s
                else:
                    prev = 0
            col_runs[i * n1 + j] = runs


@njit(cache=True, nogil=True)
def _fill(labels, held, cursor, ijk, col_off, runs):
    """Write the surface voxels (grouped by label from ``cursor[s]``) and the
    runs ``(k_first, k_last, label)`` of every column."""
    n0, n1, n2 = labels.shape
    for i in range(n0):
        for j in range(n1):
            r = col_off[i * n1 + j]
            prev = 0
            for k in range(n2):
                s = labels[i, j, k]
                if held[s]:
                    if s != prev:
                        runs[r, 0] = k
                        runs[r, 2] = s
                        r += 1
                    runs[r - 1, 1] = k
                    if _is_surface(labels, i, j, k, s):
                        c = cursor[s]
                        ijk[c, 0] = i
                        ijk[c, 1] = j
                        ijk[c, 2] = k
                        cursor[s] = c + 1
                    prev = s
                else:
                    prev = 0


@njit(cache=True, nogil=True)
def _build_tree(ijk, first, count, spacing, node, base, n_nodes):
    """Heap-ordered hierarchy over ``ijk[first:first + count]`` (reordered in
    place) into ``node[base:base + n_nodes]``: each internal node splits its
    range at the middle along the widest axis of its bounds [mm]."""
    node[base, _N_START] = first
    node[base, _N_END] = first + count
    for n in range(n_nodes):
        g = base + n
        s = node[g, _N_START]
        e = node[g, _N_END]
        for a in range(3):
            node[g, _N_LO + a] = _MAX_AXIS
            node[g, _N_HI + a] = -1
        for p in range(s, e):
            for a in range(3):
                v = ijk[p, a]
                if v < node[g, _N_LO + a]:
                    node[g, _N_LO + a] = v
                if v > node[g, _N_HI + a]:
                    node[g, _N_HI + a] = v
        c = 2 * n + 1
        if c < n_nodes:
            ax = 0
            wide = -1.0
            for a in range(3):
                w = (node[g, _N_HI + a] - node[g, _N_LO + a]) * spacing[a]
                if w > wide:
                    wide = w
                    ax = a
            order = np.argsort(ijk[s:e, ax], kind="mergesort")
            tmp = ijk[s:e].copy()
            for q in range(e - s):
                for a in range(3):
                    ijk[s + q, a] = tmp[order[q], a]
            mid = (s + e) // 2
            node[base + c, _N_START] = s
            node[base + c, _N_END] = mid
            node[base + c + 1, _N_START] = mid
            node[base + c + 1, _N_END] = e


def _tree_nodes(count: int) -> int:
    """Nodes of a heap-ordered hierarchy over ``count`` voxels (leaves hold at
    most :data:`LEAF_SIZE`; every leaf sits on the last level)."""
    if count == 0:
        return 0
    leaves = -(-count // LEAF_SIZE)
    depth = max(0, math.ceil(math.log2(leaves)))
    return 2 ** (depth + 1) - 1


# ------------------------------------------------------------------ querying
@njit(cache=True, nogil=True)
def _node_lb2(node, g, px, py, pz, geom):
    """Squared distance [mm^2] from a point to a node's voxel boxes' bounds."""
    s = 0.0
    for a in range(3):
        p = px if a == 0 else (py if a == 1 else pz)
        lo = geom[0, a] + geom[1, a] * node[g, _N_LO + a] - geom[2, a]
        hi = geom[0, a] + geom[1, a] * node[g, _N_HI + a] + geom[2, a]
        e = lo - p
        if p - hi > e:
            e = p - hi
        if e > 0.0:
            s += e * e
    return s


@njit(cache=True, nogil=True)
def _nearest2(order_s, order_lb, nt, trees, node, ijk, geom, px, py, pz, stack, stack_lb,
              best):
    """Squared distance [mm^2] from a point to the nearest voxel box of the
    structures ``order_s[:nt]`` (their roots' bounds ``order_lb``, nearest
    first) if it is below ``best``; else ``best``."""
    for t in range(nt):
        if order_lb[t] >= best:
            break
        s = order_s[t]
        base = trees[s, 0]
        cnt = trees[s, 1]
        stack[0] = 0
        stack_lb[0] = order_lb[t]
        sp = 1
        while sp > 0:
            sp -= 1
            n = stack[sp]
            if stack_lb[sp] >= best:
                continue
            c = 2 * n + 1
            if c >= cnt:                        # a leaf: its voxels' boxes
                gn = base + n
                for p in range(node[gn, _N_START], node[gn, _N_END]):
                    d2 = 0.0
                    for a in range(3):
                        pa = px if a == 0 else (py if a == 1 else pz)
                        e = abs(pa - geom[0, a] - geom[1, a] * ijk[p, a]) \
                            - geom[2, a]
                        if e > 0.0:
                            d2 += e * e
                    if d2 < best:
                        best = d2
            else:
                l1 = _node_lb2(node, base + c, px, py, pz, geom)
                l2 = _node_lb2(node, base + c + 1, px, py, pz, geom)
                near, far, lnear, lfar = c, c + 1, l1, l2
                if l2 < l1:
                    near, far, lnear, lfar = c + 1, c, l2, l1
                if lfar < best:
                    stack[sp] = far
                    stack_lb[sp] = lfar
                    sp += 1
                if lnear < best:
                    stack[sp] = near
                    stack_lb[sp] = lnear
                    sp += 1
    return best


@njit(cache=True, nogil=True)
def _distance_kernel(pos, groups, geom, dims, trees, node, ijk, col_off, runs, out):
    """Distance [mm] from each point to each group's union of voxel boxes.

    Parameters
    ----------
    pos : (n, 3) float64
        Points, case frame [mm].
    groups : (k, MAX_LABEL + 1) uint8
        1 where a structure index belongs to a group.
    geom : (3, 3) float64
        Rows: centre of voxel (0, 0, 0), spacing, half spacing [mm].
    dims : (3,) int64
        Label map shape.
    trees : (MAX_LABEL + 1, 2) int64
        First node and node count of each structure's hierarchy.
    node : (m_nodes, 8) int32
        Hierarchy nodes (module constants ``_N_*``).
    ijk : (m, 3) int16
        Surface voxels, in hierarchy order.
    col_off : (n0 * n1 + 1,) int64
        First run of each ``(i, j)`` column (``i * n1 + j``).
    runs : (r, 3) int32
        ``(k_first, k_last, label)`` of each run, by column then ``k``.
    out : (n, k) float64
        Receives the distances (0 inside, inf for a group without voxels,
        NaN for a non-finite point).
    """
    stack = np.empty(_STACK, np.int64)
    stack_lb = np.empty(_STACK)
    order_s = np.empty(MAX_LABEL + 1, np.int64)
    order_lb = np.empty(MAX_LABEL + 1)
    n0, n1, n2 = dims[0], dims[1], dims[2]
    # each group's structures that have voxels
    members = np.empty((groups.shape[0], MAX_LABEL), np.int64)
    n_mem = np.zeros(groups.shape[0], np.int64)
    for g in range(groups.shape[0]):
        for s in range(1, MAX_LABEL + 1):
            if groups[g, s] != 0 and trees[s, 1] > 0:
                members[g, n_mem[g]] = s
                n_mem[g] += 1
    # the previous finite point (row ``prev`` of ``out``): its distances
    # bound the next point's (see the module notes)
    have_prev = False
    prev = 0
    qx = qy = qz = 0.0
    for q in range(pos.shape[0]):
        px, py, pz = pos[q, 0], pos[q, 1], pos[q, 2]
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            for g in range(groups.shape[0]):
                out[q, g] = math.nan
            continue
        step = 0.0
        if have_prev:
            step = math.sqrt((px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2)
        fi = (px - geom[0, 0]) / geom[1, 0] + 0.5
        fj = (py - geom[0, 1]) / geom[1, 1] + 0.5
        fk = (pz - geom[0, 2]) / geom[1, 2] + 0.5
        col = -1
        kk = 0
        if 0.0 <= fi < n0 and 0.0 <= fj < n1 and 0.0 <= fk < n2:
            col = int(fi) * n1 + int(fj)
            kk = int(fk)
        for g in range(groups.shape[0]):
            if col >= 0:
                inside = False
                for r in range(col_off[col], col_off[col + 1]):
                    if runs[r, 0] > kk:
                        break
                    if kk <= runs[r, 1] and groups[g, runs[r, 2]] != 0:
                        inside = True
                        break
                if inside:
                    out[q, g] = 0.0
                    continue
            # squared bound: the previous distance plus the step, widened
            # past rounding (distance is 1-Lipschitz); inf for the first point
            bound = math.inf
            if have_prev:
                ub = (out[prev, g] + step) * (1.0 + _BOUND_RTOL) + _BOUND_ATOL
                bound = ub * ub
            # the group's structures, nearest root first
            nt = 0
            for m in range(n_mem[g]):
                s = members[g, m]
                lb = _node_lb2(node, trees[s, 0], px, py, pz, geom)
                t = nt
                while t > 0 and order_lb[t - 1] > lb:
                    order_lb[t] = order_lb[t - 1]
                    order_s[t] = order_s[t - 1]
                    t -= 1
                order_lb[t] = lb
                order_s[t] = s
                nt += 1
            best = _nearest2(order_s, order_lb, nt, trees, node, ijk, geom, px, py, pz,
                             stack, stack_lb, bound)
            if bound < math.inf and not best < bound:
                # nothing nearer than the bound: search afresh (never
                # taken while the bound holds)
                best = _nearest2(order_s, order_lb, nt, trees, node, ijk, geom, px, py, pz,
                                 stack, stack_lb, math.inf)
            out[q, g] = math.sqrt(best)
        have_prev = True
        prev = q
        qx, qy, qz = px, py, pz


# ------------------------------------------------------------------- public
def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


class Clearance:
    """Exact distances [mm] to structures of a label map, at its own resolution.

    Parameters
    ----------
    labels : (n0, n1, n2) uint8
        Structure index per voxel, axes along ``+x, +y, +z`` of the case
        frame (LPS); 0 is empty.
    spacing_mm : float or (3,) float
        Voxel edge along x, y, z [mm] (may be anisotropic).
    origin_mm : (3,) float
        Case-frame centre of voxel ``(0, 0, 0)`` [mm].
    structures : iterable of int
        The structure indices (1 to 255) whose distances can be asked for.

    Raises
    ------
    ValueError
        On a label map that is not 3-D uint8, an axis longer than 32767
        voxels, a non-positive or non-finite spacing, a non-finite origin, or
        a structure index outside 1 to 255.

    Notes
    -----
    Holds only the surface voxels, their hierarchies and the runs (see the
    module docstring), read-only; it pickles as plain arrays.
    """

    def __init__(self, labels, spacing_mm, origin_mm, structures: Iterable[int]):
        labels = np.asarray(labels)
        if labels.ndim != 3 or labels.dtype != np.uint8:
            raise ValueError("labels must be a 3-D uint8 array, got "
                             f"{labels.dtype} {labels.shape}")
        if max(labels.shape) > _MAX_AXIS:
            raise ValueError(f"label map {labels.shape} too large: at most {_MAX_AXIS} "
                             "voxels per axis")
        spacing = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,)).copy()
        if not np.all(np.isfinite(spacing) & (spacing > 0)):
            raise ValueError(f"spacing_mm must be positive and finite, got {spacing}")
        origin = np.asarray(origin_mm, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(origin)):
            raise ValueError(f"origin_mm must be finite, got {origin}")
        held = sorted({int(s) for s in structures})
        if any(s < 1 or s > MAX_LABEL for s in held):
            raise ValueError(f"structure indices must lie in 1-{MAX_LABEL}, got {held}")
        mask = np.zeros(MAX_LABEL + 1, dtype=np.bool_)
        mask[held] = True
        labels = np.ascontiguousarray(labels)
        n0, n1, _ = labels.shape
        n_surface = np.zeros(MAX_LABEL + 1, dtype=np.int64)
        col_runs = np.zeros(n0 * n1, dtype=np.int64)
        _count(labels, mask, n_surface, col_runs)
        col_off = np.zeros(n0 * n1 + 1, dtype=np.int64)
        np.cumsum(col_runs, out=col_off[1:])
        first = np.zeros(MAX_LABEL + 2, dtype=np.int64)
        np.cumsum(n_surface, out=first[1:])
        ijk = np.zeros((int(first[-1]), 3), dtype=np.int16)
        runs = np.zeros((int(col_off[-1]), 3), dtype=np.int32)
        _fill(labels, mask, first[:-1].copy(), ijk, col_off, runs)
        trees = np.zeros((MAX_LABEL + 1, 2), dtype=np.int64)
        n_nodes = [_tree_nodes(int(c)) for c in n_surface]
        trees[:, 0] = np.concatenate([[0], np.cumsum(n_nodes)[:-1]])
        trees[:, 1] = n_nodes
        node = np.zeros((int(sum(n_nodes)), 8), dtype=np.int32)
        for s in held:
            if n_nodes[s]:
                _build_tree(ijk, first[s], n_surface[s], spacing, node, trees[s, 0],
                            n_nodes[s])
        self.shape = tuple(int(n) for n in labels.shape)
        self.spacing_mm = _readonly(spacing)
        self.origin_mm = _readonly(origin)
        self.structures = tuple(held)
        self._geom = _readonly(np.stack([origin, spacing, spacing / 2]))
        self._dims = _readonly(np.array(self.shape, dtype=np.int64))
        self._first = _readonly(first)
        self._trees = _readonly(trees)
        self._node = _readonly(node)
        self._ijk = _readonly(ijk)
        self._col_off = _readonly(col_off)
        self._runs = _readonly(runs)

    @classmethod
    def from_native(cls, native, structures: Iterable[int]) -> "Clearance":
        """Build from a :class:`bonesim.io.volumes.NativeLabels` (the case's
        label map at the source's resolution)."""
        return cls(native.labels, native.spacing_mm, native.origin_mm, structures)

    # ------------------------------------------------------------ queries
    @property
    def nbytes(self) -> int:
        """Memory held [bytes]."""
        return int(sum(a.nbytes for a in (self._geom, self._dims, self._first, self._trees,
                                          self._node, self._ijk, self._col_off,
                                          self._runs)))

    def surface_voxels(self, structure: int) -> np.ndarray:
        """Indices ``(m, 3)`` of a structure's surface voxels (any order)."""
        s = self._check(structure)
        return np.array(self._ijk[self._first[s]:self._first[s + 1]], dtype=np.int64)

    def surface_mm(self, structure: int) -> np.ndarray:
        """Case-frame centres ``(m, 3)`` [mm] of a structure's surface voxels."""
        return self.origin_mm + self.spacing_mm * self.surface_voxels(structure)

    def _check(self, structure) -> int:
        s = int(structure)
        if s not in self.structures:
            raise ValueError(f"structure {s} is not held (held: {list(self.structures)})")
        return s

    def group_mask(self, groups: Sequence[Iterable[int]]) -> np.ndarray:
        """The ``(k, 256)`` uint8 mask of ``k`` groups of structure indices,
        for :meth:`distances` (precompute it where queries are frequent).

        Raises
        ------
        ValueError
            If a group names a structure this field does not hold.
        """
        mask = np.zeros((len(groups), MAX_LABEL + 1), dtype=np.uint8)
        for g, members in enumerate(groups):
            for s in members:
                mask[g, self._check(s)] = 1
        return mask

    def distances(self, pos_mm, groups, out: np.ndarray | None = None) -> np.ndarray:
        """Distance [mm] from points to each group's union of voxel boxes.

        Parameters
        ----------
        pos_mm : (3,) or (n, 3) float
            Points, case frame [mm].
        groups : sequence of iterables of int, or (k, 256) uint8
            Groups of structure indices, or their :meth:`group_mask`.
        out : (n, k) float64, optional
            Receives the result.

        Returns
        -------
        (n, k) float64
            0 inside (or on) a voxel of the group, inf for a group without
            voxels, NaN for a non-finite point.
        """
        p = np.ascontiguousarray(np.asarray(pos_mm, dtype=np.float64).reshape(-1, 3))
        mask = groups if isinstance(groups, np.ndarray) else self.group_mask(groups)
        if mask.ndim != 2 or mask.shape[1] != MAX_LABEL + 1 or mask.dtype != np.uint8:
            raise ValueError(f"groups mask must be (k, {MAX_LABEL + 1}) uint8, got "
                             f"{mask.dtype} {mask.shape}")
        if out is None:
            out = np.empty((p.shape[0], mask.shape[0]))
        elif out.shape != (p.shape[0], mask.shape[0]) or out.dtype != np.float64:
            raise ValueError(f"out must be ({p.shape[0]}, {mask.shape[0]}) float64")
        # the caller's arrays read-only too (the held ones are): one compiled kernel
        _distance_kernel(read_only(p), read_only(mask), self._geom, self._dims, self._trees,
                         self._node, self._ijk, self._col_off, self._runs, out)
        return out

    def distance(self, pos_mm, structures: Iterable[int] | None = None) -> np.ndarray:
        """Distance [mm] from points ``(3,)`` or ``(n, 3)`` to the union of
        ``structures`` (default: every structure held); shape ``(n,)``.
        See :meth:`distances`."""
        members = self.structures if structures is None else structures
        return self.distances(pos_mm, [members])[:, 0]

    def __setstate__(self, state: dict) -> None:
        # unpickled arrays come back writeable: read-only again, as built
        for v in state.values():
            if isinstance(v, np.ndarray):
                v.flags.writeable = False
        self.__dict__.update(state)

    def __repr__(self) -> str:
        return (f"Clearance(shape={self.shape}, spacing_mm={self.spacing_mm.tolist()}, "
                f"structures={list(self.structures)}, surface_voxels={len(self._ijk)}, "
                f"nbytes={self.nbytes})")
