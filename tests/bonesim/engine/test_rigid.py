"""Rigid motion: contact against voxel bone, plates at rest, fragments dropped,
pushed and grabbed (bonesim.engine.rigid, bonesim.engine.rigid_set)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bonesim.engine import events
from bonesim.engine.bodies import pose_matrix, set_pose, split_body
from bonesim.engine.rigid import (ASLEEP, GRAVITY_MM_S2, N_TO_INTERNAL, contact,
                                  pose_matrix_into, tool_push)
from bonesim.engine.rigid_set import RigidSet, body_samples, mesh_samples

from tests.bonesim.fakes import block_model

SP = 0.5
TOP = 19 * SP + SP / 2            # top face of the block_model bone (k < 20) [mm]
FAR = np.array([1e3, 1e3, 1e3])   # a tool far from everything


def _box_plate(lx=10.0, ly=4.0, lz=1.0, nx=11, ny=5):
    """A box plate centred on 0: grid vertices on its bottom and top faces
    with the faces' normals (flat shading, as the shipped meshes)."""
    xs, ys = np.meshgrid(np.linspace(-lx / 2, lx / 2, nx), np.linspace(-ly / 2, ly / 2, ny))
    bot = np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, -lz / 2)]
    top = bot * [1, 1, -1]
    pos = np.r_[bot, top]
    nrm = np.r_[np.tile([0, 0, -1.0], (len(bot), 1)), np.tile([0, 0, 1.0], (len(bot), 1))]
    return pos, nrm, len(bot)


def _run(rs, state, n, tool=FAR, drill=False, t0=0.0, each=None):
    for q in range(n):
        rs.advance(state, t0 + q * 1e-3, tool, drill, 2.5, 1.0)
        if each is not None:
            each()


def _quat(rx, ry, rz):
    """Unit quaternion of a rotation vector [rad]."""
    a = math.sqrt(rx * rx + ry * ry + rz * rz)
    if a == 0.0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    s = math.sin(a / 2) / a
    return np.array([math.cos(a / 2), rx * s, ry * s, rz * s])


# ------------------------------------------------------------- pose bits
def test_the_kernels_pose_matrix_is_bit_identical_to_the_bodies_one():
    rng = np.random.default_rng(3)
    out = np.zeros((3, 4))
    for _ in range(200):
        q = rng.normal(size=4)
        p = np.r_[rng.normal(size=3) * 20, q / np.linalg.norm(q)]
        np.testing.assert_array_equal(pose_matrix_into(p, out), pose_matrix(p))


# ------------------------------------------------------ contact vs reference
def _dense(state):
    """Density and body id as dense (x, y, z) arrays."""
    from bonesim.engine.bodies import voxel_bodies
    from bonesim.engine.grid import find_brick, voxel_offset

    g = state.grid
    ijk = np.indices(g.shape).reshape(3, -1).T
    dens = np.zeros(g.shape, np.float32)
    bod = np.zeros(g.shape, np.uint8)
    bod[tuple(ijk.T)] = voxel_bodies(g, state.body, ijk)
    for i, j, k in ijk:
        b = find_brick(g.keys, g.vals, i >> 3, j >> 3, k >> 3)
        dens[i, j, k] = g.density[b, voxel_offset(i, j, k)] if b >= 0 else 0.0
    return dens, bod


def _ref_contact(state, dens, bod, smp, nrm, com, k, exclude):
    """Slow reference: each sample's voxel looked up body by body; the
    penetration by marching back along -n in steps of voxel/4000; the push
    along the bone's normal, the sum of the offsets to the empty neighbours
    among the 26."""
    g = state.grid

    def solid_ijk(b, ijk):
        if (ijk < 0).any() or (ijk >= np.asarray(g.shape)).any():
            return False
        return bool(dens[tuple(ijk)] > 0 and bod[tuple(ijk)] == b)

    def voxel(p_body):
        return np.floor((p_body - g.origin_mm) / g.spacing_mm + 0.5).astype(int)

    def solid(b, p_body):
        return solid_ijk(b, voxel(p_body))

    offsets = [np.array(o) for o in np.ndindex(3, 3, 3) if o != (1, 1, 1)]

    f, tq, n_c = np.zeros(3), np.zeros(3), 0
    step = g.spacing_mm / 4000
    n_steps = int(math.ceil(4 * g.spacing_mm / step - 1e-9))
    for p, n in zip(smp, nrm):
        for b in np.flatnonzero(state.alive):
            if b == exclude:
                continue
            m = state.pose_m[b]
            pb = (p - m[:, 3]) @ m[:, :3]
            nb = n @ m[:, :3]
            if not solid(b, pb):
                continue
            # the march: every point back along -n, one step apart, up to 4
            # voxels; the depth is the run of solid points from the start
            pts = pb - (np.arange(1, n_steps + 1) * step)[:, None] * nb
            ijk = np.floor((pts - g.origin_mm) / g.spacing_mm + 0.5).astype(int)
            inside = ((ijk >= 0) & (ijk < np.asarray(g.shape))).all(axis=1)
            c = np.clip(ijk, 0, np.asarray(g.shape) - 1)
            ok = inside & (dens[c[:, 0], c[:, 1], c[:, 2]] > 0) & \
                (bod[c[:, 0], c[:, 1], c[:, 2]] == b)
            run = n_steps if ok.all() else int(np.argmin(ok))
            d = min(run * step + step / 2, 4 * g.spacing_mm)
            v = voxel(pb)
            grad = sum((o - 1 for o in offsets if not solid_ijk(b, v + o - 1)), np.zeros(3))
            normal = m[:, :3] @ grad / np.linalg.norm(grad) if grad.any() else -n
            fs = k * d * normal
            f += fs
            tq += np.cross(p - com, fs)
            n_c += 1
            break
    return f, tq, n_c


def test_contact_matches_a_slow_reference_over_two_bodies_at_different_poses():
    m, s = block_model(shape=(24, 24, 24), fill_z=12)
    # a fragment: a corner of the block, moved and turned
    split_body(s, 0, np.argwhere(np.ones((6, 6, 4), bool)) + [2, 2, 8])
    set_pose(s, 1, np.r_[[4.0, 3.0, 2.5], _quat(0.3, -0.2, 0.5)])
    dens, bod = _dense(s)
    rng = np.random.default_rng(11)
    smp = rng.uniform([0, 0, 3], [12, 12, 8], size=(300, 3))
    nrm = rng.normal(size=(300, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    com = np.array([6.0, 6.0, 6.0])
    got = contact(s, smp, nrm, com, 0.01, exclude=-1, radius_mm=50.0)
    f, tq, n_c = _ref_contact(s, dens, bod, smp, nrm, com, 0.01, -1)
    assert got["n_contact"] == n_c > 30
    # the reference marches in steps of voxel/4000: each sample within one step
    tol = n_c * 0.01 * SP / 4000
    np.testing.assert_allclose(got["force_n"], f, atol=tol)
    np.testing.assert_allclose(got["torque_nmm"], tq, atol=tol * 30)
    # excluding the fragment drops its contacts
    assert contact(s, smp, nrm, com, 0.01, exclude=1, radius_mm=50.0)["n_contact"] < n_c


# --------------------------------------------------------------- plates
def test_a_plate_comes_to_rest_flat_at_the_analytic_height():
    m, s = block_model()
    pos, nrm, n_bot = _box_plate()
    mass, k, off = 2e-3, 5e-3, 0.2
    rs = RigidSet(m.max_bodies, rate_hz=1000.0)
    tilt = _quat(0.05, -0.03, 0.4)
    slot = rs.add_plate(pos, nrm, off, mass, k, np.r_[[10.0, 10.0, TOP + 3.0], tilt])
    _run(rs, s, 4000)
    assert rs.mode[slot] == ASLEEP                    # came to rest
    d = mass * GRAVITY_MM_S2 / (n_bot * k * N_TO_INTERNAL)    # weight / (n k)
    z = rs.rpose[slot, 2]
    # bottom face at TOP + d - offset: the samples sit d deep in the bone
    assert abs(z - (TOP + 0.5 + off - d)) < 1e-4 * d + 1e-6
    R = pose_matrix(rs.rpose[slot])[:, :3]
    assert R[2, 2] > 1 - 1e-9                         # flat: its normal is +z
    # the plate published its poses as PLATE events, never a body's POSE
    ev = s.tissue.read(0)
    assert set(np.unique(ev["kind"])) == {events.PLATE}
    np.testing.assert_array_equal(ev["value"][-1], rs.rpose[slot])


def test_an_affixed_plate_moves_with_its_body():
    m, s = block_model()
    split_body(s, 0, np.argwhere(np.ones((12, 12, 4), bool)) + [14, 14, 16])
    pos, nrm, _ = _box_plate(6.0, 3.0)
    rs = RigidSet(m.max_bodies)
    slot = rs.add_plate(pos, nrm, 0.2, 1e-3, 5e-3, [10.0, 10.0, TOP + 1.5, 1, 0, 0, 0])
    _run(rs, s, 1500)
    host, second = rs.affix(s, slot)
    assert (host, second) == (1, -1)
    rel = np.linalg.inv(np.r_[pose_matrix(s.pose[1]), [[0, 0, 0, 1]]]) @ \
        np.r_[pose_matrix(rs.rpose[slot]), [[0, 0, 0, 1]]]
    for q, pose in enumerate(([3.0, -2.0, 5.0, *_quat(0.2, 0.1, -0.4)],
                              [-1.0, 4.0, 8.0, *_quat(-0.5, 0.3, 1.2)])):
        set_pose(s, 1, pose)
        _run(rs, s, 1, t0=2.0 + q)
        now = np.linalg.inv(np.r_[pose_matrix(s.pose[1]), [[0, 0, 0, 1]]]) @ \
            np.r_[pose_matrix(rs.rpose[slot]), [[0, 0, 0, 1]]]
        np.testing.assert_allclose(now, rel, atol=1e-12)
        ev = s.tissue.read(s.tissue.count - 1)
        assert ev["kind"][0] == events.PLATE and ev["label"][0] == 2   # host 1, plus one
    # body 0 does not carry it
    set_pose(s, 0, [0, 0, 1.0, 1, 0, 0, 0])
    before = rs.rpose[slot].copy()
    _run(rs, s, 1, t0=9.0)
    np.testing.assert_array_equal(rs.rpose[slot], before)


def test_a_distractor_spans_two_bodies_and_sets_their_distance():
    m, s = block_model()
    split_body(s, 0, np.argwhere(np.ones((20, 40, 20), bool)) + [20, 0, 0])
    pos, nrm, _ = _box_plate(12.0, 3.0)
    rs = RigidSet(m.max_bodies)
    slot = rs.add_plate(pos, nrm, 0.2, 1e-3, 5e-3, [10.0, 10.0, TOP + 1.0, 1, 0, 0, 0],
                        axis=(1.0, 0.0, 0.0))
    _run(rs, s, 1500)
    assert rs.affix(s, slot) == (0, 1)
    base = s.pose[1].copy()
    new = rs.distract(s, slot, 3.0)
    axis = pose_matrix(rs.rpose[slot])[:, 0]         # the mesh's x axis, case frame
    assert axis[0] > 1 - 1e-6
    np.testing.assert_allclose(new[:3] - base[:3], 3.0 * axis, atol=1e-12)
    np.testing.assert_array_equal(new[3:], base[3:])
    with pytest.raises(ValueError, match="not a distractor"):
        rs.distract(s, rs.add_plate(pos, nrm, 0.2, 1e-3, 5e-3, [5, 5, 30, 1, 0, 0, 0]), 1.0)


def test_mesh_samples_push_vertices_out_along_their_normals():
    pos = np.array([[0.0, 0, 0], [1, 0, 0]])
    out = mesh_samples(pos, [[0, 0, 2.0], [0, -1.0, 0]], 0.3)
    np.testing.assert_allclose(out["smp"], [[0, 0, 0.3], [1, -0.3, 0]])
    with pytest.raises(ValueError, match="non-zero normal"):
        mesh_samples(pos, [[0, 0, 0.0], [0, 1, 0]], 0.3)


# ------------------------------------------------------------ fragments
def _cube_model(lo=(16, 16, 28), edge=6, shape=(40, 40, 48)):
    """The bone block (k < 20) and a cube of bone at ``lo``, made fragment 1."""
    labels = np.zeros(shape, np.uint8)
    labels[:, :, :20] = 1
    i, j, k = lo
    labels[i:i + edge, j:j + edge, k:k + edge] = 1
    m, s = block_model(labels=labels)
    ijk = np.argwhere(np.ones((edge,) * 3, bool)) + np.asarray(lo)
    split_body(s, 0, ijk)
    return m, s, ijk


def _lowest_z(s, ijk):
    c = s.grid.origin_mm + SP * ijk
    return float((c @ pose_matrix(s.pose[1])[:, :3].T + s.pose[1][:3])[:, 2].min())


@settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck))
@given(drop=st.floats(0.0, 4.0), rot=st.tuples(*[st.floats(-0.6, 0.6)] * 3))
def test_a_dropped_fragment_stops_on_the_bone_and_never_passes_through(drop, rot):
    m, s, ijk = _cube_model()
    # turned about the cube's centre, raised by ``drop``
    c = s.grid.origin_mm + SP * ijk.mean(axis=0)
    q = _quat(*rot)
    R = pose_matrix(np.r_[0.0, 0.0, 0.0, q])[:, :3]
    set_pose(s, 1, np.r_[c - R @ c + [0.0, 0.0, drop], q])
    start_low = _lowest_z(s, ijk)
    rs = RigidSet(m.max_bodies)
    slot = rs.wake_body(s, 1)
    lows = []
    for q in range(300):
        _run(rs, s, 5, t0=q * 5e-3)
        lows.append(_lowest_z(s, ijk))
    # no voxel centre of the fragment gets half a voxel into the bone (its
    # samples sit half a voxel out: contact starts where the surfaces meet)
    floor = TOP - SP / 2
    assert min(lows) > floor, (min(lows), floor)
    assert start_low - min(lows) > -1e-9
    assert lows[-1] < start_low or drop == 0.0
    assert rs.mode[slot] == ASLEEP                   # at rest
    # and it rests on the face: its lowest voxel within a voxel of it
    assert lows[-1] < TOP + SP / 2 + SP


def test_body_samples_are_surface_voxels_pushed_out_half_a_voxel():
    m, s, ijk = _cube_model(edge=4)
    d = body_samples(s, 1)
    assert d["voxels"] == 64
    assert len(d["smp"]) == 64 - 8                   # every voxel but the inner 2^3
    np.testing.assert_allclose(d["com_mm"], s.grid.origin_mm + SP * (ijk.mean(axis=0)))
    assert d["mass_kg"] == pytest.approx(64 * SP ** 3 * 1.9e-6)
    np.testing.assert_allclose(np.linalg.norm(d["nrm"], axis=1), 1.0)
    with pytest.raises(ValueError, match="not a fragment"):
        body_samples(s, 0)


def test_the_stopped_tool_pushes_a_fragment_and_the_running_drill_does_not():
    m, s, _ = _cube_model(lo=(16, 16, 20))             # resting on the face
    centre = s.grid.origin_mm + SP * np.array([18.5, 18.5, 22.5])
    tool = centre - [1.5 + 2.0, 0.0, 0.0]              # 2.5 mm burr, 1 mm into its -x face
    push = tool_push(s, tool, 2.5, 1.0)
    assert push[1, 0] > 0 and abs(push[1, 1]) < 1e-12 and push[1, 6] > 0
    assert not push[0].any()
    rs = RigidSet(m.max_bodies)
    x0 = s.pose[1, 0]
    _run(rs, s, 200, tool=tool, drill=True)
    assert s.pose[1, 0] == x0                         # drilling: no push, not even awake
    _run(rs, s, 200, tool=tool, drill=False, t0=1.0)
    assert s.pose[1, 0] > x0 + 0.3                    # pushed along +x
    assert abs(s.pose[1, 1]) < 1e-6
    poses = events.select(s.tissue.read(0), events.POSE)
    assert len(poses["t_s"]) > 0 and set(poses["body"]) == {1}


def test_a_grabbed_fragment_follows_the_tool_and_drops_when_released():
    m, s, _ = _cube_model(lo=(16, 16, 20))
    rs = RigidSet(m.max_bodies)
    slot = rs.wake_body(s, 1)
    _run(rs, s, 400)                               # settles on the face
    tool = s.grid.origin_mm + SP * np.array([18.5, 18.5, 27.0])
    rs.grab(s, slot, tool)
    c0 = rs.centre(slot, s).copy()
    for q in range(1500):                          # lift 5 mm and move 3 mm along y
        f = min(q / 1000, 1.0)
        rs.advance(s, 1.0 + q * 1e-3, tool + [0.0, 3.0 * f, 5.0 * f], False, 2.5, 1.0)
    np.testing.assert_allclose(rs.centre(slot, s) - c0, [0.0, 3.0, 5.0], atol=0.02)
    assert rs.release() == 1
    _run(rs, s, 2000, t0=3.0)
    assert rs.centre(slot, s)[2] - c0[2] == pytest.approx(0.0, abs=0.05)   # back on the face


def test_a_full_set_lends_a_sleeping_fragments_slot_and_never_raises_in_the_step():
    m, s, _ = _cube_model(lo=(16, 16, 20), edge=4)
    split_body(s, 0, np.argwhere(np.ones((4, 4, 4), bool)) + [4, 4, 16])    # body 2
    rs = RigidSet(m.max_bodies, capacity=1)
    a = rs.wake_body(s, 1)
    with pytest.raises(ValueError, match="in use"):
        rs.wake_body(s, 2)                       # the only slot moves body 1
    rs.hold(1)
    assert rs.wake_body(s, 2) == a and rs.slot_of(1) == -1 and rs.slot_of(2) == a
    # a tool touching body 1 while body 2 holds the slot and moves: no error
    rs.mode[a] = 2
    centre = s.grid.origin_mm + SP * np.array([17.5, 17.5, 21.5])
    rs.advance(s, 0.0, centre - [1.6, 0.0, 0.0], False, 1.5, 1.0)
    assert rs.push[1, 6] > 0                     # it touched body 1, which found no slot
    assert rs.slot_of(1) == -1 and rs.slot_of(2) == a
