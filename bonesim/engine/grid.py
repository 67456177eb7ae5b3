"""Hashed voxel grid: bone stored as a hash table of small dense bricks.

Layout
------
Voxels are addressed by integer coordinates ``(i, j, k)`` along the case
frame's ``(x, y, z)`` axes. The centre of voxel ``(i, j, k)`` lies at
``origin_mm + spacing_mm * (i, j, k)``.

Voxels are grouped in bricks of ``BRICK**3 = 8**3`` voxels. Brick
``(bi, bj, bk) = (i >> 3, j >> 3, k >> 3)`` is found through an
open-addressing hash table (linear probing, power-of-two capacity) keyed by the
packed brick coordinate (:mod:`bonesim.engine.brick_hash`, shared with the dust);
inside a brick a voxel sits at the flat offset
``((i & 7) << 6) | ((j & 7) << 3) | (k & 7)``. Memory is proportional to the
number of bricks that hold bone (plus a one-voxel halo, so that every voxel
26-adjacent to bone lives in an allocated brick), and a lookup is O(1): one
hash probe (rarely more) and one array read.

Per voxel the grid stores

* ``density`` (float32): the amount of material left to remove, 1.0 for
  intact tissue and 0.0 for empty space;
* ``label`` (uint8): the structure index (0 = none, ``s >= 1`` is the model's
  structure ``s - 1``).

Bricks are never inserted during a run (material is only removed), so the
table is static after :meth:`Grid.from_dense` and kernels can read it without
locks.

The numba kernels below take the plain arrays (``keys, vals`` for the table,
``density`` / ``label`` of shape ``(n_bricks, 512)``) so that any other kernel
(surface, haptics, dust) can inline lookups.
"""
from __future__ import annotations

import numpy as np
from numba import njit

# the brick hash table is shared with the dust grid
from bonesim.engine.brick_hash import (BRICK, BRICK_MASK, BRICK_SHIFT, BRICK_VOXELS, EMPTY_KEY,
                                       find_brick, pack_brick_key, table_insert)
from bonesim.engine.kernel_args import read_only

__all__ = ["BRICK", "BRICK_SHIFT", "BRICK_MASK", "BRICK_VOXELS", "EMPTY_KEY",
           "pack_brick_key", "find_brick", "voxel_offset", "density_at", "gather_box",
           "Grid", "sync_replica"]

@njit(cache=True, nogil=True, inline="always")
def voxel_offset(i, j, k):
    """Flat offset of voxel ``(i, j, k)`` inside its brick."""
    return ((i & BRICK_MASK) << 6) | ((j & BRICK_MASK) << 3) | (k & BRICK_MASK)


@njit(cache=True, nogil=True)
def density_at(keys, vals, density, i, j, k):
    """Density of voxel ``(i, j, k)``; 0.0 where no brick is allocated."""
    b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
    if b < 0:
        return np.float32(0.0)
    return density[b, voxel_offset(i, j, k)]


@njit(cache=True, nogil=True)
def _insert_all(keys, vals, bcoords):
    for b in range(bcoords.shape[0]):
        table_insert(keys, vals, pack_brick_key(bcoords[b, 0], bcoords[b, 1], bcoords[b, 2]),
                     b)


@njit(cache=True, nogil=True)
def gather_box(keys, vals, arr, out, lo_i, lo_j, lo_k):
    """Copy per-voxel values of a brick array into a dense box.

    Parameters
    ----------
    keys, vals : hash table of a brick grid.
    arr : (n_bricks, 512) array
        Per-voxel values (density, label, dust, ...).
    out : (nx, ny, nz) array
        Filled with the values of voxels ``lo + (x, y, z)``; voxels without a
        brick are left as they are.
    lo_i, lo_j, lo_k : int
        First voxel of the box.
    """
    nx, ny, nz = out.shape
    for x in range(nx):
        i = lo_i + x
        for y in range(ny):
            j = lo_j + y
            for z in range(nz):
                k = lo_k + z
                b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                               k >> BRICK_SHIFT)
                if b >= 0:
                    out[x, y, z] = arr[b, voxel_offset(i, j, k)]


@njit(cache=True, nogil=True)
def _mark_bricks(lab, dens, has_dens, bmask):
    """Flag bricks (offset by +1) that hold tissue or touch it across a face,
    edge or corner: every voxel 26-adjacent to tissue gets a brick. Tissue is
    ``lab > 0`` (and ``dens > 0`` when ``has_dens``)."""
    nx, ny, nz = lab.shape
    for i in range(nx):
        bi = (i >> BRICK_SHIFT) + 1
        li = i & BRICK_MASK
        di0 = -1 if li == 0 else 0
        di1 = 1 if li == BRICK_MASK else 0
        for j in range(ny):
            bj = (j >> BRICK_SHIFT) + 1
            lj = j & BRICK_MASK
            dj0 = -1 if lj == 0 else 0
            dj1 = 1 if lj == BRICK_MASK else 0
            for k in range(nz):
                if lab[i, j, k] == 0 or (has_dens and dens[i, j, k] <= 0.0):
                    continue
                bk = (k >> BRICK_SHIFT) + 1
                lk = k & BRICK_MASK
                if li != 0 and li != BRICK_MASK and lj != 0 and lj != BRICK_MASK \
                        and lk != 0 and lk != BRICK_MASK:
                    bmask[bi, bj, bk] = True
                    continue
                dk0 = -1 if lk == 0 else 0
                dk1 = 1 if lk == BRICK_MASK else 0
                for a in range(di0, di1 + 1):
                    for b in range(dj0, dj1 + 1):
                        for c in range(dk0, dk1 + 1):
                            bmask[bi + a, bj + b, bk + c] = True


@njit(cache=True, nogil=True)
def _fill_bricks(lab, dens, has_dens, bricks, out_d, out_l):
    """Copy the dense volumes into their bricks (tissue voxels only; density
    1.0 where ``has_dens`` is False)."""
    nx, ny, nz = lab.shape
    for b in range(bricks.shape[0]):
        i0 = bricks[b, 0] * BRICK
        j0 = bricks[b, 1] * BRICK
        k0 = bricks[b, 2] * BRICK
        for x in range(BRICK):
            i = i0 + x
            if i < 0 or i >= nx:
                continue
            for y in range(BRICK):
                j = j0 + y
                if j < 0 or j >= ny:
                    continue
                for z in range(BRICK):
                    k = k0 + z
                    if k < 0 or k >= nz:
                        continue
                    if lab[i, j, k] == 0:
                        continue
                    d = dens[i, j, k] if has_dens else np.float32(1.0)
                    if d > 0.0:
                        off = (x << 6) | (y << 3) | z
                        out_d[b, off] = d
                        out_l[b, off] = lab[i, j, k]


def _brick_table(bricks):
    """A hash table ``(keys, vals)`` of brick coordinates ``bricks`` (n, 3):
    power-of-two capacity at least twice the bricks (16 or more)."""
    cap = 16
    while cap < 2 * max(len(bricks), 1):
        cap *= 2
    keys = np.full(cap, -1, dtype=np.int64)
    vals = np.full(cap, -1, dtype=np.int32)
    _insert_all(keys, vals, np.ascontiguousarray(bricks, dtype=np.int32))
    return keys, vals


class Grid:
    """Hashed brick grid of tissue density and structure labels.

    Build one with :meth:`from_dense`. The arrays are public so that numba
    kernels can take them directly.

    Attributes
    ----------
    spacing_mm : float
        Isotropic voxel edge [mm].
    origin_mm : (3,) float64
        Case-frame position of the centre of voxel (0, 0, 0) [mm].
    shape : tuple of int
        Extent ``(nx, ny, nz)`` of the volume the grid was built from [voxels].
    keys : (capacity,) int64
        Hash table of packed brick coordinates, ``-1`` for empty slots.
    vals : (capacity,) int32
        Brick index for each key.
    bricks : (n_bricks, 3) int32
        Brick coordinates ``(bi, bj, bk)``, sorted lexicographically.
    density : (n_bricks, 512) float32
        Material left to remove per voxel (1 intact, 0 empty).
    label : (n_bricks, 512) uint8
        Structure index per voxel (0 none, s >= 1 is structure s - 1).
    """

    def __init__(self, spacing_mm, origin_mm, shape, keys, vals, bricks, density, label):
        self.spacing_mm = float(spacing_mm)
        self.origin_mm = np.asarray(origin_mm, dtype=np.float64).reshape(3)
        self.shape = tuple(int(s) for s in shape)
        self.keys = keys
        self.vals = vals
        # one layout and one flag for every grid, wherever it was built
        # (np.argwhere gives Fortran order; a model's labels are read-only):
        # each kernel then compiles once, not once per variant
        self.bricks = np.ascontiguousarray(bricks, dtype=np.int32)
        self.density = density
        self.label = read_only(label)           # a grid's labels never change

    @property
    def density_ro(self) -> np.ndarray:
        """:attr:`density` as a read-only view (for kernels that only read
        it: one compiled form whether the grid is a model's or a state's)."""
        return read_only(self.density)

    # ------------------------------------------------------------------ build
    @classmethod
    def from_dense(cls, label, density=None, spacing_mm=0.5, origin_mm=(0.0, 0.0, 0.0)):
        """Build a grid from dense volumes.

        Parameters
        ----------
        label : (nx, ny, nz) integer array
            Structure index per voxel, axis order ``(x, y, z)``; 0 is empty.
            Values must be in ``[0, 255]``.
        density : (nx, ny, nz) float array, optional
            Initial density where ``label > 0``; default 1.0. Ignored where
            ``label == 0``.
        spacing_mm : float
            Isotropic voxel edge [mm].
        origin_mm : (3,) float
            Case-frame position of voxel (0, 0, 0) [mm].
        """
        label = np.asarray(label)
        if label.ndim != 3:
            raise ValueError(f"label volume must be 3-D, got shape {label.shape}")
        if label.dtype != np.uint8 and label.size and (label.min() < 0 or label.max() > 255):
            raise ValueError("labels must lie in [0, 255]")
        if not spacing_mm > 0:
            raise ValueError(f"spacing_mm must be positive, got {spacing_mm}")
        shape = label.shape
        lab = np.ascontiguousarray(label, dtype=np.uint8)
        if density is None:
            dens = np.zeros((1, 1, 1), dtype=np.float32)     # unused: 1.0 where labelled
        else:
            dens = np.ascontiguousarray(density, dtype=np.float32)
            if dens.shape != shape:
                raise ValueError("density and label volumes differ in shape")
            if (dens < 0).any() or not np.isfinite(dens).all():
                raise ValueError("density must be finite and non-negative")
        has_dens = density is not None
        # bricks holding tissue or a voxel 26-adjacent to tissue (the halo);
        # brick coordinates start at -1 so the halo below voxel 0 fits
        nb = tuple((s + BRICK - 1) // BRICK + 2 for s in shape)
        bmask = np.zeros(nb, dtype=np.bool_)
        _mark_bricks(lab, dens, has_dens, bmask)
        bricks = np.ascontiguousarray(np.argwhere(bmask) - 1, dtype=np.int32)  # lexicographic
        n_b = len(bricks)
        keys, vals = _brick_table(bricks)
        bd = np.zeros((n_b, BRICK_VOXELS), dtype=np.float32)
        bl = np.zeros((n_b, BRICK_VOXELS), dtype=np.uint8)
        _fill_bricks(lab, dens, has_dens, bricks, bd, bl)
        return cls(spacing_mm, origin_mm, shape, keys, vals, bricks, bd, bl)

    def copy(self) -> "Grid":
        """Deep copy of the mutable per-voxel arrays (the table is shared, read-only)."""
        return Grid(self.spacing_mm, self.origin_mm, self.shape, self.keys, self.vals,
                    self.bricks, self.density.copy(), self.label.copy())

    def sub_grid(self, brick_lo, brick_hi) -> "Grid":
        """The bricks of this grid inside a box of brick coordinates, as a grid
        of their own on the same lattice.

        Voxel ``(i, j, k)`` of the result is voxel ``(i, j, k)`` of this grid
        (same ``origin_mm``, ``spacing_mm`` and ``shape``); it allocates
        only the selected bricks, with a hash table of its own.

        Parameters
        ----------
        brick_lo, brick_hi : (3,) int
            First and last brick coordinates ``(bi, bj, bk)`` of the box,
            inclusive (bricks are ``BRICK`` voxels on a side).

        Returns
        -------
        Grid
            With copies of the selected bricks' density and label, in this
            grid's brick order (the bricks where
            ``all(brick_lo <= bricks <= brick_hi)``).
        """
        lo = np.asarray(brick_lo, dtype=np.int64).reshape(3)
        hi = np.asarray(brick_hi, dtype=np.int64).reshape(3)
        sel = np.all((self.bricks >= lo) & (self.bricks <= hi), axis=1)
        bricks = np.ascontiguousarray(self.bricks[sel])          # stays lexicographic
        keys, vals = _brick_table(bricks)
        return Grid(self.spacing_mm, self.origin_mm, self.shape, keys, vals, bricks,
                    self.density[sel].copy(), self.label[sel].copy())

    # ---------------------------------------------------------------- queries
    @property
    def n_bricks(self) -> int:
        return int(self.bricks.shape[0])

    @property
    def nbytes(self) -> int:
        """Memory held by the grid [bytes]."""
        return int(self.keys.nbytes + self.vals.nbytes + self.bricks.nbytes
                   + self.density.nbytes + self.label.nbytes)

    def brick_index(self, i: int, j: int, k: int) -> int:
        """Brick holding voxel ``(i, j, k)``, or -1."""
        return int(find_brick(self.keys, self.vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                              k >> BRICK_SHIFT))

    def density_at(self, i: int, j: int, k: int) -> float:
        """Density of voxel ``(i, j, k)`` (0.0 outside allocated bricks)."""
        return float(density_at(self.keys, self.vals, self.density_ro, i, j, k))

    def label_at(self, i: int, j: int, k: int) -> int:
        """Structure index of voxel ``(i, j, k)`` (0 where empty)."""
        b = self.brick_index(i, j, k)
        return 0 if b < 0 else int(self.label[b, voxel_offset(i, j, k)])

    def to_dense(self, lo=(0, 0, 0), shape=None):
        """Dense copies ``(density, label)`` of a box of voxels.

        Parameters
        ----------
        lo : (3,) int
            First voxel of the box.
        shape : (3,) int, optional
            Box extent [voxels]; default the source volume's shape.

        Returns
        -------
        density : (nx, ny, nz) float32
        label : (nx, ny, nz) uint8
        """
        shape = self.shape if shape is None else tuple(int(s) for s in shape)
        d = np.zeros(shape, dtype=np.float32)
        lab = np.zeros(shape, dtype=np.uint8)
        gather_box(self.keys, self.vals, self.density_ro, d, *map(int, lo))
        gather_box(self.keys, self.vals, self.label, lab, *map(int, lo))
        return d, lab

    def voxel_centers(self, ijk) -> np.ndarray:
        """Case-frame centres [mm] of voxels ``ijk`` (shape (n, 3))."""
        return self.origin_mm + self.spacing_mm * np.asarray(ijk, dtype=np.float64)

    def occupied_count(self) -> int:
        """Number of voxels with density > 0."""
        return int(np.count_nonzero(self.density > 0))

    def counts_by_label(self, n_labels: int) -> np.ndarray:
        """Voxels with density > 0 per structure index ``0 .. n_labels``."""
        occ = self.density > 0
        return np.bincount(self.label[occ].ravel(), minlength=n_labels + 1)


@njit(cache=True, nogil=True)
def _sync_replica(keys, vals, replica, live, removed, touched):
    for q in range(removed.shape[0]):
        i, j, k = removed[q, 0], removed[q, 1], removed[q, 2]
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        if b >= 0:
            replica[b, voxel_offset(i, j, k)] = 0.0
    for q in range(touched.shape[0]):
        i, j, k = touched[q, 0], touched[q, 1], touched[q, 2]
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        if b >= 0:
            off = voxel_offset(i, j, k)
            d = live[b, off]
            # a zero here is a removal still on its way through the ring:
            # keep the old value until the removal itself arrives
            if d > 0.0 and replica[b, off] > 0.0:
                replica[b, off] = d


def sync_replica(replica: Grid, live: Grid, removed, touched, check: bool = True) -> None:
    """Bring a consumer's copy of a grid up to date with published events.

    A consumer in another thread or process must not read the live density
    directly: the producer may already have changed voxels it has not
    published yet. The replica changes only through the events: ``removed``
    voxels become empty, ``touched`` voxels take the live density (unless
    that is already 0, i.e. their removal is still to come).

    Parameters
    ----------
    replica, live : Grid
        Grids sharing one brick table (``replica = live.copy()``).
    removed, touched : (n, 3) int32
        Voxels drained from the removal and touched rings.
    check : bool
        Check that the tables are the same object (False: the caller has
        checked that they are equal, e.g. for a model sent to another process).
    """
    if check and replica.keys is not live.keys:
        raise ValueError("replica and live grid must share their brick table")
    _sync_replica(replica.keys, replica.vals, replica.density, live.density,
                  np.ascontiguousarray(removed, dtype=np.int32).reshape(-1, 3),
                  np.ascontiguousarray(touched, dtype=np.int32).reshape(-1, 3))
