"""Datasets without drawing: options, classes, provenance, the OpenCV camera
conventions, depth from a depth buffer, normals, the voxel walk that labels
bone pixels, and the frames' dust (bonesim.session.dataset_*)."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.session import dataset_camera as dc
from bonesim.session import dataset_spec as spec
from bonesim.session.dataset_spec import DatasetOptions


# ----------------------------------------------------------------- options
def test_options_check_their_values():
    o = DatasetOptions()
    assert o.eyes == ("left",) and o.needs_labels and o.size == (640, 480)
    assert DatasetOptions(stereo_mm=5).eyes == ("left", "right")
    assert not DatasetOptions(depth=False, seg=False).needs_labels
    for kw, field in (({"camera": "side"}, "--camera"), ({"size": (8, 8)}, "--size"),
                      ({"fps": 0}, "--fps"), ({"stereo_mm": 0.0}, "--stereo"),
                      ({"zoom": -1}, "--zoom"), ({"suction": "on"}, "--suction")):
        with pytest.raises(BonesimError) as exc:
            DatasetOptions(**kw)
        assert exc.value.field == field
    with pytest.raises(BonesimError, match="nothing to write"):
        DatasetOptions(rgb=False, depth=False, seg=False)
    d = DatasetOptions(size=(320, 240)).to_dict()
    assert d["size"] == [320, 240] and spec.to_json(d) == spec.to_json(dict(d))


def test_class_table_names_structures_then_fixed_ids():
    st = [SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200)),
          SimpleNamespace(name="facial_nerve", kind="critical", display_color=(250, 230, 40))]
    t = {c["id"]: c for c in spec.class_table(st)}
    assert t[0]["name"] == "background" and t[1]["name"] == "bone"
    assert t[2]["shown_as"] == "Facial nerve" and t[2]["rgb"] == [250, 230, 40]
    assert [t[i]["name"] for i in (200, 201, 202, 210, 211, 220, 255)] == \
        ["burr", "shaft", "suction", "dust", "water", "plate", "other"]
    with pytest.raises(BonesimError):
        spec.class_table([st[0]] * 200)


def test_provenance_names_the_run_by_hash_not_path(tmp_path):
    p = tmp_path / "run.h5"
    p.write_bytes(b"abc")
    s = SimpleNamespace(path=p, header={"case": {"name": "phantom", "path": "/x/case.toml",
                                                 "sha256": "f00"}})
    prov = spec.provenance(s, DatasetOptions(), 5, ["note"])
    assert prov["run_sha256"] == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    assert prov["run_name"] == "run.h5" and prov["frames"] == 5 and prov["notes"] == ["note"]
    assert prov["case"] == {"name": "phantom", "sha256": "f00"}
    assert str(tmp_path) not in spec.to_json(prov)


# ------------------------------------------------------------------ cameras
def _vtk_view(eye, focal, up):
    """VTK's view transform of a camera (its x right, y up, z toward the eye)."""
    z = np.asarray(eye, float) - focal
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z])
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def _vtk_projection(view_angle_deg, aspect, near, far):
    f = 1.0 / math.tan(math.radians(view_angle_deg) / 2)
    p = np.zeros((4, 4))
    p[0, 0], p[1, 1] = f / aspect, f
    p[2, 2] = -(far + near) / (far - near)
    p[2, 3] = -2 * far * near / (far - near)
    p[3, 2] = -1.0
    return p


def test_extrinsics_and_intrinsics_follow_opencv():
    eye, focal, up = np.array([100.0, 5, 3]), np.array([10.0, 2, 1]), np.array([0, 0, 1.0])
    r, t = dc.opencv_extrinsics(_vtk_view(eye, focal, up))
    r2, t2 = dc.look_at(eye, focal, up)
    np.testing.assert_allclose(r, r2, atol=1e-12)
    np.testing.assert_allclose(t, t2, atol=1e-12)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(dc.cam_to_case(r, t)[:3, 3], eye)
    w, h = 640, 480
    k = dc.opencv_intrinsics(_vtk_projection(30.0, w / h, 10, 200), (w, h))
    assert k[0, 0] == pytest.approx(240 / math.tan(math.radians(15)))
    assert k[0, 0] == pytest.approx(k[1, 1]) and (k[0, 2], k[1, 2]) == (319.5, 239.5)
    # the focal point is the image centre; up in the case is up the image (v smaller)
    (uv, above), z = dc.project(k, r, t, np.stack([focal, focal + [0, 0, 5]]))
    np.testing.assert_allclose(uv, [319.5, 239.5], atol=1e-9)
    assert above[1] < 239.5 and z[0] == pytest.approx(np.linalg.norm(eye - focal))
    with pytest.raises(ValueError):
        bad = _vtk_projection(30.0, 1.0, 1, 2)
        bad[0, 2] = 0.1
        dc.opencv_intrinsics(bad, (10, 10))


def test_depth_buffer_to_metric_depth_and_back_to_points():
    p = _vtk_projection(30.0, 4 / 3, 40.0, 180.0)
    z = np.array([[40.0, 75.5], [179.9, 100.0]])
    ndc = (p[2, 2] * -z + p[2, 3]) / z                 # OpenGL: clip z / w
    zb = (ndc + 1) / 2
    zb[1, 1] = 1.0                                     # nothing drawn
    d = dc.depth_from_zbuffer(zb, p)
    np.testing.assert_allclose(d[~np.isnan(d)], [40.0, 75.5, 179.9], rtol=1e-6)
    assert np.isnan(d[1, 1]) and d.dtype == np.float32
    k = np.array([[100.0, 0, 0.5], [0, 100.0, 0.5], [0, 0, 1]])
    pts = dc.points_from_depth(np.full((2, 2), 50.0, np.float32), k)
    np.testing.assert_allclose(pts[:, :, 2], 50.0)
    (uv,), _ = dc.project(k, np.eye(3), np.zeros(3), pts[1, 0][None].astype(float))
    np.testing.assert_allclose(uv, [0.0, 1.0], atol=1e-5)


def test_normals_of_a_tilted_plane_face_the_camera():
    k = np.array([[200.0, 0, 31.5], [0, 200.0, 23.5], [0, 0, 1]])
    rays = dc.pixel_rays(k, (64, 48))
    nrm = np.array([0.3, -0.2, -1.0])
    nrm /= np.linalg.norm(nrm)
    # plane n . X = -60 (60 mm in front, facing the eye)
    depth = (-60.0 / (rays @ nrm)).astype(np.float32)
    depth[10:14, 20:24] = np.nan
    n = dc.normals_from_points(dc.points_from_depth(depth, k))
    ok = np.isfinite(n).all(axis=2)
    assert ok.sum() > 0.9 * depth.size
    np.testing.assert_allclose(n[ok], np.broadcast_to(nrm, n[ok].shape), atol=1e-3)
    assert not ok[11, 21]


def test_stereo_pair_is_parallel_and_orbit_keeps_its_distance():
    eye, focal, up = np.array([0.0, 0, 100]), np.zeros(3), np.array([0, 1.0, 0])
    (le, lf, _), (re, rf, _) = dc.stereo_cameras(eye, focal, up, 6.0)
    r, _ = dc.look_at(eye, focal, up)
    np.testing.assert_allclose(re - le, 6.0 * r[0])
    np.testing.assert_allclose(rf - re, lf - le)           # parallel axes
    assert dc.stereo_cameras(eye, focal, up, None)[0][0] is not None
    cam = SimpleNamespace(eye_mm=eye, focal_mm=focal, up=up)
    for t in (0.0, 3.0, 7.0):
        e, f, _ = dc.orbit_camera(cam, t, 25.0, 12.0)
        assert np.linalg.norm(e - f) == pytest.approx(100.0)
        cosang = (e - f) @ (eye - focal) / 100.0 ** 2
        assert math.degrees(math.acos(cosang)) == pytest.approx(25.0)
    e0, _, _ = dc.orbit_camera(cam, 0.0, 25.0, 12.0)
    assert e0[1] > 0                                        # tilted toward the image's up
    e, f, _ = dc.frame_camera("recorded", 1.0, None, cam, zoom=2.0)
    np.testing.assert_allclose(e, [0, 0, 50.0])


# ---------------------------------------------------------------- the walk
def test_voxel_walk_finds_the_first_voxel_of_the_hit_body():
    from bonesim.engine.grid import Grid
    from bonesim.session.dataset_labels import first_voxel_labels

    lab = np.zeros((20, 20, 20), np.uint8)
    lab[:, :, :10] = 1
    lab[8:12, 8:12, 9] = 2                # a structure on the top face
    g = Grid.from_dense(lab, spacing_mm=0.5)
    body = np.zeros_like(g.density, dtype=np.uint8)
    top = 9 * 0.5                          # centre of the top voxels [mm]
    # rays straight down, hitting the drawn surface at the top voxels' centres
    xs = np.array([5.0, 2.0, 7.5])
    orgs = np.stack([xs, np.full(3, 5.0), np.full(3, 50.0)], 1)
    dirs = np.tile([0.0, 0.0, -1.0], (3, 1))
    t_hit = 50.0 - top
    labels, misses = first_voxel_labels(g, body, np.zeros(3, np.int64), orgs, dirs,
                                        np.full(3, t_hit))
    assert labels.tolist() == [2, 1, 1] and misses == 0
    # another body's voxels are passed over
    other = body.copy()
    other[:] = 1
    labels, misses = first_voxel_labels(g, other, np.zeros(3, np.int64), orgs, dirs,
                                        np.full(3, t_hit))
    assert labels.tolist() == [0, 0, 0] and misses == 3
    # an oblique ray, and one that starts past the surface's voxels' cubes
    d = np.array([[0.6, 0.0, -0.8]])
    o = np.array([[2.0, 5.0, top + 0.25]]) - 10.0 * d
    labels, _ = first_voxel_labels(g, body, np.zeros(1, np.int64), o, d, np.array([10.0]))
    assert labels.tolist() == [1]


# ------------------------------------------------------------------- frames
def test_dust_is_the_same_whatever_the_frame_rate(demo_run):
    from bonesim.session.dataset_frames import FrameSource
    from bonesim.session.reader import read_session

    slow = FrameSource(read_session(demo_run), DatasetOptions(fps=1.0, start=5.0))
    slow.at(5.0)
    a = slow.at(6.0)
    fast = FrameSource(read_session(demo_run), DatasetOptions(fps=10.0, start=5.0))
    for t in fast.times:
        if t > 6.0 + 1e-9:
            break
        b = fast.at(float(t))
    assert b.frame.t_s == pytest.approx(6.0)
    for x, y in zip(a.dust, b.dust):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert len(a.dust.positions) > 0                  # the burr made dust by then
    assert a.suction is not None and a.frame.drill      # the suction tube follows
    with pytest.raises(ValueError, match="time order"):
        slow.at(1.0)
    off = FrameSource(read_session(demo_run), DatasetOptions(suction="off", start=6.0))
    assert off.at(6.0).suction is None and not off.at(6.5).irrigation
