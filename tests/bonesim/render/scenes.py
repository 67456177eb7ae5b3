"""Deterministic scenes for the rendering tests (phantom case, 400 x 300)."""
from __future__ import annotations

import numpy as np

from bonesim.engine.grid import BRICK_SHIFT

SIZE = (400, 300)

#: Close view of the lateral mastoid (looking medially, superior up).
CLOSE_EYE = (75.0, 4.0, -4.0)
CLOSE_FOCAL = (8.0, 4.0, -4.0)
UP = (0.0, 0.0, 1.0)

#: Fixed HUD (no measured rates, so the text is the same on every run).
HUD = {"case": "phantom", "burr": "cutting-5mm", "burr_kind": "cutting",
       "burr_diameter_mm": 5.0, "drill": True, "direction": 1, "speed_rpm": 60000,
       "force_n": 1.25, "haptic_hz": 1000, "frame_hz": 60, "elapsed_s": 12.5,
       "injuries": 0}


def nerve_block(shape=(32, 32, 24)):
    """(model, state): a bone block (k < 16, top face +z) with a nerve rod
    along x at k = 8..9, j = 14..17 (fake materials; 0.5 mm voxels)."""
    from tests.bonesim.fakes import BONE, NERVE, block_model

    labels = np.zeros(shape, np.uint8)
    labels[:, :, :16] = 1
    labels[:, 14:18, 8:10] = 2
    return block_model(shape=shape, labels=labels, structures=[BONE, NERVE])


def voxel_table(grid):
    """(brick, offset, ijk, centre_mm, label) of every occupied voxel."""
    b, o = np.nonzero(grid.density > 0)
    loc = np.stack([(o >> 6) & 7, (o >> 3) & 7, o & 7], axis=1)
    ijk = (grid.bricks[b].astype(np.int64) << BRICK_SHIFT) + loc
    xyz = grid.origin_mm + grid.spacing_mm * ijk
    return b, o, ijk.astype(np.int32), xyz, grid.label[b, o]


def mastoid_cavity(grid, bone_label=1):
    """Remove the bone over the sigmoid sinus and the facial nerve's mastoid
    segment (two lateral-to-medial cylinders), leaving every other tissue.

    Returns the removed voxels (n, 3) int32; densities are zeroed in place."""
    b, o, ijk, xyz, lab = voxel_table(grid)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    over_sinus = (x > 9.0) & ((y - 11.0) ** 2 + (z + 3.0) ** 2 < 6.0 ** 2)
    over_nerve = (x > 6.6) & ((y + 1.0) ** 2 + (z + 6.5) ** 2 < 4.5 ** 2)
    sel = (lab == bone_label) & (over_sinus | over_nerve)
    grid.density[b[sel], o[sel]] = 0.0
    return ijk[sel]


def dust_cloud(seed=3, n=400, centre=(9.5, 2.0, -11.5)):
    """A small pile of dust cells at the bottom of the cavity."""
    rng = np.random.default_rng(seed)
    p = np.asarray(centre) + rng.normal(0.0, 1.0, (n, 3)) * (0.6, 2.2, 0.7)
    d = rng.uniform(0.15, 1.0, n)
    return p.astype(np.float32), d.astype(np.float32)


def drilling_dust(grid, removed):
    """The dust of ``removed`` bone falling along the close view's axis (the
    app's gravity is the view direction): settled for 1 s, then the nerve's
    cavity irrigated for 0.5 s and drained for 0.5 s, then 0.3 s of suction
    at the sinus cavity's floor."""
    from bonesim.physics.dust.grid import DustGrid

    g = np.subtract(CLOSE_FOCAL, CLOSE_EYE)
    dust = DustGrid.for_grid(grid, g)
    dust.add_removed(removed)
    dt = 1.0 / 60.0
    for _ in range(60):
        dust.step(grid, dt)
    for n in range(60):
        wet = (8.0, -1.0, -6.5) if n < 30 else None
        dust.step(grid, dt, irrigation_pos_mm=wet, irrigation_radius_mm=4.0)
    for _ in range(18):
        dust.step(grid, dt, suction_pos_mm=(10.0, 12.0, -2.0), suction_radius_mm=3.0)
    return dust


#: The piece of lateral mastoid :func:`bodies_moved` splits off: voxel box
#: (inclusive) of about 8 x 10 x 10 mm under the case camera's focus.
PIECE_LO, PIECE_HI = (78, 44, 40), (94, 63, 59)
#: It is lifted this far toward the case camera (+x) [mm] ...
PIECE_LIFT_MM = (8.0, 0.0, 0.0)
#: ... and turned this much about z through its centre [deg].
PIECE_TURN_DEG = 30.0
#: An oblique view that shows both the lifted piece and the hole it left.
OBLIQUE_EYE = (80.0, -50.0, 30.0)
OBLIQUE_FOCAL = (16.0, 2.0, -1.0)


def bodies_moved(model, **scene_kw):
    """(scene, replica): the phantom with a box of lateral mastoid split off
    as body 1 (:data:`PIECE_LO` .. :data:`PIECE_HI`), lifted
    :data:`PIECE_LIFT_MM` toward the case camera and turned
    :data:`PIECE_TURN_DEG` about z through its centre, drawn by
    ``Scene.update_bodies`` from a replica that followed the events, seen
    from :data:`OBLIQUE_EYE`."""
    from bonesim.engine.bodies import publish_pose, publish_split_box
    from bonesim.engine.model import make_state
    from bonesim.engine.replica import TissueReplica
    from bonesim.render.scene import Scene

    state = make_state(model)
    rep = TissueReplica(model, state, surface=True)
    b, n = publish_split_box(state, 0, PIECE_LO, PIECE_HI, 0.0)
    g = model.grid
    centre = g.origin_mm + g.spacing_mm * (np.add(PIECE_LO, PIECE_HI) / 2.0)
    half = np.radians(PIECE_TURN_DEG) / 2.0
    q = np.array([np.cos(half), 0.0, 0.0, np.sin(half)])
    c, s_ = np.cos(2 * half), np.sin(2 * half)
    rot = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    t = centre - rot @ centre + np.asarray(PIECE_LIFT_MM)
    publish_pose(state, b, np.concatenate((t, q)), 0.0)
    ch = rep.drain()
    scene_kw.setdefault("size", SIZE)
    scene = Scene.from_model(model, rep.surface, **scene_kw)
    scene.update_bodies(rep, ch.changed, ch.touched)
    scene.set_hud({})
    scene.set_camera(OBLIQUE_EYE, OBLIQUE_FOCAL, UP)
    return scene, rep


def build(model, which: str, **scene_kw):
    """A Scene of the named reference picture.

    ``bone``     intact phantom from the case camera, no tool, no HUD
    ``drilled``  cavity over sinus and facial nerve, burr in the cavity,
                 dust, fixed HUD, close view
    ``tool``     close-up of the running burr over intact bone with dust
    ``drilled_moved``  ``drilled`` with the burr 1 mm away (must not match)
    ``tool_nodust``, ``tool_notool``  ``tool`` without the dust / the tool
    ``dust``     ``drilled`` with the removed bone turned into dust
                 (:func:`drilling_dust`): settled, partly irrigated (wet
                 paste), partly suctioned; the burr buried in the bone beside
                 the cavity, drawn as a silhouette
    """
    from bonesim.engine.model import make_state
    from bonesim.render.scene import Scene
    from bonesim.engine.surface import Surface

    state = make_state(model)
    surf = Surface.of_model(model, state.grid)     # as the app: thin bone tinted
    scene_kw.setdefault("size", SIZE)
    scene = Scene.from_model(model, surf, **scene_kw)
    scene.set_hud({})
    if which == "bone":
        pass
    elif which in ("drilled", "drilled_moved"):
        removed = mastoid_cavity(state.grid)
        surf.update(state.grid, removed)
        scene.update_surface(surf)
        scene.set_camera(CLOSE_EYE, CLOSE_FOCAL, UP)
        dx = 1.0 if which == "drilled_moved" else 0.0
        scene.set_tool((12.5, 8.0 + dx, 1.0), (-1.0, 0.2, -0.4), 2.5, True)
        scene.set_dust(*dust_cloud(), cell_mm=0.8)
        scene.set_hud(HUD)
    elif which == "dust":
        from bonesim.physics.sightline import depth_below_surface_mm

        removed = mastoid_cavity(state.grid)
        surf.update(state.grid, removed)
        scene.update_surface(surf)
        scene.set_camera(CLOSE_EYE, CLOSE_FOCAL, UP)
        scene.set_dust(*drilling_dust(state.grid, removed).sprites())
        pos = np.array([6.0, 4.0, -1.0])                      # in the bone between
        d = depth_below_surface_mm(state.grid, pos, CLOSE_EYE, 1.5)
        scene.set_tool(pos, (-1.0, 0.2, -0.4), 1.5, True, depth_mm=d)
        scene.set_hud(dict(HUD, depth_mm=d))
    elif which in ("tool", "tool_nodust", "tool_notool"):
        scene.set_camera((60.0, 4.0, 8.0), (19.0, 4.0, -3.0), UP)
        if which != "tool_notool":
            scene.set_tool((21.6, 4.0, -3.0), (-0.6, -0.8, 0.1), 2.5, True)
        if which != "tool_nodust":
            p, d = dust_cloud(seed=5, n=300, centre=(20.8, 4.0, -6.0))
            scene.set_dust(p, d, cell_mm=1.0)
    else:
        raise ValueError(which)
    return scene, surf, state
