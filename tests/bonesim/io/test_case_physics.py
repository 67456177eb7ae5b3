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


def test_the_case_default_speck_size_is_the_engines():
    from bonesim.engine.fragments import DEFAULT_SPECK_VOXELS
    from bonesim.io.case_records import Fragments

    assert Fragments().speck_voxels == DEFAULT_SPECK_VOXELS


def test_reading_a_case_does_not_load_the_kernels():
    import subprocess
    import sys

    code = ("import sys; from bonesim.io.case import load_case; "
            "print(sorted(m for m in ('numba', 'cc3d') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"
