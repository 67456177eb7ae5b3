"""Tests of the hybrid voxel / triangle surface (bonesim.engine.surface).

The centre piece is a slow, deliberately plain numpy reference of the whole
definition (dense arrays, explicit loops over cells and the 56 corner
triples, plane/side tests with cross and dot products, normals by an einsum
over the 7x7x7 Gaussian-derivative stencil written out from the formula of
bonesim.engine.normals, and the vertex's Newton step onto the smoothed
density's level set): the kernels' full tessellation must equal it, and the
incremental update must equal a full tessellation after any removal
sequence. The thin-bone tint has its own tests (test_shading.py).
"""
from __future__ import annotations

import itertools
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bonesim.engine.grid import Grid, voxel_offset
from bonesim.engine.shading import NORMAL_RADIUS, load_shading
from bonesim.engine.surface import GRAD_EPS, CanonicalSurface, Surface
from bonesim.engine.surface_window import WINDOW_DEPTH
from tests.bonesim.fakes import force_tiles

COLORS = np.array([[0, 0, 0], [230, 220, 190], [200, 60, 50], [40, 90, 210]], dtype=np.uint8)
CORNERS = [np.array(c) for c in itertools.product((0, 1), repeat=3)]   # lexicographic
# hypothesis examples per property; raise it for a soak run
_EXAMPLES = int(os.environ.get("BONESIM_SURFACE_EXAMPLES", "30"))


# ---------------------------------------------------------------------------
# numpy reference
# ---------------------------------------------------------------------------
R = NORMAL_RADIUS
#: Tolerance on positions [voxels] against the float64 reference (the
#: kernels sum in float32).
POS_ATOL = 1e-4


def _ref_weights():
    """Gaussian smoothing S and derivative D over offsets -R..R, from the
    formula (sum S = 1, sum c D = 1)."""
    sigma = load_shading().sigma_voxels
    c = np.arange(-R, R + 1, dtype=np.float64)
    smooth = np.exp(-c ** 2 / (2 * sigma ** 2))
    smooth /= smooth.sum()
    deriv = c * smooth
    deriv /= (c * deriv).sum()
    return smooth, deriv


def _ref_vertex(D, lab, p):
    """Normal, shift [voxels] and colour of the vertex at padded index p (a tuple)."""
    x, y, z = p
    nb = D[x - R:x + R + 1, y - R:y + R + 1, z - R:z + R + 1].astype(np.float64)
    smooth, deriv = _ref_weights()
    gx = np.einsum("abc,a,b,c->", nb, deriv, smooth, smooth)
    gy = np.einsum("abc,a,b,c->", nb, smooth, deriv, smooth)
    gz = np.einsum("abc,a,b,c->", nb, smooth, smooth, deriv)
    f = np.einsum("abc,a,b,c->", nb, smooth, smooth, smooth)
    g = np.array([gx, gy, gz])
    if np.linalg.norm(g) > GRAD_EPS:
        n = -g / np.linalg.norm(g)
        sp = load_shading()
        shift = float(np.clip((f - sp.iso_density) / np.linalg.norm(g), -sp.max_in_voxels,
                              sp.max_out_voxels))
    else:
        s = np.zeros(3)
        for d in itertools.product((-1, 0, 1), repeat=3):
            if d != (0, 0, 0) and not D[x + d[0], y + d[1], z + d[2]] > 0:
                s += d
        n = s / np.linalg.norm(s) if np.linalg.norm(s) > 0 else np.array([0.0, 0.0, 1.0])
        shift = 0.0
    return n, shift, [int(c) for c in COLORS[lab[p]]] + [255]


def _ref_qualifies(occ_cell, tri_idx):
    """+1/-1 orientation relative to the right-hand normal of the three corners
    in the given order, or None. occ_cell: 8 booleans, corners in CORNERS order."""
    if not all(occ_cell[c] for c in tri_idx):
        return None
    a, b, c = (CORNERS[i] for i in tri_idx)
    n = np.cross(b - a, c - a)
    rest = [i for i in range(8) if i not in tri_idx]
    side = {i: int(np.dot(n, CORNERS[i] - a)) for i in rest}
    inplane = [i for i in rest if side[i] == 0]
    if inplane and occ_cell[inplane[0]]:
        quad = sorted(list(tri_idx) + inplane, key=lambda i: tuple(CORNERS[i]))
        low = quad[0]
        opposite = max(quad, key=lambda i: np.sum((CORNERS[i] - CORNERS[low]) ** 2))
        if low not in tri_idx or opposite not in tri_idx:
            return None
    occ_sides = {np.sign(side[i]) for i in rest if side[i] != 0 and occ_cell[i]}
    emp_sides = {np.sign(side[i]) for i in rest if side[i] != 0 and not occ_cell[i]}
    if len(occ_sides) == 2:
        return None
    if len(occ_sides) == 1:
        plus = -occ_sides.pop()
        return plus if plus in emp_sides else None
    if len(emp_sides) == 2:          # sheet: normal with first non-zero component < 0
        first = n[np.flatnonzero(n)[0]]
        return -1 if first > 0 else 1
    return emp_sides.pop()


def reference(dens, label, origin=(0.0, 0.0, 0.0), spacing=1.0):
    """CanonicalSurface of the definition for dense volumes at voxel (0, 0, 0)
    (voxel (0, 0, 0) centred at ``origin`` [mm], voxels ``spacing`` [mm])."""
    origin = np.asarray(origin, dtype=np.float64)
    P = R + 1
    D = np.pad(np.where(label > 0, dens, 0).astype(np.float32), P)
    lab = np.pad(label, P)
    occ = D > 0
    nx, ny, nz = dens.shape
    verts = {}
    for p in itertools.product(range(P, P + nx), range(P, P + ny), range(P, P + nz)):
        if occ[p] and not occ[p[0] - 1:p[0] + 2, p[1] - 1:p[1] + 2, p[2] - 1:p[2] + 2].all():
            verts[tuple(int(v) - P for v in p)] = _ref_vertex(D, lab, p)
    found = {}
    for m in itertools.product(range(-1, nx), range(-1, ny), range(-1, nz)):
        mm = np.array(m) + P
        occ_cell = [bool(occ[tuple(mm + c)]) for c in CORNERS]
        if not any(occ_cell):
            continue
        for t in itertools.combinations(range(8), 3):
            o = _ref_qualifies(occ_cell, t)
            if o is None:
                continue
            vox = [tuple(int(v) for v in np.array(m) + CORNERS[i]) for i in t]
            if o < 0:
                vox = [vox[0], vox[2], vox[1]]
            key = frozenset(vox)
            found.setdefault(key, []).append((m, vox))
    tris = []
    for key, lst in found.items():
        lst.sort()
        vox = lst[0][1]                    # the lower cell decides
        for v in vox:
            assert v in verts, "triangle corner that is not a surface voxel"
        r = min(range(3), key=lambda s: vox[s])
        vox = vox[r:] + vox[:r]
        tris.append([c for v in vox for c in v])
    ijk = np.array(sorted(verts), dtype=np.int32).reshape(-1, 3)
    nrm = np.array([verts[tuple(v)][0] for v in ijk.tolist()]).reshape(-1, 3)
    shift = np.array([verts[tuple(v)][1] for v in ijk.tolist()]).reshape(-1, 1)
    col = np.array([verts[tuple(v)][2] for v in ijk.tolist()], dtype=np.uint8).reshape(-1, 4)
    tris = np.array(sorted(tris), dtype=np.int32).reshape(-1, 9)
    pos = (origin + spacing * (ijk + shift * nrm)).astype(np.float32)
    return CanonicalSurface(ijk, pos, nrm.astype(np.float32), col, tris)


def _check_vs_reference(dens, label):
    grid = Grid.from_dense(label, dens, spacing_mm=1.0)
    got = Surface.build(grid, COLORS).canonical()
    want = reference(dens, label)
    diffs = got.differences(want, atol=1e-5, pos_atol=POS_ATOL)
    assert not diffs, diffs
    return got


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------
def _set_density(grid, ijk, value):
    for i, j, k in np.asarray(ijk).reshape(-1, 3).tolist():
        grid.density[grid.brick_index(i, j, k), voxel_offset(i, j, k)] = value


def _ball(n, r, c=None):
    c = (n - 1) / 2 if c is None else c
    g = np.indices((n, n, n)) - np.array(c, dtype=float).reshape(-1, 1, 1, 1)
    return (np.sqrt((g ** 2).sum(0)) <= r).astype(np.uint8)


def _brute_tris_of(surf):
    out = {}
    for t in surf.triangle_slots:
        for v in surf.tri[t]:
            out.setdefault(int(v), set()).add(int(t))
    return out


def _assert_links(surf):
    """vertex -> triangle lists equal a brute-force scan; vmap <-> ijk agree."""
    brute = _brute_tris_of(surf)
    for v in surf.vertex_slots:
        assert set(surf.triangles_of(int(v)).tolist()) == brute.get(int(v), set())
        assert surf.vertex_at(*surf.ijk[v].tolist()) == v
    assert surf.n_vertices == len(surf.vertex_slots)
    assert surf.n_triangles == len(surf.triangle_slots)
    assert int((surf.vmap >= 0).sum()) == surf.n_vertices


def _edge_counts(tris):
    e = {}
    for a, b, c in tris.tolist():
        for u, v in ((a, b), (b, c), (c, a)):
            e[(u, v)] = e.get((u, v), 0) + 1
    return e


def _random_volume(rng, shape, p_occ, graded):
    lab = (rng.random(shape) < p_occ).astype(np.uint8) * rng.integers(1, 4, size=shape).astype(np.uint8)
    if graded:
        dens = rng.uniform(0.05, 1.0, size=shape).astype(np.float32)
    else:
        dens = np.ones(shape, dtype=np.float32)
    return dens, lab


# ---------------------------------------------------------------------------
# the lookup table against the plain geometric test
# ---------------------------------------------------------------------------
def test_table_matches_geometric_definition():
    from bonesim.engine.surface import MAX_PER_CELL, qualifying_triples
    for code in range(256):
        occ_cell = [bool((code >> c) & 1) for c in range(8)]
        want = set()
        for t in itertools.combinations(range(8), 3):
            o = _ref_qualifies(occ_cell, t)
            if o is not None:
                want.add(t if o > 0 else (t[0], t[2], t[1]))
        got = {oc for _, oc in qualifying_triples(code)}
        assert got == want, code
        assert len(got) <= MAX_PER_CELL
    assert qualifying_triples(0) == [] and qualifying_triples(255) == []


# ---------------------------------------------------------------------------
# full tessellation == numpy reference
# ---------------------------------------------------------------------------
def _shape_cases():
    n = 7
    g = np.indices((n, n, n))
    one = np.zeros((3, 3, 3), np.uint8)
    one[1, 1, 1] = 1
    diag = np.zeros((4, 4, 4), np.uint8)
    diag[1, 1, 1] = diag[2, 2, 2] = 1
    box = ((g >= 1) & (g <= 5)).all(0).astype(np.uint8)
    box[1:3, 1:6, 1:6] = 2                       # two structures
    sheet = np.zeros((5, 5, 5), np.uint8)
    sheet[1:4, 2, 1:4] = 1
    dsheet = np.zeros((6, 6, 6), np.uint8)       # one-voxel diagonal sheet x + y = 5
    for x in range(6):
        if 0 <= 5 - x < 6:
            dsheet[x, 5 - x, 1:5] = 3
    ball = _ball(n, 2.8)
    tube = ((g[0] - 3) ** 2 + (g[1] - 3) ** 2 <= 5).astype(np.uint8)
    tube[(g[0] - 3) ** 2 + (g[1] - 3) ** 2 <= 1] = 0
    return {"single": one, "diagonal pair": diag, "box": box, "sheet": sheet,
            "diagonal sheet": dsheet, "ball": ball, "tube": tube}


@pytest.mark.parametrize("name", list(_shape_cases()))
def test_build_matches_reference_on_shapes(name):
    lab = _shape_cases()[name]
    dens = np.ones(lab.shape, dtype=np.float32)
    got = _check_vs_reference(dens, lab)
    if name == "single":
        assert len(got.ijk) == 1 and len(got.tris) == 0
        np.testing.assert_array_equal(got.nrm[0], [0, 0, 1])   # no gradient, no preferred side
    if name == "diagonal pair":
        assert len(got.ijk) == 2 and len(got.tris) == 0


@pytest.mark.parametrize("seed", range(6))
def test_build_matches_reference_on_random_volumes(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(s) for s in rng.integers(3, 8, size=3))
    dens, lab = _random_volume(rng, shape, rng.uniform(0.3, 0.9), graded=seed % 2 == 1)
    _check_vs_reference(dens, lab)


@settings(max_examples=_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2 ** 32 - 1), st.floats(0.1, 0.95))
def test_build_matches_reference_hypothesis(seed, p_occ):
    rng = np.random.default_rng(seed)
    shape = tuple(int(s) for s in rng.integers(1, 6, size=3))
    dens, lab = _random_volume(rng, shape, p_occ, graded=bool(seed & 1))
    _check_vs_reference(dens, lab)


def test_build_origin_spacing_and_brick_boundaries():
    # a volume straddling several bricks, with a non-trivial origin and spacing
    rng = np.random.default_rng(7)
    dens, lab = _random_volume(rng, (11, 18, 10), 0.7, graded=True)
    grid = Grid.from_dense(lab, dens, spacing_mm=0.4, origin_mm=(-3.0, 1.5, 10.0))
    surf = Surface.build(grid, COLORS)
    can = surf.canonical()
    want = reference(dens, lab, origin=(-3.0, 1.5, 10.0), spacing=0.4)
    np.testing.assert_array_equal(can.ijk, want.ijk)
    np.testing.assert_array_equal(can.tris, want.tris)
    np.testing.assert_allclose(can.pos, want.pos, atol=0.4 * POS_ATOL)
    np.testing.assert_allclose(can.nrm, want.nrm, atol=1e-5)
    np.testing.assert_array_equal(can.col, want.col)


# ---------------------------------------------------------------------------
# analytic checks
# ---------------------------------------------------------------------------
def test_box_vertices_normals_and_closed_mesh():
    n = 12
    g = np.indices((n, n, n))
    lo, hi = 2, 9
    lab = ((g >= lo) & (g <= hi)).all(0).astype(np.uint8)
    grid = Grid.from_dense(lab, spacing_mm=1.0)
    surf = Surface.build(grid, COLORS)
    can = surf.canonical()
    inside = ((g >= lo) & (g <= hi)).all(0)
    core = ((g >= lo + 1) & (g <= hi - 1)).all(0)
    layer = {tuple(v) for v in np.argwhere(inside & ~core).tolist()}
    assert {tuple(v) for v in can.ijk.tolist()} == layer
    # vertex normals at face centres are the face's outward axis
    for axis in range(3):
        for side, val in ((-1, lo), (1, hi)):
            p = [5, 5, 5]
            p[axis] = val
            v = surf.vertex_at(*p)
            want = np.zeros(3)
            want[axis] = side
            np.testing.assert_allclose(surf.nrm[v], want, atol=1e-6)
    _assert_closed_outward(surf, centre=np.array([(lo + hi) / 2] * 3))
    # a flat face is triangulated by quads: 2 triangles per unit square
    pos, nrm, col, tris = surf.arrays()
    side = hi - lo
    assert len(tris) == 6 * side * side * 2


def _assert_closed_outward(surf, centre):
    pos, nrm, col, tris = surf.arrays()
    e = _edge_counts(tris)
    # every directed edge once, and its reverse once: closed, consistently oriented
    assert all(c == 1 for c in e.values())
    assert all((b, a) in e for (a, b) in e)
    used = np.unique(tris)
    assert len(used) - len(e) // 2 + len(tris) == 2          # a sphere (genus 0)
    a, b, c = (pos[tris[:, s]].astype(np.float64) for s in range(3))
    fn = np.cross(b - a, c - a)
    out = (a + b + c) / 3 - centre
    assert (np.einsum("ij,ij->i", fn, out) > 0).all()
    signed_volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    assert signed_volume > 0
    # vertex normals point outward too
    assert (np.einsum("ij,ij->i", nrm[used].astype(np.float64), pos[used] - centre) > 0).all()


@pytest.mark.parametrize("r", [1.5, 2.5, 4.0, 5.5, 6.3])
def test_ball_is_closed_and_outward(r):
    n = 16
    lab = _ball(n, r)
    surf = Surface.build(Grid.from_dense(lab, spacing_mm=1.0), COLORS)
    _assert_closed_outward(surf, centre=np.array([(n - 1) / 2] * 3))


def test_ellipsoid_is_closed_and_outward():
    n = 18
    g = np.indices((n, n, n)) - 8.3
    lab = (((g / np.array([7.5, 5.2, 3.4]).reshape(3, 1, 1, 1)) ** 2).sum(0) <= 1).astype(np.uint8)
    surf = Surface.build(Grid.from_dense(lab, spacing_mm=1.0), COLORS)
    _assert_closed_outward(surf, centre=np.array([8.3] * 3))


def test_each_triangle_once_and_corners_are_surface_voxels():
    rng = np.random.default_rng(3)
    dens, lab = _random_volume(rng, (9, 9, 9), 0.6, graded=False)
    grid = Grid.from_dense(lab, spacing_mm=1.0)
    surf = Surface.build(grid, COLORS)
    can = surf.canonical()
    sets = {frozenset(map(tuple, t.reshape(3, 3).tolist())) for t in can.tris}
    assert len(sets) == len(can.tris)
    d, _ = grid.to_dense(lo=(-1, -1, -1), shape=(11, 11, 11))
    for v in np.unique(can.tris.reshape(-1, 3), axis=0).tolist():
        x, y, z = (c + 1 for c in v)
        assert d[x, y, z] > 0 and not (d[x - 1:x + 2, y - 1:y + 2, z - 1:z + 2] > 0).all()


def test_colours_are_the_labels_whatever_the_density():
    """A partly drilled voxel keeps its structure's colour (no dark speck);
    its density moves its vertex instead."""
    lab = np.zeros((5, 5, 5), np.uint8)
    lab[1:4, 1:4, 1:4] = 2
    dens = np.ones(lab.shape, np.float32)
    dens[1, 2, 2] = 0.5
    dens[3, 2, 2] = 0.0001
    surf = Surface.build(Grid.from_dense(lab, dens), COLORS)
    for v in surf.vertex_slots:
        assert surf.col[v].tolist() == [200, 60, 50, 255]


@pytest.mark.parametrize("h", [0.5, 0.19])
def test_vertices_sit_where_the_bone_ends(h):
    """A flat face of intact bone is drawn about half a voxel out of its
    voxels' centres (where the voxels end); as the top layer is drilled
    down its vertices sink smoothly into the bone, within the clip."""
    sp = load_shading()
    n, top = 16, 7
    lab = np.zeros((n, n, top + 4), np.uint8)
    lab[:, :, :top + 1] = 1
    prev = None
    for d in (1.0, 0.8, 0.6, 0.4, 0.2, 0.05):
        dens = np.ones(lab.shape, np.float32)
        dens[:, :, top] = d
        grid = Grid.from_dense(lab, dens, spacing_mm=h, origin_mm=(1.0, 2.0, 3.0))
        surf = Surface.build(grid, COLORS)
        v = surf.vertex_at(8, 8, top)
        np.testing.assert_allclose(surf.nrm[v], [0, 0, 1], atol=1e-6)
        np.testing.assert_allclose(surf.pos[v, :2], [1.0 + 8 * h, 2.0 + 8 * h], atol=1e-5)
        s = float(surf.shift[v])
        assert surf.pos[v, 2] == pytest.approx(3.0 + h * (top + s), abs=1e-5)
        assert -sp.max_in_voxels <= s <= sp.max_out_voxels
        if d == 1.0:
            assert 0.35 < s < 0.55                        # about the voxels' face
        else:
            assert s < prev                               # drilling sinks it
        prev = s
    assert prev < -0.2


def test_thin_plates_do_not_collapse():
    """Both faces of a plate two voxels thick move at most max_in_voxels
    into it: they stay apart and keep facing out."""
    sp = load_shading()
    lab = np.zeros((14, 14, 9), np.uint8)
    lab[:, :, 3:5] = 1
    surf = Surface.build(Grid.from_dense(lab, spacing_mm=1.0), COLORS)
    lo, hi = surf.vertex_at(7, 7, 3), surf.vertex_at(7, 7, 4)
    assert surf.nrm[lo][2] < -0.99 and surf.nrm[hi][2] > 0.99
    assert surf.pos[hi, 2] - surf.pos[lo, 2] >= 1.0 - 2 * sp.max_in_voxels - 1e-6


def test_vertex_to_triangle_map_after_build():
    rng = np.random.default_rng(11)
    dens, lab = _random_volume(rng, (10, 9, 12), 0.55, graded=True)
    surf = Surface.build(Grid.from_dense(lab, dens), COLORS)
    _assert_links(surf)
    for t in surf.triangle_slots[:50]:
        cell, tid, flip = surf.triangle_owner(int(t))
        from bonesim.engine.surface import CORNER_OFFSETS, TRIPLE_CORNERS
        corners = [tuple(np.array(cell) + CORNER_OFFSETS[c]) for c in TRIPLE_CORNERS[tid]]
        assert {tuple(surf.ijk[v].tolist()) for v in surf.tri[t]} == set(corners)


def test_empty_grid_and_arrays():
    grid = Grid.from_dense(np.zeros((4, 4, 4), np.uint8))
    surf = Surface.build(grid, COLORS)
    assert surf.n_vertices == 0 and surf.n_triangles == 0
    pos, nrm, col, tris = surf.arrays()
    assert pos.shape == (0, 3) and nrm.shape == (0, 3) and col.shape == (0, 4) and tris.shape == (0, 3)
    assert surf.update(grid, np.zeros((0, 3), np.int32))["triangles_added"] == 0
    assert surf.update(grid, [[1, 1, 1], [50, 50, 50]])["vertices_added"] == 0


def test_arrays_are_consistent():
    lab = _ball(9, 3.3)
    grid = Grid.from_dense(lab, spacing_mm=0.5, origin_mm=(1.0, 2.0, 3.0))
    surf = Surface.build(grid, COLORS)
    pos, nrm, col, tris = surf.arrays()
    assert pos.dtype == np.float32 and nrm.dtype == np.float32
    assert col.dtype == np.uint8 and tris.dtype == np.int32
    assert len(pos) == surf.n_vertices and len(tris) == surf.n_triangles
    assert tris.min() >= 0 and tris.max() < len(pos)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-6)
    assert (col[:, 3] == 255).all()


# ---------------------------------------------------------------------------
# input validation
# ---------------------------------------------------------------------------
def test_input_validation():
    lab = _ball(6, 2)
    grid = Grid.from_dense(lab)
    with pytest.raises(ValueError):
        Surface.build(grid, COLORS[:1])                    # label 1 has no colour
    with pytest.raises(ValueError):
        Surface.build(grid, np.zeros((3, 4), np.uint8))
    with pytest.raises(TypeError):
        Surface.build(lab, COLORS)
    surf = Surface.build(grid, COLORS)
    with pytest.raises(ValueError):
        surf.update(grid, np.zeros((3, 2), np.int32))
    with pytest.raises(TypeError):
        surf.update(grid, np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError):
        surf.update(Grid.from_dense(_ball(12, 5)), [[1, 1, 1]])
    with pytest.raises(IndexError):
        surf.triangles_of(10 ** 6)


# ---------------------------------------------------------------------------
# incremental update == full tessellation
# ---------------------------------------------------------------------------
def _assert_flips(surf):
    """``tflip`` of every live triangle: its face normal against the sum of
    its corners' normals, recomputed with plain numpy."""
    ts = surf.triangle_slots
    t = surf.tri[ts]
    p, n = surf.pos.astype(np.float32), surf.nrm.astype(np.float32)
    face = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    want = (face * n[t].sum(axis=1)).sum(axis=1) < 0
    got = surf.tflip[ts] != 0
    close = np.abs((face * n[t].sum(axis=1)).sum(axis=1)) < 1e-6     # float order aside
    assert (got == want)[~close].all()


def _assert_same_as_rebuild(surf, grid):
    fresh = Surface.build(grid, COLORS)
    diffs = surf.canonical().differences(fresh.canonical())   # exact, normals included
    assert not diffs, diffs
    _assert_flips(surf)


def _run_random_removals(seed, shape, p_occ, graded, n_batches, max_batch, tiled):
    rng = np.random.default_rng(seed)
    dens, lab = _random_volume(rng, shape, p_occ, graded)
    grid = Grid.from_dense(lab, dens, spacing_mm=0.5, origin_mm=(-1.0, 0.5, 2.0))
    surf = Surface.build(grid, COLORS)
    if tiled:
        force_tiles(surf)
    for _ in range(n_batches):
        d, _ = grid.to_dense()
        occ = np.argwhere(d > 0)
        if len(occ) == 0:
            break
        k = int(rng.integers(1, max_batch + 1))
        removed = occ[rng.choice(len(occ), size=min(k, len(occ)), replace=False)]
        _set_density(grid, removed, 0.0)
        left = np.argwhere(grid.to_dense()[0] > 0)
        touched = np.zeros((0, 3), np.int64)
        if len(left) and rng.random() < 0.7:
            touched = left[rng.choice(len(left), size=min(len(left), 4), replace=False)]
            for t in touched:
                _set_density(grid, t, grid.density_at(*t) * float(rng.uniform(0.2, 0.9)))
        # duplicates in a batch are allowed
        if len(removed) > 1 and rng.random() < 0.3:
            removed = np.concatenate([removed, removed[:1]])
        surf.update(grid, removed, touched)
        _assert_same_as_rebuild(surf, grid)
    _assert_links(surf)
    return surf


@settings(max_examples=_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2 ** 32 - 1),
       shape=st.tuples(st.integers(1, 9), st.integers(1, 9), st.integers(1, 9)),
       p_occ=st.floats(0.2, 1.0), graded=st.booleans(), tiled=st.booleans())
def test_incremental_equals_rebuild_hypothesis(seed, shape, p_occ, graded, tiled):
    _run_random_removals(seed, shape, p_occ, graded, n_batches=4, max_batch=12,
                         tiled=tiled)


@pytest.mark.parametrize("tiled", [False, True])
def test_incremental_until_empty(tiled):
    surf = _run_random_removals(5, (7, 8, 6), 0.8, True, n_batches=200, max_batch=25,
                                tiled=tiled)
    assert surf.n_vertices == 0 and surf.n_triangles == 0


def _burr_path(grid_shape, r, steps):
    t = np.linspace(0, 1, steps)
    a = np.stack([grid_shape[0] * (0.15 + 0.7 * t),
                  grid_shape[1] * (0.5 + 0.25 * np.sin(6 * t)),
                  grid_shape[2] * (0.9 - 0.5 * t)], axis=1)
    return a


@pytest.mark.parametrize("tiled", [False, True])
def test_incremental_burr_sequence(tiled):
    """A spherical burr moving into a ball of bone: voxels inside the burr are
    removed, a shell around it has its density lowered."""
    n = 22
    lab = _ball(n, 9.5)
    lab[(np.indices((n, n, n))[2] < 8) & (lab > 0)] = 2
    grid = Grid.from_dense(lab, spacing_mm=0.3)
    surf = Surface.build(grid, COLORS)
    if tiled:
        force_tiles(surf)
    g = np.indices((n, n, n)).reshape(3, -1).T
    r = 3.2
    total = 0
    for step, c in enumerate(_burr_path((n, n, n), r, 14)):
        d, _ = grid.to_dense()
        dist = np.sqrt(((g - c) ** 2).sum(1))
        occ = d.reshape(-1) > 0
        removed = g[occ & (dist <= r)]
        shell = g[occ & (dist > r) & (dist <= r + 1.0)]
        _set_density(grid, removed, 0.0)
        for v in shell:
            _set_density(grid, v, grid.density_at(*v) * 0.8)
        surf.update(grid, removed.astype(np.int32), shell)
        total += len(removed)
        if step % 3 == 2:
            _assert_same_as_rebuild(surf, grid)
    assert total > 300
    _assert_same_as_rebuild(surf, grid)
    _assert_links(surf)


def test_update_grows_capacity():
    n = 20
    g = np.indices((n, n, n))
    lab = ((g >= 1) & (g <= n - 2)).all(0).astype(np.uint8)
    grid = Grid.from_dense(lab)
    surf = Surface.build(grid, COLORS)
    tiled = Surface.build(grid, COLORS)
    force_tiles(tiled, 2)              # runs out of room part way, then resumes
    vcap, tcap = surf.pos.shape[0], surf.tri.shape[0]
    # drill a grid of holes: much more surface than the box had
    holes = g.reshape(3, -1).T
    holes = holes[(holes[:, 0] % 3 == 1) & (holes[:, 1] % 3 == 1) & (holes[:, 2] >= 1)
                  & (holes[:, 2] <= n - 2) & (holes[:, 0] <= n - 2) & (holes[:, 1] <= n - 2)]
    _set_density(grid, holes, 0.0)
    stats = surf.update(grid, holes)
    assert surf.pos.shape[0] > vcap and surf.tri.shape[0] > tcap
    assert stats["vertices_added"] > 0 and stats["triangles_added"] > 0
    _assert_same_as_rebuild(surf, grid)
    _assert_links(surf)
    # the tiles change each triangle once, so they count what one window counts
    stats_tiled = tiled.update(grid, holes)
    assert tiled.pos.shape[0] > vcap and tiled.tri.shape[0] > tcap
    for key in ("vertices_added", "vertices_removed", "triangles_added", "triangles_removed"):
        assert stats_tiled[key] == stats[key], key
    _assert_same_as_rebuild(tiled, grid)
    _assert_links(tiled)


def test_removals_far_apart_are_tiled():
    """Two burr holes 80 voxels apart along k (no single window of 64
    voxels covers them) and a scatter of single voxels, with default tiles."""
    n = 96
    lab = np.zeros((24, 24, n), np.uint8)
    lab[2:22, 2:22, 2:n - 2] = 1
    grid = Grid.from_dense(lab)
    surf = Surface.build(grid, COLORS)
    g = np.indices(lab.shape).reshape(3, -1).T
    rng = np.random.default_rng(4)
    removed = np.concatenate([
        g[((g - (12, 12, 4)) ** 2).sum(1) <= 16],
        g[((g - (12, 12, 84)) ** 2).sum(1) <= 16],
        g[rng.choice(len(g), 40, replace=False)]])
    assert np.ptp(removed[:, 2]) + 1 > WINDOW_DEPTH
    _set_density(grid, removed, 0.0)
    stats = surf.update(grid, removed.astype(np.int32))
    assert stats["triangles_added"] > 0
    _assert_same_as_rebuild(surf, grid)
    _assert_links(surf)


def test_update_ignores_voxels_that_are_not_empty():
    lab = _ball(10, 4)
    grid = Grid.from_dense(lab)
    surf = Surface.build(grid, COLORS)
    before = surf.canonical()
    stats = surf.update(grid, [[4, 4, 4], [0, 0, 0], [-30, 7, 2]])  # still bone / never bone
    assert stats["triangles_added"] == stats["triangles_removed"] == 0
    assert surf.canonical() == before


def test_touched_only_reshades():
    lab = _ball(10, 4)
    grid = Grid.from_dense(lab)
    surf = Surface.build(grid, COLORS)
    tris_before = surf.canonical().tris
    _set_density(grid, [[4, 4, 0 + 1]], 0.3)
    stats = surf.update(grid, None, [[4, 4, 1]])
    assert stats["vertices_reshaded"] > 0 and stats["triangles_added"] == 0
    np.testing.assert_array_equal(surf.canonical().tris, tris_before)
    _assert_same_as_rebuild(surf, grid)


def test_warmup_runs():
    from bonesim.engine.surface import warmup
    warmup()


def test_removed_voxels_listed_again_are_harmless():
    lab = _ball(12, 5)
    grid = Grid.from_dense(lab)
    surf = Surface.build(grid, COLORS)
    a = np.argwhere(lab > 0)[:40]
    _set_density(grid, a, 0.0)
    surf.update(grid, a)
    b = np.argwhere(grid.to_dense()[0] > 0)[:30]
    _set_density(grid, b, 0.0)
    surf.update(grid, np.concatenate([a, b, a]))       # a was already processed
    _assert_same_as_rebuild(surf, grid)
    _assert_links(surf)
