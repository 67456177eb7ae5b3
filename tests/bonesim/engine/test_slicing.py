"""The slice sizes file (bonesim/data/slicing.toml): every table read, a bad
value one line naming the file and the field."""
from __future__ import annotations

import pytest

from bonesim.engine.slicing import TABLES, voxels_per_step
from bonesim.errors import BonesimError


def test_the_shipped_file_gives_every_budget():
    for table in TABLES:
        assert voxels_per_step(table) >= 1


@pytest.mark.parametrize("text, where", [
    ("[split]\nvoxels_per_step = 0\n[cut_plane]\nvoxels_per_step = 1\n"
     "[rigid]\nvoxels_per_step = 1\n", "voxels_per_step"),
    ("[split]\nvoxels_per_step = 1.5\n[cut_plane]\nvoxels_per_step = 1\n"
     "[rigid]\nvoxels_per_step = 1\n", "integer"),
    ("[split]\nvoxels_per_step = 4\n[rigid]\nvoxels_per_step = 1\n", "cut_plane"),
    ("[split]\nvoxel_per_step = 4\n[cut_plane]\nvoxels_per_step = 1\n"
     "[rigid]\nvoxels_per_step = 1\n", "voxel_per_step"),
])
def test_a_bad_file_is_one_line_naming_it(tmp_path, text, where):
    p = tmp_path / "slicing.toml"
    p.write_text(text)
    with pytest.raises(BonesimError) as e:
        voxels_per_step("split", str(p))
    msg = str(e.value)
    assert "\n" not in msg and "slicing.toml" in msg and where in msg
