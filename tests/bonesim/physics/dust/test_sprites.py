"""The sprites of the dust (bonesim.physics.dust.sprites): the one-pass
gather against plain loops over its definition (which cells, where, how
much, how old, which species), over several calls as the dust moves, and
its count against :meth:`DustGrid.note_arrivals`."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine.grid import Grid
from bonesim.physics.dust.grid import Q, DustGrid, DustParams
from bonesim.physics.dust.sprites import cell_jitter

H = 0.5                                 # cell edge [mm]
ORIGIN = np.array([-3.0, 1.5, 2.0])     # [mm]


def _case(seed):
    """A floor of bone, dry dust scattered over it in heaps, some of it
    wetted by an irrigation tip (both species)."""
    lab = np.zeros((26, 22, 30), np.uint8)
    lab[:, :, :4] = 1
    bone = Grid.from_dense(lab, spacing_mm=H, origin_mm=ORIGIN)
    dust = DustGrid.for_grid(bone, (0.0, 0.2, -1.0), DustParams(wetting_rate=50.0))
    rng = np.random.default_rng(seed)
    ijk = np.concatenate([rng.integers((2, 2, 4), (24, 20, 12), size=(400, 3)),
                          rng.integers((14, 10, 4), (22, 18, 8), size=(300, 3))])
    dust.add_removed(ijk, rng.uniform(0.1, 1.2, len(ijk)))
    return bone, dust


def _ref_sprites(dust, now, arrivals):
    """Plain loops: for each species (dry 0, wet 1), the cells over the
    threshold whose cell above (against gravity's dominant axis) holds less
    than the cover; at the cell centre plus the jitter; the age since the
    cell was last seen at or below the threshold, or its brick without dust
    (``arrivals``: species -> dense arrival times and the bricks holding
    dust, updated here as the call being checked does)."""
    p = dust.params
    thr, cover = np.floor(p.sprite_threshold * Q) / Q, np.floor(p.sprite_cover * Q) / Q
    g = np.asarray(dust.gravity, float)
    dom = int(np.argmax(np.abs(g)))
    up = -1 if g[dom] > 0 else 1
    rows = []
    for salt, name in enumerate(("dry", "wet")):
        d = np.round(dust.to_dense(species=name) * Q) / Q
        seen = arrivals.setdefault(name, np.full(d.shape, now))
        # a brick (8^3 cells) that held no dust at the previous call: every
        # cell of it has just arrived
        bricks = {tuple(int(x) for x in c) for c in np.argwhere(d > 0) >> 3}
        for bi, bj, bk in bricks - arrivals.get(name + " bricks", set()):
            seen[8 * bi:8 * bi + 8, 8 * bj:8 * bj + 8, 8 * bk:8 * bk + 8] = now
        arrivals[name + " bricks"] = bricks
        seen[d <= thr] = now
        for ijk in np.argwhere(d > thr):
            a = ijk.copy()
            a[dom] += up
            above = d[tuple(a)] if np.all(a >= 0) and np.all(a < d.shape) else 0.0
            if above >= cover:
                continue
            pos = ORIGIN + H * ijk + p.sprite_jitter * H * cell_jitter(ijk[None], salt)[0]
            rows.append((salt, *ijk, *pos, d[tuple(ijk)], now - seen[tuple(ijk)]))
    return sorted(rows)


@pytest.mark.parametrize("seed", [0, 1])
def test_sprites_match_plain_loops(seed):
    bone, dust = _case(seed)
    arrivals = {}
    tip = ORIGIN + H * np.array([18.0, 14.0, 5.0])
    for call in range(4):
        if call:
            for _ in range(3):
                dust.step(bone, 0.02, irrigation_pos_mm=tip, irrigation_radius_mm=2.0)
        want = _ref_sprites(dust, dust.time_s, arrivals)
        count = dust.note_arrivals() if call == 3 else None
        pos, val, cell_mm, age, wet = dust.sprites()
        assert cell_mm == H and pos.dtype == np.float32 and wet.dtype == np.uint8
        cells = np.round((pos - ORIGIN) / H).astype(int)
        got = sorted((int(w), *map(int, c), *map(float, p), float(v), float(a))
                     for w, c, p, v, a in zip(wet, cells, pos, val, age))
        assert len(got) == len(want) > 50
        assert {r[0] for r in got} == ({0, 1} if call else {0})   # wetted by the tip
        g, w = np.array(got), np.array(want)
        np.testing.assert_array_equal(g[:, :4], w[:, :4])       # species, cell
        np.testing.assert_allclose(g[:, 4:7], w[:, 4:7], atol=1e-5)
        np.testing.assert_allclose(g[:, 7], w[:, 7], rtol=1e-6)
        np.testing.assert_allclose(g[:, 8], w[:, 8], atol=1e-6)
        if count is not None:
            assert count == len(got)
