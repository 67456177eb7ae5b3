"""Volume-sampled drill haptics: forces, tangential drag and bone removal.

The burr is a sphere of radius ``r`` [mm] discretized into a lattice of
*samples* finer than the bone grid (spacing ``h = voxel / oversample`` [mm];
oversample 2 by default). Sample offsets are stored in the **tool frame**
(``z`` along the drill axis ``d``), so every per-sample quantity that depends
only on the geometry of the burr is precomputed once (no trigonometry in the
loop):

``unit``
    unit vector from the tool centre toward the sample, ``o / |o|``;
``tang``
    ``(p - s_c) x d`` in the tool frame, i.e. ``(o_y, -o_x, 0)`` [mm]: the
    sample's lever arm about the axis turned along the spin;
``lat``
    the latitude removal weight ``max(0, R_max - falloff * |pi/2 - theta|)``
    [1/(N s)], with ``theta`` the angle between ``d`` and ``o``; the equator
    (``theta = pi/2``) removes most, the poles least.

One haptic step with the tool centre ``t_c`` and unit axis ``d``
(:func:`haptic_kernel`):

1. every sample ``s = t_c + R o`` (``R`` the tool-to-case rotation) that lies
   in a voxel with density > 0 is *immersed*; it adds the **unit** vector from
   ``s`` toward ``t_c`` (``-R unit``) weighted by its material's stiffness
   factor ``w``; the immersed volume is ``V = h^3 sum w`` [mm^3];
2. **multi-gain** magnitude ``|F| = K_low V`` for ``V <= V_t``, else
   ``K_low V_t + K_high (V - V_t)`` [N] (gains in N/mm^3, ``V_t`` a fraction of
   the burr volume), clamped to the smaller of the burr's and the device's
   maximum force; the normal force is ``|F|`` along the summed direction;
3. while the drill runs, a **tangential** drag ``K_tan h^3 sigma phi R sum w
   tang`` [N] is added (``sigma = +1`` forward, ``-1`` reverse, ``phi`` the
   speed relative to the burr's default speed); the total is clamped again;
4. while the drill runs, each immersed sample removes
   ``f lat m phi dt h^3 / voxel^3`` density from its voxel (``f`` the applied
   force magnitude from step 2, ``m`` the material's removal factor). A voxel
   whose density reaches 0 is removed and published to the ``removed`` ring;
   a voxel that only lost density is published (once) to the ``touched`` ring.
5. structures whose material emits injuries get an injury record on contact
   onset (drill running) and on every step that removes their voxels.

All state the kernel touches is passed as plain arrays; the kernel allocates
nothing and is deterministic (same inputs, bit-identical grid).

Recorded sessions replay bit for bit, so the kernel's speed comes only from
work that changes no float result (tested against a frozen copy of the
per-sample kernel, ``tests/bonesim/engine/haptics_previous.py``): the part of
a sample's voxel coordinate shared by its lattice row, ``(c + r o_x) + r
o_y``, is computed once per row (the same operations in the same order);
the dirty-voxel list is written without a data-dependent branch (the entry is
written, and kept by counting it); contact counts are summed per run of one
label; the block is gathered by runs of voxels within a brick; indices are
unsigned (no negative-index wrapping) and the removal finds a voxel's
coordinates without integer division. Every sum still adds its nonzero terms
in sample order.

This kernel (and the row kernel of :mod:`bonesim.engine.haptics_rows`) runs
where ``voxel / oversample`` is at least the budget's finest lattice spacing
(``bonesim/data/haptics.toml``); on finer bone the fixed-budget step of
:mod:`bonesim.engine.haptics_budget` takes over, whose cost does not grow
with ``(r / voxel)^3``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from bonesim.engine.events import CONTACT as _EV_CONTACT
from bonesim.engine.events import INJURY as _EV_INJURY
from bonesim.engine.events import REMOVED as _EV_REMOVED
from bonesim.engine.grid import BRICK, BRICK_MASK, BRICK_SHIFT, find_brick, voxel_offset

__all__ = ["P_K_LOW", "P_K_HIGH", "P_V_T", "P_K_TAN", "P_MAX_FORCE", "P_H3",
           "P_INV_VOXEL_VOL", "P_RADIUS", "N_PARAMS", "O_FX", "O_FY", "O_FZ", "O_TX",
           "O_TY", "O_TZ", "O_MAG", "O_VOLUME", "O_N_IMMERSED", "O_N_REMOVED",
           "O_N_TOUCHED", "N_OUT", "MIN_DIRECTION", "Stencil", "make_stencil", "block_size",
           "block_bricks", "tool_frame", "multi_gain", "haptic_kernel"]

# Layout of the float64 ``params`` vector handed to the kernel.
(P_K_LOW, P_K_HIGH, P_V_T, P_K_TAN, P_MAX_FORCE, P_H3, P_INV_VOXEL_VOL,
 P_RADIUS) = range(8)
N_PARAMS = 8
# Layout of the float64 ``out`` vector the kernel fills.
(O_FX, O_FY, O_FZ, O_TX, O_TY, O_TZ, O_MAG, O_VOLUME, O_N_IMMERSED, O_N_REMOVED,
 O_N_TOUCHED) = range(11)
N_OUT = 11
# Directions whose summed unit contributions are shorter than this (relative
# to the number of immersed samples) are treated as having no direction: the
# burr is enclosed symmetrically and pushes nowhere in particular.
MIN_DIRECTION = 1e-9


@dataclass(frozen=True)
class Stencil:
    """Precomputed samples of a spherical burr in the tool frame.

    The kernel reads one packed float32 row per sample (20 bytes, so the
    stencil of the 7 mm burr stays in cache); the float64 views below hold
    the same values, for references and analysis.

    Attributes
    ----------
    offsets : (n, 3) float64
        Sample positions relative to the tool centre, tool frame (z = axis) [mm].
    inv_r : (n,) float64
        ``1 / |offsets|`` [1/mm] (rounded to float32, as the kernel uses it).
    lat : (n,) float64
        Latitude removal weight ``max(0, r_max - falloff |pi/2 - theta|)``
        [1/(N s)] (rounded to float32).
    packed : (n, 5) float32
        Rows ``(o_x, o_y, o_z, 1/|o|, lat)`` for :func:`haptic_kernel`.
    spacing_mm : float
        Lattice spacing ``h`` [mm].
    radius_mm : float
        Burr radius [mm].
    row_head : (n_rows, 3) float64
        The samples as lattice rows along the tool axis ``z`` (the order of
        ``offsets``: consecutive samples with equal ``(o_x, o_y)``): each row's
        ``(o_x, o_y, o_z of its first sample)`` [mm] (rounded to float32 as
        in ``packed``); its samples sit ``h`` apart along ``z``.
    row_off : (n_rows, 2) int64
        Per row, ``(start, n)``: its ``n`` samples' prefix sums are
        ``row_sums[start:start + n + 1]``.
    row_sums : (m, 3) float64
        Prefix sums over a row's samples of ``(1/|o|, o_z/|o|, lat)``
        (float32-rounded values as in ``packed``), starting with a zero
        entry: the sums over samples ``a..b-1`` of row ``r`` are
        ``row_sums[start + b] - row_sums[start + a]``. Rows that are mirror
        images about the axis (equal ``|o_x|, |o_y|`` in either order) have
        the same sums and share one block (about 1/8 of ``n + n_rows``
        entries, so that the table stays in cache). For
        :func:`bonesim.engine.haptics_rows.haptic_rows_kernel`.
    """

    offsets: np.ndarray
    inv_r: np.ndarray
    lat: np.ndarray
    packed: np.ndarray
    spacing_mm: float
    radius_mm: float
    row_head: np.ndarray = None
    row_off: np.ndarray = None
    row_sums: np.ndarray = None

    @property
    def n_rows(self) -> int:
        return int(self.row_head.shape[0])

    @property
    def n(self) -> int:
        return int(self.offsets.shape[0])

    @property
    def unit(self) -> np.ndarray:
        """(n, 3) unit vectors from the tool centre toward each sample."""
        return self.offsets * self.inv_r[:, None]

    @property
    def tang(self) -> np.ndarray:
        """(n, 3) ``(p - s_c) x d = (o_y, -o_x, 0)`` in the tool frame [mm]."""
        o = self.offsets
        return np.stack([o[:, 1], -o[:, 0], np.zeros(len(o))], axis=1)

    @property
    def sample_volume_mm3(self) -> float:
        return self.spacing_mm ** 3

    @property
    def volume_mm3(self) -> float:
        """Volume the samples stand for, ``n h^3`` [mm^3]."""
        return self.n * self.sample_volume_mm3


def make_stencil(radius_mm: float, spacing_mm: float, r_max: float,
                 falloff: float) -> Stencil:
    """Sample a spherical burr on a cubic lattice.

    Lattice points sit at ``h (n + 1/2)`` along each tool-frame axis, so the
    samples are symmetric about the centre and none lies on it.

    Parameters
    ----------
    radius_mm : float
        Burr radius [mm].
    spacing_mm : float
        Lattice spacing ``h`` [mm], usually ``voxel / oversample``.
    r_max : float
        Removal rate per unit force at the equator [1/(N s)].
    falloff : float
        Loss of removal rate per radian away from the equator [1/(N s rad)].
    """
    if not radius_mm > 0 or not spacing_mm > 0:
        raise ValueError("radius and spacing must be positive")
    if r_max < 0 or falloff < 0:
        raise ValueError("r_max and falloff must be non-negative")
    m = int(np.ceil(radius_mm / spacing_mm))
    ax = (np.arange(-m, m) + 0.5) * spacing_mm
    g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1).reshape(-1, 3)
    r = np.linalg.norm(g, axis=1)
    keep = r <= radius_mm
    if not keep.any():
        raise ValueError("burr smaller than one sample; raise the oversampling")
    g, r = g[keep], r[keep]
    theta = np.arccos(np.clip(g[:, 2] / r, -1.0, 1.0))
    lat = np.maximum(0.0, r_max - falloff * np.abs(np.pi / 2 - theta))
    packed = np.empty((len(g), 5), dtype=np.float32)
    packed[:, :3] = g
    packed[:, 3] = 1.0 / r
    packed[:, 4] = lat
    arrs = [packed[:, :3].astype(np.float64), packed[:, 3].astype(np.float64),
            packed[:, 4].astype(np.float64), packed]
    arrs += _stencil_rows(g, arrs[1], arrs[2])
    for a in arrs:
        a.flags.writeable = False
    return Stencil(*arrs[:4], spacing_mm=float(spacing_mm), radius_mm=float(radius_mm),
                   row_head=arrs[4], row_off=arrs[5], row_sums=arrs[6])


def _stencil_rows(g: np.ndarray, inv_r: np.ndarray, lat: np.ndarray) -> list:
    """The samples ``g`` (n, 3) [mm], ordered x, y, then z (as the lattice is
    built), as rows along z with prefix sums shared by the rows that are
    mirror images about the axis (see :class:`Stencil`)."""
    n = len(g)
    new_row = np.ones(n, dtype=bool)
    new_row[1:] = (g[1:, 0] != g[:-1, 0]) | (g[1:, 1] != g[:-1, 1])
    starts = np.flatnonzero(new_row)
    lengths = np.diff(np.append(starts, n))
    head = g[starts].astype(np.float32).astype(np.float64)   # as in ``packed``
    vals = np.stack([inv_r, g[:, 2].astype(np.float32) * inv_r, lat], axis=1)
    # (|o_x|, |o_y|) in either order: the same samples along z up to a mirror
    # in x, y (so the same 1/|o|, o_z/|o| and latitude)
    key = np.sort(np.abs(head[:, :2]), axis=1)
    shared = {}
    blocks = []
    off = np.zeros((len(starts), 2), dtype=np.int64)
    at = 0
    for r, (a, ln) in enumerate(zip(starts, lengths)):
        k = (float(key[r, 0]), float(key[r, 1]))
        if k not in shared:
            block = np.zeros((ln + 1, 3))
            block[1:] = np.cumsum(vals[a:a + ln], axis=0)
            shared[k] = at
            blocks.append(block)
            at += ln + 1
        off[r] = shared[k], ln
    return [head, off, np.concatenate(blocks)]


def block_size(radius_mm: float, voxel_mm: float) -> tuple[int, int]:
    """Scratch sizes for a burr: local voxel block edge and brick block edge."""
    n_vox = int(np.ceil(2 * radius_mm / voxel_mm)) + 3
    n_brick = n_vox // 8 + 2
    return n_vox, n_brick


@njit(cache=True, nogil=True)
def tool_frame(axis, R):
    """Fill ``R`` (3x3) with the tool-to-case rotation for a unit ``axis``.

    Columns are ``u, v, d`` with ``d = axis`` and ``u, v`` a deterministic
    right-handed perpendicular pair (the burr is a sphere, so the spin angle
    about ``d`` is immaterial).
    """
    dx, dy, dz = axis[0], axis[1], axis[2]
    if abs(dx) < 0.9:
        ex, ey, ez = 1.0, 0.0, 0.0
    else:
        ex, ey, ez = 0.0, 1.0, 0.0
    # u = normalize(e x d)
    ux = ey * dz - ez * dy
    uy = ez * dx - ex * dz
    uz = ex * dy - ey * dx
    n = np.sqrt(ux * ux + uy * uy + uz * uz)
    ux /= n
    uy /= n
    uz /= n
    # v = d x u
    vx = dy * uz - dz * uy
    vy = dz * ux - dx * uz
    vz = dx * uy - dy * ux
    R[0, 0], R[1, 0], R[2, 0] = ux, uy, uz
    R[0, 1], R[1, 1], R[2, 1] = vx, vy, vz
    R[0, 2], R[1, 2], R[2, 2] = dx, dy, dz


@njit(cache=True, nogil=True)
def multi_gain(volume, k_low, k_high, v_t):
    """Force magnitude [N] for an immersed volume [mm^3] (two-gain curve)."""
    if volume <= v_t:
        return k_low * volume
    return k_low * v_t + k_high * (volume - v_t)


@njit(cache=True, nogil=True, inline="always")
def block_bricks(keys, vals, pos, radius, origin, spacing, lbrick):
    """Find the bricks of the local voxel block around a burr.

    The block's first voxel is ``lo = round((pos - radius - origin) /
    spacing) - 1`` per axis; ``lbrick[x, y, z]`` receives the brick index
    (-1 for none) of the brick ``(lo >> BRICK_SHIFT) + (x, y, z)``.

    Returns
    -------
    lo0, lo1, lo2 : int
        First voxel of the block [voxels].
    any_brick : bool
        Some brick of the block is allocated.
    """
    lo0 = int(np.floor((pos[0] - radius - origin[0]) / spacing + 0.5)) - 1
    lo1 = int(np.floor((pos[1] - radius - origin[1]) / spacing + 0.5)) - 1
    lo2 = int(np.floor((pos[2] - radius - origin[2]) / spacing + 0.5)) - 1
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    nbk = lbrick.shape[0]
    any_brick = False
    for x in range(nbk):
        for y in range(nbk):
            for z in range(nbk):
                b = find_brick(keys, vals, b0 + x, b1 + y, b2 + z)
                lbrick[x, y, z] = b
                if b >= 0:
                    any_brick = True
    return lo0, lo1, lo2, any_brick


@njit(cache=True, nogil=True, inline="always")
def _gather(density, label, body, group, gsel, lo0, lo1, lo2, b0, b1, b2, n_vox, lbrick,
            ldens, llab):
    """Copy the burr's block of voxels into dense local scratch: density (0
    where the voxel's body is not in group ``gsel``; ``gsel < 0``: every
    body) and label."""
    nn = n_vox * n_vox
    for x in range(n_vox):
        i = lo0 + x
        bx = (i >> BRICK_SHIFT) - b0
        for y in range(n_vox):
            j = lo1 + y
            by = (j >> BRICK_SHIFT) - b1
            base = x * nn + y * n_vox
            # a column of the block crosses a few bricks; inside one its
            # voxels are consecutive (k is the fastest offset): copy by runs
            jo = voxel_offset(i, j, 0)
            z = 0
            while z < n_vox:
                k = lo2 + z
                kk = k & BRICK_MASK
                run = min(BRICK - kk, n_vox - z)
                b = lbrick[bx, by, (k >> BRICK_SHIFT) - b2]
                # (unsigned indices: no negative-index wrapping in the copy)
                at = np.uint64(base + z)
                if b < 0:
                    for q in range(np.uint64(run)):
                        ldens[at + q] = 0.0
                        llab[at + q] = 0
                elif gsel < 0:
                    off = np.uint64(jo | kk)
                    ub = np.uint64(b)
                    for q in range(np.uint64(run)):
                        ldens[at + q] = density[ub, off + q]
                        llab[at + q] = label[ub, off + q]
                else:
                    # bodies of other groups are not there for this pass
                    off = np.uint64(jo | kk)
                    ub = np.uint64(b)
                    for q in range(np.uint64(run)):
                        d = density[ub, off + q]
                        if d > 0.0 and group[body[ub, off + q]] != gsel:
                            d = np.float32(0.0)
                        ldens[at + q] = d
                        llab[at + q] = label[ub, off + q]
                z += run


@njit(cache=True, nogil=True, inline="always")
def _label_body(lo0, lo1, lo2, b0, b1, b2, n_vox, lbrick, ldens, llab, body, lab):
    """Body of some immersed-candidate voxel of label ``lab`` in the local
    block (rare: only called on a contact onset)."""
    nn = n_vox * n_vox
    for li in range(n_vox * nn):
        if llab[li] == lab and ldens[li] > 0.0:
            i = lo0 + li // nn
            j = lo1 + (li // n_vox) % n_vox
            k = lo2 + li % n_vox
            b = lbrick[(i >> BRICK_SHIFT) - b0, (j >> BRICK_SHIFT) - b1,
                       (k >> BRICK_SHIFT) - b2]
            return body[b, voxel_offset(i, j, k)]
    return 0


@njit(cache=True, nogil=True, inline="always")
def push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                kind, bod, lab, t, i, j, k, n, px, py, pz):
    """Append one tissue event (see :mod:`bonesim.engine.events`); head moves last."""
    h = ev_head[0] & (ev_kind.shape[0] - 1)
    ev_kind[h] = kind
    ev_body[h] = bod
    ev_label[h] = lab
    ev_t[h] = t
    ev_ijk[h, 0], ev_ijk[h, 1], ev_ijk[h, 2] = i, j, k
    ev_n[h] = n
    ev_value[h, 0], ev_value[h, 1], ev_value[h, 2] = px, py, pz
    for q in range(3, ev_value.shape[1]):
        ev_value[h, q] = 0.0
    ev_head[0] += 1


# The start and end of a pass, shared by the per-sample kernel below and the
# row kernel (bonesim.engine.haptics_rows).
@njit(cache=True, nogil=True, inline="always")
def local_frame(pos, origin, spacing, R, lo0, lo1, lo2):
    """The tool centre ``pos`` [mm] in local block voxel coordinates (the
    block's first voxel ``lo0..lo2``), shifted by +1/2 so that truncation
    toward zero rounds to the nearest voxel, and the rotation ``R`` (3, 3)
    over ``spacing`` [mm]: ``(c0, c1, c2, r00, ..., r22)``, the arithmetic
    every per-step kernel does in this order."""
    inv = 1.0 / spacing
    c0 = (pos[0] - origin[0]) * inv + 0.5 - lo0
    c1 = (pos[1] - origin[1]) * inv + 0.5 - lo1
    c2 = (pos[2] - origin[2]) * inv + 0.5 - lo2
    return (c0, c1, c2, R[0, 0] * inv, R[0, 1] * inv, R[0, 2] * inv,
            R[1, 0] * inv, R[1, 1] * inv, R[1, 2] * inv,
            R[2, 0] * inv, R[2, 1] * inv, R[2, 2] * inv)


@njit(cache=True, nogil=True)
def begin_pass(keys, vals, density, label, body, origin, spacing, params, pos, axis, group,
           gsel, first, last, R, n_vox, lbrick, ldens, llab, contact, prev_contact, lost,
           out):
    """Start of a pass (as in :func:`haptic_kernel`): clear the outputs, build
    the tool frame ``R`` and gather the burr's block into ``ldens``/``llab``.

    Returns ``(lo0, lo1, lo2, any_brick)``: the block's first voxel and whether
    any brick is allocated there (if not, the pass is over).
    """
    for q in range(out.shape[0]):
        out[q] = 0.0
    if first:
        for q in range(contact.shape[0]):
            contact[q] = 0
            lost[q] = 0
    tool_frame(axis, R)
    # local block of voxels around the burr
    lo0, lo1, lo2, any_brick = block_bricks(keys, vals, pos, params[P_RADIUS], origin,
                                            spacing, lbrick)
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    if not any_brick:
        if last:
            for q in range(prev_contact.shape[0]):
                prev_contact[q] = 0
        return lo0, lo1, lo2, False
    # gather the block's density and labels into dense local scratch
    _gather(density, label, body, group, gsel, lo0, lo1, lo2, b0, b1, b2, n_vox, lbrick,
            ldens, llab)
    return lo0, lo1, lo2, True


@njit(cache=True, nogil=True)
def remove_voxels(density, label, body, touched_flag, acc, dirty, n_dirty, scale, lo0, lo1,
                  lo2, n_vox, lbrick, t, lost, lab_body, ev_kind, ev_body, ev_label, ev_t,
                  ev_ijk, ev_n, ev_value, ev_head, tch_ijk, tch_head):
    """Voxel removal: take each local voxel's accumulated removal weight
    ``acc[dirty[:n_dirty]]`` times ``scale`` from its density (the weights are
    cleared). A voxel whose density reaches 0 is removed: counted in
    ``lost`` per label (``lab_body``: its body), published as a ``REMOVED``
    event at time ``t`` [s]; one that keeps some density is published once
    in the touched ring (until a consumer clears its flag). ``lo0..lo2`` is
    the local block's first voxel, ``n_vox`` its edge, ``lbrick`` its bricks.

    Returns
    -------
    (int, int)
        Voxels removed and newly touched.
    """
    nn = n_vox * n_vox
    # the local voxel's coordinates without integer division: (li + 1/2) / nn
    # is at least 1/(2 nn) from an integer, far more than the float error
    inv_nn = 1.0 / nn
    inv_n = 1.0 / n_vox
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    n_rem = 0
    n_tch = 0
    tcap = tch_ijk.shape[0] - 1
    for q in range(n_dirty):
        li = np.int64(dirty[q])
        uli = np.uint64(li)                 # (unsigned: no negative-index wrapping)
        amount = acc[uli] * scale
        acc[uli] = 0.0
        if amount <= 0.0:
            continue
        x = int((li + 0.5) * inv_nn)
        yz = li - x * nn
        y = int((yz + 0.5) * inv_n)
        i = lo0 + x
        j = lo1 + y
        k = lo2 + (yz - y * n_vox)
        b = np.uint64(lbrick[(i >> BRICK_SHIFT) - b0, (j >> BRICK_SHIFT) - b1,
                             (k >> BRICK_SHIFT) - b2])
        off = np.uint64(voxel_offset(i, j, k))
        d = density[b, off] - amount
        if d <= 0.0:
            density[b, off] = 0.0
            lab = label[b, off]
            lost[lab] += 1
            bod = body[b, off]
            lab_body[lab] = bod
            push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                        _EV_REMOVED, bod, lab, t, i, j, k, 0, 0.0, 0.0, 0.0)
            n_rem += 1
        else:
            density[b, off] = np.float32(d)
            if touched_flag[b, off] == 0:
                touched_flag[b, off] = 1
                h = tch_head[0] & tcap
                tch_ijk[h, 0], tch_ijk[h, 1], tch_ijk[h, 2] = i, j, k
                tch_head[0] += 1
                n_tch += 1
    return n_rem, n_tch


@njit(cache=True, nogil=True, inline="always")
def force_law(params, R, sux, suy, suz, stx, sty, wsum, n_imm, drill, direction,
              speed_factor, out):
    """The force of a pass from its summed samples (steps 2 and 3 of the
    module docstring), written to ``out``; returns the normal magnitude
    ``|F|`` [N]. One law for every step that samples the burr (this module,
    :mod:`bonesim.engine.haptics_rows`, :mod:`bonesim.engine.haptics_budget`).

    ``sux, suy, suz`` are the stiffness-weighted unit vectors summed in the
    tool frame, ``stx, sty`` the weighted lever ``(o_y, -o_x)`` [mm], ``wsum``
    the weighted count, ``n_imm`` the immersed samples; ``R`` the
    tool-to-case rotation; ``out`` gets force, tangential part, magnitude,
    immersed volume ``wsum h^3`` [mm^3] and ``n_imm``.
    """
    h3 = params[P_H3]
    volume = wsum * h3
    max_force = params[P_MAX_FORCE]
    mag = multi_gain(volume, params[P_K_LOW], params[P_K_HIGH], params[P_V_T])
    if mag > max_force:
        mag = max_force
    # normal force: along minus the summed outward unit vectors, in case frame
    fx = -(R[0, 0] * sux + R[0, 1] * suy + R[0, 2] * suz)
    fy = -(R[1, 0] * sux + R[1, 1] * suy + R[1, 2] * suz)
    fz = -(R[2, 0] * sux + R[2, 1] * suy + R[2, 2] * suz)
    fn = np.sqrt(fx * fx + fy * fy + fz * fz)
    if fn > MIN_DIRECTION * (n_imm + 1):
        fx *= mag / fn
        fy *= mag / fn
        fz *= mag / fn
    else:
        fx = fy = fz = 0.0
    tx = ty = tz = 0.0
    if drill:
        g = params[P_K_TAN] * h3 * direction * speed_factor
        tx = g * (R[0, 0] * stx + R[0, 1] * sty)
        ty = g * (R[1, 0] * stx + R[1, 1] * sty)
        tz = g * (R[2, 0] * stx + R[2, 1] * sty)
    Fx, Fy, Fz = fx + tx, fy + ty, fz + tz
    Fm = np.sqrt(Fx * Fx + Fy * Fy + Fz * Fz)
    if Fm > max_force:
        Fx *= max_force / Fm
        Fy *= max_force / Fm
        Fz *= max_force / Fm
    out[O_FX], out[O_FY], out[O_FZ] = Fx, Fy, Fz
    out[O_TX], out[O_TY], out[O_TZ] = tx, ty, tz
    out[O_MAG] = mag
    out[O_VOLUME] = volume
    out[O_N_IMMERSED] = n_imm
    return mag


@njit(cache=True, nogil=True)
def finish_pass(density, label, body, touched_flag, injury, params, drill, direction,
            speed_factor, dt, t, last, case_pos, R, n_vox, lo0, lo1, lo2, lbrick, ldens,
            llab, acc, dirty, n_dirty, contact, prev_contact, lost, lab_body,
            ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
            tch_ijk, tch_head, out, sux, suy, suz, stx, sty, wsum, n_imm):
    """End of a pass (as in :func:`haptic_kernel`): force from the summed
    samples, removal of the accumulated amounts and the pass's events.

    ``sux, suy, suz`` are the stiffness-weighted unit vectors summed in the
    tool frame, ``stx, sty`` the weighted lever ``(o_y, -o_x)`` [mm], ``wsum``
    the weighted count and ``n_imm`` the immersed samples; ``acc[dirty[:n_dirty]]``
    the removal weights per local voxel (see :func:`haptic_kernel`).
    """
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    h3 = params[P_H3]
    mag = force_law(params, R, sux, suy, suz, stx, sty, wsum, n_imm, drill, direction,
                    speed_factor, out)
    # removal: each immersed sample took lat*m*f*phi*dt of its voxel's share
    scale = mag * speed_factor * dt * h3 * params[P_INV_VOXEL_VOL]
    n_rem, n_tch = remove_voxels(density, label, body, touched_flag, acc, dirty, n_dirty,
                                 scale, lo0, lo1, lo2, n_vox, lbrick, t, lost, lab_body,
                                 ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                                 ev_head, tch_ijk, tch_head)
    out[O_N_REMOVED] = n_rem
    out[O_N_TOUCHED] = n_tch
    if not last:
        return
    # injuries, once per step over all passes
    for lab in range(contact.shape[0]):
        touching = drill and contact[lab] > 0
        if injury[lab]:
            if touching and prev_contact[lab] == 0:
                bod = _label_body(lo0, lo1, lo2, b0, b1, b2, n_vox, lbrick, ldens, llab,
                                  body, lab)
                push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                            ev_head, _EV_CONTACT, bod, lab, t, 0, 0, 0, 0,
                            case_pos[0], case_pos[1], case_pos[2])
            if lost[lab] > 0:
                push_event_kernel(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value,
                            ev_head, _EV_INJURY, lab_body[lab], lab, t, 0, 0, 0, lost[lab],
                            case_pos[0], case_pos[1], case_pos[2])
        prev_contact[lab] = 1 if touching else 0


@njit(cache=True, nogil=True)
def haptic_kernel(keys, vals, density, label, body, touched_flag, origin, spacing,
                  stiff, removal, injury,
                  samples, row_off, params,
                  pos, axis, drill, direction, speed_factor, dt, t,
                  group, gsel, first, last, case_pos,
                  R, n_vox, lbrick, ldens, llab, acc, dirty, contact, prev_contact, lost,
                  lab_body,
                  ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                  tch_ijk, tch_head,
                  out):
    """One haptic pass: force, tangential drag, removal and events.

    A step is one pass per group of bodies that share a pose (one pass when
    the bone is one body, see :func:`bonesim.engine.model.step`). The pass sees only
    the voxels of bodies whose ``group`` is ``gsel``; ``pos`` and ``axis``
    are in those bodies' frame.

    Parameters
    ----------
    keys, vals, density, label : arrays
        The grid (see :mod:`bonesim.engine.grid`); ``density`` is modified in place.
    body : (n_bricks, 512) uint8
        Body id per voxel.
    touched_flag : (n_bricks, 512) uint8
        Set to 1 when a voxel is published to the touched ring.
    origin : (3,) float64
        Case-frame centre of voxel (0, 0, 0) [mm].
    spacing : float
        Voxel edge [mm].
    stiff, removal : (n_labels + 1,) float64
        Per-label stiffness and removal factors.
    injury : (n_labels + 1,) uint8
        1 where touching or removing the label is an injury.
    samples : (n, 5) float32
        The stencil's packed rows ``(o_x, o_y, o_z, 1/|o|, lat)`` (see
        :class:`Stencil`).
    row_off : (n_rows, 2) int64
        The stencil's rows (:attr:`Stencil.row_off`): column 1 is the number
        of consecutive samples of each row (equal ``o_x, o_y``).
    params : (N_PARAMS,) float64
        ``k_low [N/mm^3], k_high [N/mm^3], V_t [mm^3], k_tan [N/mm^4],
        max_force [N], h^3 [mm^3], 1/voxel^3 [1/mm^3], burr radius [mm]``.
    pos : (3,) float64
        Tool centre in the pass's body frame [mm].
    axis : (3,) float64
        Unit drill axis in the pass's body frame.
    drill : bool
        Drill running.
    direction : float
        +1 forward, -1 reverse spin.
    speed_factor : float
        Speed relative to the burr's default speed.
    dt : float
        Step duration [s].
    t : float
        Simulation time at the end of the step [s].
    group : (max_bodies,) int32
        Pass group per body (-1: not in any pass).
    gsel : int
        The group this pass handles; -1 for every voxel (the bone is one body).
    first, last : bool
        First pass of the step (clears the per-label counts) and last pass
        (publishes contact onsets and injuries).
    case_pos : (3,) float64
        Tool centre in the case frame [mm] (recorded with injuries).
    R : (3, 3) float64
        Scratch for the tool frame.
    n_vox : int
        Edge of the local voxel block (see :func:`block_size`).
    lbrick : (nb, nb, nb) int32
        Scratch: brick indices of the burr's neighbourhood.
    ldens : (n_vox**3,) float32
        Scratch: densities of the burr's neighbourhood.
    llab : (n_vox**3,) uint8
        Scratch: labels of the burr's neighbourhood.
    acc : (n_vox**3,) float64
        Scratch accumulator; must be all zero on entry (left zero on exit).
    dirty : (n_vox**3 + 1,) int32
        Scratch list of local voxels with removal (one spare entry: the
        kernel writes the next entry before it knows whether it is kept).
    contact : (n_labels + 1,) int64
        Out: immersed samples per label.
    prev_contact : (n_labels + 1,) uint8
        In/out: 1 where the label was in contact with the drill running.
    lost : (n_labels + 1,) int64
        Out: voxels removed per label (summed over the step's passes).
    lab_body : (n_labels + 1,) int32
        Scratch: the body whose voxels of a label were removed last.
    ev_* : columns of the tissue-event ring and its (1,) int64 head.
    tch_* : the touched ring's column and head.
    out : (N_OUT,) float64
        Out: force ``(fx, fy, fz)`` [N] (including tangential), tangential part
        ``(tx, ty, tz)`` [N], normal magnitude ``|F|`` [N], immersed volume
        [mm^3], immersed samples, voxels removed, voxels touched.
    """
    lo0, lo1, lo2, any_brick = begin_pass(keys, vals, density, label, body, origin, spacing,
                                      params, pos, axis, group, gsel, first, last, R,
                                      n_vox, lbrick, ldens, llab, contact, prev_contact,
                                      lost, out)
    if not any_brick:
        return
    sux = suy = suz = 0.0
    stx = sty = 0.0
    wsum = 0.0
    n_imm = 0
    (c0, c1, c2, r00, r01, r02, r10, r11, r12, r20, r21, r22) = local_frame(
        pos, origin, spacing, R, lo0, lo1, lo2)
    # the samples row by row (consecutive samples with one (o_x, o_y), see
    # Stencil): the part of a sample's voxel coordinate that is the same along
    # its row, ``(c + r o_x) + r o_y``, is computed once per row (the same
    # operations in the same order as per sample, so the same voxel)
    # (indices are unsigned, all being >= 0: no negative-index wrapping)
    s = np.uint64(0)
    n_dirty = np.uint64(0)
    clab = -1                       # label of the current run of immersed samples
    ccnt = 0                        # its length (flushed into ``contact``)
    # that label's stiffness and removal factors, and the lever terms
    # ``w o_y``, ``w o_x`` of the row (the same products as per sample)
    w = 0.0
    rm = 0.0
    woy = 0.0
    wox = 0.0
    for r in range(row_off.shape[0]):
        ox = np.float64(samples[s, 0])
        oy = np.float64(samples[s, 1])
        woy = w * oy
        wox = w * ox
        a0 = c0 + r00 * ox + r01 * oy
        a1 = c1 + r10 * ox + r11 * oy
        a2 = c2 + r20 * ox + r21 * oy
        end = s + np.uint64(row_off[r, 1])
        while s < end:
            oz = np.float64(samples[s, 2])
            li = np.uint64((int(a0 + r02 * oz) * n_vox + int(a1 + r12 * oz)) * n_vox
                           + int(a2 + r22 * oz))
            if ldens[li] > 0.0:
                lab = llab[li]
                if lab != clab:
                    if clab >= 0:
                        contact[clab] += ccnt
                    clab = lab
                    ccnt = 0
                    w = stiff[lab]
                    rm = removal[lab]
                    woy = w * oy
                    wox = w * ox
                ccnt += 1
                n_imm += 1
                wsum += w
                wr = w * np.float64(samples[s, 3])
                sux += wr * ox
                suy += wr * oy
                suz += wr * oz
                stx += woy
                sty -= wox
                if drill:
                    # the voxel's removal weight; a voxel joins ``dirty`` on
                    # its first positive weight (written unconditionally, kept
                    # by counting it: no data-dependent branch)
                    a = np.float64(samples[s, 4]) * rm
                    pos_a = a > 0.0
                    v = acc[li]
                    dirty[n_dirty] = li
                    n_dirty += np.uint64((v == 0.0) & pos_a)
                    # adding +0.0 leaves the (never -0.0) sum as it is
                    acc[li] = v + (a if pos_a else 0.0)
            s += np.uint64(1)
    if clab >= 0:
        contact[clab] += ccnt
    finish_pass(density, label, body, touched_flag, injury, params, drill, direction,
            speed_factor, dt, t, last, case_pos, R, n_vox, lo0, lo1, lo2, lbrick, ldens,
            llab, acc, dirty, n_dirty, contact, prev_contact, lost, lab_body,
            ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
            tch_ijk, tch_head, out, sux, suy, suz, stx, sty, wsum, n_imm)
