"""surface_roughness_deg: the helpers against plain loops, and the figure
on the drilled floor (rendered and drawn surfaces smoother than the voxels)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bonesim.bench import surface_quality as SQ


def _ref_edges(tris):
    out = set()
    for tri in np.asarray(tris).tolist():
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            out.add((min(a, b), max(a, b)))
    return sorted(out)


def _ref_normals(pos, tris, n):
    acc = [[0.0, 0.0, 0.0] for _ in range(n)]
    for a, b, c in np.asarray(tris).tolist():
        u = [pos[b][k] - pos[a][k] for k in range(3)]
        w = [pos[c][k] - pos[a][k] for k in range(3)]
        f = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]]
        for v in (a, b, c):
            for k in range(3):
                acc[v][k] += f[k]
    out = []
    for x in acc:
        m = math.sqrt(sum(c * c for c in x))
        out.append([c / m for c in x] if m > 0 else [0.0, 0.0, 0.0])
    return np.array(out)


def _ref_mean_angle(nrm, edges):
    total = 0.0
    for a, b in edges:
        na = np.asarray(nrm[a], float) / np.linalg.norm(nrm[a])
        nb = np.asarray(nrm[b], float) / np.linalg.norm(nrm[b])
        total += math.degrees(math.acos(max(-1.0, min(1.0, float(na @ nb)))))
    return total / len(edges)


def test_helpers_match_plain_loops():
    rng = np.random.default_rng(4)
    pos = rng.normal(size=(30, 3))
    tris = np.array([rng.choice(30, 3, replace=False) for _ in range(50)])
    e = SQ.edges_of(tris)
    assert [tuple(x) for x in e.tolist()] == _ref_edges(tris)
    n = SQ.mesh_normals(pos, tris, 32)                   # two vertices without triangles
    np.testing.assert_allclose(n, _ref_normals(pos, tris, 32), atol=1e-12)
    assert (n[30:] == 0).all()
    nrm = rng.normal(size=(30, 3))
    assert SQ.mean_edge_angle_deg(nrm, e) == pytest.approx(_ref_mean_angle(nrm, e), abs=1e-9)
    assert math.isnan(SQ.mean_edge_angle_deg(nrm, e[:0]))


def test_a_plane_is_smooth_for_all_three():
    """An undrilled block's top face: every figure is zero."""
    from bonesim.engine.grid import Grid
    from bonesim.engine.surface import Surface

    lab = np.zeros(SQ.BLOCK_VOXELS, np.uint8)
    lab[:, :, :SQ.TOP_VOXELS - 3] = 1                   # top face below the "top": on the floor
    grid = Grid.from_dense(lab, spacing_mm=SQ.VOXEL_MM)
    surf = Surface.build(grid, np.array([[0, 0, 0], [235, 225, 200]], np.uint8))
    r = SQ.surface_roughness(surf, grid)
    assert r["floor_vertices"] > 1000 and r["floor_edges"] > 2000
    for k in ("render_deg", "voxel_deg", "render_geometry_deg"):
        assert r[k] == pytest.approx(0.0, abs=1e-3), k


def test_drilled_floor_figures():
    out = SQ.bench_surface_roughness(quick=True)["surface_roughness_deg"]
    assert out["unit"] == "deg" and out["floor_vertices"] > 1000
    # the voxels' staircase across a tilted floor is rough; what is drawn is not
    assert out["voxel_surface_deg"] > 1.0
    assert out["value"] < 0.5 * out["voxel_surface_deg"]
    assert out["render_geometry_deg"] < 0.5 * out["voxel_surface_deg"]


def test_registered_in_the_suite():
    from bonesim.bench.suite import BENCHMARKS

    assert "surface_roughness_deg" in BENCHMARKS
