"""Offscreen pictures of rigid motion against stored references: a fragment
of mastoid cut free and lifted out by the tool (tinted), and a bone plate
dropped on the mastoid, come to rest and affixed.

Regenerate the references after an intended change with::

    BONESIM_UPDATE_IMAGES=1 python -m pytest tests/bonesim/render/test_rigid_images.py
"""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine.rigid import AFFIXED, ASLEEP, gravity_direction
from bonesim.engine.rigid_set import RigidSet, publish_plate
from bonesim.render.bodyview import PLATE_COLOR, fragment_tint
from tests.bonesim.render import scenes
from tests.bonesim.render.test_images import check, region_mean

#: The piece the lift picture frees (voxel box, inclusive) and how far the
#: tool lifts it against gravity [mm].
PIECE_LO, PIECE_HI = scenes.PIECE_LO, scenes.PIECE_HI
LIFT_MM = 9.0
#: The plate is dropped from this far above the bone along the camera ray [mm].
DROP_MM = 2.0


def _camera_hit(model, eye, focal):
    """The first bone voxel centre on the ray eye -> focal [mm], and the
    ray's unit direction."""
    from bonesim.engine.grid import find_brick, voxel_offset

    g = model.grid
    d = np.subtract(focal, eye)
    d /= np.linalg.norm(d)
    for s in np.arange(0.0, 200.0, 0.1):
        p = np.asarray(eye) + s * d
        ijk = np.rint((p - g.origin_mm) / g.spacing_mm).astype(int)
        if (ijk < 0).any() or (ijk >= np.asarray(g.shape)).any():
            continue
        b = find_brick(g.keys, g.vals, ijk[0] >> 3, ijk[1] >> 3, ijk[2] >> 3)
        if b >= 0 and g.density[b, voxel_offset(*ijk)] > 0:
            return p, d
    raise AssertionError("the camera ray hits no bone")


def lifted_fragment(model, **scene_kw):
    """(scene, replica, rigid set): the piece split off, grabbed by the tool
    at its top and lifted ``LIFT_MM`` against gravity through the rigid step."""
    from bonesim.engine.bodies import publish_split_box
    from bonesim.engine.model import make_state
    from bonesim.engine.replica import TissueReplica
    from bonesim.render.scene import Scene

    state = make_state(model)
    rep = TissueReplica(model, state, surface=True)
    b, _ = publish_split_box(state, 0, PIECE_LO, PIECE_HI, 0.0)
    rs = RigidSet(model.max_bodies, gravity_dir=gravity_direction(model))
    g = model.grid
    up = -rs.gvec / np.linalg.norm(rs.gvec)
    centre = g.origin_mm + g.spacing_mm * (np.add(PIECE_LO, PIECE_HI) / 2.0)
    tool = centre.copy()
    s = rs.wake_body(state, b, at_once=True)         # measured now: no loop runs here
    rs.grab(state, s, tool)
    for q in range(1500):
        f = min(1.0, q / 1000.0)
        rs.advance(state, q * 1e-3, tool + LIFT_MM * f * up, False, 2.5, 1.0)
    ch = rep.drain()
    scene_kw.setdefault("size", scenes.SIZE)
    scene = Scene.from_model(model, rep.surface, **scene_kw)
    scene.update_bodies(rep, ch.changed, ch.touched)
    scene.set_hud({})
    scene.set_camera(scenes.OBLIQUE_EYE, scenes.OBLIQUE_FOCAL, scenes.UP)
    return scene, rep, rs


def affixed_plate(model, **scene_kw):
    """(scene, replica, rigid set): the straight 4-hole plate dropped on the
    mastoid under the case camera's focus, at rest, affixed to the bone."""
    from bonesim.engine.model import make_state
    from bonesim.engine.replica import TissueReplica
    from bonesim.io.plates import default_plates
    from bonesim.render.scene import Scene
    from bonesim.engine.world_commands import down_pose

    state = make_state(model)
    rep = TissueReplica(model, state, surface=True)
    cam = model.case.camera
    hit, view = _camera_hit(model, cam.eye_mm, cam.focal_mm)
    rs = RigidSet(model.max_bodies, gravity_dir=gravity_direction(model))
    spec = default_plates()[0]
    pose = down_pose(hit - (DROP_MM + 1.0) * view, rs.gvec / np.linalg.norm(rs.gvec))
    s = rs.add_plate(spec.pos, spec.nrm, spec.offset_mm, spec.mass_kg, spec.stiffness_n_mm,
                     pose, catalog=0, axis=spec.axis, samples=spec.samples)
    publish_plate(state, rs, s, 0.0)
    for q in range(4000):
        rs.advance(state, q * 1e-3, np.array([1e3, 1e3, 1e3]), False, 2.5, 1.0)
        if rs.mode[s] == ASLEEP:
            break
    rs.affix(state, s)
    publish_plate(state, rs, s, 4.0)
    ch = rep.drain()
    scene_kw.setdefault("size", scenes.SIZE)
    scene = Scene.from_model(model, rep.surface, **scene_kw)
    scene.update_bodies(rep, ch.changed, ch.touched)
    scene.set_hud({})
    eye = hit - 40.0 * view + np.array([0.0, -28.0, 22.0])
    scene.set_camera(tuple(eye), tuple(hit), scenes.UP)
    return scene, rep, rs


@pytest.fixture(scope="module")
def pictures(phantom):
    out = {}
    for name, build in (("fragment_lifted", lifted_fragment), ("plate_affixed", affixed_plate)):
        sc, rep, rs = build(phantom, visible_subset=False)
        out[name] = (sc.image(), rep, rs)
        sc.close()
    return out


@pytest.mark.parametrize("name", ["fragment_lifted", "plate_affixed"])
def test_matches_reference(pictures, name, tmp_path):
    img = pictures[name][0]
    assert img.shape == (300, 400, 3)
    check(name, img, tmp_path)


def test_the_lifted_fragment_is_tinted_and_out_of_its_hole(pictures):
    img, rep, rs = pictures["fragment_lifted"]
    s = rs.slot_of(1)
    assert rep.state.pose[1][:3] @ (-rs.gvec) > 0              # moved against gravity
    lift = np.linalg.norm(rep.state.pose[1][:3])
    assert lift == pytest.approx(LIFT_MM, abs=0.3)
    assert rs.mode[s] != 0
    # its tint (orange: red over green over blue, shaded or not) is in the
    # picture, where the untinted bone (nearly grey) and the structures are not
    tint = np.array(fragment_tint(1))
    assert tint[0] > tint[1] > tint[2]
    c = img.astype(int)
    orange = (c[..., 0] - c[..., 1] > 25) & (c[..., 1] - c[..., 2] > 25)
    assert orange.mean() > 0.03


def test_the_affixed_plate_rests_on_the_bone_in_titanium_grey(pictures):
    img, rep, rs = pictures["plate_affixed"]
    s = rs.last_plate
    assert rs.mode[s] == AFFIXED and rs.host[s] == 0
    assert set(rep.plates) == {s}                              # the replica follows it
    grey = (np.array(PLATE_COLOR) * 255).astype(int)
    assert region_mean(img, tuple(grey), tol=60) > 0.01
