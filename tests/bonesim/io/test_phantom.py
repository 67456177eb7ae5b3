"""The procedural left temporal-bone phantom (bonesim.io.phantom)."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs
from scipy import ndimage

from bonesim.io import phantom as P

H = P.DEFAULT_VOXEL_MM
REFERENCE = Path(__file__).resolve().parents[1] / "data" / "phantom_internal_e59789d.npz"
"""Masks of the phantom before its outer cortex was shaped as a temporal bone
(commit e59789d, default seed and grid), packed with ``np.packbits``: the
named internal structures, both dura layers, the bone envelope, the air cells
and the air of the ear (canal, middle ear, antrum; without the cells)."""


@pytest.fixture(scope="module")
def parts():
    return P.build_phantom(seed=3)


def centroid(mask, parts):
    return parts.origin_mm + H * np.argwhere(mask).mean(axis=0)


def test_deterministic_from_seed(parts):
    again = P.build_phantom(seed=3)
    for name in P.PARTS:
        np.testing.assert_array_equal(again.masks[name], parts.masks[name])
    np.testing.assert_array_equal(again.hu, parts.hu)
    other = P.build_phantom(seed=4)
    assert not np.array_equal(other.air_cells, parts.air_cells)
    # the named anatomy and the outer shape do not depend on the seed
    for name in P.PARTS[1:]:
        np.testing.assert_array_equal(other.masks[name], parts.masks[name])
    np.testing.assert_array_equal(other.envelope, parts.envelope)


def test_generation_is_fast():
    P.build_phantom(seed=0)                   # warm caches
    t0 = time.perf_counter()
    P.phantom_volume(seed=1)
    assert time.perf_counter() - t0 < 1.0


def test_every_structure_present_and_labels_follow_order():
    order = tuple(reversed(P.PARTS))
    vol = P.phantom_volume(seed=2, structures=order)
    counts = vol.counts(len(order))
    assert (counts[1:] > 0).all(), dict(zip(order, counts[1:]))
    assert vol.labels.dtype == np.uint8 and vol.hu.dtype == np.float32
    assert counts[order.index("bone") + 1] == counts[1:].max()
    with pytest.raises(ValueError, match="unknown phantom part"):
        P.phantom_volume(structures=("bone", "brain"))


def test_omitted_part_is_empty():
    vol = P.phantom_volume(seed=2, structures=("bone", "facial_nerve"))
    assert set(np.unique(vol.labels)) == {0, 1, 2}
    parts = P.build_phantom(seed=2)
    assert (vol.labels[parts.masks["labyrinth"]] == 0).all()
    assert (vol.hu[parts.masks["labyrinth"]] == P.HU_AIR).all()


def test_size_and_grid(parts):
    assert parts.hu.shape == (104, 104, 104)
    np.testing.assert_allclose(parts.origin_mm, -25.75)
    bone = np.argwhere(parts.masks["bone"])
    extent = (bone.max(0) - bone.min(0) + 1) * H
    assert (extent > 38).all() and (extent <= 52).all() and extent.max() > 44


def test_intensities(parts):
    hu = parts.hu
    bone = hu[parts.masks["bone"]]
    assert 1400 < bone.mean() < 1600 and bone.std() > 30 and bone.min() > 600
    assert (hu[parts.air_cells] == P.HU_AIR).all()
    for name in ("sigmoid_sinus", "middle_fossa_dura", "facial_nerve"):
        assert (hu[parts.masks[name]] < 100).all()
    assert (hu == np.rint(hu)).all()


def test_air_cells_keep_the_cortex(parts):
    cells = parts.air_cells
    assert 500 < cells.sum() * H ** 3 < 8000             # well pneumatized [mm^3]
    dist = ndimage.distance_transform_edt(parts.envelope, sampling=H)
    assert dist[cells].min() >= P.CORTEX_MM
    # the lateral surface is intact bone in every column that meets the block
    bone_or_soft = parts.masks["bone"] | cells
    cols = bone_or_soft.any(axis=0)
    outer = bone_or_soft.shape[0] - 1 - np.argmax(bone_or_soft[::-1], axis=0)
    assert not cells[outer[cols], *np.nonzero(cols)].any()


def test_left_ear_relations(parts):
    m = parts.masks
    bone = m["bone"]
    # lateral surface of the bone block (max x with bone per (y, z) column)
    def cortex_x(j, k):
        col = np.nonzero(bone[:, j, k] | parts.air_cells[:, j, k])[0]
        return parts.origin_mm[0] + H * col.max()

    facial = np.argwhere(m["facial_nerve"])
    z = parts.origin_mm[2] + H * facial[:, 2]
    mastoid_seg = facial[(z < -3) & (z > -14)]     # above the foramen's slope
    depth = [cortex_x(j, k) - (parts.origin_mm[0] + H * i) for i, j, k in mastoid_seg]
    assert 10.0 <= min(depth) and max(depth) <= 16.0

    sinus, fn = centroid(m["sigmoid_sinus"], parts), centroid(m["facial_nerve"], parts)
    lab = centroid(m["labyrinth"], parts)
    dura = centroid(m["middle_fossa_dura"], parts)
    assert sinus[1] > fn[1] + 8                           # sinus posterior
    assert lab[0] < fn[0]                                 # labyrinth medial to FN
    assert dura[2] > P.TEGMEN_Z_MM > P.ANTRUM_CENTER_MM[2]  # tegmen superior
    # the antrum is an air space anterior-superior in the mastoid
    a = np.rint((np.asarray(P.ANTRUM_CENTER_MM) - parts.origin_mm) / H).astype(int)
    assert not any(m[n][tuple(a)] for n in P.PARTS)
    cells = centroid(parts.air_cells, parts)
    assert P.ANTRUM_CENTER_MM[1] < cells[1] and P.ANTRUM_CENTER_MM[2] > cells[2]
    # chorda tympani leaves the facial nerve
    touching = ndimage.binary_dilation(m["chorda_tympani"]) & m["facial_nerve"]
    assert touching.any()
    # the camera of the bundled case looks from outside the bone, laterally
    assert np.argwhere(bone)[:, 0].max() * H + parts.origin_mm[0] < 25


def idx(p, parts):
    """Voxel index of a point [mm] (nearest voxel centre)."""
    return tuple(np.rint((np.asarray(p, float) - parts.origin_mm) / H).astype(int))


def coord(i, axis, parts):
    """Case-frame coordinate [mm] of voxel index ``i`` along ``axis``."""
    return parts.origin_mm[axis] + H * np.asarray(i)


def on_grid(v, axis, parts):
    """The voxel-centre coordinate nearest ``v`` [mm] along ``axis``."""
    return float(coord(np.rint((v - parts.origin_mm[axis]) / H), axis, parts))


def lateral_x(parts, y, z, mask=None):
    """x [mm] of the most lateral bone voxel in the column (y, z); NaN if none."""
    mask = parts.masks["bone"] if mask is None else mask
    _, j, k = idx((0.0, y, z), parts)
    col = np.nonzero(mask[:, j, k])[0]
    return float(coord(col.max(), 0, parts)) if col.size else np.nan


def test_landmarks_are_where_documented(parts):
    lm = P.LANDMARKS_MM
    idx_ = lambda p: idx(p, parts)
    bone = parts.masks["bone"]
    assert parts.masks["facial_nerve"][idx_(lm["facial_mastoid_mid"])]
    x, y, z = lm["mastoid_cortex"]
    assert bone[idx_((x - 1.0, y, z))]
    assert not bone[idx_((x + 1.0, y, z))]
    sx, sy, sz = lm["sigmoid_sinus_lateral"]
    assert parts.masks["sigmoid_sinus"][idx_((sx - 1.0, sy, sz))]
    assert not parts.masks["sigmoid_sinus"][idx_((sx + 1.0, sy, sz))]
    # the outer cortex's landmarks: on (or in) the bone, with air just outside
    for name in ("temporal_line", "squama"):
        x, y, z = lm[name]
        assert bone[idx_((x - 0.75, y, z))] and not bone[idx_((x + 0.75, y, z))], name
    assert bone[idx_(lm["zygomatic_root"])]
    x, y, z = lm["mastoid_tip"]
    assert bone[idx_((x, y, z + 1.0))] and not bone[idx_((x, y, z - 1.0))]
    x, y, z = lm["eac_opening"]
    assert not bone[idx_((x, y, z))] and not bone[idx_((x - 5.0, y, z))]   # the lumen


# ------------------------------------------------------ inside: as before
def _reference():
    ref = np.load(REFERENCE)
    shape = tuple(int(n) for n in ref["shape"])
    unpack = lambda a: np.unpackbits(a, count=int(np.prod(shape))).reshape(shape).astype(bool)
    return {k: unpack(ref[k]) for k in ref.files if k not in ("shape", "origin_mm")}, ref


def _box(parts, lo, hi):
    """Voxels whose centres lie in the box [lo, hi] [mm]."""
    ax = [coord(np.arange(n), a, parts) for a, n in enumerate(parts.hu.shape)]
    inside = [(v >= lo[a]) & (v <= hi[a]) for a, v in enumerate(ax)]
    return inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]


def test_inside_is_as_before_the_outer_cortex_changed():
    parts = P.build_phantom()                     # the reference's seed
    ref, raw = _reference()
    assert raw["shape"].tolist() == list(parts.hu.shape)
    np.testing.assert_allclose(raw["origin_mm"], parts.origin_mm)
    m = parts.masks
    for name in ("sigmoid_sinus", "facial_nerve", "chorda_tympani", "labyrinth", "ossicles"):
        assert np.array_equal(m[name], ref[name]), name
    # the dura of the tegmen over the middle ear, antrum and mastoid, and of
    # the posterior fossa along the sinus: none lost, hardly any added (where
    # the new, rounder body reaches a little further); the posterior fossa's
    # dura now also lines the skull's wall that closes the fossa behind and
    # covers the sinus (PF_TABLE_MM inside the outer shape)
    tegmen = _box(parts, (-5.0, -12.0, P.TEGMEN_Z_MM), (11.0, 12.0, P.TEGMEN_Z_MM + P.DURA_MM))
    along_sinus = _box(parts, (-10.0, 0.0, -12.0), (12.0, 18.0, 10.0))
    depth = ndimage.distance_transform_edt(parts.envelope | parts.masks["posterior_fossa_dura"]
                                           | (ndimage.binary_fill_holes(parts.envelope)),
                                           sampling=H)
    lining = depth <= P.PF_TABLE_MM + P.DURA_MM + H
    for name, region in (("middle_fossa_dura", tegmen), ("posterior_fossa_dura", along_sinus)):
        before = ref[name] & region
        assert before.sum() > 1000, name
        assert not (before & ~m[name]).any(), name
        added = m[name] & region & ~before
        if name == "posterior_fossa_dura":
            added &= ~lining
        assert added.sum() < 0.01 * before.sum(), name
    # the air of the ear: middle ear, antrum, aditus and the canal's medial
    # part (outside the air cells, which move with the outer shape)
    painted = np.zeros(parts.hu.shape, bool)
    for name in P.PARTS:
        painted |= m[name]
    ear = parts.envelope & ~painted & ~parts.air_cells
    medial = _box(parts, (-30.0, -30.0, -30.0), (P.EAC_OVAL_FROM_X_MM, 30.0, 30.0))
    medial &= ~(parts.air_cells | ref["air_cells"])
    assert (ref["ear_air"] & medial).sum() > 1000
    assert np.array_equal(ear & medial, ref["ear_air"] & medial)
    # the bone around nerves, labyrinth and ossicles (2 mm), above the
    # stylomastoid foramen
    critical = m["facial_nerve"] | m["chorda_tympani"] | m["labyrinth"] | m["ossicles"]
    near = ndimage.distance_transform_edt(~critical, sampling=H) <= 2.0
    near &= _box(parts, (-30.0, -30.0, -18.0), (30.0, 30.0, 30.0)) & ~critical
    assert not (ref["envelope"] & near & ~parts.envelope).any()


def test_structures_stay_covered(parts):
    """Only the ends of nerve and sinus leave the bone (stylomastoid foramen,
    jugular bulb, transverse sinus); the labyrinth is closed in."""
    labels = np.zeros(parts.hu.shape, np.uint8)
    for i, name in enumerate(P.PARTS, start=1):
        labels[parts.masks[name]] = i
    air, _ = ndimage.label(labels == 0)
    faces = np.concatenate([a.ravel() for a in (air[0], air[-1], air[:, 0], air[:, -1],
                                                air[:, :, 0], air[:, :, -1])])
    outside = np.isin(air, np.unique(faces[faces > 0]))
    touches = ndimage.binary_dilation(outside)
    assert not (touches & parts.masks["labyrinth"]).any()
    z = lambda mask: coord(np.argwhere(mask & touches)[:, 2], 2, parts)
    assert z(parts.masks["facial_nerve"]).max() < -18.0          # below the foramen
    # the sinus shows at the jugular bulb, the transverse sinus and along its
    # posterior groove, never lateral to the mastoid
    sinus_out = np.argwhere(parts.masks["sigmoid_sinus"] & touches)
    assert coord(sinus_out[:, 0], 0, parts).max() < P.LANDMARKS_MM["sigmoid_sinus_lateral"][0]


# --------------------------------------------------- outside: what a surgeon sees
def test_mastoid_process_points_down_and_forward(parts):
    env = parts.envelope
    lateral = coord(np.arange(env.shape[0]), 0, parts)[:, None] > 8.0
    canal_z = P.LANDMARKS_MM["eac_opening"][2]
    areas, ys = [], []
    for z in (-12.25, -15.25, -18.25, -21.25, -23.25):
        cut = env[:, :, idx((0, 0, z), parts)[2]] & lateral
        areas.append(cut.sum() * H * H)
        ys.append(coord(np.argwhere(cut)[:, 1], 1, parts).mean())
    assert all(a > b for a, b in zip(areas, areas[1:])), areas     # a cone...
    assert ys[-1] < ys[1] - 2.0, ys                               # ...leaning forward
    # the tip: the lowest lateral bone, 1.5-2 cm below the canal and behind it
    pts = coord(np.argwhere(parts.masks["bone"]), np.arange(3), parts)
    tip = pts[pts[:, 0] > 8.0][np.argmin(pts[pts[:, 0] > 8.0, 2])]
    assert np.linalg.norm(tip - P.LANDMARKS_MM["mastoid_tip"]) < 1.5
    assert 15.0 <= canal_z - tip[2] <= 21.0
    assert 8.0 <= tip[1] - P.LANDMARKS_MM["eac_opening"][1] <= 20.0


def test_ear_canal_opens_as_an_oval_with_a_rim(parts):
    bone = parts.masks["bone"]
    x0, y0, z0 = P.LANDMARKS_MM["eac_opening"]
    y0, z0 = on_grid(y0, 1, parts), on_grid(z0, 2, parts)
    for x in (x0 - 0.75, x0 - 2.25):
        i, j, k = idx((x, y0, z0), parts)
        col, row = bone[i, j, :], bone[i, :, k]
        up, down = np.argmax(col[k:]), np.argmax(col[k::-1])     # first bone each way
        back, front = np.argmax(row[j:]), np.argmax(row[j::-1])
        height, width = (up + down - 1) * H, (back + front - 1) * H
        assert 8.0 <= height <= 10.0 and 6.0 <= width <= 8.0, (height, width)
        assert height > width + 1.0                               # oval, upright
    # the rim: bone all round the opening at the rim plane, none in front of it
    sy, sz = P.EAC_OPENING_SEMI_MM
    for a in np.radians(np.arange(0, 360, 15)):
        ring = [idx((x, y0 + (sy + 1.0) * np.cos(a), z0 + (sz + 1.0) * np.sin(a)), parts)
                for x in np.arange(x0 - 1.5, x0 + 0.01, H)]
        assert any(bone[r] for r in ring), np.degrees(a)
    # the canal runs on to the middle ear: air along the axis
    xs = np.arange(P.EAC_AXIS_MM[1][0] + 1.0, x0, H)
    assert not any(bone[idx((x, y0, z0), parts)] for x in xs)


def test_spine_of_henle_above_behind_the_opening(parts):
    x, y, z = P.LANDMARKS_MM["henle_spine"]
    _, y0, z0 = P.LANDMARKS_MM["eac_opening"]
    assert y > y0 + 1.0 and z > z0 + 1.0                          # posterior-superior
    top = lateral_x(parts, y, z)
    assert abs(top - x) <= 1.0
    assert top >= P.EAC_RIM_X_MM + 1.0                            # stands out of the rim
    # a spine, not a wall: the cortex around it lies 1-3 mm lower
    around = [lateral_x(parts, y + dy, z + dz) for dy, dz in ((2.0, 0.0), (0.0, 2.0), (1.5, 1.5))]
    assert all(1.0 <= top - a <= 3.5 for a in around), (top, around)


def test_temporal_line_is_a_ridge_running_back(parts):
    """Across the line, the lateral face peaks at the crest (y, z) points."""
    for y, zc in P.TEMPORAL_LINE_YZ_MM[1:-1]:
        y = on_grid(y, 1, parts)
        crest = max(lateral_x(parts, y, on_grid(zc + dz, 2, parts)) for dz in (-0.5, 0.0, 0.5))
        above = lateral_x(parts, y, on_grid(zc + 3.5, 2, parts))
        below = lateral_x(parts, y, on_grid(zc - 3.5, 2, parts))
        assert crest >= max(above, below) + 0.75, (y, crest, above, below)
    # it starts at the zygomatic root, above the canal's opening
    y_start, z_start = P.TEMPORAL_LINE_YZ_MM[0]
    assert y_start > P.LANDMARKS_MM["zygomatic_root"][1]
    assert z_start > P.LANDMARKS_MM["eac_opening"][2] + P.EAC_OPENING_SEMI_MM[1]


def test_zygomatic_root_in_front_cut_off(parts):
    bone = parts.masks["bone"]
    x, y, z = P.LANDMARKS_MM["zygomatic_root"]
    _, y0, z0 = P.LANDMARKS_MM["eac_opening"]
    assert y < y0 and z > z0 + P.EAC_OPENING_SEMI_MM[1]          # anterior-superior
    # no bone in front of the saw cut; the stump reaches it, standing out laterally
    ys = coord(np.argwhere(bone)[:, 1], 1, parts)
    assert ys.min() >= P.ANTERIOR_CUT_Y_MM - H / 2
    yc = on_grid(P.ANTERIOR_CUT_Y_MM + H, 1, parts)
    zc = on_grid(P.ZYGOMA_CENTER_MM[2], 2, parts)
    assert bone[idx((P.ZYGOMA_CENTER_MM[0], yc, zc), parts)]
    squama = lateral_x(parts, on_grid(-16.0, 1, parts), on_grid(P.TEGMEN_Z_MM + 2.0, 2, parts))
    assert lateral_x(parts, yc, zc) >= squama + 1.5


def test_squama_rises_thin_above_the_tegmen(parts):
    bone, dura = parts.masks["bone"], parts.masks["middle_fossa_dura"]
    y = on_grid(P.SQUAMA_POINT_MM[1], 1, parts)
    faces = []
    for z in np.arange(P.TEGMEN_Z_MM + 3.0, P.TEGMEN_Z_MM + 12.0, 2.0):
        z = on_grid(z, 2, parts)
        _, j, k = idx((0, y, z), parts)
        col = np.nonzero(bone[:, j, k])[0]
        assert col.size * H == pytest.approx(P.SQUAMA_MM, abs=H), z     # one thin plate
        assert np.all(np.diff(col) == 1)
        assert dura[col.min() - 1, j, k]                          # the fossa medial to it
        faces.append(float(coord(col.max(), 0, parts)))
    assert max(faces) - min(faces) < 3.0                          # flat...
    assert faces[len(faces) // 2] >= 0.5 * (faces[0] + faces[-1])  # ...slightly convex


def test_lateral_surface_matches_the_voxels(parts):
    """lateral_surface_x_mm is the smooth face; the voxels add the mastoid's
    relief (up to ROUGH_MM) and their half-voxel rounding."""
    def deviations(ys, zs):
        return np.array([lateral_x(parts, y, z) - P.lateral_surface_x_mm(y, z)
                         for y in ys for z in zs])
    grid = lambda a, b: [on_grid(v, 1, parts) for v in np.arange(a, b, 1.0)]
    mastoid = deviations(grid(0.0, 14.0), [on_grid(v, 2, parts) for v in np.arange(-14.0, 0.0, 1.0)])
    squama = deviations(grid(-16.0, 0.0), [on_grid(v, 2, parts) for v in np.arange(13.0, 20.0, 1.0)])
    for d in (mastoid, squama):
        assert np.isfinite(d).all() and np.abs(d).max() <= P.ROUGH_MM + 2 * H
    assert np.abs(squama).max() <= H
    assert mastoid.std() > squama.std() + 0.05                    # the mastoid is rough
    assert np.isnan(P.lateral_surface_x_mm(40.0, 0.0))            # a column that misses


# ------------------------------------------------------ distance primitives
coords = hs.floats(-30.0, 30.0)
point = hs.tuples(coords, coords, coords)


@settings(max_examples=200, deadline=None)
@given(p=point, a=point, b=point, ra=hs.floats(0.5, 6.0), rb=hs.floats(0.5, 6.0))
def test_round_cone_distance(p, a, b, ra, rb):
    """Outside: the distance to the union of the swept balls; inside: negative."""
    if np.linalg.norm(np.subtract(b, a)) < abs(ra - rb) + 0.1:
        return                                     # one ball holds the other
    t = np.linspace(0.0, 1.0, 20001)[:, None]
    c = np.asarray(a) + t * (np.asarray(b) - np.asarray(a))
    ref = (np.linalg.norm(np.asarray(p) - c, axis=1) - (ra + (rb - ra) * t[:, 0])).min()
    d = float(P._sd_round_cone(*(np.float64(v) for v in p), a, b, ra, rb))
    if ref > 0:
        assert d == pytest.approx(ref, abs=2e-3)
    else:
        assert d <= 1e-9


@settings(max_examples=200, deadline=None)
@given(p=point, c=point, r=hs.tuples(*[hs.floats(1.0, 20.0)] * 3))
def test_ellipsoid_distance(p, c, r):
    q = (np.asarray(p) - c) / r
    d = float(P._sd_ellipsoid(*(np.float64(v) for v in p), c, r))
    assert (d < 0) == (q @ q < 1.0) or abs(q @ q - 1.0) < 1e-9
    # exact for a sphere; zero on the surface
    s = float(P._sd_ellipsoid(*(np.float64(v) for v in p), c, (r[0],) * 3))
    assert s == pytest.approx(np.linalg.norm(np.subtract(p, c)) - r[0], abs=1e-9)
    n = np.linalg.norm(q)
    if n > 1e-6:
        on = np.asarray(c) + np.asarray(r) * q / n
        assert float(P._sd_ellipsoid(*on, c, r)) == pytest.approx(0.0, abs=1e-9)


@settings(max_examples=300, deadline=None)
@given(a=hs.floats(-50, 50), b=hs.floats(-50, 50), k=hs.floats(0.0, 5.0))
def test_smooth_union(a, b, k):
    m = P._smin(np.float64(a), np.float64(b), k)
    assert min(a, b) - k / 4 - 1e-12 <= m <= min(a, b) + 1e-12
    assert m == pytest.approx(P._smin(np.float64(b), np.float64(a), k))
    if abs(a - b) >= k:
        assert m == pytest.approx(min(a, b))
    assert P._smax(np.float64(a), np.float64(b), k) == pytest.approx(-P._smin(-a, -b, k))


def test_bounding_boxes_leave_the_shape_as_the_full_field():
    """The grid field evaluates each part in its box only; its zero level is
    the full smooth union's at every voxel centre. (Values away from the
    surface may differ: the ellipsoid distance is an approximation.)"""
    cv = P.Canvas(np.full(3, 64), 0.8)
    grid = P._cortex_field(cv, relief=False)
    x, y, z = (a.astype(float) for a in cv.full()[1:])
    full = P._eval_points(P._base_parts() + P._feature_parts(), x, y, z)
    sure = np.abs(full) > 1e-3                    # beyond float32 rounding
    assert sure.mean() > 0.99
    assert np.array_equal((grid <= 0)[sure], (full <= 0)[sure])


# ----------------------------------------------------------- generations
def test_generation_2_is_the_open_posterior_fossa():
    """Generation 2 (kept as ``phantom@2`` for its recordings) differs from
    the latest only behind the mastoid: the bone closing the posterior fossa
    over the sinus; the named anatomy is the same."""
    from bonesim.io.case import case_versions, load_case

    old, new = P.build_phantom(7, generation=2), P.build_phantom(7)
    for name in ("sigmoid_sinus", "facial_nerve", "chorda_tympani", "labyrinth",
                 "ossicles"):
        np.testing.assert_array_equal(old.masks[name], new.masks[name])
    grown = new.masks["bone"] & ~old.masks["bone"]
    y = coord(np.argwhere(grown)[:, 1], 1, new)
    assert grown.sum() > 1000 and np.percentile(y, 5) > 2.0        # behind the mastoid
    assert "phantom@2" in case_versions("phantom")
    c = load_case("phantom@2")
    assert c.name == "phantom" and c.volume.generation == 2
    np.testing.assert_array_equal(c.load_volume().labels != 0,
                                  P.phantom_volume(7, generation=2).labels != 0)
    with pytest.raises(ValueError, match="generation"):
        P.build_phantom(7, generation=0)


def test_a_bad_generation_names_the_key(tmp_path):
    from bonesim.errors import BonesimError
    from bonesim.io.case import cases_dir, parse_case

    text = (cases_dir() / "phantom" / "case.toml").read_text()
    path = tmp_path / "case.toml"
    path.write_text(text.replace("generation = 3", "generation = 9"))
    with pytest.raises(BonesimError, match=r"\[volume\]: 'generation' must be one of"):
        parse_case(path)
