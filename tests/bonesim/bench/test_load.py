"""The label-stack load benchmark (bonesim.bench.load): its case and its figures."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.bench import load as B
from bonesim.io.case import load_case
from bonesim.io.phantom import phantom_volume


def test_bench_stack_case_is_the_phantom_reoriented(tmp_path):
    B.write_stack_case(tmp_path, (40, 44, 48), "PIR")
    case = load_case(tmp_path)
    assert case.orientation == ("PIR", "declared")
    vol = case.load_volume()
    native = vol.native_labels
    # P I R: columns run posterior (y), rows inferior (-z), slices right (-x)
    assert native.labels.shape == (48, 40, 44)
    ref = phantom_volume(voxel_mm=0.5)
    np.testing.assert_allclose(native.spacing_mm * native.labels.shape, ref.extent_mm)
    # the upsampled anatomy comes back on the 0.5 mm grid close to the phantom:
    # the same structures, bone within a few percent
    counts, want = vol.counts(8), ref.counts(8)
    assert (counts[1:] > 0).all()
    assert abs(counts[1] - want[1]) / want[1] < 0.05


def test_bench_load_figures_registered():
    from bonesim.bench.suite import BENCHMARKS

    out = BENCHMARKS["load_labelstack_512_s"](quick=True)
    t, mem = out["load_labelstack_512_s"], out["load_labelstack_512_peak_mb"]
    assert t["value"] > 0 and t["unit"] == "s" and t["reference_s"] > 0
    assert t["ratio_load_over_decode"] == pytest.approx(t["value"] / t["reference_s"],
                                                        rel=0.1)   # figures rounded
    assert t["stack"] == list(B.QUICK_SHAPE) and t["grid"] == [104, 104, 104]
    assert mem["unit"] == "MB" and mem["value"] >= mem["before_load_mb"] > 0
    assert BENCHMARKS["load_labelstack_512_peak_mb"] is BENCHMARKS["load_labelstack_512_s"]


def test_native_stack_case_loads_on_its_own_grid(tmp_path):
    manifest = B.write_stack_case(tmp_path, (24, 26, 28), "PIR", voxel_mm="native",
                                  camera=True)
    case = load_case(manifest)
    assert case.volume.voxel_mm == "native" and case.declared_camera is not None
    vol = case.load_volume()
    # PIR: x from the 28 slices, y from 24 columns, z from 26 rows; the finest
    # axis (x, 52 / 28 mm) is the engine's voxel, the others resampled to it
    assert vol.spacing_mm == pytest.approx(52.0 / 28) and vol.shape == (28, 28, 28)
    assert vol.native.labels.shape == (28, 24, 26)
    cube = B.write_stack_case(tmp_path / "cube", (24, 24, 24), "PIR", voxel_mm="native")
    vol = load_case(cube).load_volume()
    assert vol.native is None and vol.shape == (24, 24, 24)      # one label array


def test_bench_load_native_figures_registered():
    from bonesim.bench.suite import BENCHMARKS

    names = ("load_native_256_s", "load_native_256_peak_mb", "load_native_512_s",
             "load_native_512_peak_mb")
    assert len({BENCHMARKS[n] for n in names}) == 1
    out = BENCHMARKS["load_native_256_s"](quick=True)
    assert set(out) == set(names)
    for key, n in B.QUICK_NATIVE_SIZES.items():
        t, mem = out[f"load_native_{key}_s"], out[f"load_native_{key}_peak_mb"]
        assert t["unit"] == "s" and t["value"] > 0 and t["grid"] == [n, n, n]
        assert t["one_label_array"] and t["voxel_mm"] == pytest.approx(52.0 / n, abs=1e-5)
        assert set(t["parts"]) == {"read", "model", "clearance"}
        assert sum(p["s"] for p in t["parts"].values()) <= t["value"] + 0.01
        assert mem["unit"] == "MB" and mem["value"] >= mem["before_load_mb"] > 0
        assert mem["value"] == max(p["peak_mb"] for p in mem["parts"].values())
