"""Scenes of the cut plane and of irrigation for the reference pictures
(:mod:`tests.bonesim.render.test_cut_water_images`)."""
from __future__ import annotations

import numpy as np

from tests.bonesim.render.scenes import HUD, SIZE, UP

#: The box cut: four slots (strokes :data:`SLOT_MM` wide) along the edges of
#: a rectangle on the lateral cortex (the face at x of about 20 mm, looked at
#: along -x): the rectangle's centre [mm] (1 mm off the bone), its size
#: along y and z [mm], the slots' depth [mm].
BOX_CENTRE_MM = (21.0, 4.0, 0.0)
BOX_SIZE_MM = (14.0, 10.0)
BOX_DEPTH_MM = 6.0
SLOT_MM = 0.5
#: ... and one plane cut beside it: a window (y, z size [mm]) cut flat 4.5 mm
#: in from 1 mm off the bone.
WINDOW_CENTRE_MM = (21.0, -9.0, 7.0)
WINDOW_SIZE_MM = (8.0, 6.0)
WINDOW_DEPTH_MM = 4.5
#: An oblique view onto the lateral face that shows the depth of the cuts.
CUT_EYE = (85.0, -30.0, 28.0)
CUT_FOCAL = (19.0, -3.0, 3.0)

#: Irrigation: a basin cut flat into the lateral cortex (centre [mm], y and
#: z size [mm], depth from 1 mm off the bone [mm]), the dust of its bone (one
#: removed voxel in :data:`DUST_KEPT`: the rest went up the suction), the
#: irrigator's tip over it [mm], how long water runs [s], then how long it
#: settles [s]. Gravity along -x: the surgeon looks down into the basin.
BASIN_CENTRE_MM = (21.0, 4.0, 0.0)
BASIN_SIZE_MM = (12.0, 10.0)
BASIN_DEPTH_MM = 3.0
DUST_KEPT = 3
IRRIGATE_AT_MM = (19.0, 1.0, 2.0)
IRRIGATE_S = 8.0
SETTLE_S = 1.0
GRAVITY = (-1.0, 0.0, 0.0)
#: A view down into the basin, a little oblique.
WATER_EYE = (60.0, -6.0, 18.0)
WATER_FOCAL = (16.0, 3.0, 0.0)


def box_cut(model, state, t_s=0.0):
    """Cut the box outline and the window into ``state``; returns the voxels
    removed (n, 3)."""
    from bonesim.engine import events
    from bonesim.engine.cut_plane import plane_pose, publish_cut

    start = state.tissue.count
    into = (-1.0, 0.0, 0.0)
    c = np.asarray(BOX_CENTRE_MM)
    wy, hz = BOX_SIZE_MM
    # each stroke: centre offset (y, z), width along y, height along z
    slots = (((0.0, hz / 2), wy, SLOT_MM), ((0.0, -hz / 2), wy, SLOT_MM),
             ((wy / 2, 0.0), SLOT_MM, hz), ((-wy / 2, 0.0), SLOT_MM, hz))
    for (dy, dz), w, h in slots:
        # width axis u = +y, so v = n x u = (-x) x y = -z: height along z
        publish_cut(state, model.injury, plane_pose(c + (0.0, dy, dz), into, (0, 1, 0)),
                    w, h, BOX_DEPTH_MM, t_s)
    publish_cut(state, model.injury, plane_pose(WINDOW_CENTRE_MM, into, (0, 1, 0)),
                *WINDOW_SIZE_MM, WINDOW_DEPTH_MM, t_s)
    ev = events.removals(state.tissue.read(start))
    return ev["ijk"]


def cut_scene(model):
    from bonesim.engine.model import make_state
    from bonesim.engine.surface import Surface
    from bonesim.render.scene import Scene

    state = make_state(model)
    surf = Surface.of_model(model, state.grid)
    scene = Scene.from_model(model, surf, size=SIZE)
    scene.set_hud({})
    removed = box_cut(model, state)
    surf.update(state.grid, removed)
    scene.update_surface(surf)
    scene.set_camera(CUT_EYE, CUT_FOCAL, UP)
    return scene, state, removed


def irrigated_dust(grid, removed):
    """The dust of one in :data:`DUST_KEPT` of ``removed`` settled 1 s along
    :data:`GRAVITY`, then irrigated for :data:`IRRIGATE_S` and left
    :data:`SETTLE_S`."""
    from bonesim.physics.dust.grid import DustGrid

    dust = DustGrid.for_grid(grid, GRAVITY)
    dust.add_removed(removed[::DUST_KEPT])
    dt = 1.0 / 60.0
    for _ in range(60):
        dust.step(grid, dt)
    for _ in range(int(round(IRRIGATE_S / dt))):
        dust.step(grid, dt, irrigation_pos_mm=IRRIGATE_AT_MM, irrigation_radius_mm=2.0)
    for _ in range(int(round(SETTLE_S / dt))):
        dust.step(grid, dt)
    return dust


def water_scene(model):
    from bonesim.engine import events
    from bonesim.engine.cut_plane import plane_pose, publish_cut
    from bonesim.engine.model import make_state
    from bonesim.engine.surface import Surface
    from bonesim.physics.dust.water import water_sprites
    from bonesim.render.scene import Scene

    state = make_state(model)
    surf = Surface.of_model(model, state.grid)
    scene = Scene.from_model(model, surf, size=SIZE)
    publish_cut(state, model.injury, plane_pose(BASIN_CENTRE_MM, (-1, 0, 0), (0, 1, 0)),
                *BASIN_SIZE_MM, BASIN_DEPTH_MM, 0.0)
    removed = events.removals(state.tissue.read(0))["ijk"]
    surf.update(state.grid, removed)
    scene.update_surface(surf)
    scene.set_camera(WATER_EYE, WATER_FOCAL, UP)
    dust = irrigated_dust(state.grid, removed)
    scene.set_dust(*dust.sprites())
    scene.set_water(*water_sprites(dust))
    scene.set_hud(dict(HUD, irrigation=True))
    return scene, dust
