"""Index buffers of the hybrid surface: compaction and the visible subset."""
from __future__ import annotations

import numpy as np

from bonesim.engine.grid import voxel_offset
from bonesim.render.meshbuf import SurfaceBuffers, oriented_triangles
from bonesim.engine.surface import Surface

EYE = np.array([8.0, 8.0, 60.0])          # above the block's top face (z = 7.75 mm)
DOWN = np.array([0.0, 0.0, -1.0])


def remove(grid, ijk):
    ijk = np.asarray(ijk, dtype=np.int32).reshape(-1, 3)
    for i, j, k in ijk:
        grid.density[grid.brick_index(i, j, k), voxel_offset(i, j, k)] = 0.0
    return ijk


def pit(i0, i1, j0, j1, k0, k1):
    g = np.mgrid[i0:i1, j0:j1, k0:k1].reshape(3, -1).T
    return g.astype(np.int32)


def triples(a):
    """The triangles of ``a`` as a set, whatever their winding (the buffers
    wind them as drawn, :func:`drawn`)."""
    return {tuple(sorted(int(x) for x in t)) for t in np.asarray(a).reshape(-1, 3)}


def live(surf):
    return surf.tri[surf.triangle_slots]


def drawn(surf):
    """The live triangles wound as the scene draws them: face normal along
    the sum of the corners' normals, plain numpy."""
    t = live(surf).copy()
    p, n = surf.pos.astype(np.float64), surf.nrm.astype(np.float64)
    out = []
    for a, b, c in t.tolist():
        face = np.cross(p[b] - p[a], p[c] - p[a])
        out.append([a, c, b] if face @ (n[a] + n[b] + n[c]) < 0 else [a, b, c])
    return np.array(out, dtype=np.int32).reshape(-1, 3)


def facing_tris(surf, eye=None, direction=None):
    """Live triangles with a corner whose normal faces the camera, or whose
    face does (perspective from ``eye``, or parallel along ``direction``)."""
    p, n = surf.pos.astype(float), surf.nrm.astype(float)
    t = live(surf)
    fn = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    if direction is None:
        corner = (n * (eye - p)).sum(axis=1) > 0
        face = (fn * (eye - p[t[:, 0]])).sum(axis=1) > 0
    else:
        corner = n @ -direction > 0
        face = fn @ -direction > 0
    return t[corner[t].any(axis=1) | face]


def adopt(buf, surf, eye=EYE, direction=DOWN, parallel=False):
    job = buf.start_visible(surf, eye, direction, parallel, tag="cam")
    assert job.wait(30)
    assert buf.adopt(job, surf)
    return job


def test_full_list_is_every_live_triangle(block):
    model, state = block
    surf = Surface.build(state.grid, model.colors)
    buf = SurfaceBuffers()
    nf, nv = buf.sync(surf)
    assert (nf, nv) == (surf.n_triangles, 0)
    assert np.array_equal(buf.full[:3 * nf].reshape(-1, 3), drawn(surf))
    assert np.array_equal(buf.offsets[:nf + 1], np.arange(0, 3 * nf + 1, 3))


def test_visible_subset_is_the_triangles_with_a_facing_vertex_or_face(block):
    model, state = block
    surf = Surface.build(state.grid, model.colors)
    buf = SurfaceBuffers()
    buf.sync(surf)
    job = adopt(buf, surf)
    assert buf.vis_valid and buf.vis_tag == "cam"
    got = triples(buf.vis[:3 * buf.n_vis])
    assert got == triples(facing_tris(surf, EYE))
    assert job.n_visible == buf.n_vis < 0.6 * buf.n_full       # the far side is dropped


def test_a_face_seen_edge_on_with_averted_normals_is_kept():
    """One triangle facing +z whose three vertex normals point away from an
    eye above it: the face keeps it; turned over (winding flipped), it goes."""
    from bonesim.render.meshbuf import _visible_flags

    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    nrm = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (3, 1))
    key = np.array([7, 7], np.int32)
    tri = np.array([[0, 1, 2], [0, 2, 1]], np.int32)
    vflag, tvis = np.zeros(3, np.uint8), np.zeros(2, np.uint8)
    eye = np.array([0.2, 0.2, 5.0])
    assert _visible_flags(pos, nrm, tri, key, eye, -eye, False, vflag, tvis) == 1
    assert list(tvis) == [1, 0] and not vflag.any()
    assert _visible_flags(pos, nrm, tri, key, eye, np.array([0.0, 0.0, -1.0]), True,
                          vflag, tvis) == 1
    assert list(tvis) == [1, 0]


def test_drawn_winding_follows_the_normals(block):
    """Thin walls fold the surface: some triangles' own winding points
    against their corners' normals. Both buffers draw every triangle wound
    along its normals (never a back face whose normals face the eye: a dark
    speck under two-sided lighting), and the compact arrays agree."""
    model, state = block
    grid = state.grid
    surf = Surface.build(grid, model.colors)
    for i in range(1, 31, 3):                       # a comb of one-voxel walls
        surf.update(grid, remove(grid, pit(i, i + 2, 1, 31, 2, 16)))
    want = drawn(surf)
    assert not np.array_equal(want, live(surf))     # some triangles are turned
    buf = SurfaceBuffers()
    nf, _ = buf.sync(surf)
    got = buf.full[:3 * nf].reshape(-1, 3)
    assert np.array_equal(got, want)
    p, n = surf.pos.astype(np.float64), surf.nrm.astype(np.float64)
    face = np.cross(p[got[:, 1]] - p[got[:, 0]], p[got[:, 2]] - p[got[:, 0]])
    assert (np.einsum("ij,ij->i", face, n[got].sum(axis=1)) >= 0).all()
    adopt(buf, surf)
    nf, nv = buf.sync(surf, np.zeros((0, 3), np.int32), np.zeros((0, 3), np.int32))
    vis = buf.vis[:3 * nv].reshape(-1, 3)
    assert {tuple(t) for t in vis.tolist()} <= {tuple(t) for t in want.tolist()}
    pos, nrm, _, tris = surf.arrays()
    ot = oriented_triangles(pos, nrm, tris)
    remap = {int(v): q for q, v in enumerate(surf.vertex_slots)}
    assert np.array_equal(ot, np.vectorize(remap.get)(want))


def test_parallel_projection_uses_the_view_direction(block):
    model, state = block
    surf = Surface.build(state.grid, model.colors)
    buf = SurfaceBuffers()
    adopt(buf, surf, eye=(0.0, 0.0, 0.0), direction=DOWN, parallel=True)
    assert triples(buf.vis[:3 * buf.n_vis]) == triples(facing_tris(surf, direction=DOWN))


def test_subset_keeps_all_geometry_changed_since_the_snapshot(block):
    model, state = block
    grid = state.grid
    surf = Surface.build(grid, model.colors)
    buf = SurfaceBuffers()
    adopt(buf, surf)
    before = triples(live(surf))
    # dig a pit from the top face down to the nerve, in two updates
    surf.update(grid, remove(grid, pit(10, 22, 10, 22, 12, 16)))
    buf.sync(surf)
    surf.update(grid, remove(grid, pit(12, 20, 12, 20, 10, 12)))
    nf, nv = buf.sync(surf)
    full = triples(buf.full[:3 * nf])
    vis = triples(buf.vis[:3 * nv])
    assert full == triples(live(surf))
    assert vis <= full
    assert triples(facing_tris(surf, EYE)) <= vis          # nothing facing is lost
    assert (full - before) <= vis                          # every new triangle is drawn
    assert nv < nf


def test_buffers_grow_with_the_surface(block):
    model, state = block
    grid = state.grid
    surf = Surface.build(grid, model.colors)
    buf = SurfaceBuffers()
    buf.sync(surf)
    cap0 = buf.full.shape[0]
    # a comb of one-voxel slots multiplies the surface
    for i in range(1, 31, 2):
        surf.update(grid, remove(grid, pit(i, i + 1, 1, 31, 2, 16)))
    nf, _ = buf.sync(surf)
    assert nf == surf.n_triangles and buf.full.shape[0] > cap0
    assert np.array_equal(buf.full[:3 * nf].reshape(-1, 3), drawn(surf))


def test_invalidate_and_other_surface_drop_the_subset(block):
    model, state = block
    surf = Surface.build(state.grid, model.colors)
    buf = SurfaceBuffers()
    job = adopt(buf, surf)
    buf.invalidate()
    assert not buf.vis_valid and buf.n_vis == 0
    other = Surface.build(state.grid, model.colors)
    assert not buf.adopt(job, other)
    assert buf.adopt(job, surf)
    buf.sync(other)                      # a new surface: the old snapshot is dropped
    assert not buf.vis_valid


def drill_twice(buf, surf, grid, pass_voxels):
    a = remove(grid, pit(10, 22, 10, 22, 12, 16))
    surf.update(grid, a)
    buf.sync(surf, a if pass_voxels else None)
    b = remove(grid, pit(12, 20, 12, 20, 10, 12))
    touched = np.array([[5, 5, 15]], np.int32)
    grid.density[grid.brick_index(5, 5, 15), voxel_offset(5, 5, 15)] = 0.4
    surf.update(grid, b, touched)
    return buf.sync(surf, b if pass_voxels else None, touched if pass_voxels else None)


def test_change_marks_keep_the_same_invariants(block):
    model, state = block
    grid = state.grid
    surf = Surface.build(grid, model.colors)
    buf = SurfaceBuffers()
    adopt(buf, surf)
    assert buf.marks_in_use
    before = triples(live(surf))
    nf, nv = drill_twice(buf, surf, grid, pass_voxels=True)
    assert buf.marks_in_use
    full = triples(buf.full[:3 * nf])
    vis = triples(buf.vis[:3 * nv])
    assert full == triples(live(surf))
    assert vis <= full
    assert triples(facing_tris(surf, EYE)) <= vis
    assert (full - before) <= vis
    assert nv < nf


def test_marks_and_comparison_agree_closely(block):
    """Marks keep a superset of what the comparison keeps, and not much more."""
    from tests.bonesim.render.scenes import nerve_block

    results = []
    for pass_voxels in (True, False):
        model, state = nerve_block()
        surf = Surface.build(state.grid, model.colors)
        buf = SurfaceBuffers()
        adopt(buf, surf)
        nf, nv = drill_twice(buf, surf, state.grid, pass_voxels)
        assert buf.marks_in_use == pass_voxels
        results.append(triples(buf.vis[:3 * nv]))
    marked, compared = results
    assert compared <= marked and len(marked) < 1.2 * len(compared)


def test_unknown_changes_fall_back_to_comparison(block):
    model, state = block
    grid = state.grid
    surf = Surface.build(grid, model.colors)
    buf = SurfaceBuffers()
    adopt(buf, surf)
    buf.sync(surf)                                   # changes unknown
    assert buf.vis_valid and not buf.marks_in_use
    adopt(buf, surf)                                 # a new snapshot: marks again
    assert buf.marks_in_use
