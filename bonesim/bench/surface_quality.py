"""How smooth the drawn bone surface is over a drilled floor:
``surface_roughness_deg`` of ``bonesim bench``.

A bone block (:data:`BLOCK_VOXELS` at :data:`VOXEL_MM`, top face +z) is
drilled flat by the engine itself: the ``cutting-5mm`` burr, axis straight
down, swept in a raster of lines :data:`PITCH_MM` apart at
:data:`SPEED_MM_S`, one :func:`bonesim.engine.model.step` per millisecond,
along a plane :data:`DEPTH_MM` under the top face at the raster's centre and
tilted by :data:`TILT_DEG` about y (a floor is never aligned with the voxel
grid; tilted, it crosses several voxel layers, as a real floor does). The
floor it leaves is a plane with the burr's shallow scallops, and partly
drilled voxels along every stroke, as drilling leaves them.

The *floor* is the set of surface vertices whose voxel centre lies inside
the raster's area shrunk by :data:`FLOOR_MARGIN_MM` (away from the walls)
and more than a voxel below the block's top face. Over every edge of the mesh with both ends
on the floor, the angle between the normals at its two ends is taken; the
figure is their mean [deg]. Three sets of normals are compared on the same
edges, in the same run:

``render``
    the surface's vertex normals, the ones the renderer lights
    (:mod:`bonesim.engine.normals`): the benchmark's value;
``voxel``
    the plain voxel surface's own normals: every vertex at its voxel's
    centre (the thesis design), its normal the area-weighted mean of its
    triangles' face normals, as a flat-shaded voxel mesh shows;
``render_geometry``
    the same for the drawn mesh (vertices at their drawn, sub-voxel
    positions): how flat the drawn floor is as geometry.

A perfectly flat floor gives 0 for all three; the scallops of a 1.25 mm
raster with a 5 mm burr tilt the true surface by at most a few degrees.
"""
from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np

__all__ = ["VOXEL_MM", "BLOCK_VOXELS", "TOP_VOXELS", "DEPTH_MM", "TILT_DEG", "PITCH_MM",
           "SPEED_MM_S",
           "RASTER_MM", "FLOOR_MARGIN_MM", "drilled_floor", "floor_vertices", "edges_of",
           "mesh_normals", "mean_edge_angle_deg", "surface_roughness",
           "bench_surface_roughness"]

#: Voxel edge of the block [mm].
VOXEL_MM = 0.5
#: Block size [voxels] (i, j, k).
BLOCK_VOXELS = (100, 100, 50)
#: Bone fills ``k < TOP_VOXELS``.
TOP_VOXELS = 40
#: Depth of the burr's lowest point under the top face [mm].
DEPTH_MM = 1.5
#: Tilt of the floor's plane about the y axis [deg].
TILT_DEG = 8.0
#: Distance between the raster's lines [mm].
PITCH_MM = 1.25
#: Burr speed along a line [mm/s].
SPEED_MM_S = 15.0
#: The raster's span along x and y [mm] (burr centre), (lo, hi).
RASTER_MM = (14.0, 36.0)
#: The floor keeps this far [mm] inside the burr centre's span.
FLOOR_MARGIN_MM = 3.0
#: The burr the floor is drilled with.
BURR = "cutting-5mm"


def drilled_floor(burr: str = BURR):
    """Drill the bench block flat (module docstring).

    Returns
    -------
    model : bonesim.engine.model.Model
    state : bonesim.engine.model.State
        After the raster; ``state.grid`` holds the drilled bone.
    steps : int
        Haptic steps taken (1 ms each).
    """
    from bonesim.engine.model import Sample, make_model, make_state, step
    from bonesim.io.burrs import load_burr

    b = load_burr(burr)
    labels = np.zeros(BLOCK_VOXELS, np.uint8)
    labels[:, :, :TOP_VOXELS] = 1
    bone = SimpleNamespace(name="bone", kind="bone", display_color=(235, 225, 200))
    model = make_model(labels, VOXEL_MM, [bone], b)
    state = make_state(model)
    top = (TOP_VOXELS - 0.5) * VOXEL_MM              # the block's top face [mm]
    lo, hi = RASTER_MM
    slope = math.tan(math.radians(TILT_DEG))
    mid = 0.5 * (lo + hi)
    axis = np.array([0.0, 0.0, -1.0])
    dt = 1e-3
    xs = np.arange(lo, hi, SPEED_MM_S * dt)
    t, n = 0.0, 0
    for line, y in enumerate(np.arange(lo, hi, PITCH_MM)):
        for x in (xs if line % 2 == 0 else xs[::-1]):
            zc = top + b.radius_mm - DEPTH_MM + slope * (x - mid)
            step(model, state, Sample(t, np.array([x, y, zc]), axis, True,
                                      b.default_speed_rpm, 1))
            t += dt
            n += 1
    return model, state, n


def floor_vertices(surface, grid) -> np.ndarray:
    """(vcap,) bool: the surface's vertex slots on the floor (module docstring)."""
    lo, hi = RASTER_MM[0] + FLOOR_MARGIN_MM, RASTER_MM[1] - FLOOR_MARGIN_MM
    c = grid.origin_mm + grid.spacing_mm * surface.ijk.astype(np.float64)
    return ((surface.alive != 0) & (c[:, 0] >= lo) & (c[:, 0] <= hi) & (c[:, 1] >= lo)
            & (c[:, 1] <= hi) & (surface.ijk[:, 2] < TOP_VOXELS - 1))


def edges_of(tris) -> np.ndarray:
    """(e, 2) int64: the undirected edges of triangles ``tris`` (m, 3), each
    once, as ``(low, high)`` vertex pairs, sorted."""
    t = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    e.sort(axis=1)
    return np.unique(e, axis=0)


def mesh_normals(pos, tris, n_vertices: int) -> np.ndarray:
    """(n_vertices, 3) float64: each vertex's area-weighted mean of the face
    normals ``(b - a) x (c - a)`` of its triangles, unit (zero for a vertex
    without triangles)."""
    p = np.asarray(pos, dtype=np.float64)
    t = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    face = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    out = np.zeros((n_vertices, 3))
    for s in range(3):
        np.add.at(out, t[:, s], face)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


def mean_edge_angle_deg(nrm, edges) -> float:
    """Mean angle [deg] between the unit normals at the two ends of each edge
    (nan without edges)."""
    if len(edges) == 0:
        return math.nan
    n = np.asarray(nrm, dtype=np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True).clip(1e-300)
    c = np.einsum("ij,ij->i", n[edges[:, 0]], n[edges[:, 1]])
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))).mean())


def surface_roughness(surface, grid) -> dict:
    """The three roughness figures of the module docstring over the floor.

    Parameters
    ----------
    surface : bonesim.engine.surface.Surface
        Built from (or updated to) ``grid``.
    grid : bonesim.engine.grid.Grid

    Returns
    -------
    dict
        ``render_deg``, ``voxel_deg``, ``render_geometry_deg`` [deg],
        ``floor_vertices``, ``floor_edges``.
    """
    slots = surface.triangle_slots
    tris = surface.tri[slots].astype(np.int64)
    on = floor_vertices(surface, grid)
    e = edges_of(tris)
    e = e[on[e[:, 0]] & on[e[:, 1]]]
    n_v = surface.pos.shape[0]
    centres = grid.origin_mm + grid.spacing_mm * surface.ijk.astype(np.float64)
    return {
        "render_deg": mean_edge_angle_deg(surface.nrm, e),
        "voxel_deg": mean_edge_angle_deg(mesh_normals(centres, tris, n_v), e),
        "render_geometry_deg": mean_edge_angle_deg(mesh_normals(surface.pos, tris, n_v), e),
        "floor_vertices": int(on.sum()),
        "floor_edges": int(len(e)),
    }


def bench_surface_roughness(quick=False) -> dict:
    """``surface_roughness_deg``: the drawn surface's normals over a drilled
    floor beside the plain voxel surface's, same block, same run."""
    from bonesim.engine.surface import Surface, warmup

    warmup()
    t0 = time.perf_counter()
    model, state, n_steps = drilled_floor()
    t_drill = time.perf_counter() - t0
    surf = Surface.of_model(model, state.grid)
    r = surface_roughness(surf, state.grid)
    return {"surface_roughness_deg": {
        "value": round(r["render_deg"], 3), "unit": "deg",
        "voxel_surface_deg": round(r["voxel_deg"], 3),
        "render_geometry_deg": round(r["render_geometry_deg"], 3),
        "floor_vertices": r["floor_vertices"], "floor_edges": r["floor_edges"],
        "what": "mean angle between the vertex normals at the two ends of each mesh edge "
                "over a flat drilled floor: the rendered normals (value), the plain voxel "
                "surface's (vertices at voxel centres, area-weighted face normals), and the "
                "drawn mesh's own geometry",
        "setup": f"{BURR} swept {DEPTH_MM} mm deep along a plane tilted {TILT_DEG} deg, in "
                 f"lines {PITCH_MM} mm apart at "
                 f"{SPEED_MM_S} mm/s over a {VOXEL_MM} mm bone block ({n_steps} steps, "
                 f"{t_drill:.1f} s); floor {FLOOR_MARGIN_MM} mm inside the raster"}}
