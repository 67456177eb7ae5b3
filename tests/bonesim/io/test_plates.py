"""The plate catalogue (bonesim.io.plates): shipped meshes, checks, and a
shipped plate resting on bone."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.engine.bodies import pose_matrix
from bonesim.engine.rigid import ASLEEP
from bonesim.engine.rigid_set import RigidSet
from bonesim.errors import BonesimError
from bonesim.io.plates import PLATE_KINDS, default_plates, load_plates

from tests.bonesim.fakes import block_model


def test_the_shipped_catalogue_has_two_plates_and_a_distractor():
    plates = default_plates()
    assert [p.kind for p in plates].count("distractor") == 1
    assert {p.name for p in plates} >= {"straight-4", "l-plate", "distractor"}
    for p in plates:
        assert p.kind in PLATE_KINDS and 100 <= p.samples <= len(p.pos)
        np.testing.assert_allclose(np.linalg.norm(p.nrm, axis=1), 1.0, atol=1e-6)
        # closed, consistently wound surface: the divergence theorem gives
        # a positive volume, close to mass / titanium density
        a, b, c = (p.pos[p.tris[:, q]] for q in range(3))
        vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
        assert vol == pytest.approx(p.mass_kg * 1e3 / 4.5e-3, rel=1e-3)
        # the bottom face is at z = -0.4 and faces down
        bottom = p.pos[:, 2] == p.pos[:, 2].min()
        assert p.pos[:, 2].min() == pytest.approx(-0.4)
        assert (p.nrm[bottom & (p.nrm[:, 2] < -0.5), 2] == -1.0).any()


def _write(tmp_path, text):
    import shutil

    src = default_plates()[0].mesh
    shutil.copy(src, tmp_path / src.name)
    (tmp_path / "plates.toml").write_text(text)
    return tmp_path / "plates.toml"


GOOD = """[[plate]]
name = "a"
kind = "plate"
mesh = "plate_straight4.ply"
mass_g = 0.4
sample_offset_mm = 0.1
stiffness_n_per_mm = 0.002
"""


@pytest.mark.parametrize("edit, msg", [
    (("kind = \"plate\"", "kind = \"screw\""), "kind"),
    (("mass_g = 0.4", "mass_g = -1"), "mass_g"),
    (("plate_straight4.ply", "nothing.ply"), "not found"),
    (("stiffness_n_per_mm = 0.002", "stiffnes = 0.002"), "stiffnes"),
])
def test_a_bad_entry_names_file_table_and_field(tmp_path, edit, msg):
    path = _write(tmp_path, GOOD.replace(*edit))
    with pytest.raises(BonesimError, match=msg) as e:
        load_plates(path)
    assert "plate[0]" in str(e.value) or "plates.toml" in str(e.value)


def test_a_repeated_name_is_refused(tmp_path):
    with pytest.raises(BonesimError, match="twice"):
        load_plates(_write(tmp_path, GOOD + "\n" + GOOD))


def test_a_shipped_plate_dropped_on_bone_rests_flat_on_it():
    m, s = block_model()
    p = default_plates()[0]
    rs = RigidSet(m.max_bodies)
    slot = rs.add_plate(p.pos, p.nrm, p.offset_mm, p.mass_kg, p.stiffness_n_mm,
                        [10.0, 10.0, 13.0, 1.0, 0.0, 0.0, 0.0])
    for q in range(3000):
        rs.advance(s, q * 1e-3, np.array([1e3, 1e3, 1e3]), False, 2.5, 1.0)
    assert rs.mode[slot] == ASLEEP
    top = 19 * 0.5 + 0.25
    bottom = rs.rpose[slot, 2] - 0.4
    assert top - 0.05 < bottom - p.offset_mm < top     # samples just in the bone
    assert pose_matrix(rs.rpose[slot])[2, 2] > 1 - 1e-6        # flat within 1.5 mrad
