"""The stalls bench's pieces: the time-weighted percentile and its case (the
cube is a 512,000-voxel part apart from the slab)."""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from bonesim.bench.stalls import CUBE_EDGE, stall_case, time_weighted_percentile
from bonesim.io.burrs import load_burr


def test_time_weighted_percentile_counts_a_stall_by_its_length():
    p = np.ones(1000)
    assert time_weighted_percentile(p, 99) == 1.0
    p[500] = 150.0                        # one period in 1,000, 13 % of the time
    assert np.percentile(p, 99) == 1.0
    assert time_weighted_percentile(p, 99) == 150.0
    assert time_weighted_percentile(p, 50) == 1.0
    q = np.r_[np.ones(995), np.full(5, 1.5)]     # 0.75 % of the time in 1.5 ms periods
    assert time_weighted_percentile(q, 99) == 1.0


def test_the_case_holds_a_512k_voxel_part_apart_from_the_keeper():
    model = stall_case(load_burr("cutting-5mm"))
    dens, _ = model.grid.to_dense()
    lab, n = ndimage.label(dens > 0, np.ones((3, 3, 3), bool))
    sizes = np.bincount(lab.ravel())[1:]
    assert n == 2 and CUBE_EDGE ** 3 == 512_000 and 512_000 in sizes.tolist()
