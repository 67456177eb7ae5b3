"""The device-overhead benchmark runs over every backend's stand-in and
reports one figure per backend (figures are not asserted)."""
from __future__ import annotations

from bonesim.bench import devices
from bonesim.bench.suite import BENCHMARKS


def test_one_figure_per_backend_registered_and_reported(monkeypatch):
    monkeypatch.setattr(devices, "QUICK_STEPS", 200)
    out = devices.bench_devices(quick=True)
    names = [f"device_overhead_us_{b}" for b in devices.BACKENDS]
    assert sorted(out) == sorted(names)
    assert all(n in BENCHMARKS for n in names)
    for v in out.values():
        assert v["unit"] == "us" and v["steps"] == 200 and v["value"] > 0
        assert v["p99_us"] >= v["value"]
