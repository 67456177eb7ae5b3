"""The flying-edges comparison (bonesim.bench.native_surface) runs and
reports both figures (values not asserted: shared machines are noisy)."""
from __future__ import annotations

import pytest

from bonesim.bench.suite import BENCHMARKS


@pytest.mark.slow
def test_flying_edges_figures_are_registered_and_reported():
    names = {"tessellate_ct512_vs_flying_edges", "flying_edges_ct512_s"}
    assert names <= set(BENCHMARKS)
    out = BENCHMARKS["tessellate_ct512_vs_flying_edges"](quick=True)
    assert set(out) == names
    r, fe = out["tessellate_ct512_vs_flying_edges"], out["flying_edges_ct512_s"]
    assert r["unit"] == "x" and r["reps"] == 2 and r["shape"] == [512, 512, 300]
    assert r["value"] == pytest.approx(r["ours_s"] / r["flying_edges_s"], rel=0.01)
    assert fe["value"] == r["flying_edges_s"] and fe["sequential_s"] > 0
    # both contour the same shell: about as many points as our surface has vertices
    assert fe["points"] == pytest.approx(r["vertices"], rel=0.05)


def test_flying_edges_contours_a_cube():
    import numpy as np

    from bonesim.render.bench_surface import flying_edges

    lab = np.zeros((12, 10, 8), np.uint8)
    lab[2:9, 3:7, 2:6] = 1
    t, n_pts, n_tri = flying_edges(lab, 0.5, 0.5, "Sequential")
    assert t >= 0 and n_pts > 0
    # a closed surface of genus 0: V - E + F = 2 with E = 3 F / 2
    assert n_pts - n_tri // 2 == 2
