"""Irrigation water (bonesim.physics.dust.water): poured, drains down, pools,
carries the wet dust, is taken by suction; water and dust are accounted
for exactly."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as hs

from bonesim.engine.grid import Grid, density_at
from bonesim.physics.dust.grid import DustGrid, DustParams, Q
from bonesim.physics.dust.water import (water_grid, water_cells, water_sprites,
                                        water_totals_q)

N = 24
H = 0.5
FLOOR = 4          # bone below z = FLOOR


def _bone(ledge=False, seed=None):
    lab = np.zeros((N, N, N), np.uint8)
    lab[:, :, :FLOOR] = 1
    if ledge:                       # a raised step for x < 8
        lab[:8, :, :10] = 1
    if seed is not None:            # random pillars
        rng = np.random.default_rng(seed)
        for _ in range(6):
            i, j = rng.integers(2, N - 3, 2)
            lab[i:i + 2, j:j + 2, :rng.integers(FLOOR, N - 4)] = 1
    return Grid.from_dense(lab, spacing_mm=H)


def _mm(ijk):
    return np.asarray(ijk, float) * H


def _check(d):
    tot, add, suck = d.totals_q()
    assert tot == add - suck
    assert d.recount_q() == tot
    wt, wa, ws = water_totals_q(d)
    assert wt == wa - ws
    if d.water is not None:
        assert int(d.water.recount_q()) == wt
        assert (d.water.to_dense() >= 0).all()
    for sp in ("dry", "wet"):
        assert (d.to_dense(species=sp) >= 0).all()


cell = hs.tuples(hs.integers(0, N - 1), hs.integers(0, N - 1), hs.integers(0, N - 1))
maybe_cell = hs.none() | cell
step_args = hs.tuples(maybe_cell, maybe_cell, maybe_cell, hs.floats(1e-3, 0.05))


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=hs.integers(0, 2 ** 31), dust=hs.lists(cell, min_size=1, max_size=60),
       water=hs.lists(hs.tuples(cell, hs.floats(0.0, 1.0)), max_size=60),
       steps=hs.lists(step_args, min_size=1, max_size=25),
       gravity=hs.sampled_from([(0, 0, -1), (1, 0, -0.2), (0.3, -1, 0.1)]))
def test_water_and_dust_are_conserved_exactly(seed, dust, water, steps, gravity):
    """From any dust and water, whatever is poured, pushed, soaked and
    carried: ``total == added - suctioned`` for the dust and for the water,
    as integers, after every step; no amount negative."""
    g = _bone(seed=seed % 1000)
    d = DustGrid.for_grid(g, gravity)
    d.add_removed(np.array(dust))
    if water:                       # water standing anywhere (bone cells excepted)
        ijk = np.array([c for c, _ in water], np.int64)
        amt = np.array([int(a * Q) for _, a in water], np.int64)
        free = np.array([density_at(g.keys, g.vals, g.density, *c) == 0 for c in ijk])
        if free.any():
            water_grid(d)._add_q(ijk[free], amt[free])
    for irr, suc, tool, dt in steps:
        d.step(g, dt, irrigation_pos_mm=None if irr is None else _mm(irr),
               irrigation_radius_mm=1.0,
               suction_pos_mm=None if suc is None else _mm(suc), suction_radius_mm=1.5,
               tool_pos_mm=None if tool is None else _mm(tool), tool_radius_mm=1.0)
        _check(d)


def test_poured_water_drains_down_and_pools_flat():
    g = _bone()
    d = DustGrid.for_grid(g, (0, 0, -1))
    top = (12, 12, 20)
    for _ in range(240):
        d.step(g, 1 / 60, irrigation_pos_mm=_mm(top), irrigation_radius_mm=0.5)
    for _ in range(600):                          # the tap closed: it settles
        d.step(g, 1 / 60)
    _check(d)
    w = d.water.to_dense()
    assert water_cells(d) > 10
    by_z = w.sum((0, 1))
    # all of it on the floor, spread flat: one layer, nearly level
    assert by_z[FLOOR] == pytest.approx(w.sum()) and by_z[FLOOR + 1:].sum() == 0
    layer = w[:, :, FLOOR]
    wet = layer[layer > 0]
    assert wet.size > 0.9 * N * N and wet.max() - wet.min() < 0.05
    # the pool shows as sprites on the floor
    s = water_sprites(d)
    assert len(s.positions) > 0.9 * N * N
    np.testing.assert_allclose(s.positions[:, 2], FLOOR * H, atol=1e-6)


def test_water_drains_along_any_gravity():
    g = Grid.from_dense(np.zeros((N, N, N), np.uint8), spacing_mm=H)
    d = DustGrid.for_grid(g, (1.0, 0.0, 0.0))          # "down" is +x
    for _ in range(120):
        d.step(g, 1 / 60, irrigation_pos_mm=_mm((3, 12, 12)))
    for _ in range(300):
        d.step(g, 1 / 60)
    w = d.water.to_dense()
    assert w[N - 1].sum() == pytest.approx(w.sum())   # against the +x face


def _wet_dust_params(**kw):
    # wet dust that does not move by itself: only the water moves it
    return DustParams(wet_settle_rate=0.0, wet_spill_rate=0.0, **kw)


def test_the_water_carries_the_wet_dust_off_a_ledge():
    """Wet dust on a ledge stays there without water (its own motion is off
    here) and is carried down to the floor by the water poured on it; the
    dust carried is conserved."""
    g = _bone(ledge=True)
    ends = []
    for pour in (False, True):
        d = DustGrid.for_grid(g, (0, 0, -1), _wet_dust_params(water_flow_mm3_s=60.0))
        ijk = np.array([(x, y, 10) for x in range(2, 7) for y in range(8, 16)], np.int64)
        d._wet_grid()._add_q(ijk, np.full(len(ijk), int(0.8 * Q), np.int64))
        total = d.totals_q()[0]
        for _ in range(600):
            d.step(g, 1 / 60, irrigation_pos_mm=_mm((2, 12, 14)) if pour else None)
        wet = d.to_dense(species="wet")
        assert d.totals_q()[0] == total == d.recount_q()
        ends.append(wet[8:, :, :10].sum() / wet.sum())  # off the ledge, on the floor
    wt, wa, ws = water_totals_q(d)
    assert wt == wa - ws and wt > 0
    assert ends[0] == 0.0
    assert ends[1] > 0.3


def test_suction_takes_water_and_dust():
    g = _bone()
    d = DustGrid.for_grid(g, (0, 0, -1))
    d.add_removed(np.array([(x, y, FLOOR + 2) for x in range(8, 16) for y in range(8, 16)]))
    for _ in range(200):
        d.step(g, 1 / 60, irrigation_pos_mm=_mm((12, 12, 12)), irrigation_radius_mm=3.0)
    w0, d0 = water_totals_q(d)[0], d.totals_q()[0]
    assert w0 > 0 and d.wet_cells > 0
    for _ in range(300):
        d.step(g, 1 / 60, suction_pos_mm=_mm((12, 12, FLOOR)), suction_radius_mm=2.0)
        _check(d)
    w1, _, wsuck = water_totals_q(d)
    d1, _, dsuck = d.totals_q()
    assert w1 < 0.5 * w0 and wsuck > 0
    assert d1 < d0 and dsuck > 0
