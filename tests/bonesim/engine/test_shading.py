"""Tests of bonesim.engine.shading: smooth normals and the thin-bone tint.

References are written out here from the definitions in the module
docstrings (bonesim.engine.shading, bonesim.engine.thin_bone): the tint
weight and the colour blend as formulas, the rays' directions on their cone
and their thickness by a plain Python ray march over a dense copy of the
grid, analytic truths for slabs of known thickness; and a surface kept up
to date while bone is drilled must equal one built from scratch, tint
included. (The numpy reference of the normals and positions lives in
test_surface.py.)
"""
from __future__ import annotations

import math
import os
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bonesim.errors import BonesimError
from bonesim.engine.grid import Grid, voxel_offset
from bonesim.engine.shading import (NORMAL_RADIUS, ShadingParams, beneath, bone_labels,
                                    default_shading_path, load_shading, normal_weights,
                                    stencil_weights, tint_reach, tint_weight)
from bonesim.engine.thin_bone import (TINT_BISECT_ITERS, TINT_STEP_FRACTION, cone_table,
                                      near_radius, ray_length_mm)
from bonesim.engine.surface import Surface
from tests.bonesim.fakes import force_tiles

BONE_RGB = (235, 225, 200)
SINUS_RGB = (60, 80, 220)
NERVE_RGB = (250, 230, 40)
COLORS = np.array([(0, 0, 0), BONE_RGB, SINUS_RGB, NERVE_RGB], dtype=np.uint8)
BONE = np.array([0, 1, 0, 0], dtype=np.uint8)          # label 1 is bone
P = load_shading()
_EXAMPLES = int(os.environ.get("BONESIM_SURFACE_EXAMPLES", "30"))


# ---------------------------------------------------------------------------
# references
# ---------------------------------------------------------------------------
def ref_weight(t, p=P):
    """w(t) of the module docstring."""
    if t >= p.start_mm:
        return 0.0
    if t <= p.full_mm:
        return p.max_weight
    x = (p.start_mm - t) / (p.start_mm - p.full_mm)
    return p.max_weight * x * x * (3.0 - 2.0 * x)


def ref_colour(lab, w, acc):
    """RGBA of a vertex of label ``lab`` blended with weight ``w`` toward the
    weighted structure colour ``acc`` (3 floats)."""
    out = []
    for ch in range(3):
        base = float(COLORS[lab, ch]) * (1.0 - w) + acc[ch]
        out.append(int(min(math.floor(base + 0.5), 255)))
    return out + [255]


def plain_colour(lab, struct, w):
    """RGBA of one structure met by every ray with weight ``w``."""
    return ref_colour(lab, w, [w * float(COLORS[struct, ch]) for ch in range(3)])


class DenseTissue:
    """A dense copy of a grid's densities and labels (empty outside)."""

    def __init__(self, grid, pad=40):
        shape = np.array(grid.shape) + 2 * pad
        self.lo = np.array([-pad] * 3)
        self.d, self.lab = grid.to_dense(lo=tuple(self.lo), shape=tuple(shape))
        self.origin = np.asarray(grid.origin_mm, dtype=np.float64)
        self.h = float(grid.spacing_mm)

    def sample(self, p, bone):
        """(in bone, label if occupied else 0) of the voxel nearest point p."""
        inv_h = 1.0 / self.h
        idx = [int(math.floor((p[a] - self.origin[a]) * inv_h + 0.5)) for a in range(3)]
        loc = tuple(int(v) for v in np.array(idx) - self.lo)
        if min(loc) < 0 or any(loc[a] >= self.d.shape[a] for a in range(3)):
            return False, 0
        if not self.d[loc] > 0:
            return False, 0
        lab = int(self.lab[loc])
        return bool(bone[lab]), lab


def ref_exit(tissue, p, n, bone, max_mm):
    """The thin-bone ray of bonesim.engine.thin_bone._march, step by step:
    (distance, met); met 0 (at max_mm) when it reaches empty space, -1 when
    it is still in bone at max_mm."""
    step = TINT_STEP_FRACTION * tissue.h

    def at(t):
        return tissue.sample([p[a] + t * n[a] for a in range(3)], bone)

    lo, hi = 0.0, min(step, max_mm)
    while True:
        inside, lab = at(hi)
        if not inside:
            if lab == 0:
                return max_mm, 0
            met = lab
            break
        if hi >= max_mm:
            return max_mm, -1
        lo, hi = hi, min(hi + step, max_mm)
    for _ in range(TINT_BISECT_ITERS):
        t = 0.5 * (lo + hi)
        if at(t)[0]:
            lo = t
        else:
            hi = t
    return 0.5 * (lo + hi), met


def ref_directions(nrm, p=P):
    """The rays' ``(d, m)`` of a vertex with the (float32) normal ``nrm``:
    the normal, then the cone (Frisvad's basis), in float64."""
    nx, ny, nz = (float(np.float32(c)) for c in nrm)
    out = [((nx, ny, nz), 1.0)]
    if nz < -0.9999999:
        b1, b2 = (0.0, -1.0, 0.0), (-1.0, 0.0, 0.0)
    else:
        a = 1.0 / (1.0 + nz)
        b = -nx * ny * a
        b1, b2 = (1.0 - nx * nx * a, b, -nx), (b, 1.0 - ny * ny * a, -ny)
    tanc = math.tan(math.radians(p.cone_deg))
    for cq, sq in cone_table(p).tolist():
        d = [(nx, ny, nz)[c] + tanc * (cq * b1[c] + sq * b2[c]) for c in range(3)]
        m = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        out.append(((d[0] / m, d[1] / m, d[2] / m), m))
    return out


def ref_ray(tissue, ijk, d, m, shift, bone, p=P):
    """(thickness [mm], structure) along ``-d`` from the voxel centre,
    measured from the vertex ``shift`` (float32) voxels out."""
    c = [tissue.origin[a] + tissue.h * int(ijk[a]) for a in range(3)]
    e, met = ref_exit(tissue, c, [-v for v in d], bone, ray_length_mm(p, tissue.h))
    if met <= 0:
        return p.start_mm, met
    return max(0.0, e + tissue.h * float(np.float32(shift)) * m), met


def ref_beneath(tissue, ijk, nrm, bone, p=P, shift=0.5):
    """(thickness, structure) beneath a bone voxel along -nrm (float32)."""
    n = tuple(float(np.float32(c)) for c in nrm)
    t, s = ref_ray(tissue, ijk, n, 1.0, shift, bone, p)
    return t, max(s, 0)


def ref_tint(tissue, ijk, nrm, shift, bone, p=P):
    """``(W, acc)``: the blend weight and weighted colour over the rays."""
    wsum, acc = 0.0, [0.0, 0.0, 0.0]
    dirs = ref_directions(nrm, p)
    for q, (d, m) in enumerate(dirs):
        t, s = ref_ray(tissue, ijk, d, m, shift, bone, p)
        if s <= 0:
            continue
        w = ref_weight(t, p)
        wsum += w
        for ch in range(3):
            acc[ch] += w * float(COLORS[s, ch])
    inv = 1.0 / len(dirs)
    return wsum * inv, [a * inv for a in acc]


def ref_colours(surf, grid, bone=BONE, p=P):
    """Reference RGBA of every vertex of ``surf`` from its stored normal and shift."""
    tissue = DenseTissue(grid)
    out = {}
    for v in surf.vertex_slots:
        ijk = tuple(int(x) for x in surf.ijk[v])
        lab = grid.label_at(*ijk)
        w, acc = 0.0, [0.0, 0.0, 0.0]
        if bone[lab]:
            w, acc = ref_tint(tissue, ijk, surf.nrm[v], surf.shift[v], bone, p)
        out[ijk] = ref_colour(lab, w, acc)
    return out


def vertex_colour(surf, grid, ijk, bone=BONE, p=P):
    """Reference RGBA of the vertex at voxel ``ijk``."""
    v = surf.vertex_at(*ijk)
    w, acc = ref_tint(DenseTissue(grid), ijk, surf.nrm[v], surf.shift[v], bone, p)
    return ref_colour(grid.label_at(*ijk), w, acc)


def _set_density(grid, ijk, value):
    for i, j, k in np.asarray(ijk).reshape(-1, 3).tolist():
        grid.density[grid.brick_index(i, j, k), voxel_offset(i, j, k)] = value


def _assert_same_as_rebuild(surf, grid, bone=BONE):
    fresh = Surface.build(grid, COLORS, bone=bone).canonical()
    diffs = surf.canonical().differences(fresh)          # exact: normals and colours
    assert not diffs, diffs


# ---------------------------------------------------------------------------
# parameters
# ---------------------------------------------------------------------------
def test_shipped_parameters_and_weights():
    p = load_shading()
    assert p == load_shading(default_shading_path())
    assert 0 <= p.full_mm < p.start_mm and 0 <= p.max_weight <= 1
    s, d = normal_weights(p.sigma_voxels)
    c = np.arange(-NORMAL_RADIUS, NORMAL_RADIUS + 1)
    assert s.sum() == pytest.approx(1.0) and (c * d).sum() == pytest.approx(1.0)
    np.testing.assert_array_equal(s, s[::-1])
    np.testing.assert_array_equal(d, -d[::-1])
    w = stencil_weights(p.sigma_voxels)
    assert w.dtype == np.float32
    np.testing.assert_array_equal(w, np.float32(np.r_[s[3:], d[4:]]))
    assert tint_reach(p, 0.5) == math.floor(p.start_mm / 0.5 + 0.5) + 1
    assert 0 < p.iso_density < 1 and p.max_in_voxels <= 0.5 and p.cone_deg <= 60
    # the cone's table: K rays evenly around the normal
    c = cone_table(p)
    assert c.shape == (p.cone_rays, 2)
    for q, (cq, sq) in enumerate(c.tolist()):
        phi = 2 * math.pi * q / p.cone_rays
        assert cq == pytest.approx(math.cos(phi), abs=1e-15)
        assert sq == pytest.approx(math.sin(phi), abs=1e-15)


def test_ray_directions_lie_on_the_cone():
    """Every ray leaves the normal by cone_deg, the K of them evenly spread,
    for normals all over the sphere (the basis is continuous off -z)."""
    rng = np.random.default_rng(2)
    for n in list(rng.normal(size=(200, 3))) + [(0, 0, 1), (0, 0, -1), (1, 0, 0)]:
        n = np.asarray(n, np.float64) / np.linalg.norm(n)
        n32 = n.astype(np.float32).astype(np.float64)
        dirs = ref_directions(n32)
        assert len(dirs) == P.cone_rays + 1
        assert dirs[0][0] == tuple(n32) and dirs[0][1] == 1.0
        side = np.array([d for d, _ in dirs[1:]])
        np.testing.assert_allclose(np.linalg.norm(side, axis=1), 1.0, atol=1e-12)
        ang = np.degrees(np.arccos(np.clip(side @ n32 / np.linalg.norm(n32), -1, 1)))
        np.testing.assert_allclose(ang, P.cone_deg, atol=1e-3)   # (float32 normal)
        for (d, m) in dirs[1:]:
            assert m == pytest.approx(1.0 / math.cos(math.radians(P.cone_deg)), rel=1e-5)
        # evenly around: the side rays sum to a multiple of the normal
        perp = side.sum(0) - (side.sum(0) @ n32) * n32
        assert np.linalg.norm(perp) < 1e-6


def _write(tmp_path, text):
    f = tmp_path / "shading.toml"
    f.write_text(text)
    return f


@pytest.mark.parametrize("text, field, words", [
    ("[normals]\nsigma_voxels = 2.0\n", None, "thin_bone"),
    ("[normals]\nsigma_voxels = 2.0\n[thin_bone]\nstart_mm = 2.0\nfull_mm = 0.5\n",
     "thin_bone", "max_weight"),
    ("[normals]\nsigma_voxels = 2.0\nsize = 3\n[thin_bone]\nstart_mm = 2.0\nfull_mm = 0.5\n"
     "max_weight = 0.5\n", "normals", "size"),
    ("[normals]\nsigma_voxels = 2.0\n[thin_bone]\nstart_mm = 1.0\nfull_mm = 1.5\n"
     "max_weight = 0.5\n", "thin_bone", "below"),
    ("[normals]\nsigma_voxels = 2.0\n[thin_bone]\nstart_mm = 2.0\nfull_mm = 0.5\n"
     "max_weight = 1.5\n", "thin_bone", "max_weight"),
    ("[normals]\nsigma_voxels = 'wide'\n[thin_bone]\nstart_mm = 2.0\nfull_mm = 0.5\n"
     "max_weight = 0.5\n", "normals", "sigma_voxels"),
    ("[normals\n", None, "malformed"),
    ("[normals]\nsigma_voxels = 2.0\n[surface]\nmax_in_voxels = 0.8\n[thin_bone]\n"
     "start_mm = 2.0\nfull_mm = 0.5\nmax_weight = 0.5\n", "surface", "max_in_voxels"),
    ("[normals]\nsigma_voxels = 2.0\n[surface]\nlevel = 0.5\n[thin_bone]\n"
     "start_mm = 2.0\nfull_mm = 0.5\nmax_weight = 0.5\n", "surface", "level"),
    ("[normals]\nsigma_voxels = 2.0\n[thin_bone]\nstart_mm = 2.0\nfull_mm = 0.5\n"
     "max_weight = 0.5\ncone_rays = 2.5\n", "thin_bone", "cone_rays"),
    ("[normals]\nsigma_voxels = 2.0\n[thin_bone]\nstart_mm = 2.0\nfull_mm = 0.5\n"
     "max_weight = 0.5\ncone_deg = 75\n", "thin_bone", "cone_deg"),
])
def test_bad_shading_files(tmp_path, text, field, words):
    f = _write(tmp_path, text)
    with pytest.raises(BonesimError) as err:
        load_shading(f)
    msg = str(err.value)
    assert str(f) in msg and words in msg and "\n" not in msg
    if field:
        assert f"[{field}]" in msg


def test_custom_file_is_read(tmp_path):
    f = _write(tmp_path, "[normals]\nsigma_voxels = 1.5\n[thin_bone]\nstart_mm = 3.0\n"
                         "full_mm = 1.0\nmax_weight = 0.5\n")
    assert load_shading(f) == ShadingParams(1.5, 3.0, 1.0, 0.5)      # [surface] optional
    f = _write(tmp_path, "[normals]\nsigma_voxels = 1.5\n[surface]\niso_density = 0.4\n"
                         "max_out_voxels = 0.6\nmax_in_voxels = 0.3\n[thin_bone]\n"
                         "start_mm = 3.0\nfull_mm = 1.0\nmax_weight = 0.5\ncone_rays = 6\n"
                         "cone_deg = 30.0\n")
    assert load_shading(f) == ShadingParams(1.5, 3.0, 1.0, 0.5, 0.4, 0.6, 0.3, 6, 30.0)
    for bad in ({"iso_density": 1.0}, {"max_in_voxels": 0.6}, {"max_out_voxels": 1.0},
                {"cone_rays": 2.0}, {"cone_rays": -1}, {"cone_deg": 61.0}):
        with pytest.raises(ValueError):
            ShadingParams(**bad)
    with pytest.raises(ValueError):
        ShadingParams(start_mm=1.0, full_mm=1.0)
    with pytest.raises(ValueError):
        ShadingParams(max_weight=-0.1)


def test_tint_weight_formula():
    p = P
    assert tint_weight(p.start_mm) == 0.0 and tint_weight(p.start_mm + 5) == 0.0
    assert tint_weight(p.full_mm) == p.max_weight and tint_weight(0.0) == p.max_weight
    mid = 0.5 * (p.start_mm + p.full_mm)
    assert tint_weight(mid) == pytest.approx(0.5 * p.max_weight)
    ts = np.linspace(-1, 4, 101)
    got = tint_weight(ts)
    assert got.shape == ts.shape
    np.testing.assert_array_equal(got, [ref_weight(t) for t in ts])
    assert (np.diff(got) <= 0).all()                        # thinner: never weaker


# ---------------------------------------------------------------------------
# analytic slabs
# ---------------------------------------------------------------------------
def slab(n_bone, struct=2, h=0.5, n_struct=4, above=3, width=12):
    """Labels: ``struct`` for k < n_struct, bone for the next n_bone layers,
    air above; the top surface faces +z."""
    lab = np.zeros((width, width, n_struct + n_bone + above), np.uint8)
    lab[:, :, :n_struct] = struct
    lab[:, :, n_struct:n_struct + n_bone] = 1
    return Grid.from_dense(lab, spacing_mm=h), n_struct + n_bone - 1


@pytest.mark.parametrize("struct", [2, 3])
@pytest.mark.parametrize("n_bone", [1, 2, 3, 4, 5, 6])
@pytest.mark.parametrize("h", [0.5, 0.25])
def test_slab_shows_the_structure_by_its_thickness(n_bone, struct, h):
    grid, top = slab(n_bone, struct, h)
    surf = Surface.build(grid, COLORS, bone=BONE)
    v = surf.vertex_at(6, 6, top)
    np.testing.assert_allclose(surf.nrm[v], [0, 0, 1], atol=1e-6)
    t, s = beneath(grid, [[6, 6, top]], surf.nrm[v:v + 1], BONE)
    if n_bone * h <= P.start_mm:
        bisection = TINT_STEP_FRACTION * h / 2 ** TINT_BISECT_ITERS
        assert s[0] == struct and t[0] == pytest.approx(n_bone * h, abs=bisection)
    else:
        assert s[0] == 0 and t[0] == P.start_mm
    # measured from the vertex, which sits near the voxels' face
    t, s = beneath(grid, [[6, 6, top]], surf.nrm[v:v + 1], BONE, shift=surf.shift[v])
    if n_bone * h < P.start_mm - h:
        assert s[0] == struct
        assert t[0] == pytest.approx(n_bone * h, abs=0.1 * h)
    assert surf.col[v].tolist() == vertex_colour(surf, grid, (6, 6, top))
    if n_bone * h >= P.start_mm + h:
        assert surf.col[v].tolist() == list(BONE_RGB) + [255]
    elif n_bone * h <= P.full_mm - h:
        assert surf.col[v].tolist() == plain_colour(1, struct, P.max_weight)
    # the structure's own surface keeps its own colour
    side = surf.vertex_at(0, 6, 0)
    assert surf.col[side].tolist() == list(COLORS[struct]) + [255]


def test_the_tint_deepens_as_the_slab_thins():
    """Thinner bone is never less tinted: one step of the band per layer."""
    blues = []
    for n_bone in range(8, 0, -1):
        grid, top = slab(n_bone, 2, 0.25, width=14)
        surf = Surface.build(grid, COLORS, bone=BONE)
        blues.append(surf.col[surf.vertex_at(7, 7, top), 2])
    assert blues == sorted(blues) and blues[-1] > blues[0]


@pytest.mark.parametrize("tiled", [False, True])
def test_drilling_a_slab_thinner_strengthens_the_tint(tiled):
    h = 0.5
    grid, top = slab(5, 2, h, width=16)
    surf = Surface.build(grid, COLORS, bone=BONE)
    if tiled:
        force_tiles(surf)
    seen = []
    for layer in range(4):                 # 5 -> 1 voxels of bone over the sinus
        k = top - layer
        patch = np.array([(i, j, k) for i in range(2, 14) for j in range(2, 14)], np.int32)
        _set_density(grid, patch, 0.0)
        surf.update(grid, patch)
        v = surf.vertex_at(8, 8, k - 1)
        assert surf.col[v].tolist() == vertex_colour(surf, grid, (8, 8, k - 1))
        if seen:
            assert surf.col[v].tolist() != seen[-1]
        seen.append(surf.col[v].tolist())
        _assert_same_as_rebuild(surf, grid)
    # bluer and bluer: the blue channel rises, the red falls
    assert [c[2] for c in seen] == sorted(c[2] for c in seen)
    assert [c[0] for c in seen] == sorted((c[0] for c in seen), reverse=True)


def _wedge(n=40, h=0.5):
    """Bone over a sinus (k < 6), drilled to a floor that rises evenly along
    x from half a voxel to six and a half voxels over the sinus, the
    voxel under the floor partly drilled (as a burr leaves it)."""
    lab = np.zeros((n, 16, 24), np.uint8)
    lab[:, :, :6] = 2
    lab[:, :, 6:20] = 1
    dens = np.ones(lab.shape, np.float32)
    x = np.arange(n)[:, None, None]
    z = np.arange(24)[None, None, :]
    floor = 6 + 0.5 + 6.0 * x / (n - 1)
    frac = np.broadcast_to(floor - np.floor(floor), dens.shape)
    dens[(z >= np.floor(floor) + 1) & (lab == 1)] = 0
    part = (z == np.floor(floor)) & (lab == 1)
    dens[part] = frac[part]
    lab[dens == 0] = 0
    return Grid.from_dense(lab, dens, spacing_mm=h)


def test_a_drilled_wedge_reads_as_a_band():
    """Along a floor thinned evenly toward the sinus, the drawn floor rises
    smoothly (no voxel terraces) and the tint deepens smoothly toward the
    thin end: a band, not steps or blotches."""
    grid = _wedge()
    surf = Surface.build(grid, COLORS, bone=BONE)
    z, red = [], []
    for i in range(4, 36):                       # away from the end walls
        k = max(k for k in range(24) if grid.label_at(i, 8, k) == 1)
        v = surf.vertex_at(i, 8, k)
        z.append(float(surf.pos[v, 2]))
        red.append(int(surf.col[v, 0]))
    dz, dr = np.diff(z), np.diff(red)
    assert (dz > 0).all() and dz.max() < 0.2               # < 0.4 voxel per voxel
    assert (dr >= 0).all() and dr.max() <= 12              # bluer as it thins
    assert red[0] < BONE_RGB[0] - 80 and red[-1] >= BONE_RGB[0] - 5


def test_bone_over_air_and_non_bone_surfaces_keep_their_colour():
    lab = np.zeros((12, 12, 8), np.uint8)
    lab[:, :, 2:4] = 1                      # a 1 mm plate over air
    grid = Grid.from_dense(lab, spacing_mm=0.5)
    surf = Surface.build(grid, COLORS, bone=BONE)
    for v in surf.vertex_slots:
        assert surf.col[v].tolist() == list(BONE_RGB) + [255]
    # without bone labels there is no tint at all
    grid, top = slab(1, 2)
    plain = Surface.build(grid, COLORS)
    assert plain.col[plain.vertex_at(6, 6, top)].tolist() == list(BONE_RGB) + [255]
    # structures that are not bone are never tinted (a nerve under sinus)
    lab = np.zeros((12, 12, 8), np.uint8)
    lab[:, :, :3] = 2
    lab[:, :, 3:4] = 3
    surf = Surface.build(Grid.from_dense(lab, spacing_mm=0.5), COLORS, bone=BONE)
    assert surf.col[surf.vertex_at(6, 6, 3)].tolist() == list(NERVE_RGB) + [255]


def test_structure_across_a_brick_boundary():
    """Bone in one brick, the structure only in the brick below."""
    lab = np.zeros((12, 12, 16), np.uint8)
    lab[:, :, :8] = 2
    lab[:, :, 8:10] = 1
    grid = Grid.from_dense(lab, spacing_mm=0.5)
    surf = Surface.build(grid, COLORS, bone=BONE)
    assert surf.col[surf.vertex_at(6, 6, 9)].tolist() == vertex_colour(surf, grid, (6, 6, 9))
    assert surf.col[surf.vertex_at(6, 6, 9)].tolist() != list(BONE_RGB) + [255]


def test_partial_density_sinks_the_vertex_and_deepens_the_tint():
    """A partly drilled voxel is still bone: its colour is not darkened, its
    vertex sinks, and the bone measured from there is thinner."""
    seen = []
    for d in (1.0, 0.6, 0.2):
        grid, top = slab(4, 2, width=14)
        patch = [(i, j, top) for i in range(14) for j in range(14)]
        _set_density(grid, patch, d)
        surf = Surface.build(grid, COLORS, bone=BONE)
        v = surf.vertex_at(7, 7, top)
        assert surf.col[v].tolist() == vertex_colour(surf, grid, (7, 7, top))
        seen.append((float(surf.shift[v]), int(surf.col[v, 2])))
    assert [s for s, _ in seen] == sorted((s for s, _ in seen), reverse=True)
    assert [b for _, b in seen] == sorted(b for _, b in seen) and seen[-1][1] > seen[0][1]


def test_void_inside_the_bone_along_the_ray_ends_the_tint():
    """A voxel removed deeper than the normal stencil reaches, but on the
    vertex's ray: only the ray can notice it."""
    h = 0.25
    grid, top = slab(6, 2, h, width=16)           # 1.5 mm over the sinus
    surf = Surface.build(grid, COLORS, bone=BONE)
    v = surf.vertex_at(8, 8, top)
    before = surf.col[v].tolist()
    assert before == vertex_colour(surf, grid, (8, 8, top))
    void = np.array([[8, 8, top - NORMAL_RADIUS - 1]], np.int32)
    _set_density(grid, void, 0.0)
    stats = surf.update(grid, void)
    assert stats["vertices_reshaded"] > 0
    after = surf.col[v].tolist()
    assert after == vertex_colour(surf, grid, (8, 8, top))
    assert after[2] < before[2]                 # the central ray now meets air: less blue
    _assert_same_as_rebuild(surf, grid)


@pytest.mark.parametrize("h", [0.5, 0.19])
def test_near_structure_mask_is_the_union_of_balls(h):
    """The static mask of the voxels that cast rays: exactly those within
    near_radius (centre to centre) of a voxel of a non-bone label, brute
    force over a grid of several bricks."""
    rng = np.random.default_rng(11)
    lab = np.ones((30, 26, 34), np.uint8)
    for _ in range(4):
        lab[tuple(rng.integers(0, s) for s in lab.shape)] = 2
    lab[3:5, 20:22, 30:33] = 3
    grid = Grid.from_dense(lab, spacing_mm=h)
    surf = Surface.build(grid, COLORS, bone=BONE)
    near = surf.shader._near
    r = near_radius(P, h)
    src = np.argwhere(lab > 1)
    for b in range(grid.n_bricks):
        base = grid.bricks[b].astype(np.int64) * 8
        for o in range(512):
            ijk = base + [(o >> 6) & 7, (o >> 3) & 7, o & 7]
            want = bool((((src - ijk) ** 2).sum(axis=1) <= r * r).any())
            got = bool((int(near[b, o >> 6]) >> (o & 63)) & 1)
            assert got == want, (ijk, got, want)


# ---------------------------------------------------------------------------
# the ray against its step-by-step reference
# ---------------------------------------------------------------------------
def _random_tissue(rng, shape, h):
    """Bone with random cavities and blobs of two structures."""
    lab = np.where(rng.random(shape) < 0.75, 1, 0).astype(np.uint8)
    g = np.indices(shape).reshape(3, -1).T
    for s in (2, 3):
        c = rng.uniform(0, shape)
        r = rng.uniform(1.0, 3.5)
        sel = (((g - c) ** 2).sum(1) <= r * r).reshape(shape)
        lab[sel] = s
    dens = rng.uniform(0.2, 1.0, size=shape).astype(np.float32)
    return Grid.from_dense(lab, dens, spacing_mm=h, origin_mm=tuple(rng.uniform(-5, 5, 3)))


@settings(max_examples=_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2 ** 32 - 1), h=st.sampled_from([0.5, 0.25, 0.19]))
def test_beneath_matches_the_reference_ray(seed, h):
    rng = np.random.default_rng(seed)
    grid = _random_tissue(rng, tuple(int(s) for s in rng.integers(4, 12, 3)), h)
    d, _ = grid.to_dense()
    occ = np.argwhere(d > 0)
    if len(occ) == 0:
        return
    ijk = occ[rng.choice(len(occ), size=min(20, len(occ)), replace=False)]
    nrm = rng.normal(size=(len(ijk), 3))
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    t, s = beneath(grid, ijk, nrm, BONE)
    tissue = DenseTissue(grid)
    for q in range(len(ijk)):
        t_ref, s_ref = ref_beneath(tissue, ijk[q], nrm[q], BONE)
        assert (t[q], s[q]) == (t_ref, s_ref)


@pytest.mark.parametrize("seed", range(4))
def test_build_colours_match_the_reference(seed):
    rng = np.random.default_rng(seed)
    grid = _random_tissue(rng, (11, 9, 10), 0.25)
    surf = Surface.build(grid, COLORS, bone=BONE)
    want = ref_colours(surf, grid)
    tinted = 0
    for v in surf.vertex_slots:
        ijk = tuple(int(x) for x in surf.ijk[v])
        assert surf.col[v].tolist() == want[ijk], ijk
        tinted += want[ijk] != ref_colour(grid.label_at(*ijk), 0.0, [0.0, 0.0, 0.0])
    assert tinted > 0                                 # the test sees some tint


# ---------------------------------------------------------------------------
# incremental == rebuild, tint included
# ---------------------------------------------------------------------------
def _run_removals(seed, shape, h, n_batches, max_batch, tiled):
    rng = np.random.default_rng(seed)
    grid = _random_tissue(rng, shape, h)
    surf = Surface.build(grid, COLORS, bone=BONE)
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
        if len(left) and rng.random() < 0.5:
            touched = left[rng.choice(len(left), size=min(len(left), 5), replace=False)]
            for t in touched:
                _set_density(grid, t, grid.density_at(*t) * float(rng.uniform(0.2, 0.9)))
        surf.update(grid, removed, touched)
        _assert_same_as_rebuild(surf, grid)
    return surf


@settings(max_examples=_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2 ** 32 - 1),
       shape=st.tuples(st.integers(2, 12), st.integers(2, 12), st.integers(2, 12)),
       h=st.sampled_from([0.5, 0.25]), tiled=st.booleans())
def test_incremental_tint_equals_rebuild_hypothesis(seed, shape, h, tiled):
    _run_removals(seed, shape, h, n_batches=4, max_batch=15, tiled=tiled)


def test_incremental_until_empty():
    surf = _run_removals(3, (9, 10, 8), 0.25, n_batches=120, max_batch=20, tiled=False)
    assert surf.n_vertices == 0


def test_inputs_spread_over_several_windows():
    """Removals far apart (deeper than one window along k, and across a
    wide box) are refreshed window by window, as a rebuild would shade them."""
    lab = np.ones((24, 10, 100), np.uint8)
    lab[:, :, :3] = 2
    lab[:, :, 97:] = 3
    grid = Grid.from_dense(lab, spacing_mm=0.25)
    surf = Surface.build(grid, COLORS, bone=BONE)
    for batch in ([[2, 5, 2], [3, 5, 97], [20, 5, 50]],
                  [[0, 0, 3], [23, 9, 96], [12, 0, 4], [12, 9, 95], [5, 5, 50]]):
        b = np.array(batch, np.int32)
        _set_density(grid, b, 0.0)
        surf.update(grid, b, [[10, 5, 60], [1, 1, 1]])
        _assert_same_as_rebuild(surf, grid)


def test_burr_into_bone_over_a_sinus():
    """A ball-shaped burr sinking toward a sinus tube, cut after cut."""
    n = 26
    g = np.indices((n, n, n))
    lab = np.ones((n, n, n), np.uint8)
    lab[((g[0] - 13) ** 2 + (g[2] - 5) ** 2) <= 16] = 2           # tube along y
    lab[:, :, 20:] = 0
    grid = Grid.from_dense(lab, spacing_mm=0.5)
    surf = Surface.build(grid, COLORS, bone=BONE)
    pts = g.reshape(3, -1).T
    blue_before = (surf.col[surf.vertex_slots, 2] > 215).sum()
    for depth in np.linspace(22.0, 12.5, 8):
        c = np.array([13.0, 13.0, depth])
        dist = np.sqrt(((pts - c) ** 2).sum(1))
        d, _ = grid.to_dense()
        occ = d.reshape(-1) > 0
        removed = pts[occ & (dist <= 3.2) & (lab.reshape(-1) == 1)]
        shell = pts[occ & (dist > 3.2) & (dist <= 4.0) & (lab.reshape(-1) == 1)]
        _set_density(grid, removed, 0.0)
        for v in shell:
            _set_density(grid, v, grid.density_at(*v) * 0.9)
        surf.update(grid, removed.astype(np.int32), shell)
    _assert_same_as_rebuild(surf, grid)
    want = ref_colours(surf, grid)
    for v in surf.vertex_slots:
        assert surf.col[v].tolist() == want[tuple(int(x) for x in surf.ijk[v])]
    # the floor of the hole, thin over the tube, has turned blue
    assert (surf.col[surf.vertex_slots, 2] > 215).sum() > blue_before


# ---------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------
def test_bone_labels_and_of_model():
    structs = [SimpleNamespace(name="bone", kind="bone"),
               SimpleNamespace(name="sinus", kind="soft"),
               SimpleNamespace(name="nerve", kind="critical")]
    np.testing.assert_array_equal(bone_labels(structs), [0, 1, 0, 0])
    grid, top = slab(2, 2)
    model = SimpleNamespace(structures=structs, colors=COLORS, grid=grid)
    a = Surface.of_model(model).canonical()
    b = Surface.build(grid, COLORS, bone=[False, True, False, False]).canonical()
    assert a == b
    assert Surface.of_model(model, grid).canonical() == b


def test_finest_voxels_at_the_largest_reach():
    """Voxels so fine that the rays reach MAX_REACH_VOXELS: the 64-bit masks
    are full, and drilling still equals a rebuild."""
    from bonesim.engine.shading import MAX_REACH_VOXELS

    h = P.start_mm / (MAX_REACH_VOXELS - 0.8)
    assert tint_reach(P, h) == MAX_REACH_VOXELS
    grid, top = slab(8, 2, h, n_struct=30, above=4, width=14)
    surf = Surface.build(grid, COLORS, bone=BONE)
    v = surf.vertex_at(7, 7, top)
    t, s = beneath(grid, [[7, 7, top]], surf.nrm[v:v + 1], BONE)
    step = TINT_STEP_FRACTION * h
    assert s[0] == 2 and t[0] == pytest.approx(8 * h, abs=step / 2 ** TINT_BISECT_ITERS)
    assert surf.col[v].tolist() == vertex_colour(surf, grid, (7, 7, top))
    far = surf.vertex_at(0, 0, 0)                    # 29 voxels under the bone: no tint
    assert surf.col[far].tolist() == list(SINUS_RGB) + [255]
    rng = np.random.default_rng(5)
    for _ in range(3):
        d, _ = grid.to_dense()
        occ = np.argwhere(d > 0)
        removed = occ[rng.choice(len(occ), size=25, replace=False)]
        _set_density(grid, removed, 0.0)
        surf.update(grid, removed)
        _assert_same_as_rebuild(surf, grid)


def test_bad_bone_masks_and_reach():
    grid, _ = slab(2, 2)
    with pytest.raises(ValueError):
        Surface.build(grid, COLORS, bone=[0, 1, 0])              # one entry short
    with pytest.raises(ValueError):
        Surface.build(grid, COLORS, bone=[0, 2, 0, 0])
    with pytest.raises(TypeError):
        Surface.build(grid, COLORS, bone=[0.0, 1.0, 0.0, 0.0])
    with pytest.raises(TypeError):
        Surface.build(grid, COLORS, bone=BONE, shading={"start_mm": 2.0})
    lab = np.ones((4, 4, 4), np.uint8)
    fine = Grid.from_dense(lab, spacing_mm=0.05)
    with pytest.raises(BonesimError, match="start_mm"):
        Surface.build(fine, COLORS, bone=BONE)
    Surface.build(fine, COLORS, bone=BONE, shading=ShadingParams(start_mm=1.0, full_mm=0.3))
    Surface.build(fine, COLORS)                                  # no tint: no reach limit


def test_blend_without_tint_is_the_colour_itself():
    """_blend returns the colour at once when nothing is blended; the
    formula gives the same bytes (floor(c + 0.5) = c), and blends go through
    the formula."""
    from bonesim.engine.shading_full import blend as _blend

    def formula(c, w, a):
        return np.uint8(min(np.floor(np.float64(c) * (1.0 - w) + a + 0.5), 255.0))

    for c in range(256):
        assert _blend(c, c, c, 0.0, 0.0, 0.0, 0.0) == (formula(c, 0.0, 0.0),) * 3
        assert _blend(c, 0, 255, -0.0, 0.0, -0.0, 0.0) == (c, 0, 255)
    rng = np.random.default_rng(0)
    for _ in range(200):
        c = rng.integers(0, 256, 3)
        w = float(rng.uniform(0, 0.6))
        a = rng.uniform(0, 0.6 * 255, 3)
        assert _blend(c[0], c[1], c[2], w, a[0], a[1], a[2]) == tuple(
            formula(c[q], w, a[q]) for q in range(3))
