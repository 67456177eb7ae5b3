"""Case manifests, bundled cases, case info and exports (bonesim.case)."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from bonesim import case as C
from bonesim import phantom as P
from bonesim.errors import BonesimError


@pytest.fixture(scope="module")
def phantom_case():
    return C.load_case("phantom")


@pytest.fixture(scope="module")
def phantom_vol(phantom_case):
    return phantom_case.load_volume()


# ------------------------------------------------------------- bundled case
def test_bundled_phantom(phantom_case, phantom_vol):
    c = phantom_case
    assert c.name == "phantom" and c.side == "left" and c.volume.format == "phantom"
    assert c.names == P.PARTS
    assert c.manifest.name == "case.toml" and c.manifest.is_file()
    kinds = {s.name: s.kind for s in c.structures}
    assert kinds["bone"] == "bone" and kinds["facial_nerve"] == "critical"
    assert kinds["sigmoid_sinus"] == "soft" and kinds["chorda_tympani"] == "critical"
    assert c.index("facial_nerve") == 5 and c.bone_index == 1
    assert phantom_vol.shape == (104, 104, 104)
    assert (phantom_vol.counts(len(c.structures))[1:] > 0).all()
    # camera: outside the bone, lateral (+x for a left ear), looking medially
    eye, focal = np.array(c.camera.eye_mm), np.array(c.camera.focal_mm)
    bone_x = phantom_vol.index_to_mm(np.argwhere(phantom_vol.labels == 1))[:, 0]
    assert eye[0] > bone_x.max() and (focal - eye) @ c.lateral < 0
    t = c.target
    assert set(t.structures) <= set(c.names)
    assert all(a < b for a, b in zip(t.box_min_mm, t.box_max_mm))


def test_load_case_by_name_folder_and_file(phantom_case):
    folder = phantom_case.manifest.parent
    assert C.load_case(folder) == phantom_case
    assert C.load_case(str(phantom_case.manifest)) == phantom_case
    assert "phantom" in [c.name for c in C.list_cases()]
    import ct_cases

    assert C.cases_dir() == ct_cases.CASES_DIR


def test_unknown_case_names():
    with pytest.raises(BonesimError, match="no bundled case named 'nosuch'") as e:
        C.load_case("nosuch")
    assert "phantom" in str(e.value)
    with pytest.raises(BonesimError, match="not found"):
        C.load_case("some/where/case.toml")


def test_folder_without_manifest(tmp_path):
    with pytest.raises(BonesimError, match="folder has no case.toml") as e:
        C.load_case(tmp_path)
    assert str(tmp_path) in str(e.value)


def test_case_info(phantom_case, phantom_vol):
    info = C.case_info(phantom_case)
    assert info["name"] == "phantom" and info["format"] == "phantom"
    assert info["grid"] == [104, 104, 104] and info["voxel_mm"] == 0.5
    assert list(info["counts"]) == list(P.PARTS)
    assert info["total"] == sum(info["counts"].values()) == np.count_nonzero(
        phantom_vol.labels)
    assert info["manifest"].endswith("case.toml")


# ------------------------------------------------------------------ exports
@pytest.mark.parametrize("fmt", C.EXPORT_FORMATS)
def test_export_roundtrip(tmp_path, phantom_case, phantom_vol, fmt):
    manifest = C.export_case(phantom_case, fmt, tmp_path / fmt)
    # the export is self-contained: it still loads after moving the folder
    moved = shutil.move(str(tmp_path / fmt), str(tmp_path / "moved"))
    back = C.load_case(moved)
    assert back.volume.format == fmt and manifest.name == "case.toml"
    vol = back.load_volume()
    np.testing.assert_array_equal(vol.labels, phantom_vol.labels)
    np.testing.assert_allclose(vol.origin_mm, phantom_vol.origin_mm)
    assert vol.spacing_mm == phantom_vol.spacing_mm
    assert C.case_info(back)["counts"] == C.case_info(phantom_case)["counts"]
    assert back.names == phantom_case.names and back.camera == phantom_case.camera
    assert back.target == phantom_case.target
    if fmt != "label-stack":
        np.testing.assert_array_equal(vol.hu, phantom_vol.hu)
    else:
        pngs = sorted(p.name for p in (tmp_path / "moved" / "planes").iterdir())
        assert "plane1.png" in pngs and "plane104.png" in pngs


def test_export_of_export_and_overwrite(tmp_path, phantom_case, phantom_vol):
    m = C.export_case(phantom_case, "label-stack", tmp_path / "st")
    m2 = C.export_case(C.load_case(m), "nifti", tmp_path / "nii")   # no HU in source
    vol = C.load_case(m2).load_volume()
    np.testing.assert_array_equal(vol.labels, phantom_vol.labels)
    with pytest.raises(BonesimError, match="already exists"):
        C.export_case(phantom_case, "nrrd", tmp_path / "st")
    with pytest.raises(BonesimError, match="cannot export to 'vtk'"):
        C.export_case(phantom_case, "vtk", tmp_path / "x")


# ---------------------------------------------------------- bad manifests
GOOD = """
[case]
name = "tiny"
side = "left"

[volume]
format = "nrrd"
path = "ct.nrrd"
voxel_mm = 0.5

[[structures]]
name = "bone"
kind = "bone"
label = 1

[[structures]]
name = "nerve"
kind = "critical"
label = 2

[camera]
eye_mm = [50, 0, 0]
focal_mm = [0, 0, 0]
up = [0, 0, 1]
"""


def write_case(tmp_path, text=GOOD, replace=()):
    for old, new in replace:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / "case.toml"
    path.write_text(text)
    return path


def tiny_volume(tmp_path, hu=1500):
    from bonesim.volumes import write_nrrd

    data = np.full((4, 4, 4), -1000, np.int16)
    data[1:3, 1:3, 1:3] = hu
    write_nrrd(tmp_path / "ct.nrrd", data, 0.5, (0, 0, 0))
    lab = np.zeros((4, 4, 4), np.uint8)
    lab[1, 1, 1] = 2
    write_nrrd(tmp_path / "lab.nrrd", lab, 0.5, (0, 0, 0))


def test_good_small_case(tmp_path):
    tiny_volume(tmp_path)
    c = C.load_case(write_case(tmp_path, replace=[
        ('voxel_mm = 0.5', 'voxel_mm = 0.5\nlabels = "lab.nrrd"')]))
    info = C.case_info(c)
    assert info["counts"] == {"bone": 7, "nerve": 1} and info["total"] == 8
    # label-only case: no intensity volume, the map alone gives the structures
    c = C.load_case(write_case(tmp_path, replace=[('path = "ct.nrrd"',
                                                   'labels = "lab.nrrd"')]))
    with pytest.raises(BonesimError, match="the label map marks no bone structure"):
        c.load_volume()
    from bonesim.volumes import write_nrrd

    lab = np.zeros((4, 4, 4), np.uint8)
    lab[:2] = 1
    lab[3, 3, 3] = 2
    write_nrrd(tmp_path / "lab.nrrd", lab, 0.5, (0, 0, 0))
    vol = c.load_volume()
    assert vol.hu is None and C.case_info(c)["counts"] == {"bone": 32, "nerve": 1}


BAD = [
    # (replacements, expected message fragment, field)
    ([("[case]", "[case\n")], "malformed TOML", None),
    ([('side = "left"', 'side = "middle"')], "'side' must be one of", "case"),
    ([('kind = "critical"', 'kind = "nerve"')], "'kind' must be one of", "structures[1]"),
    ([('format = "nrrd"', 'format = "mha"')], "'format' must be one of", "volume"),
    ([("voxel_mm = 0.5", "voxel_mm = 0.5\nvoxel_size = 1")], "unknown key(s) 'voxel_size'",
     "volume"),
    ([("voxel_mm = 0.5", 'voxel_mm = 0.5\npattern = "*.png"')],
     "key 'pattern' does not apply to format 'nrrd'", "volume"),
    ([("[camera]", "[lights]\nn = 1\n[camera]")], "unknown key(s) 'lights'", "top level"),
    ([('name = "nerve"', 'name = "bone"')], "duplicate structure name 'bone'",
     "structures[1]"),
    ([("label = 2", "label = 1")], "label 1 already used", "structures[1]"),
    ([('kind = "bone"', 'kind = "soft"')], "no structure of kind 'bone'", "structures"),
    ([("voxel_mm = 0.5", "voxel_mm = -1")], "'voxel_mm' must be >=", "volume"),
    ([("up = [0, 0, 1]", "up = [1, 0, 0]")], "parallel to the viewing direction", "camera"),
    ([("up = [0, 0, 1]", "up = [0, 1]")], "'up' must be a list of 3", "camera"),
    ([("eye_mm = [50, 0, 0]", "")], "missing required key(s) 'eye_mm'", "camera"),
    ([('path = "ct.nrrd"', 'path = "ct.nrrd"\nlabels = "lab.png"')],
     "'labels' must be a .nrrd", "volume"),
    ([('path = "ct.nrrd"', "")], "missing required key 'path' (or 'labels')", "volume"),
    ([("up = [0, 0, 1]", 'up = [0, 0, 1]\n[target]\nstructures = ["brain"]')],
     "unknown structure(s) ['brain']", "target"),
    ([("up = [0, 0, 1]", "up = [0, 0, 1]\n[target]\nbox_mm = [[0, 0, 0], [1, -1, 1]]")],
     "must be below max", "target"),
    ([("label = 2", "label = 2\ncolor = [0, 0, 0]")], "reserved for background",
     "structures[1]"),
    ([("label = 2", "label = 2\nshape = 'tube'")], "unknown key(s) 'shape'",
     "structures[1]"),
]


@pytest.mark.parametrize("replace,fragment,field", BAD)
def test_bad_manifest(tmp_path, replace, fragment, field):
    path = write_case(tmp_path, replace=replace)
    with pytest.raises(BonesimError) as e:
        C.load_case(path)
    msg = str(e.value)
    assert str(path) in msg and fragment in msg, msg
    if field:
        assert e.value.field == field


def test_label_stack_and_phantom_manifest_rules(tmp_path):
    stack = [('format = "nrrd"\npath = "ct.nrrd"',
              'format = "label-stack"\npath = "planes"\nsize_mm = [2, 2, 2]')]
    with pytest.raises(BonesimError, match="needs 'color'"):
        C.load_case(write_case(tmp_path, replace=stack))
    no_size = [('format = "nrrd"\npath = "ct.nrrd"', 'format = "label-stack"\npath = "p"')]
    with pytest.raises(BonesimError, match="missing spacing: a label stack needs 'size_mm'"):
        C.load_case(write_case(tmp_path, replace=no_size))
    ph = [('format = "nrrd"\npath = "ct.nrrd"', 'format = "phantom"\nseed = 1')]
    with pytest.raises(BonesimError, match="unknown phantom part 'nerve'") as e:
        C.load_case(write_case(tmp_path, replace=ph))
    assert e.value.field == "structures[1]"


def test_missing_volume_files_name_the_file(tmp_path):
    c = C.load_case(write_case(tmp_path))
    with pytest.raises(BonesimError, match="NRRD file not found") as e:
        c.load_volume()
    assert str(tmp_path / "ct.nrrd") in str(e.value)
    c = C.load_case(write_case(tmp_path, replace=[('format = "nrrd"\npath = "ct.nrrd"',
                                                    'format = "dicom"\npath = "series"')]))
    with pytest.raises(BonesimError, match="DICOM folder not found") as e:
        c.load_volume()
    assert "series" in str(e.value)


def test_no_bone_after_threshold_names_file(tmp_path):
    tiny_volume(tmp_path, hu=100)
    c = C.load_case(write_case(tmp_path, replace=[("voxel_mm = 0.5",
                                                   "voxel_mm = 0.5\nbone_threshold_hu = 400")]))
    with pytest.raises(BonesimError, match="no bone after thresholding") as e:
        c.load_volume()
    assert "ct.nrrd" in str(e.value) and "400" in str(e.value)


def test_unknown_label_values_name_the_map(tmp_path):
    tiny_volume(tmp_path)
    from bonesim.volumes import write_nrrd

    lab = np.zeros((4, 4, 4), np.uint8)
    lab[0, 0, :2] = 9
    write_nrrd(tmp_path / "lab.nrrd", lab, 0.5, (0, 0, 0))
    c = C.load_case(write_case(tmp_path, replace=[
        ('voxel_mm = 0.5', 'voxel_mm = 0.5\nlabels = "lab.nrrd"')]))
    with pytest.raises(BonesimError, match=r"9 \(2 voxels\)") as e:
        c.load_volume()
    assert "lab.nrrd" in str(e.value)
