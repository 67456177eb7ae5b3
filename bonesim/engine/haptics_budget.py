"""The fixed-budget haptic step: force and removal whose cost does not grow
with (burr radius / voxel size)^3.

:func:`bonesim.engine.haptics.haptic_kernel` samples the burr at ``h = voxel /
oversample`` and gathers the burr's whole voxel block before sampling, so
its cost grows with ``(r / voxel)^3`` (0.19 mm bone: 8x the 0.5 mm samples
and a 40^3 block for the 7 mm burr). Where the bone is finer than the
budget, this step takes over (:class:`Budget`, ``bonesim/data/haptics.toml``):

Force: a fixed sample budget
    The burr's lattice spacing is ``h = max(voxel / oversample,
    min_spacing_mm)``; while ``voxel / oversample >= min_spacing_mm`` the
    budget is not binding and the step is exactly the per-voxel kernel (bit
    for bit: the phantom at 0.5 mm, default oversampling). Where it binds,
    each of the burr's lattice points inside it (about ``4/3 pi (r / h)^3``:
    11,536 for the 7 mm burr, 4,224 for the 5 mm) reads the *fine* voxel it
    lies in through the brick table: one read of the block's brick index
    (``lbrick``, the bricks of :func:`bonesim.engine.haptics.block_bricks`:
    ``(2 r / (8 voxel) + 3)^3`` hash probes, 1/512 of a voxel block, made
    only for the bricks the table did not hold at the previous pass), one
    read of the sample's removal cell's occupancy (an empty cell ends the
    sample: the drilled cavity) and one density read. Nothing is gathered.
    The force law is the per-voxel kernel's, with ``h^3`` per sample.

    Point samples of the fine voxels were chosen over a summarising density
    (counts per brick or per cell): a sample that reads a cell's occupied
    fraction spreads the bone surface over the cell (a 0.4 mm blur at 0.1 mm
    voxels) while a point sample is exact away from the surface and off by
    at most its own cell ``h^3`` at it; both cost one read. The error
    against the exact voxel sum (the bone volume the fine voxels put inside
    the burr): with ``N_h`` the lattice cells (edge ``h``, centred on the
    samples) that the burr's sphere or a bone voxel face cuts, and ``N_v``
    the voxels the sphere cuts,
    ``|V_samples - V_voxels| <= h^3 N_h + voxel^3 N_v`` [mm^3], about
    ``sqrt(3) (h + voxel) (4 pi r^2 + A)`` with ``A`` the bone surface
    inside the burr; the force magnitude is off by at most ``k_high`` times
    that. ``tests/bonesim/engine/test_haptics_budget.py`` checks the bound
    over random poses and resolutions.

Removal: doses per cell, flushed within a budget
    Removal cells are blocks of ``c^3`` fine voxels (``c`` the smallest
    power of two with ``c voxel >= min_spacing_mm``; a brick holds
    ``(8 / c)^3``). While the drill runs, every cell whose centre lies in
    the burr and that holds bone gets the removal law's dose
    ``f lat phi dt`` (``f`` the step's normal force [N], ``lat`` the
    latitude weight at the cell centre, from a table of
    :data:`LAT_TABLE` entries over ``|cos theta|``, ``phi`` the relative
    speed): the cells are a lattice of the grid's, so every fine voxel the
    burr covers gets its dose, however coarse the samples (no uncut
    islands). A cell's dose accumulates in the state (:class:`BudgetState`)
    until it can remove its weakest voxel (``dose >= min density /
    removal factor`` over its voxels, kept per cell); then the cell is
    queued. Every step *flushes* queued cells in order: each of the cell's
    voxels loses ``dose x`` its material's removal factor; a voxel reaching
    0 is removed (``REMOVED`` event, per-label loss for injuries), one that
    keeps density is published to the touched ring. A step flushes at most
    its removal budget of voxels (rounded up to whole cells; the cell in
    hand is finished): what the burr can cut in ``budget_s`` (1 ms) by the
    removal law at the force limit, the highest removal factor, the burr's
    maximum speed and the whole burr immersed, in voxels (the 7 mm burr:
    3.2 mm^3, 461 voxels at 0.19 mm). What exceeds the budget stays queued
    for the next steps, with or without contact, drill on or off; nothing
    is dropped, and the queue is state like the density, so a run replays
    bit for bit. The dose a cell gets is the per-voxel kernel's removal for
    a voxel the burr fully covers (``lat m f phi dt``); removal is resolved
    to the cell (``c voxel``, 0.38 mm at 0.19 mm voxels, 0.4 mm at 0.1 mm)
    rather than the voxel.

    Bodies: a dose belongs to the body of the pass that gave it (the body
    whose frame the pass runs in); a flush removes only voxels of bodies at
    that body's pose. A cell dosed by another pose while it holds a dose is
    flushed at once (a cell on a split face; rare), so no dose is lost.
    The cell's occupancy count and threshold are exact after every flush;
    removal by other means (a cut plane, a shed fragment) only makes them
    stale upward, which costs a flush that finds less, never a missed dose.

The flush's kernels are in :mod:`bonesim.engine.haptics_budget_flush`.
All kernels allocate nothing and are deterministic.

Recorded sessions replay bit for bit, so the step's speed comes only from
work that changes no result (tested against a frozen copy of the kernels
before the speed-up, ``tests/bonesim/engine/haptics_budget_previous.py``):
indices are unsigned (no negative-index wrapping); a sample reads its
voxel's density directly, without first reading its removal cell's
occupancy (a cell counted empty holds no bone: the counts are exact or
stale upward, so the density read skips the same samples); the stiffness
and lever products are computed once per run of one label and its contact
count is added at the run's end; the flush steps voxel offsets within the
cell's brick and keeps its counts in locals; the sample loop is a function
of its own (its values stay in registers) and finds a sample's brick and
place in it from its coordinate in the block (``(x + (lo & 7)) >> 3`` and
``& 7``, the same integers as ``(lo + x) >> 3 - lo >> 3``); the brick table
is kept from pass to pass and moved with the burr (the grid's brick hash
never changes, so the table is a function of the block's first brick); the
rows' first voxel coordinates are computed before the sample loop and its
immersed samples counted by label runs (its sums stay in registers); the
dosing clips a column to the table once and indexes the carried cell arrays
through flat views; the flush finds a cell by shifts, writes a removal's
record in place with the ring head in hand (the head moves last) and counts
the voxels lost by label runs; and the step calls the kernel with one
:class:`StepArgs` of its step-invariant arguments (built once per state,
model and burr) instead of 60 arguments.
Every sum still adds the same terms in sample order.

Where a step's time goes (the phantom's demo path, 5 mm burr, 0.1 mm
voxels, the slowest 2 % of steps, about 55 us): the samples about 23 us
(4,224 of them, near 1,800 immersed), the dosing about 11 us (about 1,000
cells, each a square root and a division for its latitude), the flush about
14 us (its full budget of 1,728 voxels, about 1,250 removed: some 8 us of
it is writing their tissue-event records, ten stores each), the Python
step around the kernel about 4 us. The flush is bounded by the removal
budget, the rest by the burr.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, types
from numba.experimental import structref

from bonesim.engine.events import CONTACT as _EV_CONTACT
from bonesim.engine.events import INJURY as _EV_INJURY
from bonesim.engine.grid import BRICK, BRICK_SHIFT, find_brick
from bonesim.engine.haptics import (P_RADIUS, O_N_REMOVED, O_N_TOUCHED,
                                    force_law, local_frame, push_event_kernel, tool_frame)
from bonesim.engine.haptics_budget_flush import flush_cell, flush_kernel

__all__ = ["LAT_TABLE", "BudgetSettings", "load_budget_settings", "Budget", "make_budget",
           "lattice_spacing", "removal_budget", "lat_table", "BudgetState",
           "make_budget_state", "reset_budget_state", "budget_kernel", "flush_kernel",
           "STEP_FIELDS", "StepArgs", "make_step_args", "budget_step",
           "cell_counts"]

#: Columns of a stencil's packed samples (:attr:`bonesim.engine.haptics.Stencil.packed`:
#: ``o_x, o_y, o_z, 1/|o|, lat``).
_PACKED = 5

#: Entries of the latitude table over ``|cos theta|`` in [0, 1] (linear
#: interpolation; off by < 2e-3 of ``falloff`` from the exact weight, the
#: worst next to the poles where ``asin`` is steep).
LAT_TABLE = 4097


@dataclass(frozen=True)
class BudgetSettings:
    """``bonesim/data/haptics.toml``: ``min_spacing_mm`` [mm] (the finest
    sample lattice) and ``budget_s`` [s] (the time whose worst-case removal
    one step may apply)."""

    min_spacing_mm: float
    budget_s: float


def load_budget_settings(path=None) -> BudgetSettings:
    """Read the budget settings (default: the shipped ``haptics.toml``)."""
    from bonesim.resources import data_path
    from bonesim.tomlfile import get_number, read_toml

    path = data_path("haptics.toml") if path is None else path
    doc = read_toml(path)
    smp = doc.get("sampling", {})
    rem = doc.get("removal", {})
    return BudgetSettings(
        min_spacing_mm=float(get_number(smp, "min_spacing_mm", path, "[sampling]",
                                        minimum=1e-3)),
        budget_s=float(get_number(rem, "budget_s", path, "[removal]", minimum=1e-6)))


def lattice_spacing(voxel_mm: float, oversample: int, settings: BudgetSettings) -> float:
    """The burr's sample spacing [mm]: ``voxel / oversample`` (the very
    float) unless that is finer than ``min_spacing_mm``."""
    h = voxel_mm / oversample
    return h if h >= settings.min_spacing_mm else float(settings.min_spacing_mm)


def removal_budget(burr, voxel_mm: float, cell: int, max_force_n: float,
                   max_removal: float, settings: BudgetSettings) -> int:
    """Voxels one step may flush: the removal law's worst case over
    ``budget_s`` (force at ``max_force_n`` [N], ``r_max``, the highest
    removal factor, maximum over default speed, the whole burr immersed),
    in voxels of ``voxel_mm``; at least one cell of ``cell^3``."""
    # a burr record without a maximum speed (arrays-built models) runs at its default
    phi = getattr(burr, "max_speed_rpm", burr.default_speed_rpm) / burr.default_speed_rpm
    force = max_force_n if math.isfinite(max_force_n) else burr.max_force_n
    volume = 4.0 / 3.0 * math.pi * burr.radius_mm ** 3
    vol = force * burr.r_max * max_removal * phi * volume * settings.budget_s
    return int(max(math.ceil(vol / voxel_mm ** 3), cell ** 3))


def lat_table(r_max: float, falloff: float) -> np.ndarray:
    """(LAT_TABLE,) float64: the latitude weight ``max(0, r_max - falloff
    asin|cos theta|)`` [1/(N s)] at ``|cos theta| = q / (LAT_TABLE - 1)``."""
    x = np.linspace(0.0, 1.0, LAT_TABLE)
    t = np.maximum(0.0, r_max - falloff * np.arcsin(x))
    t.flags.writeable = False
    return t


def cell_counts(density: np.ndarray, label: np.ndarray, removal: np.ndarray,
                cell: int) -> tuple[np.ndarray, np.ndarray]:
    """Per removal cell of every brick: occupied voxels and the dose that
    removes the weakest (``min density / removal factor`` over its occupied
    voxels whose factor is > 0; ``inf`` if none).

    Parameters
    ----------
    density : (n_bricks, 512) float32
    label : (n_bricks, 512) uint8
    removal : (n_labels + 1,) float64
    cell : int
        Cell edge [voxels], a power of two <= 8.

    Returns
    -------
    occ : (n_bricks, (8 / cell)^3) int32
    thr : (n_bricks, (8 / cell)^3) float64
    """
    nb = density.shape[0]
    n = BRICK // cell
    d = density.reshape(nb, n, cell, n, cell, n, cell).transpose(0, 1, 3, 5, 2, 4, 6)
    d = d.reshape(nb, n ** 3, cell ** 3)
    m = np.asarray(removal)[label].reshape(nb, n, cell, n, cell, n, cell)
    m = m.transpose(0, 1, 3, 5, 2, 4, 6).reshape(nb, n ** 3, cell ** 3)
    occ = (d > 0).sum(axis=2).astype(np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where((d > 0) & (m > 0), d.astype(np.float64) / np.where(m > 0, m, 1.0),
                     np.inf)
    return occ, r.min(axis=2) if r.size else np.zeros((nb, n ** 3))


@dataclass(frozen=True)
class Budget:
    """A model's budget (:attr:`bonesim.engine.model.Model.budget`).

    Attributes
    ----------
    settings : BudgetSettings
    binding : bool
        ``voxel / oversample < min_spacing_mm``: the step is the budget step.
    cell : int
        Removal cell edge [voxels] (power of two, <= 8).
    occ0, thr0 : (n_bricks, (8 / cell)^3) int32, float64
        The initial tissue's :func:`cell_counts` (empty when not binding).
    lat : tuple of (LAT_TABLE,) float64
        Each burr's latitude table (:func:`lat_table`).
    removal_voxels : tuple of int
        Each burr's removal budget per step [voxels] (:func:`removal_budget`).
    """

    settings: BudgetSettings
    binding: bool
    cell: int
    occ0: np.ndarray
    thr0: np.ndarray
    lat: tuple = ()
    removal_voxels: tuple = ()

    @property
    def cells_per_brick(self) -> int:
        return (BRICK // self.cell) ** 3

    def with_burrs(self, burrs, voxel_mm, max_force_n, max_removal) -> "Budget":
        """The same budget with ``burrs`` appended to the burr tables."""
        from dataclasses import replace

        lat = tuple(lat_table(b.r_max, b.falloff) for b in burrs)
        rv = tuple(removal_budget(b, voxel_mm, self.cell, min(f, b.max_force_n),
                                  max_removal, self.settings)
                   for b, f in zip(burrs, max_force_n))
        return replace(self, lat=self.lat + lat, removal_voxels=self.removal_voxels + rv)


def make_budget(grid, oversample: int, removal: np.ndarray,
                settings: BudgetSettings | None = None) -> Budget:
    """The budget of a model of ``grid`` (no burrs yet: :meth:`Budget.with_burrs`)."""
    settings = load_budget_settings() if settings is None else settings
    v = float(grid.spacing_mm)
    binding = v / oversample < settings.min_spacing_mm
    cell = 1
    while cell < BRICK and cell * v < settings.min_spacing_mm:
        cell *= 2
    if binding:
        occ0, thr0 = cell_counts(np.asarray(grid.density), np.asarray(grid.label), removal,
                                 cell)
    else:
        occ0, thr0 = np.zeros((0, 1), np.int32), np.zeros((0, 1))
    for a in (occ0, thr0):
        a.flags.writeable = False
    return Budget(settings, bool(binding), int(cell), occ0, thr0)


@dataclass
class BudgetState:
    """The removal carried from step to step (part of the
    :class:`~bonesim.engine.model.State`).

    Attributes
    ----------
    dose : (n_bricks, cpb) float64
        Accumulated removal dose per cell [density per unit removal factor].
    thr : (n_bricks, cpb) float64
        Dose that removes the cell's weakest voxel.
    occ : (n_bricks, cpb) int32
        Occupied voxels per cell (exact after a flush; may be stale upward).
    queued : (n_bricks, cpb) uint8
        1 while the cell waits in the queue.
    rep : (n_bricks, cpb) uint8
        The body whose pass gave the cell its dose.
    queue : (n_bricks * cpb,) int64
        FIFO ring of queued cells (``brick * cpb + cell``).
    qhead : (2,) int64
        Read and write counters of the ring.
    """

    dose: np.ndarray
    thr: np.ndarray
    occ: np.ndarray
    queued: np.ndarray
    rep: np.ndarray
    queue: np.ndarray
    qhead: np.ndarray

    @property
    def pending(self) -> int:
        """Cells waiting in the queue."""
        return int(self.qhead[1] - self.qhead[0])


def make_budget_state(budget: Budget) -> BudgetState:
    """Fresh carried removal for ``budget``'s initial tissue."""
    shape = budget.occ0.shape
    st = BudgetState(dose=np.zeros(shape), thr=np.zeros(shape),
                     occ=np.zeros(shape, np.int32), queued=np.zeros(shape, np.uint8),
                     rep=np.zeros(shape, np.uint8),
                     queue=np.zeros(max(1, shape[0] * shape[1]), np.int64),
                     qhead=np.zeros(2, np.int64))
    reset_budget_state(budget, st)
    return st


def reset_budget_state(budget: Budget, st: BudgetState) -> None:
    """Back to the initial tissue: no dose, nothing queued."""
    st.dose[:] = 0.0
    st.thr[:] = budget.thr0
    st.occ[:] = budget.occ0
    st.queued[:] = 0
    st.rep[:] = 0
    st.queue[:] = 0                  # touched now, not on the first steps
    st.qhead[:] = 0


# ------------------------------------------------------------------ kernels
@njit(cache=True, nogil=True)
def _dose_cells(pos, axis, radius, origin, spacing, scale, lat, lo0, lo1, lo2, lbrick, cell,
                cs, owner, bricks, density, label, body, touched_flag, removal, pose_m, dose,
                thr, occ, queued, rep, queue, qhead, t, lost, lab_body, ev_kind, ev_body,
                ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head, tch_ijk, tch_head, counts):
    """Add ``scale x lat`` to every bone-holding cell whose centre lies in
    the burr; queue the cells whose dose reaches their threshold."""
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    nbk = lbrick.shape[0]
    n = BRICK >> cs
    cpb = dose.shape[1]
    cap = queue.shape[0]
    cw = cell * spacing                       # cell edge [mm]
    half = 0.5 * (cell - 1) * spacing         # cell centre past its first voxel [mm]
    r2 = radius * radius
    nl = lat.shape[0] - 1
    # flat views: cell ``b cpb + cq``
    occ_f, dose_f, thr_f = occ.reshape(occ.size), dose.reshape(dose.size), thr.reshape(thr.size)
    queued_f, rep_f = queued.reshape(queued.size), rep.reshape(rep.size)
    # cell C's centre: origin + cw C + half
    ci_lo = int(np.ceil((pos[0] - radius - origin[0] - half) / cw))
    ci_hi = int(np.floor((pos[0] + radius - origin[0] - half) / cw))
    cj_lo = int(np.ceil((pos[1] - radius - origin[1] - half) / cw))
    cj_hi = int(np.floor((pos[1] + radius - origin[1] - half) / cw))
    for ci in range(ci_lo, ci_hi + 1):
        ox = origin[0] + cw * ci + half - pos[0]
        i0 = ci << cs
        bx = (i0 >> BRICK_SHIFT) - b0
        if bx < 0 or bx >= nbk:
            continue
        for cj in range(cj_lo, cj_hi + 1):
            oy = origin[1] + cw * cj + half - pos[1]
            rz2 = r2 - ox * ox - oy * oy
            if rz2 < 0.0:
                continue
            j0 = cj << cs
            by = (j0 >> BRICK_SHIFT) - b1
            if by < 0 or by >= nbk:
                continue
            rz = np.sqrt(rz2)
            ck_lo = int(np.ceil((pos[2] - rz - origin[2] - half) / cw))
            ck_hi = int(np.floor((pos[2] + rz - origin[2] - half) / cw))
            # the cells of the column in the table: brick ``(ck << cs) >> 3`` in
            # ``b2 .. b2 + nbk - 1`` (a cell lies in one brick)
            ck_a = max(ck_lo, (b2 << BRICK_SHIFT) >> cs)
            ck_b = min(ck_hi, (((b2 + nbk) << BRICK_SHIFT) >> cs) - 1)
            cq_ij = ((((i0 & 7) >> cs) * n) + ((j0 & 7) >> cs)) * n
            for ck in range(ck_a, ck_b + 1):
                k0 = ck << cs
                bz = (k0 >> BRICK_SHIFT) - b2
                b = lbrick[np.uint64(bx), np.uint64(by), np.uint64(bz)]
                if b < 0:
                    continue
                cq = cq_ij + ((k0 & 7) >> cs)
                # (unsigned: no negative-index wrapping)
                f = np.uint64(b * cpb + cq)
                if occ_f[f] <= 0:
                    continue
                oz = origin[2] + cw * ck + half - pos[2]
                rr = np.sqrt(ox * ox + oy * oy + oz * oz)
                u = 0.0
                if rr > 0.0:
                    u = abs(ox * axis[0] + oy * axis[1] + oz * axis[2]) / rr
                    if u > 1.0:
                        u = 1.0
                x = u * nl
                q = int(x)
                if q >= nl:
                    w = lat[nl]
                else:
                    w = lat[q] + (x - q) * (lat[q + 1] - lat[q])
                a = w * scale
                if a <= 0.0:
                    continue
                if dose_f[f] > 0.0 and rep_f[f] != owner:
                    flush_cell(b, cq, cell, cs, bricks, density, label, body, touched_flag,
                               removal, pose_m, dose, thr, occ, rep, t, lost, lab_body,
                               ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                               ev_head, tch_ijk, tch_head, counts)
                rep_f[f] = owner
                dose_f[f] += a
                if queued_f[f] == 0 and dose_f[f] >= thr_f[f]:
                    queued_f[f] = 1
                    queue[qhead[1] % cap] = b * cpb + cq
                    qhead[1] += 1


@njit(cache=True, nogil=True)
def _brick_table(keys, vals, pos, radius, origin, spacing, lbrick, lbkey):
    """:func:`bonesim.engine.haptics.block_bricks`, reusing the table of the
    previous pass: ``lbkey`` holds the first brick ``(b0, b1, b2)`` the table
    ``lbrick`` was filled for, whether it is valid and how many of its
    entries are bricks. The grid's brick hash never changes (only densities
    do), so the table is a function of its first brick alone: the same first
    brick keeps it, a nearby one moves the overlapping entries and looks up
    only the rest. The table and the returned values are exactly
    ``block_bricks``'s."""
    lo0 = int(np.floor((pos[0] - radius - origin[0]) / spacing + 0.5)) - 1
    lo1 = int(np.floor((pos[1] - radius - origin[1]) / spacing + 0.5)) - 1
    lo2 = int(np.floor((pos[2] - radius - origin[2]) / spacing + 0.5)) - 1
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    nbk = lbrick.shape[0]
    d0, d1, d2 = b0 - lbkey[0], b1 - lbkey[1], b2 - lbkey[2]
    if lbkey[3] == 1 and d0 == 0 and d1 == 0 and d2 == 0:
        return lo0, lo1, lo2, lbkey[4] > 0
    near = lbkey[3] == 1 and abs(d0) < nbk and abs(d1) < nbk and abs(d2) < nbk
    n_any = 0
    # in place: each axis is walked in the direction of the move, so an
    # entry is read before it is overwritten
    for xx in range(nbk):
        x = xx if d0 >= 0 else nbk - 1 - xx
        sx = x + d0
        for yy in range(nbk):
            y = yy if d1 >= 0 else nbk - 1 - yy
            sy = y + d1
            for zz in range(nbk):
                z = zz if d2 >= 0 else nbk - 1 - zz
                sz = z + d2
                if (near and 0 <= sx < nbk and 0 <= sy < nbk and 0 <= sz < nbk):
                    b = lbrick[sx, sy, sz]
                else:
                    b = find_brick(keys, vals, b0 + x, b1 + y, b2 + z)
                lbrick[x, y, z] = b
                if b >= 0:
                    n_any += 1
    lbkey[0], lbkey[1], lbkey[2], lbkey[3], lbkey[4] = b0, b1, b2, 1, n_any
    return lo0, lo1, lo2, n_any > 0


@njit(cache=True, nogil=True)
def _sample_rows(lbrick, density, label, body, group, gsel, stiff, samples, row_head, row_off,
                 contact, onset_body, pos, origin, spacing, R, h, lo0, lo1, lo2, row_a):
    """The budget step's samples (see :func:`budget_kernel`): the force sums
    ``(sux, suy, suz, stx, sty, wsum, n_imm)``; ``contact`` and
    ``onset_body`` updated. A function of its own so that the loop's values
    stay in registers."""
    sux = suy = suz = 0.0
    stx = sty = 0.0
    wsum = 0.0
    n_imm = 0
    (c0, c1, c2, r00, r01, r02, r10, r11, r12, r20, r21, r22) = local_frame(
        pos, origin, spacing, R, lo0, lo1, lo2)
    # the lattice's rows along the tool axis: a row's samples sit
    # h apart, so each voxel coordinate is the row's first plus k steps
    d0, d1, d2 = r02 * h, r12 * h, r22 * h
    # a sample's voxel is ``lo + x`` (x its coordinate in the block); its
    # brick in the table is ``(lo + x) >> 3 - lo >> 3 = (x + (lo & 7)) >> 3``
    # and its place in the brick ``(x + (lo & 7)) & 7``. Unsigned indices
    # (no negative-index wrapping): a sample's voxel lies in the block, past
    # its first voxel, and ``b >= 0``
    e0, e1, e2 = lo0 & 7, lo1 & 7, lo2 & 7
    # flat views: a voxel is ``brick * 512 + offset``, a table entry
    # ``(x nbk + y) nbk + z`` (no strides to keep at hand)
    nbk = np.uint64(lbrick.shape[0])
    lbf = lbrick.reshape(lbrick.size)
    dens = density.reshape(density.size)
    labf = label.reshape(label.size)
    bodf = body.reshape(body.size)
    smp = samples.reshape(samples.size)        # rows of _PACKED (a constant stride)
    # the stiffness and lever products change only with the label: one
    # run of a label computes them once and counts its contacts (and the
    # immersed samples) at its end
    run_lab = -1
    run_n = 0
    w = wox = woy = 0.0
    s = 0
    # each row's first voxel coordinates, before the samples (fewer values
    # in hand in their loop)
    for r in range(row_head.shape[0]):
        ox = row_head[r, 0]
        oy = row_head[r, 1]
        oz = row_head[r, 2]
        row_a[r, 0] = c0 + r00 * ox + r01 * oy + r02 * oz
        row_a[r, 1] = c1 + r10 * ox + r11 * oy + r12 * oz
        row_a[r, 2] = c2 + r20 * ox + r21 * oy + r22 * oz
    for r in range(row_head.shape[0]):
        ox = row_head[r, 0]
        oy = row_head[r, 1]
        a0 = row_a[r, 0]
        a1 = row_a[r, 1]
        a2 = row_a[r, 2]
        wox = w * ox
        woy = w * oy
        n = row_off[r, 1]
        us = np.uint64(s)
        for q in range(n):
            ui = np.uint64(int(a0 + d0 * q) + e0)
            uj = np.uint64(int(a1 + d1 * q) + e1)
            uk = np.uint64(int(a2 + d2 * q) + e2)
            b = lbf[((ui >> np.uint64(BRICK_SHIFT)) * nbk + (uj >> np.uint64(BRICK_SHIFT))) * nbk
                    + (uk >> np.uint64(BRICK_SHIFT))]
            if b < 0:
                continue
            v = ((np.uint64(b) << np.uint64(3 * BRICK_SHIFT))
                 | ((ui & np.uint64(7)) << np.uint64(6))
                 | ((uj & np.uint64(7)) << np.uint64(3)) | (uk & np.uint64(7)))
            if dens[v] <= 0.0:
                continue
            if gsel >= 0 and group[bodf[v]] != gsel:
                continue
            lab = labf[v]
            if lab != run_lab:
                if run_n > 0:
                    contact[run_lab] += run_n
                    n_imm += run_n
                run_lab = lab
                run_n = 0
                w = stiff[lab]
                wox = w * ox
                woy = w * oy
                if contact[lab] == 0:
                    onset_body[lab] = bodf[v]
            run_n += 1
            wsum += w
            uq = (us + np.uint64(q)) * np.uint64(_PACKED)
            wr = w * np.float64(smp[uq + np.uint64(3)])
            sux += wr * ox
            suy += wr * oy
            suz += wr * np.float64(smp[uq + np.uint64(2)])
            stx += woy
            sty -= wox
        s += n
    if run_n > 0:
        contact[run_lab] += run_n
        n_imm += run_n
    return sux, suy, suz, stx, sty, wsum, n_imm


@njit(cache=True, nogil=True)
def budget_kernel(keys, vals, bricks, density, label, body, touched_flag, origin, spacing,
                  stiff, removal, injury, samples, row_head, row_off, h, params, lat,
                  budget_vox, cell, cs,
                  pos, axis, drill, direction, speed_factor, dt, t,
                  group, gsel, owner, first, last, case_pos, pose_m,
                  R, lbrick, contact, prev_contact, lost, lab_body, onset_body,
                  dose, thr, occ, queued, rep, queue, qhead, counts,
                  ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                  tch_ijk, tch_head, out, lbkey, row_a):
    """One haptic pass of the fixed-budget step (see the module notes).

    Parameters as :func:`bonesim.engine.haptics.haptic_kernel`, except:

    bricks : (n_bricks, 3) int32
        Brick coordinates (:attr:`bonesim.engine.grid.Grid.bricks`).
    samples : (n, 5) float32
        The budget stencil's packed rows (spacing ``h``; ``params[P_H3]`` is ``h^3``).
    row_head, row_off : arrays
        The stencil's lattice rows along the tool axis
        (:attr:`bonesim.engine.haptics.Stencil.row_head`, ``row_off``): the
        samples are visited row by row, each voxel coordinate stepping by
        ``h`` along the axis (a sample within float rounding of a voxel face
        may land on its other side than a per-sample sum would put it).
    h : float
        The lattice spacing [mm].
    lat : (LAT_TABLE,) float64
        The burr's latitude table (:func:`lat_table`).
    budget_vox : int
        The step's removal budget [voxels] (:func:`removal_budget`).
    cell, cs : int
        Removal cell edge [voxels] and its log2.
    gsel : int
        As the per-voxel kernel's; -2: sample nothing (the step of a burr
        out of every body's reach only flushes).
    owner : int
        The body whose frame this pass runs in (its doses are flushed onto
        the voxels of bodies at its pose).
    pose_m : (max_bodies, 3, 4) float64
        Body poses (equal poses share doses).
    onset_body : (n_labels + 1,) int32
        Scratch: the body of the first immersed sample per label.
    dose, thr, occ, queued, rep, queue, qhead :
        The :class:`BudgetState` arrays (modified).
    counts : (2,) int64
        Scratch.
    lbrick : (nb, nb, nb) int32
        The brick table (as the per-voxel kernel's), kept from pass to pass.
    lbkey : (5,) int64
        What ``lbrick`` holds: its first brick, whether it is filled, how
        many of its entries are bricks (zeros: not filled).
    row_a : (>= n_rows, 3) float64
        Scratch: each lattice row's first voxel coordinates.

    The pass also flushes the queue when ``last`` (once per step).
    """
    for q in range(out.shape[0]):
        out[q] = 0.0
    if first:
        for q in range(contact.shape[0]):
            contact[q] = 0
            lost[q] = 0
    counts[0] = 0
    counts[1] = 0
    tool_frame(axis, R)
    radius = params[P_RADIUS]
    lo0, lo1, lo2, any_brick = _brick_table(keys, vals, pos, radius, origin, spacing, lbrick,
                                            lbkey)
    sux = suy = suz = 0.0
    stx = sty = 0.0
    wsum = 0.0
    n_imm = 0
    if any_brick and gsel != -2:              # -2: a pass that only flushes
        sux, suy, suz, stx, sty, wsum, n_imm = _sample_rows(
            lbrick, density, label, body, group, gsel, stiff, samples, row_head, row_off,
            contact, onset_body, pos, origin, spacing, R, h, lo0, lo1, lo2, row_a)
    # force: the per-voxel kernel's law
    mag = force_law(params, R, sux, suy, suz, stx, sty, wsum, n_imm, drill, direction,
                    speed_factor, out)
    # removal: dose the burr's cells, then flush within the budget
    scale = mag * speed_factor * dt
    if drill and any_brick and n_imm > 0 and scale > 0.0:
        _dose_cells(pos, axis, radius, origin, spacing, scale, lat, lo0, lo1, lo2, lbrick,
                    cell, cs, owner, bricks, density, label, body, touched_flag, removal,
                    pose_m, dose, thr, occ, queued, rep, queue, qhead, t, lost, lab_body,
                    ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                    tch_ijk, tch_head, counts)
    if last:
        flush_kernel(budget_vox, cell, cs, bricks, density, label, body, touched_flag,
                     removal, pose_m, dose, thr, occ, queued, rep, queue, qhead, t, lost,
                     lab_body, ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                     ev_head, tch_ijk, tch_head, counts)
    out[O_N_REMOVED] = counts[0]
    out[O_N_TOUCHED] = counts[1]
    if not last:
        return
    for lab in range(contact.shape[0]):
        touching = drill and contact[lab] > 0
        if injury[lab]:
            if touching and prev_contact[lab] == 0:
                push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                  ev_head, _EV_CONTACT, onset_body[lab], lab, t, 0, 0, 0, 0,
                                  case_pos[0], case_pos[1], case_pos[2])
            if lost[lab] > 0:
                push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                  ev_head, _EV_INJURY, lab_body[lab], lab, t, 0, 0, 0,
                                  lost[lab], case_pos[0], case_pos[1], case_pos[2])
        prev_contact[lab] = 1 if touching else 0


# ------------------------------------------------------- one-argument call
#: :func:`budget_kernel`'s arguments that stay the same from step to step,
#: in its order (those of a pass, ``pos`` .. ``t`` and ``gsel`` .. ``last``,
#: are :func:`budget_step`'s own).
STEP_FIELDS = (
    "keys", "vals", "bricks", "density", "label", "body", "touched_flag", "origin", "spacing",
    "stiff", "removal", "injury", "samples", "row_head", "row_off", "h", "params", "lat",
    "budget_vox", "cell", "cs", "group", "case_pos", "pose_m", "R", "lbrick", "contact",
    "prev_contact", "lost", "lab_body", "onset_body", "dose", "thr", "occ", "queued", "rep",
    "queue", "qhead", "counts", "ev_kind", "ev_body", "ev_label", "ev_t", "ev_ijk", "ev_n",
    "ev_value", "ev_head", "tch_ijk", "tch_head", "out", "lbkey", "row_a")


@structref.register
class _StepArgsType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(typ)) for name, typ in fields)


class StepArgs(structref.StructRefProxy):
    """:func:`budget_kernel`'s step-invariant arguments (:data:`STEP_FIELDS`:
    a state's arrays and a model's tables for one burr) in one object, built
    once by :func:`make_step_args`: :func:`budget_step` takes one argument
    where the kernel takes 60 (numba's call costs about 50 ns an argument)."""

    def __new__(cls, *args):
        return structref.StructRefProxy.__new__(cls, *args)


structref.define_proxy(StepArgs, _StepArgsType, list(STEP_FIELDS))


@njit(cache=True)
def make_step_args(keys, vals, bricks, density, label, body, touched_flag, origin, spacing,
                   stiff, removal, injury, samples, row_head, row_off, h, params, lat,
                   budget_vox, cell, cs, group, case_pos, pose_m, R, lbrick, contact,
                   prev_contact, lost, lab_body, onset_body, dose, thr, occ, queued, rep, queue,
                   qhead, counts, ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                   ev_head, tch_ijk, tch_head, out, lbkey, row_a):
    """A :class:`StepArgs` of :data:`STEP_FIELDS` (compiled once, cached)."""
    return StepArgs(keys, vals, bricks, density, label, body, touched_flag, origin, spacing,
                    stiff, removal, injury, samples, row_head, row_off, h, params, lat,
                    budget_vox, cell, cs, group, case_pos, pose_m, R, lbrick, contact,
                    prev_contact, lost, lab_body, onset_body, dose, thr, occ, queued, rep, queue,
                    qhead, counts, ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                    ev_head, tch_ijk, tch_head, out, lbkey, row_a)


@njit(cache=True, nogil=True)
def budget_step(a, pos, axis, drill, direction, speed_factor, dt, t, gsel, owner, first,
                last):
    """:func:`budget_kernel` with its step-invariant arguments ``a``
    (:class:`StepArgs`) and a pass's own: burr centre and axis, drill,
    direction, speed factor, time step and time, the pass's group, owner
    body, first and last flags."""
    budget_kernel(a.keys, a.vals, a.bricks, a.density, a.label, a.body, a.touched_flag, a.origin,
                  a.spacing, a.stiff, a.removal, a.injury, a.samples, a.row_head, a.row_off, a.h,
                  a.params, a.lat, a.budget_vox, a.cell, a.cs, pos, axis, drill, direction,
                  speed_factor, dt, t, a.group, gsel, owner, first, last, a.case_pos, a.pose_m,
                  a.R, a.lbrick, a.contact, a.prev_contact, a.lost, a.lab_body, a.onset_body,
                  a.dose, a.thr, a.occ, a.queued, a.rep, a.queue, a.qhead, a.counts, a.ev_kind,
                  a.ev_body, a.ev_label, a.ev_t, a.ev_ijk, a.ev_n, a.ev_value, a.ev_head,
                  a.tch_ijk, a.tch_head, a.out, a.lbkey, a.row_a)
