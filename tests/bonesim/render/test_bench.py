"""bench_render returns both figures in the bench format (values not asserted)."""
from __future__ import annotations

import pytest


@pytest.mark.slow
def test_bench_render_quick(gl_info):
    from bonesim.render.bench import bench_render

    out = bench_render(quick=True)
    assert set(out) == {"render_update_1000_ms", "first_frame_s"}
    upd, ff = out["render_update_1000_ms"], out["first_frame_s"]
    assert upd["unit"] == "ms" and upd["value"] > 0 and upd["blobs"] == 8
    assert upd["subset_by_marks"] is True
    assert 600 < upd["voxels_per_blob_mean"] < 2000
    assert ff["unit"] == "s" and ff["value"] > 0 and ff["render_s"] > 0


@pytest.mark.slow
def test_bench_fps_quick(gl_info):
    from bonesim.bench.suite import BENCHMARKS

    out = BENCHMARKS["render_fps_1024x768"](quick=True)
    fps = out["render_fps_1024x768"]
    assert fps["unit"] == "Hz" and fps["value"] > 0 and fps["frames"] >= 1
    assert fps["size"] == [1024, 768] and fps["drawn"] == "visible"
    assert fps["lod"] is False                     # 0.5 mm: full detail
    assert fps["order_independent_blending"] is True
    assert fps["dust_sprites"] > 100 and fps["removed_voxels"] > 1000


@pytest.mark.slow
def test_bench_native_quick(gl_info, tmp_path):
    from bonesim.bench.suite import BENCHMARKS

    out = BENCHMARKS["render_fps_native_019"].resolve()(quick=True,
                                                       screenshot=tmp_path / "native.png")
    assert set(out) == {"render_update_native_019_ms", "render_fps_native_019"}
    upd, fps = out["render_update_native_019_ms"], out["render_fps_native_019"]
    assert upd["voxel_mm"] == fps["voxel_mm"] == 0.19
    assert upd["unit"] == "ms" and upd["value"] >= upd["p50_ms"] > 0
    assert fps["unit"] == "Hz" and fps["value"] > 0 and fps["drilling"] is True
    assert fps["cut_voxels_per_frame"] > 0 and fps["size"] == [1024, 768]
    assert fps["lod"] is True and fps["drawn_triangles"] < 0.3 * fps["triangles"]
    assert fps["order_independent_blending"] is False    # in draw order: the frame budget
    assert (tmp_path / "native.png").stat().st_size > 10_000
