"""Vision datasets rendered offscreen (bonesim.render.dataset), checked
against references computed here on the CPU, independently of the renderer:

* depth at sampled pixels equals a ray cast against the bone's drawn
  surface (its triangles, whatever positions their vertices have) within
  half a voxel, and against the tools' analytic shapes;
* the class at those pixels is the structure of the first voxel the ray
  reaches (marched in fine steps from the eye), or the burr, shaft or
  suction tube where the tool is nearer; dust and water pixels lie on a
  sprite's core;
* a stereo pair's disparity agrees with depth (d = f B / z) within a pixel;
* the intrinsics and extrinsics reproject a known point (the burr's
  centre, placed in free space) onto its pixels;
* points and normals agree with depth and cameras.

The recording is 8 s of the planned demo on the phantom
(the ``demo_run`` fixture, tests/bonesim/conftest.py); frames are 160x120.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from bonesim.session import dataset_spec as spec
from bonesim.session.dataset_camera import look_at, project
from bonesim.session.dataset_frames import FrameSource
from bonesim.session.dataset_spec import DatasetOptions
from bonesim.render.dataset import DatasetRenderer

SIZE = (160, 120)
T_FRAME = 6.5          # mid-drilling in the 8 s recording [s]
BASELINE_MM = 4.0
SHAFT_LENGTH_MM = 40.0


@pytest.fixture(scope="module")
def scene(gl_info, demo_run):
    """One stereo frame with every stream, and what the references need."""
    from bonesim.session.reader import read_session

    opts = DatasetOptions(size=SIZE, fps=2.0, start=T_FRAME, camera="fixed", zoom=2.5,
                          stereo_mm=BASELINE_MM, normals=True, points=True,
                          suction="follow")
    src = FrameSource(read_session(demo_run), opts)
    rend = DatasetRenderer(src.player, opts)
    fs = src.at(T_FRAME)
    eyes = rend.render(fs)
    sprites = {"dust": rend.scene.dust._bufs,
               "water": getattr(getattr(rend.scene, "water", None), "_bufs", None)}
    yield {"src": src, "fs": fs, "eyes": eyes, "rend": rend, "sprites": sprites,
           "opts": opts}
    rend.close()


# ------------------------------------------------------------ references
def _rays(cam, pix):
    """Unit ray directions (case frame) and the camera-frame ray (z = 1) of
    pixels ``pix`` (n, 2) as (v, u)."""
    k, r = cam["K"], cam["R"]
    uv1 = np.stack([(pix[:, 1] - k[0, 2]) / k[0, 0], (pix[:, 0] - k[1, 2]) / k[1, 1],
                    np.ones(len(pix))], 1)
    d = uv1 @ r                            # R.T @ ray
    return d / np.linalg.norm(d, axis=1)[:, None], uv1


def _ray_triangles(o, d, pos, tri, balls=None):
    """Nearest hit distance of the ray ``o + t d`` with the triangles (inf: none).

    ``balls`` (:func:`_bounding_balls`) leaves out first the triangles whose
    bounding ball the ray's line misses (they cannot be hit)."""
    if balls is not None:
        cen, rad2 = balls
        w = np.cross(cen - o, d)
        tri = tri[np.einsum("ij,ij->i", w, w) <= rad2]
    a, b, c = pos[tri[:, 0]], pos[tri[:, 1]], pos[tri[:, 2]]
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - a
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9) & (t > 0)
    return float(t[hit].min()) if hit.any() else math.inf


def _bounding_balls(pos, tri):
    """Per triangle, its centroid and the squared radius of a ball about it
    holding its corners (slightly enlarged against rounding)."""
    cen = pos[tri].mean(axis=1)
    rad2 = (np.linalg.norm(pos[tri] - cen[:, None, :], axis=2).max(axis=1) * 1.001
            + 1e-9) ** 2
    return cen, rad2


def _ray_sphere(o, d, c, r):
    oc = o - c
    b = oc @ d
    disc = b * b - (oc @ oc - r * r)
    if disc < 0:
        return math.inf
    t = -b - math.sqrt(disc)
    return t if t > 0 else math.inf


def _ray_cylinder(o, d, base, axis, r, length):
    """Capped cylinder from ``base`` along unit ``axis`` for ``length``."""
    best = math.inf
    w = o - base
    dd = d - (d @ axis) * axis
    ww = w - (w @ axis) * axis
    a = dd @ dd
    if a > 1e-15:
        b = 2 * dd @ ww
        c = ww @ ww - r * r
        disc = b * b - 4 * a * c
        if disc >= 0:
            for t in ((-b - math.sqrt(disc)) / (2 * a), (-b + math.sqrt(disc)) / (2 * a)):
                s = (w + t * d) @ axis
                if t > 0 and 0 <= s <= length:
                    best = min(best, t)
    den = d @ axis
    if abs(den) > 1e-15:
        for s0 in (0.0, length):
            t = (s0 - w @ axis) / den
            p = w + t * d - s0 * axis
            if t > 0 and p @ p - (p @ axis) ** 2 <= r * r:
                best = min(best, t)
    return best


def _voxel_walk(dens, lab, grid, o, d, t0, t1, step):
    """First occupied voxel along the ray, by fine steps: (t, label)."""
    ts = np.arange(t0, t1, step)
    p = o + ts[:, None] * d
    ijk = np.rint((p - grid.origin_mm) / grid.spacing_mm).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < np.asarray(grid.shape)), axis=1)
    occ = np.zeros(len(ts), bool)
    ii = ijk[inside]
    occ[inside] = dens[ii[:, 0], ii[:, 1], ii[:, 2]] > 0
    if not occ.any():
        return math.inf, 0
    q = int(np.argmax(occ))
    return float(ts[q]), int(lab[tuple(ijk[q])])


def _tools(fs):
    """(class id, hit function of (o, d)) of the drawn tools."""
    f = fs.frame
    r = float(f.burr.radius_mm)
    ax = np.asarray(f.axis, float) / np.linalg.norm(f.axis)
    out = [(spec.CLASS_BURR, lambda o, d: _ray_sphere(o, d, f.pos_mm, r)),
           (spec.CLASS_SHAFT, lambda o, d: _ray_cylinder(o, d, f.pos_mm, -ax,
                                                         min(0.8, 0.45 * r), SHAFT_LENGTH_MM))]
    if fs.suction is not None:
        tip, sax, sr = fs.suction
        sax = np.asarray(sax, float) / np.linalg.norm(sax)
        out.append((spec.CLASS_SUCTION, lambda o, d: _ray_cylinder(o, d, np.asarray(tip),
                                                                   -sax, sr,
                                                                   SHAFT_LENGTH_MM)))
    return out


def _interior(cls, depth, step=3):
    """Sample pixels (v, u) on a grid whose 3x3 neighbourhood has one class and
    a depth spread under 1 mm (away from silhouettes and edges)."""
    h, w = cls.shape
    out = []
    for v in range(2, h - 2, step):
        for u in range(2, w - 2, step):
            c = cls[v - 1:v + 2, u - 1:u + 2]
            z = depth[v - 1:v + 2, u - 1:u + 2]
            if cls[v, u] == 0 or (c != cls[v, u]).any() or not np.isfinite(z).all():
                continue
            if z.max() - z.min() > 1.0:
                continue
            out.append((v, u))
    return np.array(out)


# ------------------------------------------------------------------ tests
def test_streams_shapes_and_types(scene):
    w, h = SIZE
    assert len(scene["eyes"]) == 2
    for res in scene["eyes"]:
        assert res["rgb"].shape == (h, w, 3) and res["rgb"].dtype == np.uint8
        assert res["depth"].shape == (h, w) and res["depth"].dtype == np.float32
        assert res["class"].dtype == np.uint8 and res["instance"].dtype == np.int16
        assert res["normals"].shape == (h, w, 3) and res["points_case"].shape == (h, w, 3)
        bg = res["class"] == spec.CLASS_BACKGROUND
        assert np.isnan(res["depth"][bg]).all() and np.isfinite(res["depth"][~bg]).all()
        assert (res["instance"][bg] == spec.NO_INSTANCE).all()
    left = scene["eyes"][0]
    present = set(np.unique(left["class"]).tolist())
    # the bone, the burr, its shaft and the trailing suction tube are in view
    assert {1, spec.CLASS_BURR, spec.CLASS_SHAFT, spec.CLASS_SUCTION} <= present
    # tissue carries its body (one body: 0), tools none
    assert (left["instance"][left["class"] == 1] == 0).all()
    assert (left["instance"][left["class"] == spec.CLASS_BURR] == spec.NO_INSTANCE).all()
    assert scene["rend"].stats["label_misses"] == 0


def _structure_meshes(rend):
    """Triangles [mm] of the structures' own meshes the scene draws (static,
    in the case frame): (points (n, 3), triangles (m, 3))."""
    from vtkmodules.util import numpy_support

    pts, tris, off = [], [], 0
    for actor in rend.scene._structures.values():
        pd = actor.GetMapper().GetInput()
        p = numpy_support.vtk_to_numpy(pd.GetPoints().GetData()).astype(np.float64)
        t = numpy_support.vtk_to_numpy(pd.GetPolys().GetConnectivityArray()).reshape(-1, 3)
        pts.append(p)
        tris.append(t + off)
        off += len(p)
    return np.concatenate(pts), np.concatenate(tris)


def test_depth_equals_a_ray_cast_to_the_drawn_surface_and_the_tools(scene):
    """The bone surface's triangles as the replica holds them (whatever
    positions its vertices have) plus the structures' own meshes, cast on
    the CPU; the tools analytically."""
    src, fs = scene["src"], scene["fs"]
    res = scene["eyes"][0]
    cam = res["camera"]
    grid = src.player.grid
    h = grid.spacing_mm
    pos, _, _, tri = src.player.surface.arrays()
    spos, stri = _structure_meshes(scene["rend"])
    pos = np.concatenate([pos.astype(np.float64), spos])
    tri = np.concatenate([tri, stri + len(pos) - len(spos)])
    pix = _interior(res["class"], res["depth"])
    dirs, uv1 = _rays(cam, pix)
    eye = cam["cam_to_case"][:3, 3]
    tools = dict(_tools(fs))
    errs, tool_errs = [], []
    balls = _bounding_balls(pos, tri)
    for (v, u), d, r1 in zip(pix, dirs, uv1):
        c = int(res["class"][v, u])
        z = float(res["depth"][v, u])
        norm = float(np.linalg.norm(r1))
        if 1 <= c <= spec.MAX_STRUCTURE_ID:
            errs.append(abs(_ray_triangles(eye, d, pos, tri, balls) / norm - z))
        elif c in tools:
            tool_errs.append(abs(tools[c](eye, d) / norm - z))
    errs, tool_errs = np.array(errs), np.array(tool_errs)
    assert len(errs) > 200 and len(tool_errs) > 10
    assert errs.max() < 0.5 * h, errs.max()
    assert np.median(errs) < 0.01            # the same triangles: far tighter
    assert tool_errs.max() < 0.05, tool_errs.max()   # tessellated sphere and cylinders


def test_segmentation_is_the_structure_the_ray_reaches_or_the_nearer_tool(scene):
    """The reference marches each sampled pixel's ray from the eye in steps of
    1/16 voxel and takes the first voxel holding tissue, unless a tool is
    nearer. The drawn surface is smoother than the voxels' cubes: where the
    ray only clips a cube's corner at a rim that the drawn surface rounds
    off (the first voxel reached lies more than two voxels from the point
    drawn), the picture shows what lies behind; there the reference marches
    from a voxel before the drawn depth instead. Such pixels must stay rare."""
    src, fs = scene["src"], scene["fs"]
    res = scene["eyes"][0]
    cam = res["camera"]
    grid = src.player.grid
    h = grid.spacing_mm
    dens, lab = grid.to_dense()
    pix = _interior(res["class"], res["depth"], step=2)
    dirs, uv1 = _rays(cam, pix)
    eye = cam["cam_to_case"][:3, 3]
    tools = _tools(fs)
    checked, wrong, grazed = 0, [], 0
    counts = {}
    for (v, u), d, r1 in zip(pix, dirs, uv1):
        c = int(res["class"][v, u])
        if c in (spec.CLASS_DUST, spec.CLASS_WATER):
            continue                          # checked against the sprites below
        t_hit = float(res["depth"][v, u]) * float(np.linalg.norm(r1))
        t_vox, want = _voxel_walk(dens, lab, grid, eye, d, 20.0, 120.0, h / 16)
        first = np.rint((eye + t_vox * d - grid.origin_mm) / h) if math.isfinite(t_vox) \
            else np.full(3, np.inf)
        off = np.linalg.norm(grid.origin_mm + h * first - (eye + t_hit * d))
        if 1 <= c <= spec.MAX_STRUCTURE_ID and off > 2 * h:
            grazed += 1
            t_vox, want = _voxel_walk(dens, lab, grid, eye, d, t_hit - h, t_hit + 2 * h,
                                      h / 16)
        t_tool, tool = min(((f(eye, d), cid) for cid, f in tools), default=(math.inf, 0))
        if t_tool < t_vox:
            want = tool
        checked += 1
        counts[want] = counts.get(want, 0) + 1
        if c != want:
            wrong.append(((v, u), c, want))
    assert checked > 500
    assert counts.get(1, 0) > 300 and counts.get(spec.CLASS_BURR, 0) > 5
    assert grazed <= 0.01 * checked, (grazed, checked)
    assert not wrong, wrong[:10]


def test_dust_and_water_pixels_lie_on_a_sprite_core(scene):
    res = scene["eyes"][0]
    cam = res["camera"]
    k = cam["K"]
    pts = res["points_case"]
    found = 0
    for cid, name in ((spec.CLASS_DUST, "dust"), (spec.CLASS_WATER, "water")):
        bufs = scene["sprites"][name]
        m = res["class"] == cid
        if not m.any():
            continue
        pos, radius, rgba = (np.asarray(b, np.float64) for b in bufs)
        alpha = rgba[:, 3] / 255.0
        keep = alpha >= spec.SPRITE_LABEL_OPACITY
        core = radius[keep] * np.sqrt(1 - np.sqrt(spec.SPRITE_LABEL_OPACITY / alpha[keep]))
        centres = pos[keep]
        cc = centres @ cam["R"].T + cam["t"]             # camera frame
        for p in pts[m]:
            pc = cam["R"] @ p + cam["t"]
            # on the sprite's screen-aligned disc: same depth, within its core
            # (one pixel's footprint of slack at the disc's edge)
            dz = np.abs(cc[:, 2] - pc[2])
            lat = np.linalg.norm(cc[:, :2] - pc[:2], axis=1)
            foot = pc[2] / k[0, 0]
            assert ((dz < 1e-3) & (lat <= core + foot)).any()
            found += 1
    assert found > 0                          # the frame shows dust or water


def test_stereo_disparity_agrees_with_depth(scene):
    left, right = scene["eyes"]
    cl, cr = left["camera"], right["camera"]
    k = cl["K"]
    np.testing.assert_allclose(cr["K"], k)
    np.testing.assert_allclose(cr["R"], cl["R"], atol=1e-12)
    # the right eye sits BASELINE_MM along the left one's +x
    np.testing.assert_allclose(cr["cam_to_case"][:3, 3] - cl["cam_to_case"][:3, 3],
                               BASELINE_MM * cl["R"][0], atol=1e-9)
    np.testing.assert_allclose(cr["t"] - cl["t"], [-BASELINE_MM, 0, 0], atol=1e-9)
    pix = _interior(left["class"], left["depth"], step=2)
    f = k[0, 0]
    errs = []
    h, w = left["depth"].shape
    for v, u in pix:
        z = float(left["depth"][v, u])
        p = left["points_case"][v, u].astype(np.float64)
        d_expect = f * BASELINE_MM / z
        ur = u - d_expect
        lo, hi = int(math.floor(ur)) - 4, int(math.ceil(ur)) + 5
        if lo < 0 or hi > w:
            continue
        # rectified: the point projects onto the same row of the right image
        (uvr,), _ = project(cr["K"], cr["R"], cr["t"], p[None])
        assert abs(uvr[1] - v) < 1e-3            # (points are float32)
        # where that row of the right image shows the same point: the segment
        # between two neighbouring pixels' points that passes nearest to it
        cand = right["points_case"][v, lo:hi].astype(np.float64)
        a, b = cand[:-1], cand[1:]
        ab = b - a
        den = np.einsum("ij,ij->i", ab, ab)
        with np.errstate(invalid="ignore", divide="ignore"):
            s_ = np.clip(np.einsum("ij,ij->i", p - a, ab) / den, 0.0, 1.0)
        near = a + s_[:, None] * ab
        dist = np.linalg.norm(near - p, axis=1)
        if not np.isfinite(dist).any():
            continue
        q = int(np.nanargmin(dist))
        if dist[q] > 0.5 * z / f:             # occluded in the right eye
            continue
        errs.append(abs((u - (lo + q + s_[q])) - d_expect))
    errs = np.array(errs)
    assert len(errs) > 300
    assert errs.max() <= 1.0, errs.max()


def test_intrinsics_reproject_a_known_point(scene):
    """The burr's centre placed in free space in front of the bone: its
    projection with K, R, t is the centre of the burr's pixels, and the
    depth there is the sphere's front."""
    fs, rend = scene["fs"], scene["rend"]
    eye, focal, up = fs.cameras[0]
    r0, _ = look_at(eye, focal, up)
    # off the optical axis toward the image's upper right, 15 mm before the
    # focal point (the bone's cortex), 25 mm from the eye
    c = np.asarray(focal) + 15.0 * (np.asarray(eye) - focal) / np.linalg.norm(
        np.asarray(eye) - focal) + 2.0 * r0[0] - 1.5 * r0[1]
    # the shaft leaves up the image, in the view plane: the sphere shows whole
    f = dataclasses.replace(fs.frame, pos_mm=c, axis=r0[1].copy(), drill=False)
    one = dataclasses.replace(fs, frame=f, cameras=fs.cameras[:1], suction=None)
    res = rend.render(one)[0]
    cam = res["camera"]
    r_expect, t_expect = look_at(eye, focal, up)
    np.testing.assert_allclose(cam["R"], r_expect, atol=1e-9)
    np.testing.assert_allclose(cam["t"], t_expect, atol=1e-7)
    w, h = SIZE
    fy = (h / 2) / math.tan(math.radians(15.0))       # the 30 degree view angle
    np.testing.assert_allclose(cam["K"], [[fy, 0, (w - 1) / 2], [0, fy, (h - 1) / 2],
                                          [0, 0, 1]], rtol=1e-12)
    (uv,), (z,) = project(cam["K"], cam["R"], cam["t"], c[None])
    m = res["class"] == spec.CLASS_BURR
    vv, uu = np.nonzero(m)
    assert m.sum() > 100
    # the sphere's outline is an ellipse centred a hair off the projected
    # centre (perspective); well inside half a pixel at this field of view
    assert abs(uu.mean() - uv[0]) < 0.5 and abs(vv.mean() - uv[1]) < 0.5
    ui, vi = int(round(uv[0])), int(round(uv[1]))
    assert res["class"][vi, ui] == spec.CLASS_BURR
    d, r1 = _rays(cam, np.array([[vi, ui]]))
    t = _ray_sphere(cam["cam_to_case"][:3, 3], d[0], c, float(f.burr.radius_mm))
    assert res["depth"][vi, ui] == pytest.approx(t / np.linalg.norm(r1[0]), abs=0.02)
    # and every drawn pixel's point projects back onto its pixel
    pts = res["points_case"]
    ok = np.isfinite(res["depth"])
    vs, us = np.nonzero(ok)
    uvs, _ = project(cam["K"], cam["R"], cam["t"], pts[ok].astype(np.float64))
    assert np.abs(uvs[:, 0] - us).max() < 1e-2 and np.abs(uvs[:, 1] - vs).max() < 1e-2


def test_normals_face_the_camera_and_fit_the_points(scene):
    res = scene["eyes"][0]
    n = res["normals"].astype(np.float64)
    pc = res["points_cam"].astype(np.float64)
    ok = np.isfinite(n).all(axis=2)
    assert ok.sum() > 0.5 * np.isfinite(res["depth"]).sum()
    np.testing.assert_allclose(np.linalg.norm(n[ok], axis=1), 1.0, atol=1e-5)
    assert ((n[ok] * pc[ok]).sum(axis=1) <= 1e-9).all()        # toward the eye
    # the burr's normals point away from its centre
    f = res["class"] == spec.CLASS_BURR
    cam = res["camera"]
    centre = cam["R"] @ scene["fs"].frame.pos_mm + cam["t"]
    radial = pc[f & ok] - centre
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    assert np.median((n[f & ok] * radial).sum(axis=1)) > 0.95


def test_a_moved_fragment_and_a_plate_carry_their_instance_ids(phantom):
    """A piece of the phantom split off as body 1 and lifted toward the camera,
    and a plate placed in front of the bone: the piece's pixels are bone of
    instance 1 lying where the piece now is, the plate's are class plate with
    its slot."""
    from types import SimpleNamespace

    from bonesim.engine.bodies import pose_matrix, publish_pose, publish_split_box
    from bonesim.engine.model import make_state
    from bonesim.engine.replica import TissueReplica
    from bonesim.engine.rigid import gravity_direction
    from bonesim.engine.rigid_set import RigidSet, publish_plate
    from bonesim.io.plates import default_plates
    from bonesim.session.playback import Frame
    from bonesim.session.dataset_frames import FrameState
    from tests.bonesim.render import scenes

    model = phantom
    state = make_state(model)
    rep = TissueReplica(model, state, surface=True)

    b, _ = publish_split_box(state, 0, scenes.PIECE_LO, scenes.PIECE_HI, 0.0)
    publish_pose(state, b, np.array([*scenes.PIECE_LIFT_MM, 1.0, 0.0, 0.0, 0.0]), 0.0)
    rs = RigidSet(model.max_bodies, gravity_dir=gravity_direction(model))
    spec_ = default_plates()[0]
    g = model.grid
    centre = g.origin_mm + g.spacing_mm * (np.add(scenes.PIECE_LO, scenes.PIECE_HI) / 2.0)
    plate_at = centre + np.array([4.0, -14.0, 0.0])
    s = rs.add_plate(spec_.pos, spec_.nrm, spec_.offset_mm, spec_.mass_kg,
                     spec_.stiffness_n_mm, (*plate_at, math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0),
                     catalog=0, axis=spec_.axis, samples=spec_.samples)
    publish_plate(state, rs, s, 0.0)
    rep.drain()
    assert sorted(rep.body_surfaces) == [0, b] and s in rep.plates
    player = SimpleNamespace(model=model, replica=rep, surface=rep.surface, grid=rep.grid,
                             burrs=[model.burr])
    far = np.array([60.0, 60.0, 60.0])                        # the burr out of sight
    frame = Frame(t_s=0.0, duration_s=1.0, index=0, pos_mm=far, axis=np.array([-1.0, 0, 0]),
                  drill=False, speed_rpm=0.0, direction=1, burr_index=0, burr=model.burr,
                  force_n=0.0, epoch=0, voxels_removed=0, volume_removed_mm3=0.0)
    eye = np.array(scenes.OBLIQUE_EYE)
    focal = np.array(scenes.OBLIQUE_FOCAL)
    fs = FrameState(frame, [(eye, focal, np.array(scenes.UP))])
    opts = DatasetOptions(size=SIZE, rgb=False, depth=True, seg=True, points=True)
    with DatasetRenderer(player, opts) as rend:
        res = rend.render(fs)[0]
        assert rend.stats["label_misses"] == 0
    piece = res["instance"] == b
    assert piece.sum() > 50
    assert set(np.unique(res["class"][piece]).tolist()) <= {1}           # bone
    # the piece's pixels lie on the piece where it now is (lifted)
    lo = g.origin_mm + g.spacing_mm * np.asarray(scenes.PIECE_LO) + scenes.PIECE_LIFT_MM
    hi = g.origin_mm + g.spacing_mm * np.asarray(scenes.PIECE_HI) + scenes.PIECE_LIFT_MM
    pts = res["points_case"][piece]
    assert ((pts >= lo - 0.5) & (pts <= hi + 0.5)).all()
    np.testing.assert_allclose(pose_matrix(rep.state.pose[b])[:, 3], scenes.PIECE_LIFT_MM)
    plate = res["class"] == spec.CLASS_PLATE
    assert plate.sum() > 20 and (res["instance"][plate] == s).all()
    main = (res["instance"] == 0) & (res["class"] == 1)
    assert main.sum() > 1000
