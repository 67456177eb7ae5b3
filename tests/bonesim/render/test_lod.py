"""Level of detail of the bone surface (bonesim.render.lod): representatives
and far flags against plain loops over the definition (near box and drilled
blocks), kept through removals near and far from the burr; drawn lists
against a plain evaluation; the coarse mesh stays closed (no cracks), also
after drilling far from the burr; what the burr opens is drawn at full
detail, and stays so after the burr moves away; and the picture with it
stays close to the picture without. The same for the second level (coarse
representatives outside the mid box)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from bonesim.engine.grid import voxel_offset
from bonesim.engine.normals import NORMAL_RADIUS
from bonesim.engine.surface import Surface
from bonesim.render.lod import BLOCK_SHIFT, CLUSTER_SHIFT, COARSE_SHIFT, SurfaceLOD, voxel_px
from bonesim.render.meshbuf import SurfaceBuffers
from tests.bonesim.render.scenes import nerve_block

EYE = np.array([9.0, 7.0, 40.0])
SAVE = None            # a path: the picture test saves both images side by side
DOWN = np.array([0.0, 0.0, -1.0])


def _remove(grid, ijk):
    out = []
    for i, j, k in np.asarray(ijk).reshape(-1, 3):
        b = grid.brick_index(i, j, k)
        if b >= 0 and grid.density[b, voxel_offset(i, j, k)] > 0:
            grid.density[b, voxel_offset(i, j, k)] = 0.0
            out.append((i, j, k))
    return np.array(out, np.int32).reshape(-1, 3)


def _ball(c, r):
    g = np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1].reshape(3, -1).T
    return np.asarray(c) + g[(g ** 2).sum(1) <= r * r]


@pytest.fixture
def drilled():
    """A bone block with a bowl and a few pits drilled in its top face."""
    model, state = nerve_block()
    grid = state.grid
    surf = Surface.build(grid, model.colors)
    for c, r in (((16, 16, 16), 6), ((5, 6, 15), 2), ((26, 9, 15), 3), ((9, 25, 15), 2)):
        rem = _remove(grid, _ball(c, r))
        surf.update(grid, rem)
    return model, state, surf


def _box(lo, hi):
    return np.array(lo, np.int64), np.array(hi, np.int64)


def _ref_drilled(block, changed):
    """Plain rule: ``block`` meets the box of NORMAL_RADIUS + 1 voxels
    around one of the ``changed`` voxels (along every axis)."""
    reach = NORMAL_RADIUS + 1
    size = 1 << BLOCK_SHIFT
    for c in changed:
        if all(block[a] * size <= c[a] + reach and block[a] * size + size - 1 >= c[a] - reach
               for a in range(3)):
            return True
    return False


def _ref_lod(surf, box, changed=(), mid=None):
    """Plain loops over the definition: (rep, level) of every live vertex
    (level 0 full detail, 1 far, 2 far outside the ``mid`` box);
    ``changed``: every voxel removed since the level of detail was built."""
    live = surf.vertex_slots
    at = {tuple(int(x) for x in surf.ijk[v]): int(v) for v in live}
    changed = [tuple(int(x) for x in c) for c in np.asarray(changed).reshape(-1, 3)]
    drilled = {}
    rep, far = {}, {}
    n = 1 << CLUSTER_SHIFT
    for v in live:
        ijk = surf.ijk[v].astype(int)
        blk = tuple(int(x) for x in ijk >> BLOCK_SHIFT)
        inside = box is not None and bool(np.all(np.array(blk) >= box[0])
                                          and np.all(np.array(blk) <= box[1]))
        if blk not in drilled:
            drilled[blk] = _ref_drilled(blk, changed)
        in_mid = mid is None or bool(np.all(np.array(blk) >= mid[0])
                                     and np.all(np.array(blk) <= mid[1]))
        far[int(v)] = 0 if (inside or drilled[blk]) else (1 if in_mid else 2)
        base = (ijk >> CLUSTER_SHIFT) << CLUSTER_SHIFT
        cand = [at[tuple(base + d)] for d in np.ndindex(n, n, n) if tuple(base + d) in at]
        rep[int(v)] = cand[0]              # ndindex is (i, j, k) order
    return rep, far


def _ref_rep2(surf, min_cos, rep1):
    """Plain loops: the coarse representative of every live vertex (the
    vertex of its coarse cluster whose normal is nearest the mean normal,
    or ``rep1`` where a normal lies under ``min_cos`` from the mean)."""
    at = {tuple(int(x) for x in surf.ijk[v]): int(v) for v in surf.vertex_slots}
    n = 1 << COARSE_SHIFT
    out = {}
    for v in surf.vertex_slots:
        base = (surf.ijk[v].astype(int) >> COARSE_SHIFT) << COARSE_SHIFT
        members = [at[tuple(base + d)] for d in np.ndindex(n, n, n) if tuple(base + d) in at]
        sx = sy = sz = 0.0                      # float64 sums in (i, j, k) order
        for u in members:
            sx, sy, sz = sx + float(surf.nrm[u, 0]), sy + float(surf.nrm[u, 1]), \
                sz + float(surf.nrm[u, 2])
        norm = float(np.sqrt(sx * sx + sy * sy + sz * sz))
        dots = [float(surf.nrm[u, 0]) * sx + float(surf.nrm[u, 1]) * sy
                + float(surf.nrm[u, 2]) * sz for u in members]
        smooth = norm > 0 and all(d >= min_cos * norm for d in dots)
        out[int(v)] = members[int(np.argmax(dots))] if smooth else rep1[int(v)]
    return out


def _check_against_ref(lod, surf, box, changed=(), mid=None):
    """Representatives and levels against the plain loops; with a second
    level, the coarse representatives of the vertices drawn with them."""
    rep, far = _ref_lod(surf, box, changed, mid)
    for v in surf.vertex_slots:
        assert lod.rep[v] == rep[int(v)], v
        assert int(lod.far[v]) == far[int(v)], v
    if mid is not None and lod.coarse_min_cos is not None:
        rep2 = _ref_rep2(surf, lod.coarse_min_cos, rep)
        for v in surf.vertex_slots:
            if far[int(v)] == 2:
                assert lod.rep2[v] == rep2[int(v)], v


def _ref_drawn(surf, lod, eye=None):
    """Plain evaluation of the drawn triangles as a multiset of sorted
    triples: near ones as they are, far ones as their representatives'
    (degenerate ones dropped); with ``eye``, only far ones facing it."""
    p, nrm = surf.pos.astype(np.float64), surf.nrm.astype(np.float64)
    out = []
    for t in surf.triangle_slots:
        a, b, c = (int(x) for x in surf.tri[t])
        if not (lod.far[a] or lod.far[b] or lod.far[c]):
            out.append((a, b, c))
            continue
        a, b, c = (int(lod.rep2[x]) if lod.far[x] == 2 else int(lod.rep[x]) if lod.far[x]
                   else x for x in (a, b, c))
        if len({a, b, c}) < 3:
            continue
        if eye is not None:
            face = np.cross(p[b] - p[a], p[c] - p[a]) @ (eye - p[a]) > 0
            corner = any(nrm[v] @ (eye - p[v]) > 0 for v in (a, b, c))
            if not (face or corner):
                continue
        out.append((a, b, c))
    return sorted(tuple(sorted(t)) for t in out)


def _drawn(flat):
    return sorted(tuple(sorted(int(x) for x in t)) for t in np.asarray(flat).reshape(-1, 3))


def _far_triples(buf, surf, flat):
    lod = buf.lod
    return [t for t in _drawn(flat) if any(lod.far[v] for v in t)]


def test_representatives_match_the_definition(drilled):
    model, state, surf = drilled
    for box in (None, _box((1, 1, 1), (2, 2, 2)), _box((0, 0, 0), (9, 9, 9))):
        lod = SurfaceLOD()
        lod.rebuild(surf, box)
        _check_against_ref(lod, surf, box)
    assert lod.far[surf.vertex_slots].sum() == 0              # everything near


def test_representatives_follow_removals(drilled):
    """Removals inside the near box and far from it (the blocks they reach
    turn drilled: full detail from then on), and the near box moving away
    and back; the drilled blocks stay through a rebuild of the same
    surface."""
    model, state, surf = drilled
    grid = state.grid
    box = _box((1, 1, 1), (2, 2, 2))
    lod = SurfaceLOD()
    lod.rebuild(surf, box)
    _check_against_ref(lod, surf, box)
    assert len(lod.drilled_blocks()) == 0
    changed = []
    # the last: one voxel whose NORMAL_RADIUS + 1 box reaches blocks its
    # NORMAL_RADIUS box does not (i - 4 = 23, block 2; j - 4 < 0)
    for c, r in (((16, 16, 12), 3), ((4, 26, 15), 3), ((17, 15, 9), 2), ((27, 3, 15), 0)):
        rem = _remove(grid, _ball(c, r))
        assert len(rem)
        changed.append(rem)
        surf.update(grid, rem)
        lod.sync(surf, rem)
        _check_against_ref(lod, surf, box, np.concatenate(changed))
    assert len(lod.drilled_blocks()) > 0
    # the near box elsewhere, then none: the drilled blocks stay fine
    for b in (_box((0, 0, 0), (0, 0, 0)), None):
        lod.set_box(b)
        _check_against_ref(lod, surf, b, np.concatenate(changed))
    rem = _remove(grid, _ball((8, 8, 15), 2))                 # drilled with no near box
    changed.append(rem)
    surf.update(grid, rem)
    lod.sync(surf, rem)
    _check_against_ref(lod, surf, None, np.concatenate(changed))
    lod.rebuild(surf, box)
    _check_against_ref(lod, surf, box, np.concatenate(changed))
    lod.sync(surf, None)                                       # changes not given
    _check_against_ref(lod, surf, box, np.concatenate(changed))
    # another surface: nothing drilled on it yet
    other = Surface.build(grid, model.colors)
    lod.rebuild(other, box)
    assert len(lod.drilled_blocks()) == 0
    _check_against_ref(lod, other, box)


def test_drilled_blocks_kept_while_off(drilled):
    """Removals while the level of detail is off are still followed: when
    it is on again, their blocks are drawn at full detail."""
    model, state, surf = drilled
    grid = state.grid
    buf = SurfaceBuffers()
    buf.sync(surf)
    box = _box((0, 0, 0), (0, 0, 0))
    buf.set_lod(surf, True, box)
    first = _remove(grid, _ball((24, 8, 15), 2))
    surf.update(grid, first)
    buf.sync(surf, first)
    assert buf.set_lod(surf, False)
    rem = _remove(grid, _ball((24, 24, 15), 3))
    surf.update(grid, rem)
    buf.sync(surf, rem)
    assert buf.set_lod(surf, True, box)
    _check_against_ref(buf.lod, surf, box, np.concatenate([first, rem]))
    assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, buf.lod)


def test_drawn_lists_are_near_triangles_and_far_representatives(drilled):
    model, state, surf = drilled
    buf = SurfaceBuffers()
    buf.sync(surf)
    box = _box((1, 1, 1), (2, 2, 2))
    assert buf.set_lod(surf, True, box)
    assert not buf.set_lod(surf, True, box)                    # unchanged: nothing to do
    lod = buf.lod
    assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, lod)
    assert buf.n_full < 0.8 * surf.n_triangles                 # fewer triangles
    job = buf.start_visible(surf, EYE, DOWN, False, tag="cam")
    assert job.wait(30) and buf.adopt(job, surf)
    far_vis = _far_triples(buf, surf, buf.vis[:3 * buf.n_vis])
    want = [t for t in _ref_drawn(surf, lod, EYE) if any(lod.far[v] for v in t)]
    assert far_vis == want
    # near triangles: the visible subset's rule (facing in the snapshot)
    near_vis = [t for t in _drawn(buf.vis[:3 * buf.n_vis]) if t not in set(far_vis)]
    near_facing = {tuple(sorted(int(x) for x in surf.tri[t])) for t in np.flatnonzero(job.tvis)}
    assert set(near_vis) <= near_facing
    # off again: the full-detail lists
    assert buf.set_lod(surf, False)
    assert buf.n_full == surf.n_triangles


def _edge_counts(flat):
    t = np.asarray(flat).reshape(-1, 3)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    e.sort(axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return counts


@pytest.mark.parametrize("box", [None, ((1, 1, 1), (2, 2, 2))])
def test_coarse_mesh_stays_closed(drilled, box):
    """No cracks: every edge of the drawn full list is used an even number
    of times, as in the full-detail surface (the drilled block is closed)."""
    model, state, surf = drilled
    buf = SurfaceBuffers()
    buf.sync(surf)
    assert np.all(_edge_counts(buf.full[:3 * buf.n_full]) % 2 == 0)
    buf.set_lod(surf, True, None if box is None else _box(*box))
    counts = _edge_counts(buf.full[:3 * buf.n_full])
    assert len(counts) and np.all(counts % 2 == 0)
    # and after drilling across the seam between near and far, and far
    # from the burr (drilled blocks next to far ones)
    for c, r in (((16, 17, 12), 4), ((26, 25, 15), 3), ((4, 14, 15), 2)):
        rem = _remove(state.grid, _ball(c, r))
        assert len(rem)
        surf.update(state.grid, rem)
        buf.sync(surf, rem)
        counts = _edge_counts(buf.full[:3 * buf.n_full])
        assert np.all(counts % 2 == 0)
    assert buf.lod.far[surf.vertex_slots].any()               # still some far


def test_what_the_burr_opens_is_drawn_at_full_detail(drilled):
    model, state, surf = drilled
    grid = state.grid
    buf = SurfaceBuffers()
    buf.sync(surf)
    job = buf.start_visible(surf, EYE, DOWN, False, tag="cam")
    assert job.wait(30) and buf.adopt(job, surf)
    centre = np.array([16, 16, 11])
    lo = (centre - 6) >> BLOCK_SHIFT
    hi = (centre + 6) >> BLOCK_SHIFT
    buf.set_lod(surf, True, (lo, hi))
    before = {tuple(sorted(int(x) for x in surf.tri[t])) for t in surf.triangle_slots}
    rem = _remove(grid, _ball(centre, 2))
    assert len(rem)
    surf.update(grid, rem)
    buf.sync(surf, rem)
    new = {tuple(sorted(int(x) for x in surf.tri[t])) for t in surf.triangle_slots} - before
    assert new
    assert new <= set(_drawn(buf.vis[:3 * buf.n_vis]))         # every one, as it is
    assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, buf.lod)


def test_drilled_rim_stays_at_full_detail_after_the_burr_moves_away(drilled):
    """The burr cuts a pit, then moves far away: every triangle with a
    corner within the blocks the cut reached is drawn as it is (none is
    mapped to a representative), as the surgeon sees the cavity's rim."""
    model, state, surf = drilled
    grid = state.grid
    buf = SurfaceBuffers()
    buf.sync(surf)
    job = buf.start_visible(surf, EYE, DOWN, False, tag="cam")
    assert job.wait(30) and buf.adopt(job, surf)
    centre = np.array([24, 24, 14])
    buf.set_lod(surf, True, ((centre - 6) >> BLOCK_SHIFT, (centre + 6) >> BLOCK_SHIFT))
    rem = _remove(grid, _ball(centre, 3))
    assert len(rem)
    surf.update(grid, rem)
    buf.sync(surf, rem)
    assert buf.set_lod(surf, True, _box((0, 0, 0), (0, 0, 0)))   # the burr moved on
    # the vertices within NORMAL_RADIUS + 1 voxels of the cut (whose
    # positions and normals it changed) lie in drilled blocks
    reach = NORMAL_RADIUS + 1
    live = surf.alive != 0
    d = np.abs(surf.ijk[:, None, :].astype(int) - rem[None, :, :].astype(int)).max(axis=2)
    touched = live & (d.min(axis=1) <= reach)
    assert touched.sum() > 50
    assert not buf.lod.far[touched].any()
    blk = [tuple(int(x) for x in b) for b in surf.ijk >> BLOCK_SHIFT]
    inside = np.array([bool(live[v]) and _ref_drilled(blk[v], rem) for v in range(len(blk))])
    assert not buf.lod.far[inside].any()
    assert buf.lod.far[surf.vertex_slots].any()               # the rest is reduced
    rim = {tuple(sorted(int(x) for x in surf.tri[t])) for t in surf.triangle_slots
           if inside[surf.tri[t]].all()}
    assert any(touched[list(t)].all() for t in rim)
    drawn = set(_drawn(buf.full[:3 * buf.n_full]))
    assert rim <= drawn                                        # every one, as it is
    job = buf.start_visible(surf, EYE, DOWN, False, tag="cam2")     # a snapshot as of now
    assert job.wait(30) and buf.adopt(job, surf)
    vis = set(_drawn(buf.vis[:3 * buf.n_vis]))
    facing = {tuple(sorted(int(x) for x in surf.tri[t])) for t in np.flatnonzero(job.tvis)}
    assert rim & facing and (rim & facing) <= vis
    assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, buf.lod)


def test_far_changes_are_drawn_too(drilled):
    """Voxels removed away from the burr (far) change the far lists at once."""
    model, state, surf = drilled
    grid = state.grid
    buf = SurfaceBuffers()
    buf.sync(surf)
    buf.set_lod(surf, True, _box((0, 0, 0), (0, 0, 0)))
    rem = _remove(grid, _ball((24, 24, 15), 3))
    surf.update(grid, rem)
    buf.sync(surf, rem)
    assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, buf.lod)
    rem = _remove(grid, _ball((24, 24, 12), 2))
    surf.update(grid, rem)
    buf.sync(surf, None)                                        # changes not given
    assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, buf.lod)


MIN_COS = 0.9          # the second level's smoothness (render.toml's)


def _odd_edges(flat):
    """Edges (sorted vertex pairs) used an odd number of times: the cracks."""
    t = np.asarray(flat).reshape(-1, 3)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    e.sort(axis=1)
    u, counts = np.unique(e, axis=0, return_counts=True)
    return {tuple(int(x) for x in p) for p in u[counts % 2 == 1]}


def _no_new_cracks(buf, surf):
    """The drawn full list's cracks are the full-detail surface's, mapped
    by the level of detail's vertex map (some cuts leave the surface itself
    with a few odd edges; the map must add none): none where it has none."""
    lod = buf.lod
    f = np.where(lod.far == 2, lod.rep2, np.where(lod.far == 1, lod.rep, np.arange(
        len(lod.far))))
    want = {}
    for a, b in _odd_edges(surf.tri[surf.triangle_slots]):
        fa, fb = int(f[a]), int(f[b])
        if fa != fb:
            key = (min(fa, fb), max(fa, fb))
            want[key] = want.get(key, 0) ^ 1
    assert _odd_edges(buf.full[:3 * buf.n_full]) == {k for k, v in want.items() if v}


def _vertex_at(surf) -> dict:
    """Voxel ``(i, j, k)`` -> the vertex slot there, for :func:`_coarse_smooth`."""
    return {tuple(int(x) for x in surf.ijk[u]): int(u) for u in surf.vertex_slots}


def _coarse_smooth(surf, v, min_cos, at):
    """Whether the coarse cluster of vertex ``v`` is smooth (plain loops;
    ``at``: :func:`_vertex_at` of ``surf``)."""
    n = 1 << COARSE_SHIFT
    base = (surf.ijk[v].astype(int) >> COARSE_SHIFT) << COARSE_SHIFT
    nrm = np.array([surf.nrm[at[tuple(base + d)]] for d in np.ndindex(n, n, n)
                    if tuple(base + d) in at], np.float64)
    mean = nrm.sum(axis=0)
    mean /= np.linalg.norm(mean)
    return bool(np.all(nrm @ mean >= min_cos - 1e-9))


def test_coarse_representatives_match_the_definition(drilled):
    """Levels 0, 1 and 2 (near box, mid box) and the coarse representatives
    against plain loops; clusters that are not smooth keep the first level's
    representatives; without a smoothness cosine there is no second level."""
    model, state, surf = drilled
    near, mid = _box((1, 1, 1), (1, 1, 1)), _box((0, 0, 0), (2, 2, 2))
    lod = SurfaceLOD(coarse_min_cos=MIN_COS)
    lod.rebuild(surf, near, mid)
    _check_against_ref(lod, surf, near, mid=mid)
    live = surf.vertex_slots
    lv = lod.far[live]
    assert set(np.unique(lv).tolist()) == {0, 1, 2}
    two = live[lv == 2]
    at = _vertex_at(surf)
    smooth = np.array([_coarse_smooth(surf, v, MIN_COS, at) for v in two])
    assert smooth.any() and not smooth.all()               # the block's edges are not
    assert np.all(lod.rep2[two[~smooth]] == lod.rep[two[~smooth]])
    assert np.any(lod.rep2[two[smooth]] != lod.rep[two[smooth]])
    # a coarse representative is a vertex of the same coarse cluster
    assert np.all(surf.ijk[lod.rep2[two]] >> COARSE_SHIFT == surf.ijk[two] >> COARSE_SHIFT)
    plain = SurfaceLOD()
    plain.rebuild(surf, near, mid)
    assert np.array_equal(plain.far[live], np.minimum(lv, 1))
    assert np.array_equal(plain.rep2[live], plain.rep[live])


def test_coarse_level_follows_removals_and_stays_closed(drilled):
    """With the second level: drawn lists against a plain evaluation and
    no cracks (every edge used an even number of times), through removals
    inside the near box, in the second level's region and across the seam
    between the levels, the mid box moving, and the visible subset."""
    model, state, surf = drilled
    grid = state.grid
    near, mid = _box((1, 1, 1), (1, 1, 1)), _box((0, 0, 0), (2, 2, 2))
    buf = SurfaceBuffers(coarse_min_cos=MIN_COS)
    buf.sync(surf)
    assert buf.set_lod(surf, True, near)
    n_first = buf.n_full
    assert buf.set_lod(surf, True, near, mid)
    assert not buf.set_lod(surf, True, near, mid)              # unchanged: nothing to do
    assert buf.n_full < n_first                                # fewer triangles
    _check_against_ref(buf.lod, surf, near, mid=mid)
    assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, buf.lod)
    assert not _odd_edges(buf.full[:3 * buf.n_full])         # closed
    changed = []
    for c, r in (((12, 12, 14), 2), ((28, 28, 15), 2), ((24, 14, 15), 2)):
        rem = _remove(grid, _ball(c, r))
        assert len(rem)
        changed.append(rem)
        surf.update(grid, rem)
        buf.sync(surf, rem)
        _check_against_ref(buf.lod, surf, near, np.concatenate(changed), mid)
        assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, buf.lod)
        _no_new_cracks(buf, surf)
    assert (buf.lod.far[surf.vertex_slots] == 2).any()         # still some at level 2
    mid2 = _box((0, 0, 0), (1, 1, 2))
    assert buf.set_lod(surf, True, near, mid2)
    _check_against_ref(buf.lod, surf, near, np.concatenate(changed), mid2)
    assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, buf.lod)
    _no_new_cracks(buf, surf)
    job = buf.start_visible(surf, EYE, DOWN, False, tag="cam")
    assert job.wait(30) and buf.adopt(job, surf)
    far_vis = _far_triples(buf, surf, buf.vis[:3 * buf.n_vis])
    assert far_vis == [t for t in _ref_drawn(surf, buf.lod, EYE)
                       if any(buf.lod.far[v] for v in t)]
    rem = _remove(grid, _ball((6, 26, 15), 2))                # changes not given
    surf.update(grid, rem)
    buf.sync(surf, None)
    _check_against_ref(buf.lod, surf, near, np.concatenate(changed), mid2)
    assert _drawn(buf.full[:3 * buf.n_full]) == _ref_drawn(surf, buf.lod)


def test_voxel_px():
    # 30 deg, 100 mm away: the view is 53.6 mm high; 768 px
    h = 2 * 100 * np.tan(np.radians(15))
    assert voxel_px(0.19, 100.0, 30.0, 768) == pytest.approx(0.19 * 768 / h)
    assert voxel_px(0.5, 0.0, 30.0, 768, parallel_scale_mm=10.0) == pytest.approx(0.5 * 768 / 20)
    assert voxel_px(0.5, 0.0, 30.0, 768) == float("inf")


def _lod_style(on: bool, coarse_mm: float = 0.0):
    from bonesim.render.style import RenderStyle, default_style

    st = default_style()
    lod = SimpleNamespace(**{**vars(st.lod), "max_voxel_px": 1000.0 if on else 0.0,
                             "min_triangles": 0.0, "near_mm": 1.5, "coarse_mm": coarse_mm,
                             "coarse_max_voxel_px": 1000.0})
    return RenderStyle(**{**vars(st), "lod": lod})


@pytest.mark.parametrize("coarse_mm", [0.0, 4.0])
def test_picture_with_level_of_detail_is_close(gl_info, drilled, coarse_mm):
    """The same drilled block drawn at full detail and with the level of
    detail (burr in one corner; with the second level beyond ``coarse_mm``
    of it, too): the bone covers the same pixels but for a few at its
    outline, and the shading differs little."""
    from bonesim.render.scene import Scene

    model, state, surf = drilled
    images = []
    for on in (False, True):
        sc = Scene(size=(320, 240), panel=False, style=_lod_style(on, coarse_mm))
        sc.update_surface(surf)
        # a voxel covers about 2.5 px, as a native-resolution voxel does
        sc.set_camera((8.0, 2.0, 50.0), (8.0, 7.9, 4.0), up=(0.0, 1.0, 0.0))
        sc.set_tool((3.0, 3.0, 8.0), (0.0, 0.0, -1.0), 1.0)
        for a in (sc._burr, sc._shaft):
            a.SetVisibility(False)
        assert sc.refresh_visible()
        img = sc.image().astype(int)
        assert (sc._buffers.lod is not None) == on
        assert sc.dust.keep_one_in == (int(sc.style.lod.dust_keep_one_in) if on else 1)
        # no coordinate shift-scale scan and no frustum culler with it on
        assert sc._surface_mapper.GetVBOShiftScaleMethod() == (0 if on else 1)
        assert sc.renderer.GetCullers().GetNumberOfItems() == (0 if on else 1)
        if on:
            assert sc._buffers.n_vis < 0.7 * n_vis_full
            levels = sc._buffers.lod.far[surf.vertex_slots]
            assert (levels == 2).any() == (coarse_mm > 0)
        else:
            n_vis_full = sc._buffers.n_vis
        sc.close()
        images.append(img)
    full, lod = images
    if SAVE:
        from PIL import Image

        Image.fromarray(np.concatenate([full, lod], axis=1).astype(np.uint8)).save(SAVE)
    bg = np.array([13, 15, 20])
    bone_full = np.abs(full - bg).max(axis=2) > 6
    bone_lod = np.abs(lod - bg).max(axis=2) > 6
    assert bone_full.sum() > 0.1 * bone_full.size
    # no holes or cracks: inside the outline (5 px in) no background shows;
    # the outline itself moves by a pixel or two (the block's sharp corners
    # are cut by a cluster)
    inside = binary_erosion(bone_full, iterations=5)
    assert inside.sum() > 0.8 * bone_full.sum()
    assert not np.any(inside & ~bone_lod)
    assert (bone_full ^ bone_lod).sum() < 0.03 * bone_full.sum()
    both = bone_full & bone_lod
    diff = np.abs(full - lod).max(axis=2)[both]
    assert diff.mean() < 5.0 and np.mean(diff > 24) < 0.06
