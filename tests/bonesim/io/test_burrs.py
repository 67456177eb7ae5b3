"""Tests for burr definitions (bonesim.io.burrs and the shipped burrs/*.toml)."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import burrs as burr_package
from bonesim.io.burrs import (BURR_KINDS, Burr, burr_folder, burr_table, list_burrs,
                              load_burr, load_burr_file)
from bonesim.errors import BonesimError

# Values for a complete user family (every field set in [family]).
FAMILY_VALUES = """\
r_max = 3.0
falloff = 1.0
k_low = 1.0
k_high = 3.0
n_t_fraction = 0.005
k_tan = 0.2
max_force_n = 3.5
vib_free_hz = 1000.0
vib_contact_hz = 800.0
vib_amp_n = 0.03
vib_amp_per_n = 0.02
vib_harmonics = [[400.0, 0.5]]
sound_base_hz = 1000.0
sound_harmonics = [[1, 1.0], [2, 0.5]]
sound_noise = 0.2
sound_force_hz_per_n = -50.0
sound_contact_light_n = 0.05
sound_contact_firm_n = 1.0
thin_bone_mm = 2.0
thin_bone_gain = 0.3
default_speed_rpm = 50000
max_speed_rpm = 80000
"""


def family_text(extra_family: str = "", entries: str = "[[burr]]\ndiameter_mm = 3\n",
                kind: str = "cutting", name: str | None = "mine") -> str:
    head = "[family]\n"
    if name is not None:
        head += f'name = "{name}"\n'
    head += f'kind = "{kind}"\n' + FAMILY_VALUES + extra_family + "\n"
    return head + entries


def write(tmp_path: Path, text: str, name: str = "mine.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def error_of(path_or_name) -> BonesimError:
    with pytest.raises(BonesimError) as info:
        load_burr(path_or_name)
    return info.value


# --------------------------------------------------------------------------
# Shipped burrs
# --------------------------------------------------------------------------

def test_folder_is_the_burrs_package():
    assert burr_folder() == Path(burr_package.__file__).resolve().parent
    assert burr_package.folder() == burr_folder()
    assert sorted(p.name for p in burr_folder().glob("*.toml")) >= ["cutting.toml",
                                                                    "diamond.toml"]


@pytest.mark.parametrize("path", sorted(Path(burr_package.folder()).glob("*.toml")),
                         ids=lambda p: p.name)
def test_every_shipped_file_loads(path):
    burrs = load_burr_file(path)
    assert burrs
    for b in burrs:
        assert b.kind in BURR_KINDS
        assert b.source == path
        assert b.k_high >= b.k_low > 0
        assert 0 < b.n_t_fraction < 1
        assert b.default_speed_rpm <= b.max_speed_rpm


def test_names_and_sizes():
    names = {b.name for b in list_burrs()}
    for d in range(1, 8):
        assert f"cutting-{d}mm" in names
    for d in range(1, 6):
        assert f"diamond-{d}mm" in names
    for name in names:
        assert re.fullmatch(r"[a-z]+-\d+(\.\d+)?mm", name), name


def test_list_is_sorted_by_kind_then_diameter():
    burrs = list_burrs()
    keys = [(b.kind, b.diameter_mm) for b in burrs]
    assert keys == sorted(keys)
    assert len({b.name for b in burrs}) == len(burrs)


def test_load_by_name_and_fields():
    b = load_burr("cutting-5mm")
    assert isinstance(b, Burr)
    assert (b.name, b.family, b.kind) == ("cutting-5mm", "cutting", "cutting")
    assert b.diameter_mm == 5.0 and b.radius_mm == 2.5
    assert (b.vib_free_hz, b.vib_contact_hz) == (1030.0, 875.0)
    d = load_burr("diamond-2mm")
    assert (d.vib_free_hz, d.vib_contact_hz) == (1049.0, 625.0)
    assert load_burr("cutting-5.0mm") == b
    with pytest.raises(Exception):
        b.r_max = 1.0  # frozen


def test_cutting_removes_more_and_falls_off_more_than_diamond():
    for c in (b for b in list_burrs() if b.kind == "cutting"):
        for d in (b for b in list_burrs() if b.kind == "diamond"):
            assert c.r_max > d.r_max
            assert c.falloff > d.falloff


def test_default_speeds():
    for b in list_burrs():
        if b.kind == "cutting":
            assert 60000 <= b.default_speed_rpm <= 80000
    cut = load_burr("cutting-3mm").default_speed_rpm
    assert load_burr("diamond-3mm").default_speed_rpm < cut


def test_shipped_inheritance_and_override():
    small, big = load_burr("cutting-3mm"), load_burr("cutting-7mm")
    # 3 mm inherits the family amplitude, 7 mm overrides it.
    assert small.vib_amp_n == 0.04
    assert big.vib_amp_n > small.vib_amp_n
    assert small.r_max == big.r_max == 4.0


@pytest.mark.parametrize("depth_mm, low_n, high_n", [(0.2, 0.3, 2.0), (0.3, 0.5, 2.0)])
def test_shallow_penetration_gives_moderate_force(depth_mm, low_n, high_n):
    # Exact spherical-cap volume of a burr pressed depth_mm into flat bone.
    for b in list_burrs():
        r, h = b.radius_mm, depth_mm
        cap = math.pi * h * h * (3 * r - h) / 3
        assert low_n <= b.force_n(cap) <= high_n, b.name


def test_force_saturates_at_max_force():
    for b in list_burrs():
        assert 3.0 <= b.max_force_n <= 4.0
        assert b.force_n(b.volume_mm3) == b.max_force_n


def test_gains_shrink_with_size():
    for kind in BURR_KINDS:
        burrs = [b for b in list_burrs() if b.kind == kind]
        for a, b in zip(burrs, burrs[1:]):
            assert a.k_low > b.k_low and a.k_high > b.k_high and a.k_tan > b.k_tan


def test_multi_gain_is_monotone_and_continuous():
    for b in list_burrs():
        v = np.linspace(0.0, b.volume_mm3, 2001)
        f = b.force_n(v)
        assert np.all(np.diff(f) >= 0)
        vt = b.threshold_mm3
        assert b.force_n(vt) == pytest.approx(b.k_low * vt)
        eps = vt * 1e-9
        assert b.force_n(vt + eps) == pytest.approx(b.force_n(vt), abs=1e-9)
        # slope above the threshold is the high gain
        assert (b.force_n(vt * 1.5) - b.force_n(vt)) / (0.5 * vt) == pytest.approx(b.k_high)


def test_removal_peaks_at_equator():
    for b in list_burrs():
        assert b.removal_per_n(math.pi / 2) == b.r_max
        pole = b.removal_per_n(0.0)
        assert pole == pytest.approx(max(0.0, b.r_max - b.falloff * math.pi / 2))
        assert b.removal_per_n(np.array([0.0, math.pi / 2])).shape == (2,)


def test_contact_levels():
    b = load_burr("diamond-3mm")
    assert b.contact_level(0.0) == "none"
    assert b.contact_level(b.sound_contact_light_n) == "light"
    assert b.contact_level(b.sound_contact_firm_n) == "firm"


def test_vibration_harmonics_fit_a_1khz_loop():
    for b in list_burrs():
        assert b.vib_harmonics
        for freq, amp in b.vib_harmonics:
            assert 0 < freq < 500 and 0 <= amp <= 1


def test_burr_table_is_json_ready():
    rows = burr_table(list_burrs())
    text = json.dumps(rows)
    back = json.loads(text)
    assert [r["name"] for r in back] == [b.name for b in list_burrs()]
    assert back[0]["radius_mm"] == back[0]["diameter_mm"] / 2
    assert isinstance(back[0]["vib_harmonics"][0], list)
    assert back[0]["source"].endswith(".toml")


def test_unknown_name_lists_known():
    err = error_of("cutting-9mm")
    assert "unknown burr 'cutting-9mm'" in str(err)
    assert "cutting-5mm" in str(err) and "diamond-2mm" in str(err)
    assert "did you mean" in str(error_of("cuting-5mm"))


# --------------------------------------------------------------------------
# User files
# --------------------------------------------------------------------------

def test_user_family_inherits_and_overrides(tmp_path):
    entries = ("[[burr]]\ndiameter_mm = 2.5\n\n"
               "[[burr]]\ndiameter_mm = 4\nk_low = 2.0\nk_high = 5.0\n")
    path = write(tmp_path, family_text(entries=entries))
    a, b = load_burr_file(path)
    assert a.name == "mine-2.5mm" and b.name == "mine-4mm"
    assert a.k_low == 1.0 and a.k_high == 3.0      # inherited
    assert b.k_low == 2.0 and b.k_high == 5.0      # overridden
    assert a.r_max == b.r_max == 3.0
    assert load_burr(f"{path}#mine-4mm") == b
    assert load_burr(str(path) + "#mine-2.5mm") == a


def test_family_name_defaults_to_file_stem(tmp_path):
    path = write(tmp_path, family_text(name=None), name="coarse.toml")
    assert load_burr(path).name == "coarse-3mm"


def test_single_burr_file(tmp_path):
    text = '[burr]\nkind = "diamond"\ndiameter_mm = 1.5\n' + FAMILY_VALUES
    path = write(tmp_path, text)
    b = load_burr(path)
    assert (b.name, b.family, b.kind) == ("diamond-1.5mm", "diamond", "diamond")
    text = '[burr]\nfamily = "fine"\nkind = "diamond"\ndiameter_mm = 1.5\n' + FAMILY_VALUES
    assert load_burr(str(write(tmp_path, text, "fine.toml"))).name == "fine-1.5mm"


def test_family_file_with_several_burrs_needs_a_pick(tmp_path):
    entries = "[[burr]]\ndiameter_mm = 2\n\n[[burr]]\ndiameter_mm = 3\n"
    path = write(tmp_path, family_text(entries=entries))
    err = error_of(path)
    assert "defines 2 burrs" in str(err) and "mine-2mm" in str(err)
    err = error_of(f"{path}#mine-9mm")
    assert "unknown burr 'mine-9mm'" in str(err) and str(path) in str(err)


@settings(max_examples=30, deadline=None)
@given(st.floats(min_value=0.1, max_value=10.0, allow_nan=False))
def test_any_positive_diameter_round_trips_through_its_name(tmp_path_factory, d):
    tmp = tmp_path_factory.mktemp("d")
    path = write(tmp, family_text(entries=f"[[burr]]\ndiameter_mm = {d!r}\n"))
    b = load_burr(path)
    assert b.diameter_mm == d
    assert load_burr(f"{path}#{b.name}") == b


# --------------------------------------------------------------------------
# Bad input: each gives a clear error naming the file, the place and the problem
# --------------------------------------------------------------------------

def check_error(tmp_path, text, *needles, name="mine.toml"):
    path = write(tmp_path, text, name)
    err = error_of(path)
    msg = str(err)
    assert str(path) in msg
    for needle in needles:
        assert needle in msg, msg
    return err


def test_missing_file(tmp_path):
    err = error_of(tmp_path / "nope.toml")
    assert "nope.toml" in str(err) and "not found" in str(err)


def test_malformed_toml(tmp_path):
    check_error(tmp_path, "[family\nkind=", "malformed TOML")


def test_unknown_key_in_family(tmp_path):
    err = check_error(tmp_path, family_text(extra_family="r_maxx = 1.0\n"),
                      "unknown key", "'r_maxx'")
    assert err.field == "family"


def test_unknown_key_in_entry(tmp_path):
    err = check_error(tmp_path, family_text(entries="[[burr]]\ndiameter_mm = 3\nspeed = 1\n"),
                      "unknown key", "'speed'")
    assert err.field == "burr[0]"


def test_wrong_type(tmp_path):
    err = check_error(tmp_path, family_text(entries='[[burr]]\ndiameter_mm = 3\nk_low = "high"\n'),
                      "'k_low' must be a number", "'high'")
    assert err.field == "burr[0]"
    check_error(tmp_path, family_text(entries="[[burr]]\ndiameter_mm = true\n"),
                "'diameter_mm' must be a number")


def test_wrong_type_in_pairs(tmp_path):
    check_error(tmp_path, family_text(
        entries="[[burr]]\ndiameter_mm = 3\nvib_harmonics = [[400.0]]\n"),
        "'vib_harmonics' item 0", "freq_hz, rel_amp")
    check_error(tmp_path, family_text(
        entries="[[burr]]\ndiameter_mm = 3\nsound_harmonics = []\n"),
        "'sound_harmonics' needs at least 1")
    check_error(tmp_path, family_text(
        entries="[[burr]]\ndiameter_mm = 3\nvib_harmonics = 5\n"),
        "'vib_harmonics' must be a list")


@pytest.mark.parametrize("value", ["0", "-2.0"])
def test_non_positive_diameter(tmp_path, value):
    check_error(tmp_path, family_text(entries=f"[[burr]]\ndiameter_mm = {value}\n"),
                "'diameter_mm' must be > 0")


def test_missing_diameter(tmp_path):
    check_error(tmp_path, family_text(entries="[[burr]]\nk_low = 1.0\n"),
                "missing required key", "'diameter_mm'")


def test_non_finite_value(tmp_path):
    check_error(tmp_path, family_text(entries="[[burr]]\ndiameter_mm = 3\nr_max = nan\n"),
                "'r_max' must be finite")


def test_unknown_kind(tmp_path):
    err = check_error(tmp_path, family_text(kind="ceramic"), "'kind' must be one of",
                      "ceramic")
    assert err.field == "family"


def test_missing_kind(tmp_path):
    check_error(tmp_path, "[family]\nname = \"x\"\n" + FAMILY_VALUES
                + "\n[[burr]]\ndiameter_mm = 3\n", "missing required key", "'kind'")


def test_duplicate_names(tmp_path):
    entries = "[[burr]]\ndiameter_mm = 3\n\n[[burr]]\ndiameter_mm = 3.0\n"
    err = check_error(tmp_path, family_text(entries=entries), "duplicate burr 'mine-3mm'")
    assert err.field.startswith("burr[1]")


def test_k_high_below_k_low(tmp_path):
    err = check_error(tmp_path, family_text(
        entries="[[burr]]\ndiameter_mm = 3\nk_low = 4.0\nk_high = 2.0\n"),
        "'k_low' (4) must be <= 'k_high' (2)")
    assert "mine-3mm" in err.field


@pytest.mark.parametrize("value", ["0", "1", "1.5", "-0.1"])
def test_threshold_fraction_range(tmp_path, value):
    check_error(tmp_path, family_text(
        entries=f"[[burr]]\ndiameter_mm = 3\nn_t_fraction = {value}\n"),
        "'n_t_fraction' must be > 0 and < 1")


def test_missing_field_names_it(tmp_path):
    text = family_text().replace("k_tan = 0.2\n", "")
    check_error(tmp_path, text, "missing field(s) 'k_tan'", "[family]")


def test_contact_thresholds_ordered(tmp_path):
    check_error(tmp_path, family_text(
        entries="[[burr]]\ndiameter_mm = 3\nsound_contact_firm_n = 0.01\n"),
        "'sound_contact_light_n' (0.05) must be < 'sound_contact_firm_n'")


def test_speeds_ordered(tmp_path):
    check_error(tmp_path, family_text(
        entries="[[burr]]\ndiameter_mm = 3\ndefault_speed_rpm = 90000\n"),
        "'default_speed_rpm' (90000) must be <= 'max_speed_rpm'")


def test_pitch_must_stay_positive(tmp_path):
    check_error(tmp_path, family_text(
        entries="[[burr]]\ndiameter_mm = 3\nsound_force_hz_per_n = -400\n"),
        "pitch must stay > 0")


def test_misplaced_keys(tmp_path):
    check_error(tmp_path, family_text(entries='[[burr]]\ndiameter_mm = 3\nkind = "diamond"\n'),
                "'kind' is not allowed here")
    check_error(tmp_path, family_text(extra_family="diameter_mm = 3\n"),
                "'diameter_mm' is not allowed here")


def test_bad_family_name(tmp_path):
    check_error(tmp_path, family_text(name="my burr"), "'name' must start with a letter")


def test_no_entries(tmp_path):
    check_error(tmp_path, family_text(entries=""), "at least one [[burr]] entry")
    check_error(tmp_path, family_text(entries="[burr]\ndiameter_mm = 3\n"),
                "double brackets")


def test_no_burr_at_all(tmp_path):
    check_error(tmp_path, "title = 'x'\n", "no burr found")
    check_error(tmp_path, "[[burr]]\ndiameter_mm = 3\n", "need a [family] table")


def test_unknown_top_level_key(tmp_path):
    check_error(tmp_path, family_text() + "\n[extra]\na = 1\n", "unknown key", "'extra'")


def test_single_burr_file_missing_field(tmp_path):
    text = '[burr]\nkind = "diamond"\ndiameter_mm = 2\n' + FAMILY_VALUES.replace(
        "falloff = 1.0\n", "")
    check_error(tmp_path, text, "missing field(s) 'falloff'")


def test_not_a_name_or_path():
    with pytest.raises(BonesimError, match="by name or path"):
        load_burr(5)
