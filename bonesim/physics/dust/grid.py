"""Bone dust as an Eulerian density field on a growing hashed brick grid.

No particles: dust is an amount per cell of the bone grid's lattice (cell
``(i, j, k)`` is bone voxel ``(i, j, k)``, centre ``origin_mm + spacing_mm *
(i, j, k)`` [mm]), moved between face-adjacent cells by a few local rules.

Units and storage
-----------------
A cell's *density* is the dust it holds in *cells*: 1.0 (:data:`FULL`) means
the cell is packed full; its volume is ``density * spacing_mm**3`` [mm^3].
Removed bone becomes ``bulking`` cells of dust per removed voxel (loose chips
take more room than the solid bone they came from; see :class:`DustParams`).

Densities are stored in fixed point, as int32 multiples of ``1 / Q`` cells
(``Q = 2**20``). Every rule moves an integer amount from one cell to another,
so

* mass is conserved *exactly*: ``total == added - suctioned`` holds as an
  integer identity at all times (:meth:`DustGrid.totals_q`), not only up to
  rounding;
* scattering moves is order independent (integer addition commutes), so the
  result does not depend on the hash table's layout or the brick order.

A cell holds at most ``2**31 / Q = 2048`` cells of dust.

Grid
----
Cells are grouped in bricks of ``8**3`` like :mod:`bonesim.engine.grid` (same
``pack_brick_key`` / ``voxel_offset`` layout), found through an
open-addressing table that *grows*: dust appears where bone is removed and
falls into empty space, so bricks are inserted at run time. Each brick keeps
the indices of its six face neighbours (``nbr``, -1 if absent), so the
kernels step across brick faces without hashing.

Allocation happens only in Python (:meth:`DustGrid._reserve`): the kernels
take bricks from a preallocated pool; when the pool is short, a stage of the
step kernel stops *before* changing anything and reports how many bricks it
needs, the wrapper recycles dead bricks (no dust, no dusty face neighbour)
or, if that is not enough, grows every array, and calls the kernel again
from the same stage.

Before each transport rule runs, every brick holding dust has its face
neighbours that touch the domain allocated (the halo), so a rule can always
write one cell further.

Domain
------
Dust lives in a box of cells ``[lo, hi)`` (``bounds_vox``; by default the
bone grid's volume ``[0, shape)``). A *wall* cell is one outside that box or
one holding bone (bone density > 0 in the bone grid passed to
:meth:`DustGrid.step`). Rules 1-2 never move dust into a wall, nor out of one
(dust added to a cell that is still bone stays put until the bone goes).

Bodies
------
The lattice is the case frame. The bone's bodies
(:mod:`bonesim.engine.bodies`) keep their voxels where they were cut, each
in its own frame, so with the body arrays given (``bodies``):

* a removal of a body at a pose other than the identity becomes dust in the
  case-frame cell of the voxel's centre, ``round((R c + t - origin) /
  spacing)`` with ``c`` the centre in the body's frame (dust that would land
  outside the domain is dropped: a fragment moved out of the volume);
* walls are the bone voxels of the bodies at the identity pose only. A moved
  body is **not** a dust wall (its voxels are not resampled onto the
  lattice): dust passes through a fragment that was moved, and falls where
  it was cut away.

While every body sits at the identity pose (one body until fragments exist)
the bodies are ignored: the same kernels run on the same data as before.

One step (:meth:`DustGrid.step`)
--------------------------------
Let ``g`` be the unit gravity vector; its *dominant axis* ``a*`` is the axis of
its largest component, and "down" is the neighbour along ``a*`` in the
direction of ``g``. A cell's *room* is ``1 - density`` (negative if overfull).
``dt`` is the step [s]. All amounts are in fixed point and every product is
rounded down (``floor(x * y)`` below means ``(x * y_fixed) >> 16`` with
``y`` in 16-bit fixed point).

1. **Gravity** (``settle_rate`` [cells/s]). With ``split_gravity`` (default)
   gravity is shared among the axes: axis ``a`` with ``|g_a| > 1e-6`` gets the
   weight ``w_a = |g_a| / sum_b |g_b|`` and the neighbour ``n_a = c +
   sign(g_a) e_a``; otherwise only the dominant axis is used, with weight 1.
   Each cell ``c`` sends along each of its axes

   ``f_a = floor(w_a * min(d(c), settle_rate * dt, room(n_a)))``

   into ``n_a`` unless either is a wall. A cell receives from at most one
   source per axis, each bounded by ``w_a * room``, so gravity never pushes a
   cell past full, and ``sum_a f_a <= d(c)``.
2. **Piling and spilling** (``spill_rate`` [1/s], ``repose`` [cells]). With
   ``k = min(spill_rate * dt, 0.2)``, a non-wall cell is a *source* if it is
   overfull (density > 1), or if it holds more than ``repose`` and is
   *supported*: the cell below is a wall or holds at least a full cell. A
   source sends to each non-wall lateral neighbour ``n`` (the four face
   neighbours perpendicular to ``a*``)

   ``f = min(floor(k * (d(c) - d(n) - repose)), floor(room(n) / 5))``

   when positive: dust runs down the slope of a pile until side-by-side cells
   differ by at most ``repose`` (0 levels the dust flat; larger values leave
   steeper piles), and spills over edges, to fall in the next step. An
   overfull source also pushes ``min(floor(k * (d(c) - 1)), floor(room(up) /
   5))`` into the non-wall cell above it (against ``a*``): a packed hole
   overflows upward and the dust spills over its rim. A cell receives from at
   most five sources (four sides and below), each bounded by a fifth of its
   room, and ``k <= 0.2`` keeps a source's outflow within ``d(c)``. (A fifth of
   a room under 5 fixed-point units rounds to 0, so an overfull cell walled in
   by cells that full can keep an excess of a few units, < 1e-4 cells.)
3. **Tool push** (``push_search`` [cells]). Every cell whose centre is
   strictly inside the tool sphere (distance < radius) is emptied into one
   cell just outside it, radially: the first cell, for ``t = 0 ..
   push_search - 1``, containing the point at distance ``radius + (t + 1/2)
   * spacing`` from the tool centre along the ray from the centre through the
   cell (straight up, ``-g``, for the centre cell), whose centre is not
   inside the sphere and that is not a wall. If there is none (the tool is
   buried in bone) the dust stays. The push may overfill its targets; rule 2
   of later steps sheds the excess.
4. **Suction** (``suction_rate`` [cells/s]). Every cell whose centre lies
   within the suction radius of the suction tip loses ``min(d, suction_rate
   * dt)``; the amount is counted (:attr:`DustGrid.suctioned_cells`).

Rules 1 and 2 are Jacobi updates: every flux is computed from the densities
at the start of the rule and applied to a second buffer. Rules 3 and 4 only
move dust out of cells they do not write into, so they work in place.

Cost
----
Rules 1-2 visit the bricks that hold dust (their fluxes reach into the face
neighbours); rules 3-4 visit the bricks under the tool and the suction tip.
Within a brick, each direction is one branch-free loop over the cells whose
neighbour lies in the same brick (it vectorizes) plus the 64 cells of the face
toward the neighbour brick.

Wet dust (irrigation)
---------------------
Irrigation makes dust *wet*: it becomes a paste that is mobile. A
:class:`DustGrid` holds two species on the same lattice, dry and wet, each
a density field stepped by the rules above with its own constants: the wet
one with the ``wet_*`` fields of :class:`DustParams` (faster settling and
spilling, no angle of repose), so it drains downhill along gravity, spreads
flat and gathers in the low points, where suction takes it. The two species
do not limit each other's room (water fills the pores of dry dust).

5. **Wetting** (``wetting_rate`` [cells/s]). With an irrigation tip given to
   :meth:`DustGrid.step`, every dry cell whose centre lies within the
   irrigation radius of the tip loses ``min(d, wetting_rate * dt)`` to the
   wet species in the same cell (run after rules 1-4 of the dry species and
   before the wet species' step). Wet dust never dries in this model.

The tool pushes (rule 3) and suction takes (rule 4) both species. Water
(rules 6-9, :mod:`bonesim.physics.dust.water`) carries the wet dust.
Conservation holds for the pair: ``total == added - suctioned`` with
``total`` and ``suctioned`` summed over both (:meth:`DustGrid.totals_q`),
as an exact integer identity.

Sprites
-------
:meth:`DustGrid.sprites` lists what the window draws: one sprite per dusty
cell of the top layer, jittered inside its cell, with its density, the age
of its dust and whether it is wet (see :mod:`bonesim.physics.dust.sprites`); how a
sprite looks is the renderer's business (:meth:`bonesim.render.scene.Scene.set_dust`).

Modules: this one holds the model and its Python API; the kernels live in
:mod:`bonesim.physics.dust.bricks` (storage), :mod:`bonesim.physics.dust.rules` (rules 1-5)
and :mod:`bonesim.physics.dust.sprites` (rendering output).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from bonesim.physics.dust.bricks import (MAX_RATE_Q, MIN_GRAVITY_COMPONENT, N_CTR, N_FP, N_IP, W_ONE,
                                         C_ADDED, C_CUR, C_HW, C_NALIVE, C_NEED, C_NFREE, C_PUSHED, C_SUCKED,
                                         C_SUCKED_STEP, C_WETTED, F_H, F_OX, F_OZ, F_SR, F_SX, F_SZ, F_TR,
                                         F_TX, F_TZ, F_UX, F_UZ, F_WR, F_WX, F_WZ, FULL, I_DOM, I_DSGN, I_GAX,
                                         I_GSG, I_GWQ, I_KQ, I_LAT0, I_LAT1, I_NG, I_RATE, I_REPOSE, I_SEARCH,
                                         I_SRATE, I_SUCTION, I_TOOL, I_WRATE, MAX_SPILL_FRACTION, Q, Q_SHIFT,
                                         STAGE_DONE, STAGE_GRAVITY, ensure_bricks, recycle_bricks,
                                         refresh_bone_bricks, rehash_bricks)
from bonesim.physics.dust.rules import SC_SIZE, add_dust, recount, step_kernel, wet_out
from bonesim.engine import events
from bonesim.engine.bodies import all_identity
from bonesim.physics.dust.bodies import case_cells, wall_arrays
from bonesim.physics.dust.params import DustParams
from bonesim.physics.dust.sprites import DustSprites, gather_sprites, stamp_arrivals
from bonesim.physics.dust.water import step_water
from bonesim.engine.brick_hash import SC_WIDTH, sphere_cells_bound
from bonesim.engine.grid import BRICK_SHIFT, BRICK_VOXELS, gather_box

__all__ = ["DustGrid", "DustParams", "DustSprites", "Q", "Q_SHIFT", "FULL",
           "MAX_SPILL_FRACTION", "warmup"]


# ================================================================ python API
def _vec3(v, name) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {v!r}")
    return a


def _nonneg(v, name) -> float:
    v = float(v)
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be finite and >= 0, got {v}")
    return v


def _to_q(x: float) -> int:
    return int(min(round(x * Q), MAX_RATE_Q))


class DustGrid:
    """Bone dust density on a growing hashed brick grid.

    Parameters
    ----------
    spacing_mm : float
        Cell edge, the bone grid's voxel edge [mm].
    origin_mm : (3,) float
        Case-frame centre of cell (0, 0, 0), the bone grid's origin [mm].
    gravity : (3,) float
        Direction of gravity in the case frame (normalised here).
    params : DustParams, optional
        Model constants (default :class:`DustParams()`).
    bounds_vox : ((3,) int, (3,) int), optional
        Domain ``[lo, hi)`` in cells; dust never moves outside it. Default:
        the volume ``[0, shape)`` of the bone grid first passed to
        :meth:`step`.

    Attributes
    ----------
    spacing_mm : float
        Cell edge [mm].
    origin_mm : (3,) float64
        Centre of cell (0, 0, 0) [mm].
    gravity : (3,) float64
        Unit gravity vector (case frame).
    bounds : (6,) int64
        Domain ``lo, hi`` [cells] (valid once set).
    keys, vals : (table,) int64 / int32
        Brick hash table (``-1`` empty), as in :mod:`bonesim.engine.grid`.
    bcoord : (pool, 3) int32
        Brick coordinates of each pool slot.
    nbr : (pool, 6) int32
        Face neighbours ``-x, +x, -y, +y, -z, +z`` of each brick (-1 absent).
    dens : (2, pool, 512) int32
        The two density buffers, in units of ``1 / Q`` cells;
        ``dens[ctr[C_CUR]]`` is current.
    bmass : (pool,) int64
        Dust per brick [1/Q cells]; 0 means the brick is zero in both buffers.
    time_s : float
        Simulated time, the sum of the steps' ``dt`` [s].
    wet : DustGrid or None
        The wet species (same lattice, the ``wet_*`` constants), made by the
        first irrigated step. The storage attributes above are the dry
        species'; the totals, :meth:`to_dense` and :meth:`sprites` cover both.
    """

    def __init__(self, spacing_mm, origin_mm, gravity, params: DustParams | None = None,
                 *, bounds_vox=None, _wet_species: bool = False):
        self.spacing_mm = _nonneg(spacing_mm, "spacing_mm")
        if not self.spacing_mm > 0:
            raise ValueError("spacing_mm must be positive")
        self.origin_mm = _vec3(origin_mm, "origin_mm")
        self.params = DustParams() if params is None else params
        if not isinstance(self.params, DustParams):
            raise TypeError("params must be a DustParams")
        self.bounds = np.zeros(6, dtype=np.int64)
        self._bounds_set = False
        self.wet = self.water = None        # species: wet dust, irrigation water
        if bounds_vox is not None:
            self.set_bounds(*bounds_vox)
        self._ip = np.zeros(N_IP, dtype=np.int64)
        self._fp = np.zeros(N_FP, dtype=np.float64)
        self._sc = np.zeros(SC_SIZE, dtype=np.int64)
        self._cells = np.zeros((0, SC_WIDTH), dtype=np.int64)   # sphere_cells scratch
        self._wall = np.zeros(BRICK_VOXELS, dtype=np.uint8)
        self._elig = np.zeros(BRICK_VOXELS, dtype=np.uint8)
        self._flux = np.zeros(BRICK_VOXELS, dtype=np.int64)
        self.set_gravity(gravity)
        self._ctr = np.zeros(N_CTR, dtype=np.int64)
        self._alloc(int(self.params.initial_bricks))
        self._no_bone = (np.full(16, -1, np.int64), np.full(16, -1, np.int32))
        self._bkeys, self._bvals = self._no_bone
        self._bone_src = None
        self._no_bone_dens = np.zeros((1, BRICK_VOXELS), np.float32)
        self.time_s = 0.0
        self._is_wet = bool(_wet_species)
        self._wet_out = (np.zeros((0, 3), np.int64), np.zeros(0, np.int64))

    @classmethod
    def for_grid(cls, grid, gravity, params: DustParams | None = None) -> "DustGrid":
        """A dust grid on ``grid``'s lattice with the domain ``[0, grid.shape)``."""
        return cls(grid.spacing_mm, grid.origin_mm, gravity, params,
                   bounds_vox=((0, 0, 0), grid.shape))

    # ------------------------------------------------------------ settings
    def set_bounds(self, lo, hi) -> None:
        """Set the domain ``[lo, hi)`` [cells]."""
        lo = np.asarray(lo, dtype=np.int64).reshape(3)
        hi = np.asarray(hi, dtype=np.int64).reshape(3)
        if (hi <= lo).any() or (np.abs(np.concatenate([lo, hi])) >= (1 << 22)).any():
            raise ValueError(f"bad dust domain [{lo}, {hi})")
        self.bounds[:3] = lo
        self.bounds[3:] = hi
        self._bounds_set = True
        if self.wet is not None:
            self.wet.set_bounds(lo, hi)

    def set_gravity(self, gravity) -> None:
        """Set the gravity direction (case frame; any non-zero length)."""
        g = _vec3(gravity, "gravity")
        n = float(np.linalg.norm(g))
        if not n > 0:
            raise ValueError("gravity must be non-zero")
        g = g / n
        self.gravity = g
        ip = self._ip
        dom = int(np.argmax(np.abs(g)))
        ip[I_DOM] = dom
        ip[I_DSGN] = 1 if g[dom] > 0 else -1
        lat = [a for a in range(3) if a != dom]
        ip[I_LAT0], ip[I_LAT1] = lat
        axes = [a for a in range(3) if abs(g[a]) > MIN_GRAVITY_COMPONENT] \
            if self.params.split_gravity else [dom]
        tot = sum(abs(g[a]) for a in axes)
        ip[I_NG] = len(axes)
        for q in range(3):
            ip[I_GAX + q] = ip[I_GSG + q] = ip[I_GWQ + q] = 0
        for q, a in enumerate(axes):
            ip[I_GAX + q] = a
            ip[I_GSG + q] = 1 if g[a] > 0 else -1
            ip[I_GWQ + q] = int(math.floor(abs(g[a]) / tot * W_ONE)) if len(axes) > 1 \
                else W_ONE
        self._fp[F_UX:F_UZ + 1] = -g
        if self.wet is not None:
            self.wet.set_gravity(g)

    # ------------------------------------------------------------ storage
    def _alloc(self, n: int) -> None:
        tcap = 16
        while tcap < 2 * n:
            tcap *= 2
        self.keys = np.full(tcap, -1, dtype=np.int64)
        self.vals = np.full(tcap, -1, dtype=np.int32)
        self.bcoord = np.zeros((n, 3), dtype=np.int32)
        self.nbr = np.full((n, 6), -1, dtype=np.int32)
        self.alive = np.zeros(n, dtype=np.uint8)
        self.dens = np.zeros((2, n, BRICK_VOXELS), dtype=np.int32)
        self.bmass = np.zeros(n, dtype=np.int64)
        self.bone_b = np.full(n, -1, dtype=np.int32)
        self.free = np.arange(n - 1, -1, -1, dtype=np.int32)      # pops 0, 1, 2, ...
        self._active = np.zeros(n, dtype=np.int32)
        self._seen = np.zeros((n, BRICK_VOXELS), dtype=np.float64)
        self._seen_key = np.full(n, -1, dtype=np.int64)
        self._ctr[C_NFREE] = n

    def _grow(self, need: int) -> None:
        """Enlarge the pool so that at least ``need`` bricks are free."""
        old = self.pool_size
        n = max(2 * old, old + need - int(self._ctr[C_NFREE]))
        tcap = 16
        while tcap < 2 * n:
            tcap *= 2
        hw = int(self._ctr[C_HW])
        keys = np.full(tcap, -1, dtype=np.int64)
        vals = np.full(tcap, -1, dtype=np.int32)
        rehash_bricks(keys, vals, self.bcoord, self.alive, hw)
        self.keys, self.vals = keys, vals

        def grown(a, fill, axis=0):
            shape = list(a.shape)
            shape[axis] = n
            out = np.full(shape, fill, dtype=a.dtype)
            idx = [slice(None)] * a.ndim
            idx[axis] = slice(0, old)
            out[tuple(idx)] = a
            return out

        self.bcoord = grown(self.bcoord, 0)
        self.nbr = grown(self.nbr, -1)
        self.alive = grown(self.alive, 0)
        self.dens = grown(self.dens, 0, axis=1)
        self.bmass = grown(self.bmass, 0)
        self.bone_b = grown(self.bone_b, -1)
        self._seen = grown(self._seen, 0.0)
        self._seen_key = grown(self._seen_key, -1)
        nf = int(self._ctr[C_NFREE])
        free = np.zeros(n, dtype=np.int32)
        free[:n - old] = np.arange(n - 1, old - 1, -1, dtype=np.int32)
        free[n - old:n - old + nf] = self.free[:nf]                # old free slots first
        self.free = free
        self._ctr[C_NFREE] = nf + n - old
        self._active = np.zeros(n, dtype=np.int32)

    def _reserve(self, need: int) -> None:
        """Make ``need`` bricks free: recycle dead bricks, else grow."""
        if need <= self._ctr[C_NFREE]:
            return
        recycle_bricks(self.keys, self.vals, self.bcoord, self.nbr, self.alive, self.bmass,
                 self.free, self._ctr)
        if need > self._ctr[C_NFREE]:
            self._grow(need)

    def recycle(self) -> int:
        """Return bricks without dust (and without dusty neighbours) to the pool;
        returns how many."""
        return sum(int(recycle_bricks(g.keys, g.vals, g.bcoord, g.nbr, g.alive, g.bmass, g.free,
                                g._ctr)) for g in self._species())

    def _use_bone(self, grid) -> None:
        """Point the per-brick bone-brick cache at ``grid`` (None: no bone)."""
        src = None if grid is None else grid.keys
        if src is self._bone_src:
            return
        if grid is not None:
            if abs(grid.spacing_mm - self.spacing_mm) > 1e-9 * self.spacing_mm or \
                    not np.allclose(grid.origin_mm, self.origin_mm, rtol=0, atol=1e-9):
                raise ValueError("the bone grid's lattice differs from the dust grid's "
                                 "(spacing_mm / origin_mm)")
            self._bkeys, self._bvals = grid.keys, grid.vals
        else:
            self._bkeys, self._bvals = self._no_bone
        self._bone_src = src
        refresh_bone_bricks(self.bcoord, self.alive, int(self._ctr[C_HW]), self._bkeys,
                             self._bvals, self.bone_b)

    # ------------------------------------------------------------ queries
    @property
    def pool_size(self) -> int:
        """Bricks allocated in memory (alive or free)."""
        return int(self.bcoord.shape[0])

    def _species(self):
        return (self,) if self.wet is None else (self, self.wet)

    @property
    def n_bricks(self) -> int:
        """Bricks in the table (both species)."""
        return sum(int(g._ctr[C_NALIVE]) for g in self._species())

    @property
    def n_active_bricks(self) -> int:
        """Bricks holding dust (both species)."""
        return sum(int(np.count_nonzero(g.bmass[:int(g._ctr[C_HW])]))
                   for g in self._species())

    @property
    def density_q(self) -> np.ndarray:
        """The current buffer (pool, 512) int32 [1/Q cells] of the dry
        species (a view)."""
        return self.dens[int(self._ctr[C_CUR])]

    def _own_mass_q(self) -> int:
        return int(self.bmass[:int(self._ctr[C_HW])].sum())

    def totals_q(self) -> tuple[int, int, int]:
        """``(total, added, suctioned)`` dust [1/Q cells], exact integers over
        both species; ``total == added - suctioned`` always."""
        total = sum(g._own_mass_q() for g in self._species())
        sucked = sum(int(g._ctr[C_SUCKED]) for g in self._species())
        return total, int(self._ctr[C_ADDED]), sucked

    def recount_q(self) -> int:
        """Total dust summed cell by cell [1/Q cells] (checks the per-brick totals)."""
        return sum(int(recount(g.alive, int(g._ctr[C_HW]), g.density_q))
                   for g in self._species())

    @property
    def total_cells(self) -> float:
        """Dust present, both species [cells] (times ``spacing_mm**3`` for mm^3)."""
        return self.totals_q()[0] / Q

    @property
    def wet_cells(self) -> float:
        """Wet dust present [cells]."""
        return 0.0 if self.wet is None else self.wet._own_mass_q() / Q

    @property
    def wetted_cells(self) -> float:
        """Dry dust turned wet by irrigation so far [cells]."""
        return int(self._ctr[C_WETTED]) / Q

    @property
    def added_cells(self) -> float:
        """Dust added so far [cells]."""
        return int(self._ctr[C_ADDED]) / Q

    @property
    def suctioned_cells(self) -> float:
        """Dust removed by suction so far, both species [cells]."""
        return self.totals_q()[2] / Q

    @property
    def last_pushed_cells(self) -> float:
        """Dust the tool pushed out of its sphere in the last step [cells]."""
        return sum(int(g._ctr[C_PUSHED]) for g in self._species()) / Q

    def to_dense(self, lo=None, shape=None, species: str = "all") -> np.ndarray:
        """Dense copy of a box of densities [cells] (float64, exact).

        Parameters
        ----------
        lo : (3,) int, optional
            First cell of the box (default the domain's ``lo``).
        shape : (3,) int, optional
            Box extent [cells] (default the domain's extent).
        species : {"all", "dry", "wet"}
            Which dust: both species summed, or one.
        """
        if species not in ("all", "dry", "wet"):
            raise ValueError(f"species must be 'all', 'dry' or 'wet', got {species!r}")
        if lo is None or shape is None:
            if not self._bounds_set:
                raise ValueError("give lo and shape: the domain is not set yet")
        lo = self.bounds[:3] if lo is None else np.asarray(lo, dtype=np.int64).reshape(3)
        shape = tuple(self.bounds[3:] - self.bounds[:3]) if shape is None else shape
        total = np.zeros(tuple(int(s) for s in shape), dtype=np.int64)
        grids = {"all": self._species(), "dry": (self,),
                 "wet": () if self.wet is None else (self.wet,)}[species]
        for g in grids:
            out = np.zeros(total.shape, dtype=np.int32)
            gather_box(g.keys, g.vals, g.density_q, out, *map(int, lo))
            total += out
        return total.astype(np.float64) / Q

    def sprites(self, threshold: float | None = None, *, top_only: bool = True,
                jitter: float | None = None) -> DustSprites:
        """Dusty cells for rendering as soft translucent sprites (both species).

        Parameters
        ----------
        threshold : float, optional
            Cells holding more than this are returned [cells] (default
            ``params.sprite_threshold``).
        top_only : bool
            Only cells whose neighbour above (against gravity's dominant
            axis) holds less than ``params.sprite_cover``: the top layer.
        jitter : float, optional
            Largest offset from the cell centre along each axis [cell
            edges] (default ``params.sprite_jitter``; 0: cell centres).

        Returns
        -------
        DustSprites
            ``positions, density, cell_mm, age_s, wet`` (dry sprites first).
            Calling this also updates the cells' arrival times (see
            :mod:`bonesim.physics.dust.sprites`), at the simulated time
            :attr:`time_s`.
        """
        p = self.params
        thr = p.sprite_threshold if threshold is None else _nonneg(threshold, "threshold")
        jit = p.sprite_jitter if jitter is None else _nonneg(jitter, "jitter")
        if jit > 0.5:
            raise ValueError(f"jitter must lie in [0, 0.5] cell edges, got {jit}")
        tq = int(math.floor(thr * Q))
        cover = int(math.floor(p.sprite_cover * Q))
        return gather_sprites(self._species(), tq, cover, int(self._ip[I_DOM]),
                              int(self._ip[I_DSGN]), bool(top_only), float(self.time_s),
                              self.origin_mm, self.spacing_mm, jit)

    def note_arrivals(self, top_only: bool = True) -> int:
        """Update the cells' arrival times as :meth:`sprites` does, at
        :attr:`time_s`, without gathering the sprites (a tenth of the cost:
        for stepping through a recording whose frames are not drawn).

        Returns
        -------
        int
            How many sprites :meth:`sprites` would return.
        """
        p = self.params
        return stamp_arrivals(self._species(), int(math.floor(p.sprite_threshold * Q)),
                              int(math.floor(p.sprite_cover * Q)), int(self._ip[I_DOM]),
                              int(self._ip[I_DSGN]), bool(top_only), float(self.time_s))

    # ------------------------------------------------------------ updates
    def add_removed(self, ijk, amount=None, *, body=None, bodies=None) -> None:
        """Turn removed bone into dust in its cell.

        Parameters
        ----------
        ijk : (n, 3) int
            Removed voxels (e.g. the ``ijk`` column of the ``removed`` ring),
            each in its body's frame; repeats add up.
        amount : float or (n,) float, optional
            Dust per voxel [cells] (default ``params.bulking``), in [0, 64].
        body : (n,) int, optional
            The body of each removal (the events' ``body`` column); None: the
            voxels are in the case frame.
        bodies : Bodies or State, optional
            The body arrays (``pose_m``, ``pose``, ``alive`` are read). A
            removal of a body at a pose other than the identity lands in the
            case-frame cell of its centre; one that lands outside the domain
            is dropped (see the module docstring).
        """
        ijk = np.asarray(ijk)
        if ijk.size == 0:
            return
        if ijk.ndim != 2 or ijk.shape[1] != 3 or not np.issubdtype(ijk.dtype, np.integer):
            raise ValueError(f"ijk must be an (n, 3) integer array, got {ijk.shape} "
                             f"{ijk.dtype}")
        if np.abs(ijk).max() >= (1 << 22):
            raise ValueError("cell coordinates out of range")
        ijk = np.ascontiguousarray(ijk, dtype=np.int64)
        amt = self.params.bulking if amount is None else amount
        amt = np.broadcast_to(np.asarray(amt, dtype=np.float64), (len(ijk),))
        if body is not None and not all_identity(bodies):
            ijk, amt = case_cells(ijk, amt, body, bodies, self.origin_mm, self.spacing_mm,
                                  self.bounds if self._bounds_set else None)
            if len(ijk) == 0:
                return
        if self._bounds_set:
            lo, hi = self.bounds[:3], self.bounds[3:]
            if ((ijk < lo) | (ijk >= hi)).any():
                raise ValueError("dust added outside the domain")
        if not np.isfinite(amt).all() or (amt < 0).any() or (amt > 64).any():
            raise ValueError("amount must lie in [0, 64] cells per voxel")
        amount_q = np.round(amt * Q).astype(np.int64)
        self._add_q(ijk, amount_q)

    def drain(self, cursor, amount=None, bodies=None) -> int:
        """Add the dust of every removal a cursor on a tissue-event ring has
        not seen yet (see :mod:`bonesim.engine.events`); returns how many voxels.

        ``bodies`` (the consumer's body arrays, e.g. its replica's state)
        places the removals of moved bodies in the case frame
        (:meth:`add_removed`); the poses are those ``bodies`` holds now."""
        rec = events.removals(cursor.drain())
        self.add_removed(rec["ijk"], amount, body=rec["body"], bodies=bodies)
        return int(len(rec["ijk"]))

    def step(self, bone_grid, dt, tool_pos_mm=None, tool_radius_mm=0.0,
             suction_pos_mm=None, suction_radius_mm=0.0, suction_rate=None,
             irrigation_pos_mm=None, irrigation_radius_mm=0.0, bodies=None) -> float:
        """Advance the dust by ``dt``: gravity, spilling, tool push, suction,
        wetting (both species).

        Parameters
        ----------
        bone_grid : bonesim.engine.grid.Grid or None
            Current bone (cells with density > 0 are walls); same lattice.
            None: no bone.
        dt : float
            Step [s], >= 0.
        tool_pos_mm : (3,) float, optional
            Burr centre [mm]; no push if None.
        tool_radius_mm : float
            Burr radius [mm].
        suction_pos_mm : (3,) float, optional
            Suction tip [mm]; no suction if None.
        suction_radius_mm : float
            Suction reach [mm].
        suction_rate : float, optional
            Dust removed per second from each cell in reach [cells/s]
            (default ``params.suction_rate``).
        irrigation_pos_mm : (3,) float, optional
            Where the irrigation water lands and pours [mm]; none if None.
        irrigation_radius_mm : float
            Radius of the irrigated region [mm].
        bodies : Bodies or State, optional
            The bone's body arrays (``body`` laid out like the bone grid's
            density, ``pose``, ``alive``). Only the bone of bodies at the
            identity pose is a wall; moved bodies are not (module
            docstring). None, or every body at the identity: all bone is.

        Returns
        -------
        float
            Dust removed by suction in this step, both species [cells].
        """
        dt = _nonneg(dt, "dt")
        irrigate = irrigation_pos_mm is not None
        if irrigate:
            wpos = _vec3(irrigation_pos_mm, "irrigation_pos_mm")
            wrad = _nonneg(irrigation_radius_mm, "irrigation_radius_mm")
            if self._is_wet:
                raise ValueError("the wet species is not irrigated")
        walls = wall_arrays(bone_grid, bodies)
        sucked = self._step_own(bone_grid, dt, tool_pos_mm, tool_radius_mm, suction_pos_mm,
                                suction_radius_mm, suction_rate, walls)
        if irrigate and wrad > 0:
            self._wet_grid()
            self._irrigate(wpos, wrad, dt)
        step_water(self, bone_grid, walls, dt, wpos if irrigate else None, tool_pos_mm,
                   tool_radius_mm, suction_pos_mm, suction_radius_mm)   # rules 6-9
        if self.wet is not None:
            sucked += self.wet._step_own(bone_grid, dt, tool_pos_mm, tool_radius_mm,
                                         suction_pos_mm, suction_radius_mm, suction_rate,
                                         walls)
            self.wet.time_s = self.time_s
        return sucked

    def _wet_grid(self) -> "DustGrid":
        """The wet species, made on first use."""
        if self.wet is None:
            p = self.params
            wp = replace(p, settle_rate=p.wet_settle_rate, spill_rate=p.wet_spill_rate,
                         repose=p.wet_repose)
            w = DustGrid(self.spacing_mm, self.origin_mm, self.gravity, wp,
                         _wet_species=True)
            if self._bounds_set:
                w.set_bounds(self.bounds[:3], self.bounds[3:])
            w.time_s = self.time_s
            self.wet = w
        return self.wet

    def _irrigate(self, pos, rad, dt) -> None:
        """Rule 5: move dry dust within ``rad`` of ``pos`` to the wet species."""
        n_box = self._sphere_scratch(rad)
        if self._wet_out[1].shape[0] < n_box:
            self._wet_out = (np.zeros((n_box, 3), np.int64), np.zeros(n_box, np.int64))
        ip, fp = self._ip, self._fp
        ip[I_WRATE] = _to_q(self.params.wetting_rate * dt)
        fp[F_WX:F_WZ + 1] = pos
        fp[F_WR] = rad
        out_ijk, out_q = self._wet_out
        n = int(wet_out(self.keys, self.vals, self.dens, self.bmass, self._ctr, ip, fp,
                         self._cells, out_ijk, out_q))
        if n:
            self.wet._add_q(out_ijk[:n], out_q[:n])

    def _sphere_scratch(self, *radii_mm) -> int:
        """Grow the scratch of the sphere walk for spheres of these radii
        [mm]; returns the rows one may fill."""
        n = max(sphere_cells_bound(r, self.spacing_mm) for r in radii_mm)
        if self._cells.shape[0] < n:
            self._cells = np.zeros((n, SC_WIDTH), dtype=np.int64)
        return n

    def _add_q(self, ijk, amount_q) -> None:
        """Add ``amount_q`` [1/Q cells] to cells ``ijk`` (n, 3) int64 (valid)."""
        coords = np.unique(ijk >> BRICK_SHIFT, axis=0)
        while True:
            need = ensure_bricks(self.keys, self.vals, self.bcoord, self.nbr, self.alive,
                                  self.dens, self.bmass, self.bone_b, self.free, self._ctr,
                                  self._bkeys, self._bvals, coords)
            if not need:
                break
            self._reserve(int(need))
        add_dust(self.keys, self.vals, self.dens, self.bmass, self._ctr, ijk, amount_q)

    def _step_own(self, bone_grid, dt, tool_pos_mm, tool_radius_mm, suction_pos_mm,
                  suction_radius_mm, suction_rate, walls) -> float:
        """Rules 1-4 on this species alone."""
        if not self._bounds_set:
            if bone_grid is None:
                raise ValueError("no domain: pass bounds_vox or a bone grid")
            self.set_bounds((0, 0, 0), bone_grid.shape)
        self._use_bone(bone_grid)
        bone_dens = self._no_bone_dens if bone_grid is None else bone_grid.density
        p = self.params
        ip, fp = self._ip, self._fp
        ip[I_RATE] = _to_q(p.settle_rate * dt)
        ip[I_KQ] = int(math.floor(min(p.spill_rate * dt, MAX_SPILL_FRACTION) * W_ONE))
        ip[I_REPOSE] = _to_q(p.repose)
        ip[I_SEARCH] = int(p.push_search)
        rate = p.suction_rate if suction_rate is None else _nonneg(suction_rate,
                                                                  "suction_rate")
        ip[I_SRATE] = _to_q(rate * dt)
        ip[I_TOOL] = 0 if tool_pos_mm is None else 1
        if tool_pos_mm is not None:
            fp[F_TX:F_TZ + 1] = _vec3(tool_pos_mm, "tool_pos_mm")
            fp[F_TR] = _nonneg(tool_radius_mm, "tool_radius_mm")
        ip[I_SUCTION] = 0 if suction_pos_mm is None else 1
        if suction_pos_mm is not None:
            fp[F_SX:F_SZ + 1] = _vec3(suction_pos_mm, "suction_pos_mm")
            fp[F_SR] = _nonneg(suction_radius_mm, "suction_radius_mm")
        fp[F_OX:F_OZ + 1] = self.origin_mm
        fp[F_H] = self.spacing_mm
        self._sphere_scratch(fp[F_TR] if ip[I_TOOL] else 0.0,
                             fp[F_SR] if ip[I_SUCTION] else 0.0)
        stage = STAGE_GRAVITY
        while True:
            stage = step_kernel(stage, self.keys, self.vals, self.bcoord, self.nbr,
                                 self.alive, self.dens, self.bmass, self.bone_b, self.free,
                                 self._ctr, self._bkeys, self._bvals, bone_dens,
                                 walls[0], walls[1], self._active, self.bounds, ip, fp, self._sc,
                                 self._wall, self._elig, self._flux, self._cells)
            if stage == STAGE_DONE:
                break
            self._reserve(int(self._ctr[C_NEED]))
        self.time_s += dt
        return int(self._ctr[C_SUCKED_STEP]) / Q


def warmup() -> None:
    """Compile (or load from the cache) every kernel of this module.

    The step is compiled for a writable bone density array (the run's
    :class:`~bonesim.engine.model.State` grid); a read-only one (e.g. the
    :class:`~bonesim.engine.model.Model`'s initial grid) is another numba type and
    compiles its own specialization (~10 s) on first use.
    """
    from bonesim.engine.grid import Grid

    lab = np.zeros((20, 20, 20), dtype=np.uint8)
    lab[:, :, :3] = 1
    for grid in (Grid.from_dense(lab, spacing_mm=0.5), None):
        dust = DustGrid(0.5, (0.0, 0.0, 0.0), (0.0, 0.0, -1.0),
                        DustParams(initial_bricks=1), bounds_vox=((0, 0, 0), (20, 20, 20)))
        dust.add_removed(np.array([[5, 5, 9], [9, 9, 9]], dtype=np.int32))
        for _ in range(3):
            dust.step(grid, 0.01, (2.5, 2.5, 4.5), 1.0, (4.5, 4.5, 4.5), 1.0,
                      irrigation_pos_mm=(3.0, 3.0, 4.5), irrigation_radius_mm=2.0)
        dust.sprites()
        dust.to_dense()
        dust.recount_q()
        dust.recycle()
