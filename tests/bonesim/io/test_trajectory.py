"""Tests for trajectory CSV files (bonesim.io.trajectory)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from hypothesis.extra import numpy as hnp

from bonesim.errors import BonesimError
from bonesim.engine.model import Sample
from bonesim.io.trajectory import (COLUMNS, OPTIONAL_COLUMNS, Trajectory, TrajectorySample,
                                   read_trajectory, write_trajectory)

HEADER = "t_s, x_mm, y_mm, z_mm, axis_x, axis_y, axis_z, drill, speed_rpm"
GOOD_ROWS = [
    "0.0, 0, 0, 0, 0, 0, 1, 0, 0",
    "0.5, 1, 2, 3, 0, 1, 0, 1, 60000",
    "1.0, 2, 4, 6, 0, 0, 2, 0, 0",
]


def write(tmp_path: Path, lines, name="traj.csv") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def good(tmp_path) -> Path:
    return write(tmp_path, [HEADER, *GOOD_ROWS])


def error_of(path: Path) -> BonesimError:
    with pytest.raises(BonesimError) as info:
        read_trajectory(path)
    assert str(path) in str(info.value)
    return info.value


def simple(n=3) -> Trajectory:
    t = np.arange(n, dtype=float)
    pos = np.column_stack([t, 2 * t, -t])
    axis = np.tile([0.0, 0.0, 1.0], (n, 1))
    return Trajectory(t, pos, axis, np.ones(n, bool), np.full(n, 60000.0))


# --------------------------------------------------------------------------
# Reading good files
# --------------------------------------------------------------------------

def test_read_good_file(tmp_path):
    traj = read_trajectory(good(tmp_path))
    assert len(traj) == 3
    assert traj.t_s.dtype == np.float64 and traj.t_s.shape == (3,)
    assert traj.pos_mm.shape == (3, 3) and traj.axis.shape == (3, 3)
    assert traj.drill.dtype == bool and traj.direction.dtype == np.int8
    np.testing.assert_array_equal(traj.pos_mm[1], [1, 2, 3])
    np.testing.assert_allclose(np.linalg.norm(traj.axis, axis=1), 1.0)
    np.testing.assert_array_equal(traj.axis[2], [0, 0, 1])   # (0, 0, 2) normalized
    np.testing.assert_array_equal(traj.drill, [False, True, False])
    np.testing.assert_array_equal(traj.speed_rpm, [0, 60000, 0])
    np.testing.assert_array_equal(traj.direction, [1, 1, 1])
    assert traj.suction.dtype == bool and traj.irrigation.dtype == bool
    assert not traj.suction.any() and not traj.irrigation.any()     # absent: off
    assert (traj.start_s, traj.end_s, traj.duration_s) == (0.0, 1.0, 1.0)


RINSE_HEADER = HEADER + ", suction, irrigation"
RINSE_ROWS = [
    "0.0, 0, 0, 0, 0, 0, 1, 1, 60000, 0, 0",
    "1.0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1",       # irrigating
    "2.0, 2, 0, 0, 0, 0, 1, 0, 0, 1, 1",       # suction-irrigator
    "3.0, 3, 0, 0, 0, 0, 1, 0, 0, 1, 0",       # suction
    "4.0, 4, 0, 0, 0, 0, 1, 1, 60000, 0, 0",
]


def test_suction_and_irrigation_columns(tmp_path):
    traj = read_trajectory(write(tmp_path, [RINSE_HEADER, *RINSE_ROWS]))
    np.testing.assert_array_equal(traj.drill, [1, 0, 0, 0, 1])
    np.testing.assert_array_equal(traj.suction, [0, 0, 1, 1, 0])
    np.testing.assert_array_equal(traj.irrigation, [0, 1, 1, 0, 0])
    # one column alone is fine too
    only = read_trajectory(write(tmp_path, [HEADER + ", suction",
                                            "0, 0, 0, 0, 0, 0, 1, 0, 0, 1"], "s.csv"))
    assert only.suction.tolist() == [True] and only.irrigation.tolist() == [False]
    # held between samples like the drill
    s = traj.sample_at(2.5)
    assert isinstance(s, TrajectorySample)
    assert (s.drill, s.suction, s.irrigation) == (False, True, True)
    np.testing.assert_allclose(s.pos_mm, [2.5, 0, 0])
    assert traj.sample(1).irrigation and not traj.sample(1).suction
    r = traj.resample(2.0)
    np.testing.assert_array_equal(r.suction, [0, 0, 0, 0, 1, 1, 1, 1, 0])
    np.testing.assert_array_equal(r.irrigation, [0, 0, 1, 1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(r.drill, [1, 1, 0, 0, 0, 0, 0, 0, 1])
    a = traj.at_times([0.5, 3.25])
    assert a.suction.tolist() == [False, True] and a.irrigation.tolist() == [False, False]


def test_trajectory_samples_are_device_samples():
    traj = Trajectory([0.0, 1.0], np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)),
                      [False, False], [0.0, 0.0], suction=[True, False])
    s = traj.sample_at(0.5)
    d = s.device_sample()
    assert isinstance(d, Sample) and tuple(d)[:6] == tuple(s)[:6] and d.burr == 0
    assert s._fields[:6] == Sample._fields[:6]


def test_columns_in_any_order_with_direction(tmp_path):
    path = write(tmp_path, [
        "direction,speed_rpm,drill,axis_z,axis_y,axis_x,z_mm,y_mm,x_mm,t_s",
        "-1,100,1,1,0,0,3,2,1,0.1",
        "+1,200,0,1,0,0,6,5,4,0.2",
    ])
    traj = read_trajectory(path)
    np.testing.assert_array_equal(traj.pos_mm, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(traj.direction, [-1, 1])
    np.testing.assert_array_equal(traj.t_s, [0.1, 0.2])


def test_blank_lines_and_bom_are_fine(tmp_path):
    path = tmp_path / "traj.csv"
    path.write_text("\ufeff" + HEADER + "\n\n" + GOOD_ROWS[0] + "\n\n" + GOOD_ROWS[1] + "\n",
                    encoding="utf-8")
    assert len(read_trajectory(path)) == 2


def test_arrays_are_read_only(tmp_path):
    traj = read_trajectory(good(tmp_path))
    with pytest.raises(ValueError):
        traj.pos_mm[0, 0] = 5.0


# --------------------------------------------------------------------------
# Interpolation and resampling (checked against hand computations)
# --------------------------------------------------------------------------

def test_sample_at_hand_computation(tmp_path):
    traj = read_trajectory(good(tmp_path))
    s = traj.sample_at(0.25)
    assert isinstance(s, TrajectorySample)
    assert s.t_s == 0.25
    np.testing.assert_allclose(s.pos_mm, [0.5, 1.0, 1.5])
    # halfway between (0,0,1) and (0,1,0): normalized (0, 0.5, 0.5)
    np.testing.assert_allclose(s.axis, [0, np.sqrt(0.5), np.sqrt(0.5)])
    assert s.drill is False and s.speed_rpm == 0.0 and s.direction == 1
    # a quarter of the way from sample 1 to 2: axis (0, 0.75, 0.25) normalized
    s = traj.sample_at(0.625)
    np.testing.assert_allclose(s.pos_mm, [1.25, 2.5, 3.75])
    np.testing.assert_allclose(s.axis, np.array([0, 0.75, 0.25]) / np.hypot(0.75, 0.25))
    assert s.drill is True and s.speed_rpm == 60000.0      # held from t = 0.5


def test_sample_at_exact_times_and_clamping(tmp_path):
    traj = read_trajectory(good(tmp_path))
    for i in range(len(traj)):
        s = traj.sample_at(traj.t_s[i])
        np.testing.assert_array_equal(s.pos_mm, traj.pos_mm[i])
        np.testing.assert_array_equal(s.axis, traj.axis[i])
        assert s.drill == traj.drill[i] and s.speed_rpm == traj.speed_rpm[i]
    before, after = traj.sample_at(-5.0), traj.sample_at(9.0)
    assert before.t_s == 0.0 and after.t_s == 1.0
    np.testing.assert_array_equal(before.pos_mm, traj.pos_mm[0])
    np.testing.assert_array_equal(after.pos_mm, traj.pos_mm[-1])


@settings(max_examples=150, deadline=None)
@given(n=st.integers(1, 6), seed=st.integers(0, 2**32 - 1),
       times=st.lists(st.floats(-2.0, 12.0), min_size=1, max_size=8),
       at_samples=st.booleans())
def test_sample_at_is_the_arrays_interpolation_to_the_bit(n, seed, times, at_samples):
    """One time (the scripted device's path) gives exactly what the arrays'
    interpolation (of :meth:`Trajectory.at_times`, before the constructor
    normalizes the axes once more) gives at that time."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.01, 3.0, n)) - rng.uniform(0, 1)
    axis = rng.normal(size=(n, 3))
    if n > 1 and rng.random() < 0.3:
        axis[1] = -axis[0]                          # opposite axes cancel half-way
    traj = Trajectory(t, rng.normal(size=(n, 3)) * 30, axis, rng.random(n) < 0.5,
                      rng.uniform(0, 9e4, n), np.where(rng.random(n) < 0.5, 1, -1),
                      burr=rng.integers(0, 3, n))
    if at_samples:
        times = list(t) + [float(t[0] + (t[-1] - t[0]) / 2) if n > 1 else float(t[0])]
    if n > 1 and rng.random() < 0.3:
        times.append(float((t[0] + t[1]) / 2))      # where opposite axes cancel
    for tq in times:
        s = traj.sample_at(tq)
        r_t, r_pos, r_axis, r_drill, r_speed, r_dir, _, _, r_burr = traj._interpolate(
            np.array([tq]))
        assert s.t_s == r_t[0]
        np.testing.assert_array_equal(s.pos_mm, r_pos[0])
        np.testing.assert_array_equal(s.axis, r_axis[0])
        assert (s.drill, s.speed_rpm, s.direction, s.burr) == (
            r_drill[0], r_speed[0], r_dir[0], r_burr[0])


def test_opposite_axes_hold_the_earlier_axis():
    traj = Trajectory([0.0, 1.0], np.zeros((2, 3)), [[0, 0, 1], [0, 0, -1]],
                      [True, True], [1.0, 1.0])
    np.testing.assert_array_equal(traj.sample_at(0.5).axis, [0, 0, 1])
    np.testing.assert_allclose(np.linalg.norm(traj.sample_at(0.3).axis), 1.0)


def test_resample_hand_computation(tmp_path):
    traj = read_trajectory(good(tmp_path))
    r = traj.resample(4.0)
    np.testing.assert_allclose(r.t_s, [0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(r.pos_mm, [[0, 0, 0], [0.5, 1, 1.5], [1, 2, 3],
                                          [1.5, 3, 4.5], [2, 4, 6]])
    np.testing.assert_array_equal(r.drill, [False, False, True, True, False])
    np.testing.assert_array_equal(r.speed_rpm, [0, 0, 60000, 60000, 0])
    np.testing.assert_allclose(np.linalg.norm(r.axis, axis=1), 1.0)


def test_resample_haptic_rate_counts_and_span():
    traj = simple(3)                  # 0 .. 2 s
    r = traj.resample(1000)
    assert len(r) == 2001
    np.testing.assert_allclose(np.diff(r.t_s), 1e-3)
    np.testing.assert_allclose(r.pos_mm[:, 0], r.t_s, atol=1e-12)
    part = traj.resample(10, start_s=0.5, end_s=1.0)
    np.testing.assert_allclose(part.t_s, [0.5, 0.6, 0.7, 0.8, 0.9, 1.0])


def test_resample_holds_reverse_direction():
    traj = Trajectory([0.0, 1.0, 2.0], np.zeros((3, 3)), np.tile([1.0, 0, 0], (3, 1)),
                      [1, 1, 1], [5, 6, 7], direction=[1, -1, 1])
    r = traj.resample(2)
    np.testing.assert_array_equal(r.direction, [1, 1, -1, -1, 1])
    np.testing.assert_array_equal(r.speed_rpm, [5, 5, 6, 6, 7])


@pytest.mark.parametrize("rate", [0, -5, float("nan"), float("inf"), "fast", True])
def test_resample_bad_rate(rate):
    with pytest.raises(BonesimError, match="rate must be a positive number"):
        simple().resample(rate)


def test_resample_bad_span():
    with pytest.raises(BonesimError, match="empty"):
        simple().resample(10, start_s=1.5, end_s=1.0)


def test_single_sample_trajectory():
    traj = simple(1)
    assert len(traj.resample(1000)) == 1
    np.testing.assert_array_equal(traj.sample_at(3.0).pos_mm, [0, 0, 0])


def test_samples_iterate_in_order():
    traj = simple(4)
    assert [s.t_s for s in traj.samples()] == [0.0, 1.0, 2.0, 3.0]


# --------------------------------------------------------------------------
# Round trip
# --------------------------------------------------------------------------

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@st.composite
def trajectories(draw):
    n = draw(st.integers(min_value=1, max_value=20))
    steps = draw(hnp.arrays(np.float64, n, elements=st.floats(1e-3, 10.0)))
    t0 = draw(st.floats(-100, 100))
    t = t0 + np.cumsum(steps)       # steps >= 1 ms: strictly increasing
    pos = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-1000, 1000)))   # limits.toml coordinate_mm
    axis = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-10, 10)))
    axis[np.linalg.norm(axis, axis=1) < 1e-3] = [0.0, 0.0, 1.0]
    drill = draw(hnp.arrays(bool, n))
    speed = draw(hnp.arrays(np.float64, n, elements=st.floats(0, 1e5)))
    direction = draw(hnp.arrays(np.int8, n, elements=st.sampled_from([1, -1])))
    suction = draw(hnp.arrays(bool, n)) & ~drill
    irrigation = draw(hnp.arrays(bool, n)) & ~drill
    burr = draw(hnp.arrays(np.uint8, n, elements=st.integers(0, 255)))
    return Trajectory(t, pos, axis, drill, speed, direction, suction, irrigation, burr)


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(traj=trajectories())
def test_round_trip(tmp_path, traj):
    path = tmp_path / "rt.csv"
    write_trajectory(path, traj)
    back = read_trajectory(path)
    np.testing.assert_array_equal(back.t_s, traj.t_s)
    np.testing.assert_array_equal(back.pos_mm, traj.pos_mm)
    np.testing.assert_allclose(back.axis, traj.axis, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(back.drill, traj.drill)
    np.testing.assert_array_equal(back.speed_rpm, traj.speed_rpm)
    np.testing.assert_array_equal(back.direction, traj.direction)
    np.testing.assert_array_equal(back.suction, traj.suction)
    np.testing.assert_array_equal(back.irrigation, traj.irrigation)
    np.testing.assert_array_equal(back.burr, traj.burr)


@settings(max_examples=40, deadline=None)
@given(traj=trajectories(), frac=st.floats(0, 1))
def test_interpolation_stays_between_neighbours(traj, frac):
    t = traj.start_s + frac * traj.duration_s
    s = traj.sample_at(t)
    i = max(0, int(np.searchsorted(traj.t_s, t, side="right")) - 1)
    j = min(i + 1, len(traj) - 1)
    lo = np.minimum(traj.pos_mm[i], traj.pos_mm[j])
    hi = np.maximum(traj.pos_mm[i], traj.pos_mm[j])
    tol = 1e-9 * (1 + np.abs(hi))
    assert np.all(s.pos_mm >= lo - tol) and np.all(s.pos_mm <= hi + tol)
    assert abs(np.linalg.norm(s.axis) - 1) < 1e-12
    assert s.drill == traj.drill[i] and s.direction == traj.direction[i]
    assert s.suction == traj.suction[i] and s.irrigation == traj.irrigation[i]
    assert s.burr == traj.burr[i]


def test_written_header_is_exact(tmp_path):
    path = tmp_path / "w.csv"
    write_trajectory(path, simple())
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS + OPTIONAL_COLUMNS)
    assert OPTIONAL_COLUMNS == ("direction", "suction", "irrigation", "burr")


def test_burr_column_is_held_and_checked(tmp_path):
    rows = [HEADER + ", burr", "0, 0, 0, 0, 0, 0, 1, 1, 60000, 0",
            "1, 1, 0, 0, 0, 0, 1, 0, 0, 1", "2, 2, 0, 0, 0, 0, 1, 1, 40000, 1"]
    traj = read_trajectory(write(tmp_path, rows))
    assert traj.burr.tolist() == [0, 1, 1] and traj.sample_at(0.5).burr == 0
    assert read_trajectory(write(tmp_path, rows[:2], "b.csv")).burr.tolist() == [0]
    assert simple().burr.tolist() == [0] * len(simple())
    for bad in ("1.5", "-1", "256"):
        p = write(tmp_path, [HEADER + ", burr", "0, 0, 0, 0, 0, 0, 1, 1, 60000, " + bad],
                  "bad.csv")
        with pytest.raises(BonesimError, match="column 'burr'.*burr index 0..255"):
            read_trajectory(p)


def test_write_to_missing_folder(tmp_path):
    with pytest.raises(BonesimError, match="cannot write"):
        write_trajectory(tmp_path / "no" / "such" / "x.csv", simple())


# --------------------------------------------------------------------------
# Bad files: each error names the file, the line and the column
# --------------------------------------------------------------------------

def test_missing_file(tmp_path):
    assert "file not found" in str(error_of(tmp_path / "nope.csv"))


def test_empty_file(tmp_path):
    path = tmp_path / "e.csv"
    path.write_text("\n  \n")
    assert "empty file" in str(error_of(path))


def test_header_only(tmp_path):
    assert "no samples" in str(error_of(write(tmp_path, [HEADER])))


def test_not_text(tmp_path):
    path = tmp_path / "b.csv"
    path.write_bytes(b"\xff\xfe\x00\x81\x90")
    assert "not a UTF-8" in str(error_of(path))


def test_missing_column(tmp_path):
    err = error_of(write(tmp_path, [HEADER.replace(", speed_rpm", ""), "0,0,0,0,0,0,1,0"]))
    assert "missing column(s) speed_rpm" in str(err) and err.field == "line 1"


def test_extra_column(tmp_path):
    err = error_of(write(tmp_path, [HEADER + ", force_n", GOOD_ROWS[0] + ", 1"]))
    assert "unknown column 'force_n'" in str(err) and err.field == "line 1"


def test_misspelled_column(tmp_path):
    err = error_of(write(tmp_path, [HEADER.replace("speed_rpm", "sped_rpm"), GOOD_ROWS[0]]))
    assert "unknown column 'sped_rpm' (did you mean 'speed_rpm'?)" in str(err)


def test_repeated_and_empty_column(tmp_path):
    assert "appears twice" in str(error_of(write(tmp_path, [HEADER + ", drill"])))
    assert "empty column name" in str(error_of(write(tmp_path, [HEADER + ","])))


def test_wrong_cell_count(tmp_path):
    err = error_of(write(tmp_path, [HEADER, GOOD_ROWS[0], "0.5, 1, 2"]))
    assert "expected 9 cells" in str(err) and err.field == "line 3"


def test_non_numeric_cell(tmp_path):
    err = error_of(write(tmp_path, [HEADER, GOOD_ROWS[0], "0.5, 1, two, 3, 0, 1, 0, 1, 6"]))
    assert "not a number: 'two'" in str(err)
    assert err.field == "line 3, column 'y_mm'"


def test_empty_cell(tmp_path):
    err = error_of(write(tmp_path, [HEADER, "0, 0, 0, , 0, 0, 1, 0, 0"]))
    assert "empty cell" in str(err) and err.field == "line 2, column 'z_mm'"


@pytest.mark.parametrize("cell", ["nan", "inf", "-inf"])
def test_non_finite(tmp_path, cell):
    err = error_of(write(tmp_path, [HEADER, GOOD_ROWS[0], f"0.5, {cell}, 2, 3, 0, 1, 0, 1, 6"]))
    assert "must be finite" in str(err) and err.field == "line 3, column 'x_mm'"


@pytest.mark.parametrize("t1", ["0.0", "-0.5"])
def test_time_not_increasing(tmp_path, t1):
    err = error_of(write(tmp_path, [HEADER, GOOD_ROWS[0], f"{t1}, 1, 2, 3, 0, 1, 0, 1, 6"]))
    assert "time must increase strictly" in str(err)
    assert err.field == "line 3, column 't_s'"


def test_zero_axis(tmp_path):
    err = error_of(write(tmp_path, [HEADER, GOOD_ROWS[0], "0.5, 1, 2, 3, 0, 0.0, 0, 1, 6"]))
    assert "zero vector" in str(err) and err.field.startswith("line 3")


@pytest.mark.parametrize("cell", ["2", "0.5", "-1"])
def test_drill_not_boolean(tmp_path, cell):
    err = error_of(write(tmp_path, [HEADER, f"0, 0, 0, 0, 0, 0, 1, {cell}, 0"]))
    assert f"drill must be 0 or 1, got '{cell}'" in str(err)
    assert err.field == "line 2, column 'drill'"


def test_negative_speed(tmp_path):
    err = error_of(write(tmp_path, [HEADER, "0, 0, 0, 0, 0, 0, 1, 1, -100"]))
    assert "speed_rpm must be >= 0, got '-100'" in str(err)
    assert err.field == "line 2, column 'speed_rpm'"


def test_bad_direction(tmp_path):
    err = error_of(write(tmp_path, [HEADER + ", direction", "0, 0, 0, 0, 0, 0, 1, 1, 5, 0"]))
    assert "direction must be +1 or -1, got '0'" in str(err)
    assert err.field == "line 2, column 'direction'"


@pytest.mark.parametrize("column", ["suction", "irrigation"])
@pytest.mark.parametrize("cell", ["2", "0.5", "-1"])
def test_rinse_flags_not_boolean(tmp_path, column, cell):
    err = error_of(write(tmp_path, [HEADER + f", {column}", GOOD_ROWS[0] + ", 0",
                                    f"0.5, 0, 0, 0, 0, 0, 1, 0, 0, {cell}"]))
    assert f"{column} must be 0 or 1, got '{cell}'" in str(err)
    assert err.field == f"line 3, column '{column}'"


@pytest.mark.parametrize("column", ["suction", "irrigation"])
def test_rinse_needs_the_drill_off(tmp_path, column):
    err = error_of(write(tmp_path, [HEADER + f", {column}", GOOD_ROWS[0] + ", 1",
                                    "0.5, 0, 0, 0, 0, 0, 1, 1, 60000, 1"]))
    assert f"{column} needs the drill off" in str(err)
    assert err.field == f"line 3, column '{column}'"
    with pytest.raises(ValueError, match="need the drill off"):
        Trajectory([0.0], np.zeros((1, 3)), [[0, 0, 1]], [True], [0.0],
                   **{column: [True]})


def test_earliest_problem_is_reported(tmp_path):
    # line 3 has a bad drill, line 4 a bad time: line 3 is reported.
    err = error_of(write(tmp_path, [HEADER, GOOD_ROWS[0], "0.5, 1, 2, 3, 0, 1, 0, 7, 6",
                                    "0.1, 1, 2, 3, 0, 1, 0, 1, 6"]))
    assert err.field == "line 3, column 'drill'"


def test_line_numbers_count_blank_lines(tmp_path):
    err = error_of(write(tmp_path, [HEADER, "", GOOD_ROWS[0], "", "0.5, x, 2, 3, 0, 1, 0, 1, 6"]))
    assert err.field == "line 5, column 'x_mm'"


def test_constructor_checks_shapes():
    with pytest.raises(ValueError, match="pos_mm has shape"):
        Trajectory([0.0, 1.0], np.zeros((3, 3)), np.ones((2, 3)), [1, 1], [0, 0])
    with pytest.raises(ValueError, match="increase strictly"):
        Trajectory([1.0, 1.0], np.zeros((2, 3)), np.ones((2, 3)), [1, 1], [0, 0])
    with pytest.raises(ValueError, match="zero"):
        Trajectory([0.0], np.zeros((1, 3)), np.zeros((1, 3)), [1], [0])
    with pytest.raises(ValueError, match="suction has shape"):
        Trajectory([0.0, 1.0], np.zeros((2, 3)), np.ones((2, 3)), [0, 0], [0, 0],
                   suction=[0, 0, 0])
    with pytest.raises(ValueError, match="irrigation must hold only 0/1"):
        Trajectory([0.0], np.zeros((1, 3)), np.ones((1, 3)), [0], [0], irrigation=[2])
