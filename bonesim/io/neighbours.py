"""Which structures of a label map are neighbours, measured on a fixed lattice.

Display colours keep neighbouring structures apart
(:func:`bonesim.io.anatomy.resolve_colors`). So that a structure keeps its
colour whatever voxel size a case is loaded at, neighbours are measured on
the source's labels pooled onto a lattice of the case frame that does not
depend on the engine's grid:

Pooling (:func:`pool_presence`)
    Cell ``k`` spans ``[k c, (k + 1) c)`` along each axis (``c`` the cell
    edge, ``analysis_mm`` of ``bonesim/data/anatomy.toml``). A cell holds the
    set of structures (a bit set) one of whose voxel centres falls in it: a
    structure counts wherever it reaches, so a chorda thinner than a cell is
    kept, and two structures may share a cell.
Neighbours (:func:`neighbours`)
    Structures ``s`` and ``t`` are neighbours when a cell holding ``s`` and a
    cell holding ``t`` have centres at most ``reach = max(c, voxel) +
    within_mm`` apart (two structures in one cell are neighbours). Only
    *boundary* cells need looking at (a cell with a face neighbour holding
    another set): of the closest pair of an ``s`` cell and a ``t`` cell, the
    ``s`` cell's step toward the ``t`` cell leaves ``s``. Each boundary cell
    ORs the sets of the cells within reach on one side of it (a half ball
    of offsets; the closest pair is found from whichever end its offset
    points away from), and the structures it holds collect them. The half
    ball is read as columns along z (:func:`ball_columns`) from ORs over
    z windows of the next few cell planes, kept in a small ring.

Both are numba kernels over the label map as it is (no copy of the volume,
no distance field; the cells take 8 bytes each, 0.5 mm cells of a 512^3
map at 0.19 mm about 70 MB): a 256^3 map at 0.19 mm takes about 0.1 s of
CPU, a 512^3 one with air cells everywhere about 0.8 s
(``tests/bonesim/io/test_anatomy_defaults.py`` checks the 256^3 time).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["pool_presence", "neighbours", "ball_offsets", "ball_columns", "warmup"]

#: Bits of one word of a cell's structure set.
WORD_BITS = 64


def _axis_cells(n: int, origin: float, spacing: float, cell_mm: float) -> np.ndarray:
    """Lattice cell of each of ``n`` voxel centres along one axis (a centre on
    a cell edge goes to the upper cell)."""
    x = (origin + spacing * np.arange(n, dtype=np.float64)) / cell_mm
    return np.floor(np.round(x, 6)).astype(np.int64)


@njit(cache=True, nogil=True)
def _pool_kernel(labels, c0, c1, c2, lut, out, pad):   # pragma: no cover - numba
    """OR each voxel's bit set (``lut[label]``) into its cell ``(c0[i], c1[j],
    c2[k])`` (shifted by ``pad``), once per run of one label in one cell."""
    n0, n1, n2 = labels.shape
    w = out.shape[3]
    for i in range(n0):
        ci = c0[i] + pad
        for j in range(n1):
            cj = c1[j] + pad
            last = -1
            lastk = -1
            for k in range(n2):
                v = labels[i, j, k]
                if v == 0:
                    continue
                ck = c2[k] + pad
                if v == last and ck == lastk:
                    continue
                for q in range(w):
                    out[ci, cj, ck, q] |= lut[v, q]
                last = v
                lastk = ck


def _pool(labels, n, spacing_mm, origin_mm, cell_mm, pad):
    labels = np.asarray(labels)
    if labels.ndim != 3:
        raise ValueError(f"labels must be 3-D, got shape {labels.shape}")
    if labels.dtype != np.uint8:
        raise ValueError(f"labels must be uint8, got {labels.dtype}")
    sp = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,))
    org = np.asarray(origin_mm, dtype=np.float64).reshape(3)
    if not (np.all(sp > 0) and cell_mm > 0):
        raise ValueError("spacing_mm and cell_mm must be positive")
    n = int(n)
    if not 0 <= n <= 255:
        raise ValueError(f"n_structures must be 0..255, got {n}")
    w = max(1, -(-n // WORD_BITS))
    lut = np.zeros((256, w), np.uint64)
    for s in range(1, n + 1):
        lut[s, (s - 1) // WORD_BITS] = np.uint64(1) << np.uint64((s - 1) % WORD_BITS)
    cells = [_axis_cells(m, o, d, cell_mm) for m, o, d in zip(labels.shape, org, sp)]
    first = np.array([c[0] for c in cells], dtype=np.int64)
    shape = tuple(int(c[-1] - c[0] + 1 + 2 * pad) for c in cells)
    out = np.zeros(shape + (w,), np.uint64)
    _pool_kernel(labels, *(c - c[0] for c in cells), lut, out, int(pad))
    return out, first


def pool_presence(labels: np.ndarray, n_structures: int, spacing_mm, origin_mm,
                  cell_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Which structures reach each cell of the fixed lattice.

    Parameters
    ----------
    labels : (n0, n1, n2) uint8
        Structure index per voxel (0 empty), axes x, y, z of the case frame.
    n_structures : int
        Number of structures (indices 1 .. n, at most 255).
    spacing_mm : float or (3,) float
        Voxel edge along x, y, z [mm].
    origin_mm : (3,) float
        Case-frame centre of voxel ``(0, 0, 0)`` [mm].
    cell_mm : float
        Cell edge [mm].

    Returns
    -------
    bits : (c0, c1, c2, w) uint64
        Bit ``(s - 1) % 64`` of word ``(s - 1) // 64`` set where structure
        ``s`` reaches the cell.
    first : (3,) int64
        Lattice index of cell ``bits[0, 0, 0]`` (cell ``k`` spans
        ``[k cell_mm, (k + 1) cell_mm)`` of the case frame).
    """
    return _pool(labels, n_structures, spacing_mm, origin_mm, float(cell_mm), 0)


def ball_offsets(reach_cells: float) -> np.ndarray:
    """Integer offsets ``o`` with ``|o| <= reach_cells`` in the half space
    ``o > 0`` (lexicographically) and ``o = 0``: (m, 3) int64."""
    r = int(math.floor(reach_cells + 1e-9))
    g = np.arange(-r, r + 1)
    o = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    o = o[(o * o).sum(axis=1) <= reach_cells * reach_cells + 1e-6]
    half = (o[:, 0] > 0) | ((o[:, 0] == 0) & ((o[:, 1] > 0) | ((o[:, 1] == 0)
                                                                & (o[:, 2] >= 0))))
    return o[half]


@njit(cache=True, nogil=True)
def _near_kernel(bits, pad, offsets, seen):               # pragma: no cover - numba
    s0, s1, s2, w = bits.shape
    m = offsets.shape[0]
    acc = np.zeros(w, np.uint64)
    for i in range(pad, s0 - pad):
        for j in range(pad, s1 - pad):
            for k in range(pad, s2 - pad):
                empty = True
                for q in range(w):
                    if bits[i, j, k, q] != 0:
                        empty = False
                if empty:
                    continue
                edge = False
                for q in range(w):
                    b = bits[i, j, k, q]
                    if (bits[i - 1, j, k, q] != b or bits[i + 1, j, k, q] != b
                            or bits[i, j - 1, k, q] != b or bits[i, j + 1, k, q] != b
                            or bits[i, j, k - 1, q] != b or bits[i, j, k + 1, q] != b):
                        edge = True
                if not edge:
                    continue
                for q in range(w):
                    acc[q] = 0
                for p in range(m):
                    a = i + offsets[p, 0]
                    b_ = j + offsets[p, 1]
                    c = k + offsets[p, 2]
                    for q in range(w):
                        acc[q] |= bits[a, b_, c, q]
                for q in range(w):
                    b = bits[i, j, k, q]
                    while b != 0:
                        low = b & (~b + np.uint64(1))          # lowest set bit
                        s = q * 64
                        t = low
                        while t > np.uint64(1):
                            t >>= np.uint64(1)
                            s += 1
                        for q2 in range(w):
                            seen[s, q2] |= acc[q2]
                        b ^= low


def ball_columns(reach_cells: float) -> np.ndarray:
    """The half ball of :func:`ball_offsets` as columns along z: rows
    ``(dx, dy, h)`` for the offsets ``(dx, dy, -h .. h)`` with ``dx > 0``, or
    ``dx = 0`` and ``dy > 0``; the column ``dx = dy = 0`` (offsets ``0 ..
    r``) is left to the caller. (m, 3) int64."""
    r = int(math.floor(reach_cells + 1e-9))
    rows = []
    for dx in range(0, r + 1):
        for dy in range(-r, r + 1):
            if dx == 0 and dy <= 0:
                continue
            rest = reach_cells * reach_cells + 1e-6 - dx * dx - dy * dy
            if rest >= 0:
                rows.append((dx, dy, int(math.floor(math.sqrt(rest)))))
    return np.array(rows, dtype=np.int64).reshape(-1, 3)


@njit(cache=True, nogil=True)
def _window_plane(bits, p, r, out):                      # pragma: no cover - numba
    """``out[h - 1, j, k]``: OR of plane ``p`` over ``k - h .. k + h``, for
    ``h = 1 .. r`` (every ``j``; ``k`` clear of the padding)."""
    s1, s2 = bits.shape[1], bits.shape[2]
    for j in range(s1):
        for k in range(r, s2 - r):
            acc = bits[p, j, k]
            for h in range(1, r + 1):
                acc |= bits[p, j, k - h] | bits[p, j, k + h]
                out[h - 1, j, k] = acc


@njit(cache=True, nogil=True)
def _near_kernel1(bits, pad, r, cols, seen):             # pragma: no cover - numba
    """:func:`_near_kernel` for sets of one word (up to 64 structures), the
    half ball read as columns along z (:func:`ball_columns`) from windowed
    ORs of the next ``r + 1`` planes, kept in a ring of planes."""
    s0, s1, s2 = bits.shape
    m = cols.shape[0]
    ring = np.zeros((r + 1, max(r, 1), s1, s2), np.uint64)
    for p in range(pad, min(pad + r, s0)):
        _window_plane(bits, p, r, ring[p % (r + 1)])
    for i in range(pad, s0 - pad):
        _window_plane(bits, i + r, r, ring[(i + r) % (r + 1)])
        for j in range(pad, s1 - pad):
            for k in range(pad, s2 - pad):
                b = bits[i, j, k]
                if b == 0:
                    continue
                if (bits[i, j, k - 1] == b and bits[i, j, k + 1] == b
                        and bits[i, j - 1, k] == b and bits[i, j + 1, k] == b
                        and bits[i - 1, j, k] == b and bits[i + 1, j, k] == b):
                    continue
                acc = b
                for dz in range(1, r + 1):
                    acc |= bits[i, j, k + dz]
                for q in range(m):
                    h = cols[q, 2]
                    if h == 0:
                        acc |= bits[i + cols[q, 0], j + cols[q, 1], k]
                    else:
                        acc |= ring[(i + cols[q, 0]) % (r + 1), h - 1, j + cols[q, 1], k]
                if acc == b and (b & (b - np.uint64(1))) == 0:
                    continue                            # only itself, alone
                s = 0
                while b != 0:
                    if b & np.uint64(1):
                        seen[s] |= acc
                    b >>= np.uint64(1)
                    s += 1


def neighbours(labels: np.ndarray, n_structures: int, spacing_mm, within_mm: float,
               origin_mm=(0.0, 0.0, 0.0), cell_mm: float | None = None) -> np.ndarray:
    """Which structures touch or lie within ``within_mm`` of each other, on the
    lattice of ``cell_mm`` (see the module docstring).

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel (0 empty), axes x, y, z.
    n_structures : int
        Number of structures (indices 1 .. n, at most 255).
    spacing_mm : float or (3,) float
        Voxel edge along x, y, z [mm].
    within_mm : float
        Largest gap between neighbours [mm].
    origin_mm : (3,) float
        Case-frame centre of voxel ``(0, 0, 0)`` [mm].
    cell_mm : float, optional
        Cell edge [mm]; default the largest voxel edge. With the voxel edge
        and voxel centres on the lattice (an origin that is a multiple of it)
        this is the rule on the voxels themselves: centres within
        ``spacing_mm + within_mm``.

    Returns
    -------
    (n, n) bool
        Symmetric, ``[s - 1, t - 1]`` for structures ``s`` and ``t``; the
        diagonal is False.
    """
    sp = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,))
    if not np.all(sp > 0) or not within_mm >= 0:
        raise ValueError("spacing_mm must be positive and within_mm non-negative")
    cell = float(sp.max()) if cell_mm is None else float(cell_mm)
    n = int(n_structures)
    out = np.zeros((n, n), dtype=bool)
    if n == 0:
        return out
    reach = (max(cell, float(sp.max())) + float(within_mm)) / cell        # [cells]
    pad = int(math.floor(reach + 1e-9)) + 1
    bits, _ = _pool(labels, n, sp, origin_mm, cell, pad)
    seen = np.zeros((max(n, 1), bits.shape[3]), np.uint64)
    offsets = ball_offsets(reach)
    if bits.shape[3] == 1:
        seen1 = np.zeros(max(n, 1), np.uint64)
        _near_kernel1(np.ascontiguousarray(bits[..., 0]), pad,
                      int(math.floor(reach + 1e-9)), ball_columns(reach), seen1)
        seen[:, 0] = seen1
    else:
        _near_kernel(bits, pad, offsets, seen)
    for s in range(n):
        for t in range(n):
            if t != s and (int(seen[s, t // WORD_BITS]) >> (t % WORD_BITS)) & 1:
                out[s, t] = out[t, s] = True
    return out


def warmup() -> None:
    """Compile (or load) the kernels."""
    labels = np.zeros((4, 4, 4), np.uint8)
    labels[1, 1, 1], labels[2, 1, 1] = 1, 2
    neighbours(labels, 2, 0.5, 0.5)
