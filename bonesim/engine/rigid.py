"""Rigid motion of bone bodies (fragments) and of plates and distractors.

A **rigid** is either a voxel body other than body 0 (a fragment, see
:mod:`bonesim.engine.bodies`) or a plate / distractor mesh. It lives in a
slot of a :class:`~bonesim.engine.rigid_set.RigidSet` (fixed capacity,
arrays allocated once). Body 0, the anchored case, never moves. Its
*rigid frame* is the body's own frame (fragment) or the mesh's frame
(plate); its pose ``(tx, ty, tz [mm], qw, qx, qy, qz)`` maps that frame to
the case frame, exactly like a body pose.

Contact samples
    Points fixed in the rigid frame with outward unit normals: a fragment's
    surface voxels (voxel centre pushed out by half a voxel along the
    occupancy gradient, :func:`~bonesim.engine.rigid_set.body_samples`), or
    a mesh's vertices pushed out by the plate's sample offset along their
    normals (:func:`~bonesim.engine.rigid_set.mesh_samples`).
    At most :data:`MAX_SAMPLES` per rigid (a deterministic stride keeps the
    rest).
Contact force (:func:`contact`)
    A sample that lies in a voxel with density of another body (at that
    body's pose) is traced back along ``-n`` through that body's voxels
    (an exact voxel walk) to where it leaves the bone: the penetration
    ``d`` [mm] (at most :data:`MAX_DEPTH_VOXELS` voxels). The sample feels
    ``(k d + c v_n) m`` along the bone's outward normal ``m`` there (the
    occupancy gradient of that body's voxels around it; ``-n`` where it has
    none; ``k`` [N/mm] per sample, ``c`` a damping per sample, ``v_n`` the
    sample's speed into the bone; never pulling), at the sample point;
    forces and torques about the centre of mass are summed. (Pushing along
    the bone's normal rather than the sample's lets a fragment landing on an
    edge tip over onto a face instead of sliding away on its bevelled
    samples.)
Friction
    Coulomb friction at the rigid's level, integrated implicitly: with
    ``N`` the summed contact force, the velocity across it and the spin about
    it lose at most what ``FRICTION_COEFF |N|`` (and its torque over half the
    rigid's radius) takes in a substep; a rigid that this stops sticks (it
    rests on slopes up to ``atan(FRICTION_COEFF)``), a harder push slides it.
Motion (:meth:`bonesim.engine.rigid_set.RigidSet.advance`)
    Gravity ``m g`` along the case's gravity direction
    (:data:`GRAVITY_MM_S2`), viscous drag (:data:`DRAG_TIME_S`), contact, the
    tool's push (the reaction to the tool--fragment contact, see
    :func:`tool_push`) and, for a grabbed rigid, a critically damped spring
    toward the tool (:data:`GRAB_HZ`). Semi-implicit Euler with
    :data:`SUBSTEPS` fixed substeps per haptic step; the quaternion is
    renormalized every substep. A rigid whose centre stays within
    :data:`SLEEP_MM` of where it was for :data:`SLEEP_STEPS` steps sleeps
    (costs nothing) until the tool touches or grabs it again (a voxel
    surface makes a resting rigid tremble by far less than that). A
    fragment wakes when the stopped tool first touches it or it is grabbed:
    a piece just cut free stays where it was cut until then. Gyroscopic
    terms are left out (the drag dominates at these sizes); a fragment's
    samples and mass are taken when it first wakes (later drilling of it
    does not change them).

Units inside the kernels: mm, kg, s; force kg mm/s^2 (= 1e-3 N); public
parameters are in N/mm and N.

Every pose change is published as a tissue event from the kernel:
``POSE`` for a fragment (the body's pose, so every replica, the recorder
and replay apply it), :data:`~bonesim.engine.events.PLATE` for a plate.
:meth:`~bonesim.engine.rigid_set.RigidSet.advance` runs between two haptic
steps, at the time of the step that follows (as commands do), so re-stepping a recording with its
recorded poses reproduces it bit for bit. Building a rigid's samples
(waking a fragment for the first time, placing a plate) allocates; the
per-step path does not.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.bodies import near_body_box
from bonesim.engine.events import PLATE, POSE
from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset

__all__ = ["GRAVITY_MM_S2", "DEFAULT_GRAVITY_DIR", "BONE_DENSITY_KG_MM3", "N_TO_INTERNAL",
           "MAX_SAMPLES", "MAX_DEPTH_VOXELS", "SUBSTEPS", "DRAG_TIME_S", "GRAB_HZ",
           "SLEEP_MM", "SLEEP_STEPS", "MAX_SPEED_MM_S", "FRAGMENT_STIFFNESS_N_MM_PER_KG",
           "DAMPING_RATIO", "CONTACT_SHARE", "FRICTION_COEFF",
           "FREE", "ASLEEP", "DYNAMIC", "GRABBED", "AFFIXED", "KIND_FRAGMENT", "KIND_PLATE",
           "gravity_direction", "pose_matrix_into", "contact", "tool_push", "advance_kernel",
           "solid_at", "empty_side"]

#: Standard gravity [mm/s^2].
GRAVITY_MM_S2 = 9810.0
#: Gravity direction of a model without a case (case frame LPS: inferior).
DEFAULT_GRAVITY_DIR = (0.0, 0.0, -1.0)
#: Density of bone for a fragment's mass [kg/mm^3] (cortical bone, 1.9 g/cm^3).
BONE_DENSITY_KG_MM3 = 1.9e-6
#: 1 N in the kernels' force unit kg mm/s^2.
N_TO_INTERNAL = 1000.0
#: Contact samples kept per rigid.
MAX_SAMPLES = 1024
#: Deepest penetration a sample's trace measures [voxels].
MAX_DEPTH_VOXELS = 4.0
#: Fixed substeps per haptic step.
SUBSTEPS = 4
#: Time constant of the viscous drag on linear and angular velocity [s]: a
#: fragment in the irrigated cavity falls at most ``g DRAG_TIME_S`` (about
#: 0.2 m/s), so an impact never drives it deep into the bone.
DRAG_TIME_S = 0.02
#: Natural frequency of the spring that pulls a grabbed rigid to the tool [Hz].
GRAB_HZ = 25.0
#: A rigid whose centre stays this close [mm] to where it was is calm.
SLEEP_MM = 0.01
#: Calm steps after which a rigid sleeps.
SLEEP_STEPS = 200
#: A fragment's contact stiffness per sample per kg of its mass [N/mm/kg]:
#: its rest penetration ``g / (n_contact k)`` does not depend on its size.
FRAGMENT_STIFFNESS_N_MM_PER_KG = 60.0
#: Contact damping of a sample, relative to critical for its share of the
#: mass when :data:`CONTACT_SHARE` of the samples touch.
DAMPING_RATIO = 1.0
#: The share of a rigid's samples expected to touch at rest (one face).
CONTACT_SHARE = 0.125
#: Coulomb friction coefficient of a rigid on bone (a fragment, a titanium
#: plate: both rest on slopes up to 31 degrees).
FRICTION_COEFF = 0.6
#: Fastest a rigid moves [mm/s] (and turns, [rad/s] per mm of its bounding
#: radius): a safety net against a rigid started deep inside bone.
MAX_SPEED_MM_S = 500.0
# most bodies one rigid's contact pass looks at (the candidates that overlap)
MAX_CAND = 64

# slot modes and kinds
FREE, ASLEEP, DYNAMIC, GRABBED, AFFIXED = range(5)
KIND_FRAGMENT, KIND_PLATE = 1, 2


def gravity_direction(model) -> np.ndarray:
    """Unit gravity direction of a model's case, (3,) case frame.

    The case's ``[physics] gravity`` when it has one (a
    :class:`~bonesim.io.case_records.Case` exposes it as ``gravity_dir``),
    else :data:`DEFAULT_GRAVITY_DIR`.
    """
    g = getattr(getattr(model, "case", None), "gravity_dir", None)
    g = np.asarray(DEFAULT_GRAVITY_DIR if g is None else g, dtype=np.float64)
    n = float(np.linalg.norm(g))
    if g.shape != (3,) or not n > 0.0 or not math.isfinite(n):
        raise ValueError(f"gravity direction must be a finite non-zero 3-vector, got {g}")
    return g / n


# ------------------------------------------------------------- pose helpers
@njit(cache=True, nogil=True)
def pose_matrix_kernel(p, m):
    # the same expressions, in the same order, as bodies.pose_matrix
    tx, ty, tz, w, x, y, z = p[0], p[1], p[2], p[3], p[4], p[5], p[6]
    m[0, 0] = 1 - 2 * (y * y + z * z)
    m[0, 1] = 2 * (x * y - w * z)
    m[0, 2] = 2 * (x * z + w * y)
    m[0, 3] = tx
    m[1, 0] = 2 * (x * y + w * z)
    m[1, 1] = 1 - 2 * (x * x + z * z)
    m[1, 2] = 2 * (y * z - w * x)
    m[1, 3] = ty
    m[2, 0] = 2 * (x * z - w * y)
    m[2, 1] = 2 * (y * z + w * x)
    m[2, 2] = 1 - 2 * (x * x + y * y)
    m[2, 3] = tz


def pose_matrix_into(pose, out) -> np.ndarray:
    """:func:`bonesim.engine.bodies.pose_matrix` written into ``out`` (3, 4)
    without allocating; bit-identical to it."""
    pose_matrix_kernel(np.asarray(pose, np.float64), out)
    return out


@njit(cache=True, nogil=True)
def _qmul(a0, a1, a2, a3, b0, b1, b2, b3):
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


# ------------------------------------------------------------ voxel queries
@njit(cache=True, nogil=True)
def solid_at(keys, vals, body, density, bid, i, j, k):
    if i < 0 or j < 0 or k < 0:
        return False
    b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
    if b < 0:
        return False
    off = voxel_offset(i, j, k)
    return body[b, off] == bid and density[b, off] > 0.0


@njit(cache=True, nogil=True, inline="always")
def empty_side(keys, vals, body, density, bid, i, j, k):
    """Where solid voxel ``(i, j, k)`` of body ``bid`` borders no bone of its
    body: ``(gx, gy, gz, face)``, the sum of the offsets [voxels] to those of
    its 26 neighbours that are not solid voxels of the body (a surface
    voxel's outward normal, unnormalised) and whether a face neighbour is
    among them (the voxel is on the body's surface)."""
    gx = gy = gz = 0.0
    face = False
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-1, 2):
                if a == 0 and b == 0 and c == 0:
                    continue
                if not solid_at(keys, vals, body, density, bid, i + a, j + b, k + c):
                    gx += a
                    gy += b
                    gz += c
                    if abs(a) + abs(b) + abs(c) == 1:
                        face = True
    return gx, gy, gz, face


@njit(cache=True, nogil=True)
def _depth(keys, vals, body, density, bid, gx, gy, gz, ux, uy, uz, max_t):
    """Distance [voxels] from grid point ``g`` (voxel units, voxel ``i``
    spans ``[i - 1/2, i + 1/2)``) along unit ``u`` to the first point outside
    body ``bid``'s solid voxels; -1 when ``g`` is not in a solid voxel; at
    most ``max_t``."""
    cx, cy, cz = gx + 0.5, gy + 0.5, gz + 0.5
    ix, iy, iz = int(math.floor(cx)), int(math.floor(cy)), int(math.floor(cz))
    if not solid_at(keys, vals, body, density, bid, ix, iy, iz):
        return -1.0
    inf = 1e300
    sx = 1 if ux > 0 else -1
    sy = 1 if uy > 0 else -1
    sz = 1 if uz > 0 else -1
    tx = ((ix + 1 - cx) / ux if ux > 0 else (cx - ix) / -ux) if ux != 0 else inf
    ty = ((iy + 1 - cy) / uy if uy > 0 else (cy - iy) / -uy) if uy != 0 else inf
    tz = ((iz + 1 - cz) / uz if uz > 0 else (cz - iz) / -uz) if uz != 0 else inf
    dx = 1.0 / abs(ux) if ux != 0 else inf
    dy = 1.0 / abs(uy) if uy != 0 else inf
    dz = 1.0 / abs(uz) if uz != 0 else inf
    while True:
        if tx <= ty and tx <= tz:
            t = tx
            ix += sx
            tx += dx
        elif ty <= tz:
            t = ty
            iy += sy
            ty += dy
        else:
            t = tz
            iz += sz
            tz += dz
        if t >= max_t:
            return max_t
        if not solid_at(keys, vals, body, density, bid, ix, iy, iz):
            return t


@njit(cache=True, nogil=True)
def _contact(keys, vals, body, density, alive, pose_m, bounds, origin, spacing,
             smp, nrm, n_smp, R, t, com_w, vel, omg, radius, exclude, k, c, cand, out):
    """Sum of the contact forces on one rigid (see :func:`contact`); ``out``:
    ``(fx, fy, fz, tx, ty, tz, n_contact)``, kg mm/s^2 and kg mm^2/s^2."""
    for q in range(7):
        out[q] = 0.0
    n_cand = 0
    for b in range(alive.shape[0]):
        if alive[b] == 0 or b == exclude or n_cand >= cand.shape[0]:
            continue
        if near_body_box(pose_m, bounds, b, com_w, radius / spacing + 1.0, origin, spacing):
            cand[n_cand] = b
            n_cand += 1
    if n_cand == 0:
        return
    max_t = MAX_DEPTH_VOXELS
    for s in range(n_smp):
        # sample and normal in the case frame
        px = R[0, 0] * smp[s, 0] + R[0, 1] * smp[s, 1] + R[0, 2] * smp[s, 2] + t[0]
        py = R[1, 0] * smp[s, 0] + R[1, 1] * smp[s, 1] + R[1, 2] * smp[s, 2] + t[1]
        pz = R[2, 0] * smp[s, 0] + R[2, 1] * smp[s, 1] + R[2, 2] * smp[s, 2] + t[2]
        nx = R[0, 0] * nrm[s, 0] + R[0, 1] * nrm[s, 1] + R[0, 2] * nrm[s, 2]
        ny = R[1, 0] * nrm[s, 0] + R[1, 1] * nrm[s, 1] + R[1, 2] * nrm[s, 2]
        nz = R[2, 0] * nrm[s, 0] + R[2, 1] * nrm[s, 1] + R[2, 2] * nrm[s, 2]
        for q in range(n_cand):
            b = cand[q]
            dx, dy, dz = px - pose_m[b, 0, 3], py - pose_m[b, 1, 3], pz - pose_m[b, 2, 3]
            gx = ((pose_m[b, 0, 0] * dx + pose_m[b, 1, 0] * dy + pose_m[b, 2, 0] * dz)
                  - origin[0]) / spacing
            gy = ((pose_m[b, 0, 1] * dx + pose_m[b, 1, 1] * dy + pose_m[b, 2, 1] * dz)
                  - origin[1]) / spacing
            gz = ((pose_m[b, 0, 2] * dx + pose_m[b, 1, 2] * dy + pose_m[b, 2, 2] * dz)
                  - origin[2]) / spacing
            if gx < bounds[b, 0] - 0.5 or gx >= bounds[b, 3] + 0.5 or \
                    gy < bounds[b, 1] - 0.5 or gy >= bounds[b, 4] + 0.5 or \
                    gz < bounds[b, 2] - 0.5 or gz >= bounds[b, 5] + 0.5:
                continue
            # trace back along -n, in the body's frame
            ux = -(pose_m[b, 0, 0] * nx + pose_m[b, 1, 0] * ny + pose_m[b, 2, 0] * nz)
            uy = -(pose_m[b, 0, 1] * nx + pose_m[b, 1, 1] * ny + pose_m[b, 2, 1] * nz)
            uz = -(pose_m[b, 0, 2] * nx + pose_m[b, 1, 2] * ny + pose_m[b, 2, 2] * nz)
            d = _depth(keys, vals, body, density, b, gx, gy, gz, ux, uy, uz, max_t)
            if d < 0.0:
                continue
            d *= spacing
            # the bone's outward normal there (occupancy gradient), case frame
            ix = int(math.floor(gx + 0.5))
            iy = int(math.floor(gy + 0.5))
            iz = int(math.floor(gz + 0.5))
            ex = ey = ez = 0.0
            for a in range(-1, 2):
                for bb in range(-1, 2):
                    for cc in range(-1, 2):
                        if not solid_at(keys, vals, body, density, b, ix + a, iy + bb, iz + cc):
                            ex += a
                            ey += bb
                            ez += cc
            en = math.sqrt(ex * ex + ey * ey + ez * ez)
            if en > 0.0:
                mx = (pose_m[b, 0, 0] * ex + pose_m[b, 0, 1] * ey + pose_m[b, 0, 2] * ez) / en
                my = (pose_m[b, 1, 0] * ex + pose_m[b, 1, 1] * ey + pose_m[b, 1, 2] * ez) / en
                mz = (pose_m[b, 2, 0] * ex + pose_m[b, 2, 1] * ey + pose_m[b, 2, 2] * ez) / en
            else:
                mx, my, mz = -nx, -ny, -nz
            rx, ry, rz = px - com_w[0], py - com_w[1], pz - com_w[2]
            # the sample's velocity; its part into the bone
            vx = vel[0] + omg[1] * rz - omg[2] * ry
            vy = vel[1] + omg[2] * rx - omg[0] * rz
            vz = vel[2] + omg[0] * ry - omg[1] * rx
            vn = -(vx * mx + vy * my + vz * mz)
            f = k * d + c * vn
            if f <= 0.0:
                continue
            # pushed out along the bone's normal (friction: see _advance)
            fx = f * mx
            fy = f * my
            fz = f * mz
            out[0] += fx
            out[1] += fy
            out[2] += fz
            out[3] += ry * fz - rz * fy
            out[4] += rz * fx - rx * fz
            out[5] += rx * fy - ry * fx
            out[6] += 1.0
            break                       # one body pushes a sample back
    return


def contact(state, smp_case, nrm_case, com_mm, k_n_mm: float, exclude: int = -1,
            vel_mm_s=(0.0, 0.0, 0.0), omega_rad_s=(0.0, 0.0, 0.0), c_n_s_mm: float = 0.0,
            radius_mm: float | None = None) -> dict:
    """Contact force of the bone on a set of samples (see the module docstring).

    Parameters
    ----------
    state : State
        Its grid density, body ids and body poses are read.
    smp_case, nrm_case : (n, 3) float
        Sample points [mm] and outward unit normals, case frame.
    com_mm : (3,) float
        Centre of mass, case frame [mm] (torques are about it).
    k_n_mm : float
        Stiffness per sample [N/mm].
    exclude : int
        A body the samples ignore (the rigid's own body; -1: none).
    vel_mm_s, omega_rad_s : (3,) float
        The rigid's velocity [mm/s] and angular velocity [rad/s] (damping).
    c_n_s_mm : float
        Damping per sample [N s/mm].
    radius_mm : float, optional
        Bounding radius of the samples about ``com_mm`` (default: computed).

    Returns
    -------
    dict
        ``force_n`` (3,) [N], ``torque_nmm`` (3,) [N mm], ``n_contact``.
    """
    smp = np.ascontiguousarray(smp_case, np.float64).reshape(-1, 3)
    nrm = np.ascontiguousarray(nrm_case, np.float64).reshape(-1, 3)
    if smp.shape != nrm.shape:
        raise ValueError(f"samples {smp.shape} and normals {nrm.shape} differ in shape")
    com = np.asarray(com_mm, np.float64)
    if radius_mm is None:
        radius_mm = float(np.linalg.norm(smp - com, axis=1).max()) if len(smp) else 0.0
    g = state.grid
    out = np.zeros(7)
    _contact(g.keys, g.vals, state.body, g.density, state.alive, state.pose_m,
             state.bounds, g.origin_mm, g.spacing_mm, smp, nrm, len(smp), np.eye(3),
             np.zeros(3), com, np.asarray(vel_mm_s, np.float64),
             np.asarray(omega_rad_s, np.float64), float(radius_mm), int(exclude),
             float(k_n_mm) * N_TO_INTERNAL, float(c_n_s_mm) * N_TO_INTERNAL,
             np.zeros(MAX_CAND, np.int32), out)
    return {"force_n": out[:3] / N_TO_INTERNAL, "torque_nmm": out[3:6] / N_TO_INTERNAL,
            "n_contact": int(out[6])}


# ------------------------------------------------------------- the tool's push
@njit(cache=True, nogil=True)
def tool_push_kernel(keys, vals, body, density, alive, pose_m, bounds, origin, spacing, tool,
               radius, gain, first, out):
    """Per body ``b >= first`` within reach: the reaction of the tool sphere's
    contact, ``out[b] = (fx, fy, fz, cx, cy, cz, pen)`` case frame (kg mm/s^2,
    contact centroid [mm], deepest penetration [mm]); zeros elsewhere.
    Returns the number of bodies touched."""
    n_touch = 0
    vox3 = spacing * spacing * spacing
    for b in range(out.shape[0]):
        for q in range(7):
            out[b, q] = 0.0
        if b < first or b >= alive.shape[0] or alive[b] == 0:
            continue
        dx, dy, dz = tool[0] - pose_m[b, 0, 3], tool[1] - pose_m[b, 1, 3], \
            tool[2] - pose_m[b, 2, 3]
        c0 = pose_m[b, 0, 0] * dx + pose_m[b, 1, 0] * dy + pose_m[b, 2, 0] * dz
        c1 = pose_m[b, 0, 1] * dx + pose_m[b, 1, 1] * dy + pose_m[b, 2, 1] * dz
        c2 = pose_m[b, 0, 2] * dx + pose_m[b, 1, 2] * dy + pose_m[b, 2, 2] * dz
        g0 = (c0 - origin[0]) / spacing
        g1 = (c1 - origin[1]) / spacing
        g2 = (c2 - origin[2]) / spacing
        rv = radius / spacing
        lo0 = max(int(math.floor(g0 - rv)), bounds[b, 0])
        lo1 = max(int(math.floor(g1 - rv)), bounds[b, 1])
        lo2 = max(int(math.floor(g2 - rv)), bounds[b, 2])
        hi0 = min(int(math.ceil(g0 + rv)), bounds[b, 3])
        hi1 = min(int(math.ceil(g1 + rv)), bounds[b, 4])
        hi2 = min(int(math.ceil(g2 + rv)), bounds[b, 5])
        n = 0
        sx = sy = sz = 0.0
        ax = ay = az = 0.0
        pen = 0.0
        for i in range(lo0, hi0 + 1):
            for j in range(lo1, hi1 + 1):
                for k in range(lo2, hi2 + 1):
                    ex, ey, ez = i - g0, j - g1, k - g2
                    rr = math.sqrt(ex * ex + ey * ey + ez * ez)
                    if rr >= rv or rr == 0.0:
                        continue
                    if not solid_at(keys, vals, body, density, b, i, j, k):
                        continue
                    n += 1
                    sx += ex / rr
                    sy += ey / rr
                    sz += ez / rr
                    ax += i
                    ay += j
                    az += k
                    pen = max(pen, (rv - rr) * spacing)
        if n == 0:
            continue
        sn = math.sqrt(sx * sx + sy * sy + sz * sz)
        if sn <= 1e-9 * n:
            continue
        f = gain * n * vox3 / sn
        # body frame -> case frame
        for a in range(3):
            out[b, a] = f * (pose_m[b, a, 0] * sx + pose_m[b, a, 1] * sy
                             + pose_m[b, a, 2] * sz)
        px = origin[0] + spacing * ax / n
        py = origin[1] + spacing * ay / n
        pz = origin[2] + spacing * az / n
        for a in range(3):
            out[b, 3 + a] = (pose_m[b, a, 0] * px + pose_m[b, a, 1] * py
                             + pose_m[b, a, 2] * pz + pose_m[b, a, 3])
        out[b, 6] = pen
        n_touch += 1
    return n_touch


def tool_push(state, tool_mm, radius_mm: float, gain_n_mm3: float, out=None) -> np.ndarray:
    """The push of a spherical tool on every body but body 0.

    The reaction to the tool--body contact: the tool feels ``K V`` (``V``
    the immersed volume of the body's voxels, ``K`` the burr's low gain) along
    the sum of unit vectors from the immersed voxels to its centre; the body
    feels the opposite, at the centroid of its immersed voxels.

    Parameters
    ----------
    state : State
    tool_mm : (3,) float
        Tool centre, case frame [mm].
    radius_mm : float
        Tool radius [mm].
    gain_n_mm3 : float
        ``K`` [N/mm^3].
    out : (max_bodies, 7) float64, optional
        Written in place.

    Returns
    -------
    (max_bodies, 7) float64
        Per body ``(fx, fy, fz [N], cx, cy, cz [mm], pen [mm])``, case frame;
        zeros for bodies not touched (and body 0).
    """
    if out is None:
        out = np.zeros((len(state.alive), 7))
    g = state.grid
    tool_push_kernel(g.keys, g.vals, state.body, g.density, state.alive, state.pose_m,
               state.bounds, g.origin_mm, g.spacing_mm, np.asarray(tool_mm, np.float64),
               float(radius_mm), float(gain_n_mm3) * N_TO_INTERNAL, 1, out)
    out[:, :3] /= N_TO_INTERNAL
    return out


# ------------------------------------------------------------------- motion
@njit(cache=True, nogil=True)
def _publish(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head, kind, bod,
             lab, t, i, j, k, n, cur):
    h = ev_head[0] & (ev_kind.shape[0] - 1)
    ev_kind[h] = kind
    ev_body[h] = bod
    ev_label[h] = lab
    ev_t[h] = t
    ev_ijk[h, 0], ev_ijk[h, 1], ev_ijk[h, 2] = i, j, k
    ev_n[h] = n
    for q in range(ev_value.shape[1]):
        ev_value[h, q] = cur[q] if q < 7 else 0.0
    ev_head[0] += 1


@njit(cache=True, nogil=True)
def compose_poses(a, b, out):
    # out = a o b (poses (t, q)): R_a t_b + t_a, q_a q_b
    w, x, y, z = a[3], a[4], a[5], a[6]
    r00 = 1 - 2 * (y * y + z * z)
    r01 = 2 * (x * y - w * z)
    r02 = 2 * (x * z + w * y)
    r10 = 2 * (x * y + w * z)
    r11 = 1 - 2 * (x * x + z * z)
    r12 = 2 * (y * z - w * x)
    r20 = 2 * (x * z - w * y)
    r21 = 2 * (y * z + w * x)
    r22 = 1 - 2 * (x * x + y * y)
    out[0] = r00 * b[0] + r01 * b[1] + r02 * b[2] + a[0]
    out[1] = r10 * b[0] + r11 * b[1] + r12 * b[2] + a[1]
    out[2] = r20 * b[0] + r21 * b[1] + r22 * b[2] + a[2]
    q0, q1, q2, q3 = _qmul(a[3], a[4], a[5], a[6], b[3], b[4], b[5], b[6])
    qn = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    out[3], out[4], out[5], out[6] = q0 / qn, q1 / qn, q2 / qn, q3 / qn


@njit(cache=True, nogil=True)
def _friction(cout, v, w, pm, ib_inv, m, radius, mu, h):
    """Coulomb friction of one substep on velocity ``v`` and spin ``w`` (in
    place), about the summed contact force ``cout[:3]``."""
    nf = math.sqrt(cout[0] * cout[0] + cout[1] * cout[1] + cout[2] * cout[2])
    if nf <= 0.0:
        return
    nx, ny, nz = cout[0] / nf, cout[1] / nf, cout[2] / nf
    vn = v[0] * nx + v[1] * ny + v[2] * nz
    tx, ty, tz = v[0] - vn * nx, v[1] - vn * ny, v[2] - vn * nz
    vt = math.sqrt(tx * tx + ty * ty + tz * tz)
    dv = mu * nf * h / m
    f = 1.0 if vt <= dv else dv / vt
    v[0] -= f * tx
    v[1] -= f * ty
    v[2] -= f * tz
    # spin about the normal: the same force's torque over half the radius
    a0 = pm[0, 0] * nx + pm[1, 0] * ny + pm[2, 0] * nz
    a1 = pm[0, 1] * nx + pm[1, 1] * ny + pm[2, 1] * nz
    a2 = pm[0, 2] * nx + pm[1, 2] * ny + pm[2, 2] * nz
    inv_n = (a0 * (ib_inv[0, 0] * a0 + ib_inv[0, 1] * a1 + ib_inv[0, 2] * a2)
             + a1 * (ib_inv[1, 0] * a0 + ib_inv[1, 1] * a1 + ib_inv[1, 2] * a2)
             + a2 * (ib_inv[2, 0] * a0 + ib_inv[2, 1] * a1 + ib_inv[2, 2] * a2))
    wn = w[0] * nx + w[1] * ny + w[2] * nz
    dw = mu * nf * h * 0.5 * radius * inv_n
    g = wn if abs(wn) <= dw else (dw if wn > 0 else -dw)
    w[0] -= g * nx
    w[1] -= g * ny
    w[2] -= g * nz


@njit(cache=True, nogil=True)
def _plate_moved(s, label, md, t, cur, rpose, tag, cat, ev_kind, ev_body, ev_label, ev_t,
                 ev_ijk, ev_n, ev_value, ev_head) -> int:
    """Plate slot ``s`` is now at ``cur``: if that differs from its last
    pose ``rpose[s]``, keep it and publish a ``PLATE`` event (``label`` its
    host body + 1, 0 free; ``md`` its mode); returns 1 if published, else 0."""
    same = True
    for q in range(7):
        if cur[q] != rpose[s, q]:
            same = False
    if same:
        return 0
    for q in range(7):
        rpose[s, q] = cur[q]
    _publish(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
             PLATE, s, label, t, tag[s], md, 0, cat[s], cur)
    return 1


@njit(cache=True, nogil=True)
def _advance(keys, vals, body, density, alive, pose, pose_m, bounds, origin, spacing,
             mode, kind, owner, host, cat, tag, rpose, rel, vel, omg, mass, ib_inv, com_b,
             k, c, radius, smp, nrm, n_smp, calm, anchor, grab_off, push, tool, gvec, h, nsub,
             drag_s, fric, grab_w, sleep_mm, sleep_n, max_v, t,
             ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
             cand, cout, pm, cur, com_w):
    n_moved = 0
    for s in range(mode.shape[0]):
        md = mode[s]
        if md == FREE or md == ASLEEP:
            continue
        if md == AFFIXED:
            compose_poses(pose[host[s]], rel[s], cur)
            n_moved += _plate_moved(s, host[s] + 1, md, t, cur, rpose, tag, cat, ev_kind,
                                    ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head)
            continue
        frag = kind[s] == KIND_FRAGMENT
        ob = owner[s]
        for q in range(7):
            cur[q] = pose[ob, q] if frag else rpose[s, q]
        pose_matrix_kernel(cur, pm)
        for a in range(3):
            com_w[a] = (pm[a, 0] * com_b[s, 0] + pm[a, 1] * com_b[s, 1]
                        + pm[a, 2] * com_b[s, 2] + pm[a, 3])
        m = mass[s]
        pfx = pfy = pfz = 0.0
        pcx = pcy = pcz = 0.0
        if frag and md != GRABBED and push[ob, 6] > 0.0:
            pfx, pfy, pfz = push[ob, 0], push[ob, 1], push[ob, 2]
            pcx, pcy, pcz = push[ob, 3], push[ob, 4], push[ob, 5]
            # at most what clears the penetration within one haptic step
            lim = m * push[ob, 6] / ((h * nsub) * (h * nsub))
            fm = math.sqrt(pfx * pfx + pfy * pfy + pfz * pfz)
            if fm > lim:
                pfx, pfy, pfz = pfx * lim / fm, pfy * lim / fm, pfz * lim / fm
            calm[s] = 0
        for sub in range(nsub):
            _contact(keys, vals, body, density, alive, pose_m, bounds, origin, spacing,
                     smp[s], nrm[s], n_smp[s], pm[:, :3], pm[:, 3], com_w, vel[s], omg[s],
                     radius[s], ob if frag else -1, k[s], c[s], cand, cout)
            fx = cout[0] + m * gvec[0] + pfx
            fy = cout[1] + m * gvec[1] + pfy
            fz = cout[2] + m * gvec[2] + pfz
            rx, ry, rz = pcx - com_w[0], pcy - com_w[1], pcz - com_w[2]
            tx = cout[3] + (ry * pfz - rz * pfy if frag else 0.0)
            ty = cout[4] + (rz * pfx - rx * pfz if frag else 0.0)
            tz = cout[5] + (rx * pfy - ry * pfx if frag else 0.0)
            damp = 1.0 + h / drag_s
            if md == GRABBED:
                # the hand holds its weight and pulls it to the tool
                fx -= m * gvec[0]
                fy -= m * gvec[1]
                fz -= m * gvec[2]
                w2 = grab_w * grab_w
                fx += m * (w2 * (tool[0] + grab_off[s, 0] - com_w[0]) - 2 * grab_w * vel[s, 0])
                fy += m * (w2 * (tool[1] + grab_off[s, 1] - com_w[1]) - 2 * grab_w * vel[s, 1])
                fz += m * (w2 * (tool[2] + grab_off[s, 2] - com_w[2]) - 2 * grab_w * vel[s, 2])
                damp += 2 * grab_w * h
            vel[s, 0] = (vel[s, 0] + h * fx / m) / (1.0 + h / drag_s)
            vel[s, 1] = (vel[s, 1] + h * fy / m) / (1.0 + h / drag_s)
            vel[s, 2] = (vel[s, 2] + h * fz / m) / (1.0 + h / drag_s)
            # world inverse inertia R I^-1 R^T applied to the torque
            b0 = pm[0, 0] * tx + pm[1, 0] * ty + pm[2, 0] * tz
            b1 = pm[0, 1] * tx + pm[1, 1] * ty + pm[2, 1] * tz
            b2 = pm[0, 2] * tx + pm[1, 2] * ty + pm[2, 2] * tz
            a0 = ib_inv[s, 0, 0] * b0 + ib_inv[s, 0, 1] * b1 + ib_inv[s, 0, 2] * b2
            a1 = ib_inv[s, 1, 0] * b0 + ib_inv[s, 1, 1] * b1 + ib_inv[s, 1, 2] * b2
            a2 = ib_inv[s, 2, 0] * b0 + ib_inv[s, 2, 1] * b1 + ib_inv[s, 2, 2] * b2
            for a in range(3):
                omg[s, a] = (omg[s, a] + h * (pm[a, 0] * a0 + pm[a, 1] * a1
                                              + pm[a, 2] * a2)) / damp
            _friction(cout, vel[s], omg[s], pm, ib_inv[s], m, radius[s], fric, h)
            sp = math.sqrt(vel[s, 0] ** 2 + vel[s, 1] ** 2 + vel[s, 2] ** 2)
            if sp > max_v:
                for a in range(3):
                    vel[s, a] *= max_v / sp
            sw = math.sqrt(omg[s, 0] ** 2 + omg[s, 1] ** 2 + omg[s, 2] ** 2)
            if sw * radius[s] > max_v:
                for a in range(3):
                    omg[s, a] *= max_v / (sw * radius[s])
            for a in range(3):
                com_w[a] += h * vel[s, a]
            q0, q1, q2, q3 = _qmul(0.0, omg[s, 0], omg[s, 1], omg[s, 2],
                                   cur[3], cur[4], cur[5], cur[6])
            q0 = cur[3] + 0.5 * h * q0
            q1 = cur[4] + 0.5 * h * q1
            q2 = cur[5] + 0.5 * h * q2
            q3 = cur[6] + 0.5 * h * q3
            qn = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
            cur[3], cur[4], cur[5], cur[6] = q0 / qn, q1 / qn, q2 / qn, q3 / qn
            cur[0] = cur[1] = cur[2] = 0.0
            pose_matrix_kernel(cur, pm)
            for a in range(3):
                cur[a] = com_w[a] - (pm[a, 0] * com_b[s, 0] + pm[a, 1] * com_b[s, 1]
                                     + pm[a, 2] * com_b[s, 2])
                pm[a, 3] = cur[a]
        dd = math.sqrt((com_w[0] - anchor[s, 0]) ** 2 + (com_w[1] - anchor[s, 1]) ** 2
                       + (com_w[2] - anchor[s, 2]) ** 2)
        if md == DYNAMIC and dd < sleep_mm:
            calm[s] += 1
            if calm[s] >= sleep_n:
                mode[s] = ASLEEP
                for a in range(3):
                    vel[s, a] = 0.0
                    omg[s, a] = 0.0
        else:
            calm[s] = 0
            for a in range(3):
                anchor[s, a] = com_w[a]
        if frag:
            same = True
            for q in range(7):
                if cur[q] != pose[ob, q]:
                    same = False
            if not same:
                for q in range(7):
                    pose[ob, q] = cur[q]
                pose_matrix_kernel(cur, pose_m[ob])
                _publish(ev_kind, ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head,
                         POSE, ob, 0, t, 0, 0, 0, 0, cur)
                n_moved += 1
        else:
            n_moved += _plate_moved(s, 0, mode[s], t, cur, rpose, tag, cat, ev_kind,
                                    ev_body, ev_label, ev_t, ev_ijk, ev_n, ev_value, ev_head)
    return n_moved


#: The motion kernel, for :class:`bonesim.engine.rigid_set.RigidSet` (one call per step).
advance_kernel = _advance
