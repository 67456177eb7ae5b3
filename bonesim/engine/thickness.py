"""Bone thickness under the burr, by ray casting through the voxel grid.

The drill sound rises in pitch as the bone under the burr gets thin (see
:mod:`bonesim.sound.drill`). This module measures that thickness:

1. **Contacted surface voxels**: voxels with density > 0 whose centre lies
   within ``radius + voxel / 2`` of the burr centre and that have at least one
   empty (density <= 0) voxel among their 26 neighbours.
2. **Inward normal** of each: the density gradient (it points from empty
   space into bone), by central differences averaged over the 3 x 3
   cross-section with Sobel weights (1, 2, 1) x (1, 2, 1), which keeps staircase
   surfaces from snapping normals to the axes. Where the gradient vanishes (a
   sliver one voxel thick, empty on both sides) the direction from the burr
   centre to the voxel centre is used instead (the burr pushes into the bone).
3. **Ray cast**: from the voxel centre ``p`` march along the normal ``n`` in
   steps of ``STEP_FRACTION`` voxel until the sample's voxel (nearest voxel
   centre) is empty, then bisect the last step ``BISECT_ITERS`` times: that is
   the exit distance ``s_out``. March the same way along ``-n`` for the
   entry distance ``s_in``. The thickness is the chord
   ``s_in + s_out`` [mm], capped at ``max_mm``. Bone is ``density > 0``, as
   for the haptic force; a slab ``N`` voxels thick measured along its normal
   gives ``N * voxel`` exactly.
4. **Average** over the contacted surface voxels.

Bodies (:mod:`bonesim.engine.bodies`): given the state's body arrays, the
cast runs once per group of bodies near the burr at one pose (as the haptic
step's passes, :func:`~bonesim.engine.bodies.plan_passes`): the burr centre
is transformed into that group's frame, and only the voxels of its bodies
count as bone (the others read as empty), so the normals and rays live in the
body's frame. The result is the minimum over the groups. When every body
sits at the identity pose (one body until fragments exist) the bodies are
ignored and the figures are exactly those of a single grid.

The march of step 3 is :func:`exit_ray`; with a mask of bone labels it also
says which structure the ray meets where it leaves the bone, which is how
:mod:`bonesim.engine.shading` lets thin bone over the sinus, the dura or a nerve
take on that structure's colour.

Cost: the box around the burr is copied once into a dense scratch array
(one hash lookup per brick) for the surface test and the normals; each ray
takes ``thickness / (STEP_FRACTION * voxel)`` samples plus the bisection,
with a hash lookup only when it enters another brick. Measured at 0.5 mm
voxels on a 2-core machine shared with other jobs: 7 mm burr pressed 1 mm
into bone, 60 to 110 us on a 2 mm plate and 110 to 140 us on thick bone
(rays run to ``max_mm`` = 10 mm); a 5 mm burr at first contact, 15 to 30 us.
Passing ``max_mm`` just above the burr's ``thin_bone_mm`` (all the sound
needs) shortens the rays in thick bone. That is affordable every haptic step
but more than the sound needs: calling it every few milliseconds is plenty. It reads the grid without
locks; a voxel removed meanwhile changes one sample, never crashes.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.bodies import all_identity, plan_passes, to_body_frame
from bonesim.engine.grid import BRICK, BRICK_SHIFT, find_brick, voxel_offset

__all__ = ["STEP_FRACTION", "BISECT_ITERS", "MIN_GRADIENT", "NO_CONTACT",
           "ThicknessBuffers", "bone_thickness_mm", "contact_thickness", "thickness_kernel",
           "box_half_width", "exit_ray", "warmup"]

#: Ray-marching step as a fraction of the voxel edge.
STEP_FRACTION = 0.25
#: Bisection steps refining where a ray leaves the bone (the exit is then
#: known to ``STEP_FRACTION * voxel / 2**BISECT_ITERS``).
BISECT_ITERS = 10
#: Gradients shorter than this (density units per voxel, Sobel-weighted sum
#: of 9 central differences) count as zero: the fallback direction is used.
MIN_GRADIENT = 1e-6
#: What :func:`bone_thickness_mm` returns when no surface voxel is in contact
#: (no thin-bone effect: infinitely thick).
NO_CONTACT = math.inf
_SOBEL = (1.0, 2.0, 1.0)
# "no brick cached yet" marker of the ray's brick cache
_NO_BRICK = -2


_NO_LABELS = np.zeros((1, 1), dtype=np.uint8)    # label / bone arrays of the tissue-only ray
_ALL_BONE = np.ones(1, dtype=np.uint8)


@njit(cache=True, nogil=True)
def _march(keys, vals, density, label, bone, use_bone, body, group, gsel, origin, inv_h, px,
           py, pz, nx, ny, nz, step, max_mm, structures_only):
    # exit_ray; with gsel >= 0 only voxels whose body is in group gsel
    # (group[body] == gsel) are tissue, the others empty
    if step >= max_mm:
        return max_mm, 0
    cbi = cbj = cbk = np.int64(0)
    cb = np.int64(_NO_BRICK)
    lo = 0.0
    hi = step
    marching = True
    met = 0
    iters = 0
    while True:
        t = hi if marching else 0.5 * (lo + hi)
        i = int(math.floor((px + t * nx - origin[0]) * inv_h + 0.5))
        j = int(math.floor((py + t * ny - origin[1]) * inv_h + 0.5))
        k = int(math.floor((pz + t * nz - origin[2]) * inv_h + 0.5))
        bi, bj, bk = i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT
        if bi != cbi or bj != cbj or bk != cbk or cb == _NO_BRICK:
            cbi, cbj, cbk = bi, bj, bk
            cb = np.int64(find_brick(keys, vals, bi, bj, bk))
        inside = False
        lab = 0
        if cb >= 0:
            o = voxel_offset(i, j, k)
            if density[cb, o] > 0.0 and (gsel < 0 or group[body[cb, o]] == gsel):
                inside = True
                if use_bone:
                    lab = np.int64(label[cb, o])
                    inside = bone[lab] != 0
        if marching:
            if inside:
                lo = hi
                hi += step
                if hi >= max_mm:
                    return max_mm, 0
            else:
                if structures_only and lab == 0:
                    return max_mm, 0
                marching = False
                met = lab
        else:
            if inside:
                lo = t
            else:
                hi = t
            iters += 1
            if iters == BISECT_ITERS:
                return 0.5 * (lo + hi), met


@njit(cache=True, nogil=True)
def exit_ray(keys, vals, density, label, bone, use_bone, origin, inv_h, px, py, pz,
             nx, ny, nz, step, max_mm, structures_only=False):
    """March from ``p`` along ``n`` until the ray leaves the bone.

    Samples are taken every ``step`` [mm]; a sample is *in bone* when its
    voxel (nearest voxel centre) has density > 0 and, if ``use_bone``, a
    label ``l`` with ``bone[l] != 0``. At the first sample not in bone the
    last step is bisected ``BISECT_ITERS`` times. Every sample lies at a
    distance below ``max_mm`` from ``p``. The brick of the last sample is
    cached: consecutive samples mostly share it.

    Parameters
    ----------
    keys, vals, density, label
        The grid's hash table and per-brick arrays (``label`` is read only
        if ``use_bone``).
    bone : (n_labels + 1,) uint8
        1 for the labels that count as bone (read only if ``use_bone``).
    use_bone : bool
        False: any tissue (density > 0) counts, as for the drill sound.
    origin : (3,) float64
        Centre of voxel (0, 0, 0) [mm].
    inv_h : float
        1 / voxel edge [1/mm].
    px, py, pz : float
        Start [mm] (inside bone).
    nx, ny, nz : float
        Unit direction.
    step, max_mm : float
        Marching step and longest distance [mm].
    structures_only : bool
        If the ray leaves the bone into empty space, return ``(max_mm, 0)``
        at once (for a caller that only cares about structures beneath).

    Returns
    -------
    distance : float
        Where the ray leaves the bone [mm], or ``max_mm`` if it does not
        before.
    met : int
        Label of the voxel of the first sample not in bone if that voxel is
        occupied (density > 0), else 0 (empty space, or no exit before
        ``max_mm``).
    """
    return _march(keys, vals, density, label, bone, use_bone, _NO_BODY, _NO_GROUP, -1, origin,
                  inv_h, px, py, pz, nx, ny, nz, step, max_mm, structures_only)


@njit(cache=True, nogil=True)
def _exit_distance(keys, vals, density, origin, inv_h, px, py, pz, nx, ny, nz, step,
                   max_mm):
    """Distance [mm] along ``n`` from ``p`` (inside tissue) to where the ray
    leaves the tissue (density > 0), or ``max_mm`` if it does not within
    that distance (:func:`exit_ray` without labels)."""
    d, _ = exit_ray(keys, vals, density, _NO_LABELS, _ALL_BONE, False, origin, inv_h,
                    px, py, pz, nx, ny, nz, step, max_mm)
    return d


@njit(cache=True, nogil=True)
def _exit_selected(keys, vals, density, body, group, gsel, origin, inv_h, px, py, pz,
                   nx, ny, nz, step, max_mm):
    """:func:`_exit_distance` reading only the voxels whose body is in group
    ``gsel`` (``group[body] == gsel``) as tissue; the others are empty."""
    d, _ = _march(keys, vals, density, _NO_LABELS, _ALL_BONE, False, body, group, gsel, origin,
                  inv_h, px, py, pz, nx, ny, nz, step, max_mm, False)
    return d


@njit(cache=True, nogil=True)
def _gather_box(keys, vals, density, body, group, gsel, i0, j0, k0, local):
    """Copy the densities of the box starting at voxel ``(i0, j0, k0)`` into
    ``local`` (0 where no brick, and, if ``gsel >= 0``, where the voxel's body
    is not in group ``gsel``), one hash lookup per brick."""
    n0, n1, n2 = local.shape
    local[:] = 0.0
    for bi in range(i0 >> BRICK_SHIFT, ((i0 + n0 - 1) >> BRICK_SHIFT) + 1):
        ia, ib = max(i0, bi * BRICK), min(i0 + n0, bi * BRICK + BRICK)
        for bj in range(j0 >> BRICK_SHIFT, ((j0 + n1 - 1) >> BRICK_SHIFT) + 1):
            ja, jb = max(j0, bj * BRICK), min(j0 + n1, bj * BRICK + BRICK)
            for bk in range(k0 >> BRICK_SHIFT, ((k0 + n2 - 1) >> BRICK_SHIFT) + 1):
                b = find_brick(keys, vals, bi, bj, bk)
                if b < 0:
                    continue
                ka, kb = max(k0, bk * BRICK), min(k0 + n2, bk * BRICK + BRICK)
                for i in range(ia, ib):
                    for j in range(ja, jb):
                        for k in range(ka, kb):
                            o = voxel_offset(i, j, k)
                            if gsel < 0 or group[body[b, o]] == gsel:
                                local[i - i0, j - j0, k - k0] = density[b, o]


def box_half_width(radius_mm: float, spacing_mm: float) -> int:
    """Half-width [voxels] of the box, centred on the voxel nearest the burr
    centre, holding every voxel whose centre is within ``radius + voxel / 2``
    of the burr centre (which is within half a voxel of that voxel's centre
    on each axis): ``floor(radius / voxel) + 1``."""
    return int(math.floor(radius_mm / spacing_mm + 1e-9)) + 1


@njit(cache=True, nogil=True)
def thickness_kernel(keys, vals, density, body, group, gsel, origin, spacing, centre,
                     radius, max_mm, local, out_ijk, out_normal, out_thick):
    """Ray-cast thickness at every contacted surface voxel.

    Parameters
    ----------
    keys, vals, density
        The grid's hash table and per-brick densities (see :mod:`bonesim.engine.grid`).
    body : (n_bricks, 512) uint8
        Body id per voxel (read only if ``gsel >= 0``).
    group : (max_bodies,) int32
        Group of each body (read only if ``gsel >= 0``).
    gsel : int
        Only voxels whose body's group is ``gsel`` are tissue; -1: every
        voxel (the bodies are ignored).
    origin : (3,) float64
        Centre of voxel (0, 0, 0) [mm], in the frame of the bodies read.
    spacing : float
        Voxel edge [mm].
    centre : (3,) float64
        Burr centre [mm], in the frame of the bodies read.
    radius : float
        Burr radius [mm].
    max_mm : float
        Longest chord measured [mm].
    local : (w + 2, w + 2, w + 2) float64
        Scratch for a dense copy of the box scanned around the burr plus a
        one-voxel rim; ``w = 2 h + 1`` with ``h`` the box's half-width,
        at least :func:`box_half_width` ``(radius, spacing)``.
    out_ijk : (m, 3) int32
        Receives the contacted voxels; ``m >= w**3``.
    out_normal : (m, 3) float64
        Receives the unit inward normals.
    out_thick : (m,) float64
        Receives the thickness per voxel [mm].

    Returns
    -------
    int
        Number of contacted surface voxels written.
    """
    inv_h = 1.0 / spacing
    reach = radius + 0.5 * spacing
    reach2 = reach * reach
    step = STEP_FRACTION * spacing
    m = (local.shape[0] - 3) // 2
    ci = int(math.floor((centre[0] - origin[0]) * inv_h + 0.5))
    cj = int(math.floor((centre[1] - origin[1]) * inv_h + 0.5))
    ck = int(math.floor((centre[2] - origin[2]) * inv_h + 0.5))
    # local[x, y, z] is voxel (ci - m - 1 + x, ...)
    lo_i, lo_j, lo_k = ci - m - 1, cj - m - 1, ck - m - 1
    _gather_box(keys, vals, density, body, group, gsel, lo_i, lo_j, lo_k, local)
    count = 0
    for x in range(1, 2 * m + 2):
        i = lo_i + x
        px = origin[0] + spacing * i
        dx = px - centre[0]
        for y in range(1, 2 * m + 2):
            j = lo_j + y
            py = origin[1] + spacing * j
            dy = py - centre[1]
            for z in range(1, 2 * m + 2):
                k = lo_k + z
                pz = origin[2] + spacing * k
                dz = pz - centre[2]
                if dx * dx + dy * dy + dz * dz > reach2:
                    continue
                if not local[x, y, z] > 0.0:
                    continue
                surface = False
                for a in range(x - 1, x + 2):
                    for b in range(y - 1, y + 2):
                        for c in range(z - 1, z + 2):
                            if not local[a, b, c] > 0.0:
                                surface = True
                if not surface:
                    continue
                gx = 0.0
                gy = 0.0
                gz = 0.0
                for u in range(3):
                    for v in range(3):
                        w = _SOBEL[u] * _SOBEL[v]
                        gx += w * (local[x + 1, y + u - 1, z + v - 1]
                                   - local[x - 1, y + u - 1, z + v - 1])
                        gy += w * (local[x + u - 1, y + 1, z + v - 1]
                                   - local[x + u - 1, y - 1, z + v - 1])
                        gz += w * (local[x + u - 1, y + v - 1, z + 1]
                                   - local[x + u - 1, y + v - 1, z - 1])
                g = math.sqrt(gx * gx + gy * gy + gz * gz)
                if g > MIN_GRADIENT:
                    nx, ny, nz = gx / g, gy / g, gz / g
                else:
                    r = math.sqrt(dx * dx + dy * dy + dz * dz)
                    if r > 0.0:
                        nx, ny, nz = dx / r, dy / r, dz / r
                    else:
                        nx, ny, nz = 0.0, 0.0, 1.0
                if gsel < 0:
                    s_out = _exit_distance(keys, vals, density, origin, inv_h, px, py, pz,
                                           nx, ny, nz, step, max_mm)
                    s_back = _exit_distance(keys, vals, density, origin, inv_h, px, py,
                                            pz, -nx, -ny, -nz, step, max_mm)
                else:
                    s_out = _exit_selected(keys, vals, density, body, group, gsel, origin,
                                           inv_h, px, py, pz, nx, ny, nz, step, max_mm)
                    s_back = _exit_selected(keys, vals, density, body, group, gsel, origin,
                                            inv_h, px, py, pz, -nx, -ny, -nz, step, max_mm)
                out_ijk[count, 0] = i
                out_ijk[count, 1] = j
                out_ijk[count, 2] = k
                out_normal[count, 0] = nx
                out_normal[count, 1] = ny
                out_normal[count, 2] = nz
                out_thick[count] = min(s_out + s_back, max_mm)
                count += 1
    return count


def _check(grid, centre_mm, radius_mm, max_mm):
    c = np.asarray(centre_mm, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.isfinite(c).all():
        raise ValueError(f"centre_mm must be 3 finite numbers, got {centre_mm!r}")
    radius_mm = float(radius_mm)
    if not (math.isfinite(radius_mm) and radius_mm >= 0.0):
        raise ValueError(f"radius_mm must be finite and >= 0, got {radius_mm!r}")
    max_mm = float(max_mm)
    if not (math.isfinite(max_mm) and max_mm > 0.0):
        raise ValueError(f"max_mm must be finite and > 0, got {max_mm!r}")
    return c, radius_mm, max_mm, box_half_width(radius_mm, grid.spacing_mm)


class ThicknessBuffers:
    """Output buffers for :func:`bone_thickness_mm`, grown on demand and
    reused, so that steady calls allocate nothing large. One per thread."""

    def __init__(self):
        self.half_width = -1
        self.local = self.ijk = self.normal = self.thick = None
        self.group = self.pass_body = self.pass_ident = None

    def fit(self, half_width: int) -> "ThicknessBuffers":
        """Size the buffers for a box of the given half-width [voxels]; return self."""
        if half_width != self.half_width:
            w = 2 * half_width + 1
            self.half_width = half_width
            self.local = np.zeros((w + 2, w + 2, w + 2))
            if self.ijk is None or self.ijk.shape[0] < w ** 3:
                self.ijk = np.zeros((w ** 3, 3), dtype=np.int32)
                self.normal = np.zeros((w ** 3, 3))
                self.thick = np.zeros(w ** 3)
        return self

    def fit_bodies(self, max_bodies: int) -> "ThicknessBuffers":
        """Size the per-body pass plan for ``max_bodies`` bodies; return self."""
        if self.group is None or len(self.group) != max_bodies:
            self.group = np.zeros(max_bodies, np.int32)
            self.pass_body = np.zeros(max_bodies, np.int32)
            self.pass_ident = np.zeros(max_bodies, np.bool_)
        return self


# body and group arrays of the path that ignores bodies (never read)
_NO_BODY = np.zeros((1, 512), dtype=np.uint8)
_NO_GROUP = np.zeros(1, dtype=np.int32)


def _passes(grid, bodies, c, radius_mm, s):
    """``(body, group, gsel, centre, R)`` per cast: one with every voxel when
    all bodies sit at the identity, else one per pose group near the burr
    (its centre in the group's frame, ``R`` its rotation to the case frame,
    None for the identity)."""
    if all_identity(bodies):
        return [(_NO_BODY, _NO_GROUP, -1, c, None)]
    s.fit_bodies(len(bodies.alive))
    n_pass = plan_passes(bodies.alive, bodies.pose, bodies.pose_m, bodies.bounds, c,
                         radius_mm, np.asarray(grid.origin_mm, np.float64),
                         grid.spacing_mm, s.group, s.pass_body, s.pass_ident)
    out = []
    for q in range(n_pass):
        if s.pass_ident[q]:
            out.append((bodies.body, s.group, q, c, None))
        else:
            m = bodies.pose_m[s.pass_body[q]]
            out.append((bodies.body, s.group, q, to_body_frame(m, c), m[:, :3]))
    return out


def contact_thickness(grid, centre_mm, radius_mm: float, max_mm: float = 10.0,
                      bodies=None):
    """Thickness at each contacted surface voxel.

    Parameters
    ----------
    grid : Grid
        The current tissue (``keys, vals, density, origin_mm, spacing_mm``).
    centre_mm : (3,) array_like
        Burr centre, case frame [mm].
    radius_mm : float
        Burr radius [mm].
    max_mm : float
        Longest chord measured [mm]; thicker bone reads ``max_mm``.
    bodies : Bodies or State, optional
        The body arrays (:class:`bonesim.engine.bodies.Bodies`); None: one
        body at the identity pose.

    Returns
    -------
    ijk : (n, 3) int32
        Contacted surface voxels (see the module docstring), each in its own
        body's frame (the body is ``bodies.body`` at that voxel).
    normals : (n, 3) float64
        Unit inward normals used for the rays, case frame.
    thickness : (n,) float64
        Entry-to-exit chord along each normal [mm].
    """
    c, radius_mm, max_mm, half = _check(grid, centre_mm, radius_mm, max_mm)
    s = ThicknessBuffers().fit(half)
    parts = []
    for body, group, gsel, cb, rot in _passes(grid, bodies, c, radius_mm, s):
        n = thickness_kernel(grid.keys, grid.vals, grid.density, body, group, gsel,
                             grid.origin_mm, grid.spacing_mm, cb, radius_mm, max_mm,
                             s.local, s.ijk, s.normal, s.thick)
        nrm = s.normal[:n].copy() if rot is None else s.normal[:n] @ rot.T
        parts.append((s.ijk[:n].copy(), nrm, s.thick[:n].copy()))
    if not parts:
        return np.zeros((0, 3), np.int32), np.zeros((0, 3)), np.zeros(0)
    if len(parts) == 1:
        return parts[0]
    return tuple(np.concatenate(a) for a in zip(*parts))


_SCRATCH = ThicknessBuffers()


def bone_thickness_mm(grid, centre_mm, radius_mm: float, max_mm: float = 10.0,
                      scratch: ThicknessBuffers | None = None, bodies=None) -> float:
    """Mean bone thickness under the burr [mm].

    Parameters
    ----------
    grid : Grid
        The current tissue.
    centre_mm : (3,) array_like
        Burr centre, case frame [mm].
    radius_mm : float
        Burr radius [mm].
    max_mm : float
        Cap on each ray's chord [mm].
    scratch : optional
        Buffers to reuse (:class:`ThicknessBuffers`); by default a
        module-level one, so calls from several threads at once should each
        pass their own.
    bodies : Bodies or State, optional
        The body arrays (``body, pose, pose_m, alive, bounds``, see
        :class:`bonesim.engine.bodies.Bodies`); None or every body at the
        identity pose: the grid is read as one body.

    Returns
    -------
    float
        Mean chord over the contacted surface voxels [mm], the least such
        mean over the pose groups of bodies near the burr, or
        :data:`NO_CONTACT` (``inf``) when the burr touches no surface voxel.
    """
    c, radius_mm, max_mm, half = _check(grid, centre_mm, radius_mm, max_mm)
    s = (scratch or _SCRATCH).fit(half)
    best = NO_CONTACT
    for body, group, gsel, cb, _ in _passes(grid, bodies, c, radius_mm, s):
        n = thickness_kernel(grid.keys, grid.vals, grid.density, body, group, gsel,
                             grid.origin_mm, grid.spacing_mm, cb, radius_mm, max_mm,
                             s.local, s.ijk, s.normal, s.thick)
        if n:
            best = min(best, float(s.thick[:n].mean()))
    return best


def warmup() -> None:
    """Compile the thickness kernel (cached on disk after the first run)."""
    from bonesim.engine.grid import Grid

    labels = np.zeros((8, 8, 8), dtype=np.uint8)
    labels[:, :, :4] = 1
    g = Grid.from_dense(labels, spacing_mm=0.5)
    bone_thickness_mm(g, (2.0, 2.0, 2.2), 1.0)
    body = np.zeros((g.n_bricks, 512), np.uint8)
    bone_thickness_mm(g, (2.0, 2.0, 2.2), 1.0, bodies=_warm_bodies(body))


def _warm_bodies(body):
    """Two bodies, one moved: the per-body path of the kernels."""
    from bonesim.engine.bodies import Bodies, pose_matrix

    pose = np.array([[0.0, 0, 0, 1, 0, 0, 0], [0.1, 0, 0, 1, 0, 0, 0]])
    pose_m = np.stack([pose_matrix(p) for p in pose])
    bounds = np.array([[0, 0, 0, 7, 7, 7]] * 2, np.int32)
    return Bodies(body, pose, pose_m, np.ones(2, np.uint8), bounds)
