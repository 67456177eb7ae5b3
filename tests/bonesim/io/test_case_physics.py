"""The case manifest's ``[physics]`` table: the gravity direction."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.io.case import parse_case

BASE = """
[case]
name = "g"
side = "left"

[volume]
format = "phantom"

[[structures]]
name = "bone"
kind = "bone"

[camera]
eye_mm = [100.0, 0.0, 0.0]
focal_mm = [10.0, 0.0, 0.0]
up = [0.0, 0.0, 1.0]
"""


def _case(tmp_path, extra=""):
    p = tmp_path / "case.toml"
    p.write_text(BASE + extra)
    return parse_case(p)


def test_gravity_defaults_to_the_cameras_viewing_direction(tmp_path):
    c = _case(tmp_path)
    assert c.gravity is None
    np.testing.assert_allclose(c.gravity_dir, [-1.0, 0.0, 0.0])


def test_a_declared_gravity_is_normalised(tmp_path):
    c = _case(tmp_path, "\n[physics]\ngravity = [0, 0, -2.5]\n")
    assert c.gravity == (0.0, 0.0, -2.5)
    np.testing.assert_allclose(c.gravity_dir, [0.0, 0.0, -1.0])


@pytest.mark.parametrize("bad, msg", [("[0, 0, 0]", "non-zero"), ("[1, 2]", "gravity"),
                                      ('"down"', "gravity")])
def test_a_bad_gravity_names_the_table_and_key(tmp_path, bad, msg):
    with pytest.raises(BonesimError, match=msg) as e:
        _case(tmp_path, f"\n[physics]\ngravity = {bad}\n")
    assert "physics" in str(e.value)


def test_an_unknown_physics_key_is_refused(tmp_path):
    with pytest.raises(BonesimError, match="friction"):
        _case(tmp_path, "\n[physics]\nfriction = 0.3\n")
