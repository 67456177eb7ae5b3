"""Tests for the per-kind material table (bonesim.engine.materials)."""
from __future__ import annotations

from pathlib import Path

import pytest

from bonesim.errors import BonesimError
from bonesim.engine.materials import (MATERIAL_KINDS, Material, default_materials_path,
                                      load_materials)

GOOD = """\
[bone]
stiffness = 1.0
removal = 1.0
injury = false

[critical]
stiffness = 0.6
removal = 0.5
injury = true

[soft]
description = "dura"
stiffness = 0.25
removal = 1.5
injury = true
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "materials.toml"
    path.write_text(text)
    return path


def error_of(tmp_path: Path, text: str) -> BonesimError:
    path = write(tmp_path, text)
    with pytest.raises(BonesimError) as info:
        load_materials(path)
    assert str(path) in str(info.value)
    return info.value


def test_shipped_materials():
    mats = load_materials()
    assert list(mats) == list(MATERIAL_KINDS)
    assert all(isinstance(m, Material) for m in mats.values())
    bone, critical, soft = mats["bone"], mats["critical"], mats["soft"]
    assert (bone.stiffness, bone.removal, bone.injury) == (1.0, 1.0, False)
    assert soft.stiffness < critical.stiffness < bone.stiffness
    assert critical.removal < bone.removal < soft.removal
    assert critical.injury and soft.injury
    assert all(m.description for m in mats.values())
    assert default_materials_path().is_file()
    assert default_materials_path().parent.name == "data"


def test_custom_file(tmp_path):
    mats = load_materials(write(tmp_path, GOOD))
    assert mats["soft"].description == "dura"
    assert mats["bone"].description == ""
    assert mats["critical"] == Material("critical", 0.6, 0.5, True, "")
    with pytest.raises(Exception):
        mats["bone"].stiffness = 2.0  # frozen


def test_missing_file(tmp_path):
    with pytest.raises(BonesimError, match="not found"):
        load_materials(tmp_path / "none.toml")


def test_missing_kind(tmp_path):
    text = GOOD.split("[soft]")[0]
    assert "missing material kind(s) 'soft'" in str(error_of(tmp_path, text))


def test_unknown_kind(tmp_path):
    err = error_of(tmp_path, GOOD + "\n[muscle]\nstiffness = 0.1\nremoval = 1\ninjury = true\n")
    assert "unknown material kind(s) 'muscle'" in str(err)


def test_unknown_key(tmp_path):
    err = error_of(tmp_path, GOOD.replace("removal = 1.5", "removal = 1.5\ncolour = 3"))
    assert "unknown key" in str(err) and "'colour'" in str(err) and err.field == "soft"


def test_missing_key(tmp_path):
    err = error_of(tmp_path, GOOD.replace("removal = 0.5\n", ""))
    assert "missing required key" in str(err) and "'removal'" in str(err)
    assert err.field == "critical"


@pytest.mark.parametrize("old, new, needle", [
    ("stiffness = 1.0", 'stiffness = "hard"', "'stiffness' must be a number"),
    ("stiffness = 1.0", "stiffness = -1.0", "'stiffness' must be >= 0"),
    ("removal = 1.0", "removal = inf", "'removal' must be finite"),
    ("removal = 1.0", "removal = true", "'removal' must be a number"),
    ("injury = false", "injury = 0", "'injury' must be true or false"),
])
def test_bad_values(tmp_path, old, new, needle):
    err = error_of(tmp_path, GOOD.replace(old, new, 1))
    assert needle in str(err) and err.field == "bone"


def test_bad_description(tmp_path):
    err = error_of(tmp_path, GOOD.replace('description = "dura"', "description = 5"))
    assert "'description' must be a string" in str(err)


def test_kind_not_a_table(tmp_path):
    err = error_of(tmp_path, "bone = 1\n" + GOOD.split("\n", 4)[4])
    assert "expected a table" in str(err)
