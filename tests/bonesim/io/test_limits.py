"""Physical bounds and memory checks (bonesim/io/limits.py, bonesim/data/limits.toml),
and hostile sizes refused before anything is allocated (issue 24, row 5): a 200 mm
burr, voxel_mm = 0.01, a phantom of 5200 mm, a trajectory ending at t = 1e12 s,
1e300 mm positions and 1e300 rpm; the last under an address-space cap."""
from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.io import limits

ROOT = Path(__file__).resolve().parents[3]
PHANTOM = (ROOT / "ct_cases" / "phantom" / "case.toml").read_text()
HEAD = "t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,drill,speed_rpm\n"


def test_every_bound_has_min_max_unit_and_why():
    from bonesim.tomlfile import read_toml

    doc = read_toml(limits.data_path(limits.LIMITS_FILE))
    names = [k for k in doc if k not in ("memory", "reading", "network")]
    assert {"burr_diameter_mm", "voxel_mm", "case_extent_mm", "grid_voxels",
            "trajectory_duration_s", "trajectory_rows", "coordinate_mm", "speed_rpm",
            "window_px", "frames", "rate_hz"} <= set(names)
    for name in names:
        b = limits.bound(name)
        assert b.min <= b.max and b.unit and len(b.why) > 10, name
    assert limits.setting("memory", "engine_bytes_per_voxel") > 0


@pytest.mark.parametrize("value, needle", [
    (200.0, r"x.toml \[burr\]: diameter 200 mm is outside the physical bounds 0.1 .. 12 mm"),
    (math.nan, "must be a finite number"), (math.inf, "must be a finite number"),
    ("wide", "must be a number"), (0.0, "outside the physical bounds")])
def test_check_refuses_in_one_line_naming_file_field_and_bounds(value, needle):
    with pytest.raises(BonesimError, match=needle) as err:
        limits.check("burr_diameter_mm", value, "x.toml", "burr", what="diameter")
    assert "\n" not in str(err.value)
    assert limits.check("burr_diameter_mm", 2.0) == 2.0


def test_memory_beyond_what_is_available_is_refused_with_the_estimate():
    free = limits.available_memory()
    assert free is not None and free > 0
    with pytest.raises(BonesimError, match=r"needs about 4 TiB of memory; .* are available"):
        limits.check_memory(4 * 2 ** 40, "this", "a.toml")
    limits.check_memory(1024, "a little")
    assert limits.format_bytes(7.11 * 2 ** 50) == "7.11 PiB"


def test_a_grid_is_checked_before_it_is_allocated():
    assert limits.check_grid((52, 52, 52), 0.5) == 104 ** 3
    with pytest.raises(BonesimError, match=r"5200 x 5200 x 5200 grid .* outside"):
        limits.check_grid((52, 52, 52), 0.01, "case.toml", "volume")
    with pytest.raises(BonesimError, match="'s extent 5200 mm is outside"):
        limits.check_grid((5200, 52, 52), 1.0)


def _case(tmp_path, old, new) -> Path:
    p = tmp_path / "c" / "case.toml"
    p.parent.mkdir(exist_ok=True)
    p.write_text(PHANTOM.replace(old, new))
    return p


@pytest.mark.parametrize("old, new, needle", [
    ("voxel_mm = 0.5", "voxel_mm = 0.01", "5200 x 5200 x 5200 grid"),
    ("size_mm = [52.0, 52.0, 52.0]", "size_mm = [5200.0, 52.0, 52.0]", "'size_mm' 5200 mm"),
    ("voxel_mm = 0.5", "voxel_mm = nan", "'voxel_mm' must be a number"),
    ("box_mm = [[7.0", "box_mm = [[nan", "'box_mm' must be"),
])
def test_hostile_case_sizes_are_refused_before_loading(tmp_path, old, new, needle):
    from bonesim.io.case import load_case

    with pytest.raises(BonesimError, match=needle) as err:
        load_case(_case(tmp_path, old, new)).load_volume()     # refused before allocating
    assert "case.toml" in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("row, needle", [
    ("1e12,0,0,0,0,0,-1,1,60000", r"duration .* 1e\+12 s is outside"),
    ("0.01,1e300,0,0,0,0,-1,1,60000", r"line 3, column 'x_mm'.*outside"),
    ("0.01,0,0,0,0,0,-1,1,1e300", r"line 3, column 'speed_rpm'.*outside"),
])
def test_hostile_trajectories_are_refused_naming_line_and_column(tmp_path, row, needle):
    from bonesim.io.trajectory import read_trajectory

    p = tmp_path / "t.csv"
    p.write_text(HEAD + "0,0,0,0,0,0,-1,1,60000\n" + row + "\n")
    with pytest.raises(BonesimError, match=needle) as err:
        read_trajectory(p)
    assert "t.csv" in str(err.value)


def test_resampling_beyond_the_memory_is_refused_with_the_estimate():
    from bonesim.io.trajectory import Trajectory

    tr = Trajectory([0.0, 40000.0], [[0, 0, 0]] * 2, [[0, 0, 1]] * 2, [1, 1], [6e4, 6e4])
    with pytest.raises(BonesimError, match=r"resampling .* needs about .* of memory"):
        tr.resample(1e9)


def test_trajectories_are_read_in_chunks_with_progress(tmp_path, monkeypatch):
    from bonesim.io import trajectory as T

    rng = np.random.default_rng(1)
    n = 1000
    rows = "".join(f"{i * 0.001:.3f},{x:.4f},0,0,0,0,-1,1,60000\n"
                   for i, x in enumerate(rng.uniform(-30, 30, n)))
    p = tmp_path / "t.csv"
    p.write_text(HEAD + rows)
    whole = T.read_trajectory(p)
    real = limits.setting
    monkeypatch.setattr(T, "setting", lambda t, k: 64 if k == "trajectory_chunk_rows"
                        else real(t, k))
    seen = []
    chunked = T.read_trajectory(p, progress=lambda done, total: seen.append((done, total)))
    np.testing.assert_array_equal(chunked.t_s, whole.t_s)
    np.testing.assert_array_equal(chunked.pos_mm, whole.pos_mm)
    assert len(seen) == math.ceil(n / 64) and seen[-1][0] == p.stat().st_size
    assert all(a[0] < b[0] for a, b in zip(seen, seen[1:]))
    # an error in a late chunk still names its line and cell
    bad = rows.splitlines()
    bad[900] = bad[900].replace(",60000", ",-5")
    p.write_text(HEAD + "\n".join(bad) + "\n")
    with pytest.raises(BonesimError, match=r"line 902, column 'speed_rpm'.*'-5'"):
        T.read_trajectory(p)
    # the row count is bounded as the chunks come in
    real_bound = limits.bound
    monkeypatch.setattr(T, "bound", lambda k: dataclasses.replace(real_bound(k), max=100)
                        if k == "trajectory_rows" else real_bound(k))
    p.write_text(HEAD + rows)
    with pytest.raises(BonesimError, match=r"number of rows .* is outside"):
        T.read_trajectory(p)


_CAPPED = """
import resource, sys
sys.path.insert(0, sys.argv[1])
from bonesim.cli.main import main
vm = int(open("/proc/self/status").read().split("VmSize:")[1].split()[0]) * 1024
cap = vm + (768 << 20)                     # 768 MiB more than the imports map
resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("case_change, needle", [
    (("voxel_mm = 0.5", "voxel_mm = 0.1"), r"520 x 520 x 520 grid of 0.1 mm voxels needs "
                                           r"about 6.\d+ GiB of memory"),
    (("voxel_mm = 0.5", "voxel_mm = 0.01"), r"5200 x 5200 x 5200 grid .* outside the physical"),
    (("size_mm = [52.0, 52.0, 52.0]", "size_mm = [250.0, 250.0, 250.0]"),
     r"500 x 500 x 500 grid of 0.5 mm voxels needs about"),
])
def test_hostile_sizes_under_a_memory_cap_give_one_line(tmp_path, case_change, needle):
    """A case whose grid is within the bounds but not within a 768 MiB cap is
    refused with the estimate; no MemoryError, no OOM kill, no traceback."""
    case = _case(tmp_path, *case_change)
    p = subprocess.run([sys.executable, "-c", _CAPPED, str(ROOT), "case-info", str(case)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and p.stderr.count("\n") == 1, p.stderr
    assert p.stderr.startswith("bonesim: error: ") and "case.toml" in p.stderr
    import re

    assert re.search(needle, p.stderr), p.stderr


def test_a_long_trajectory_under_a_memory_cap_is_refused_before_reading(tmp_path):
    p = tmp_path / "long.csv"
    p.write_text(HEAD + "0,0,0,0,0,0,-1,1,6e4\n" * 2 + "#" * (400 << 20))  # 400 MB
    r = subprocess.run([sys.executable, "-c", _CAPPED, str(ROOT), "simulate", "--trajectory",
                        str(p)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert re_match(r"long.csv: reading this trajectory needs about .* of memory", r.stderr)


def re_match(pattern, text) -> bool:
    import re

    return re.search(pattern, text) is not None


def test_a_burr_lattice_beyond_the_memory_is_refused_before_it_is_built():
    assert limits.check_burr_lattice(5.0, 0.5, 2) == 20 ** 3
    with pytest.raises(BonesimError, match=r"\[burr\]: the 12 mm burr's sample lattice "
                                           r"\(19200\^3 samples .* needs about .* TiB"):
        limits.check_burr_lattice(12.0, 0.01, 16)
    with pytest.raises(BonesimError, match="oversample"):
        limits.check_burr_lattice(1.0, 0.5, 4096)
