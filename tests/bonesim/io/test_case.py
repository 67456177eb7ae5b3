"""Case manifests, bundled cases, case info and exports (bonesim.io.case)."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from bonesim.io import case as C
from bonesim.io import case_records
from bonesim.io import phantom as P
from bonesim.io import volumes as VOL
from bonesim.errors import BonesimError
from bonesim.io.segmentation import read_seg_segments
from tests.bonesim.io.test_anatomy import assert_looks_at_mastoid


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
    # camera: derived from the anatomy (no [camera] in the manifest), outside
    # the bone, lateral (+x for a left ear), looking medially at the mastoid
    assert c.declared_camera is None and c.camera_source == "anatomy"
    eye, focal = np.array(c.camera.eye_mm), np.array(c.camera.focal_mm)
    bone_x = phantom_vol.index_to_mm(np.argwhere(phantom_vol.labels == 1))[:, 0]
    assert eye[0] > bone_x.max() and (focal - eye) @ c.lateral < 0
    assert_looks_at_mastoid(c.surgical_view, phantom_vol.labels, phantom_vol.origin_mm,
                            "left")
    assert c.orientation == ("LPS", "generated")
    assert [s.name for s in c.structures if s.monitor] == ["facial_nerve",
                                                           "chorda_tympani"]
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
def _colors(case, vol):
    return [s.display_color for s in case.resolved(vol).structures]


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
    assert back.names == phantom_case.names and back.camera_source == "anatomy"
    np.testing.assert_allclose(np.r_[back.camera.eye_mm, back.camera.focal_mm],
                               np.r_[phantom_case.camera.eye_mm,
                                     phantom_case.camera.focal_mm], atol=1e-9)
    assert back.target == phantom_case.target
    assert _colors(back, vol) == _colors(phantom_case, phantom_vol)
    assert [s.monitor for s in back.structures] == [s.monitor for s in
                                                    phantom_case.structures]
    if fmt == "seg-nrrd":                 # labels only, as Slicer writes them
        assert vol.hu is None
        segs = read_seg_segments(tmp_path / "moved" / "segmentation.seg.nrrd")
        assert [g.name for g in segs] == list(phantom_case.names)
    elif fmt != "label-stack":
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
    from bonesim.io.volumes import write_nrrd

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
    from bonesim.io.volumes import write_nrrd

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
    ([("voxel_mm = 0.5", "voxel_mm = -1")], "'voxel_mm' must be a number of mm from 0.01 "
     "to 10 or \"native\" (the source's own spacing), got -1", "volume"),
    ([("voxel_mm = 0.5", 'voxel_mm = "nativ"')], "or \"native\"", "volume"),
    ([("voxel_mm = 0.5", 'voxel_mm = "0.3"')], "got '0.3'", "volume"),
    ([("voxel_mm = 0.5", "voxel_mm = true")], "got True", "volume"),
    ([("voxel_mm = 0.5", "voxel_mm = 11")], "got 11", "volume"),
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
    from bonesim.io.volumes import write_nrrd

    lab = np.zeros((4, 4, 4), np.uint8)
    lab[0, 0, :2] = 9
    write_nrrd(tmp_path / "lab.nrrd", lab, 0.5, (0, 0, 0))
    c = C.load_case(write_case(tmp_path, replace=[
        ('voxel_mm = 0.5', 'voxel_mm = 0.5\nlabels = "lab.nrrd"')]))
    with pytest.raises(BonesimError, match=r"9 \(2 voxels\)") as e:
        c.load_volume()
    assert "lab.nrrd" in str(e.value)


# ------------------------------------------------ other people's label stacks
# The phantom as another simulator would hand it over: structures in other
# colours (the facial nerve and chorda in near-identical yellows), slices
# permuted and flipped, finer in-plane pixels than the engine's voxels, and a
# manifest with only [case], [volume] (orientation declared) and [[structures]].
THEIR_COLORS = {"bone": (255, 255, 255), "sigmoid_sinus": (0, 0, 255),
                "posterior_fossa_dura": (255, 0, 255), "middle_fossa_dura": (255, 128, 128),
                "facial_nerve": (250, 230, 40), "chorda_tympani": (252, 231, 41),
                "labyrinth": (128, 0, 255), "ossicles": (0, 255, 255)}
THEIR_KINDS = {"bone": "bone", "sigmoid_sinus": "soft", "posterior_fossa_dura": "soft",
               "middle_fossa_dura": "soft", "facial_nerve": "critical",
               "chorda_tympani": "critical", "labyrinth": "critical",
               "ossicles": "critical"}


def their_manifest(folder, side="left", orientation="PIR", size_mm=(52, 52, 52),
                   extra_volume=""):
    lines = [f'[case]\nname = "theirs"\nside = "{side}"\n',
             f'[volume]\nformat = "label-stack"\npath = "slices"\npattern = "*.png"\n'
             f'size_mm = {list(size_mm)}\n'
             + (f'orientation = "{orientation}"\n' if orientation else "") + extra_volume]
    for name in P.PARTS:
        lines.append(f'[[structures]]\nname = "{name}"\nkind = "{THEIR_KINDS[name]}"\n'
                     f'color = {list(THEIR_COLORS[name])}\n')
    path = folder / "case.toml"
    path.write_text("\n".join(lines))
    return path


@pytest.fixture(scope="module")
def their_stack(tmp_path_factory, phantom_vol):
    """PIR stack, columns and rows at 0.25 mm (each voxel drawn 2 x 2), slices
    at 0.5 mm."""
    from bonesim.io.orientation import from_lps

    folder = tmp_path_factory.mktemp("theirs")
    fine = np.repeat(np.repeat(phantom_vol.labels, 2, axis=1), 2, axis=2)   # y, z
    # PIR: columns = y (P), rows = z (I), slices = x (R); write_label_stack takes
    # LPS data and the code, so give it the fine LPS array
    VOL.write_label_stack(folder / "slices", fine, [THEIR_COLORS[n] for n in P.PARTS],
                          orientation="PIR")
    img = from_lps(fine, "PIR")
    assert img.shape == (208, 208, 104)                  # columns, rows, slices
    return folder


def test_their_label_stack_loads_in_the_patient_frame(their_stack, phantom_case,
                                                      phantom_vol):
    case = C.load_case(their_manifest(their_stack))
    assert case.orientation == ("PIR", "declared") and case.camera_source == "anatomy"
    assert case.declared_camera is None
    vol = case.load_volume()
    np.testing.assert_array_equal(vol.labels, phantom_vol.labels)   # voxel-identical
    np.testing.assert_allclose(vol.origin_mm, phantom_vol.origin_mm)
    assert vol.native.labels.shape == (104, 208, 208)
    np.testing.assert_allclose(vol.native.spacing_mm, [0.5, 0.25, 0.25])
    # the nerves are monitored without a flag
    assert [s.name for s in case.structures if s.monitor] == ["facial_nerve",
                                                              "chorda_tympani"]
    # label colours by default; the chorda's near-twin of the facial nerve's
    # yellow is changed (it touches the nerve), nothing else
    rc = case.resolved(vol)
    got = {s.name: s.display_color for s in rc.structures}
    assert all(s.color_source == "label" for s in rc.structures)
    for name in P.PARTS:
        if name != "chorda_tympani":
            assert got[name] == THEIR_COLORS[name], name
    from bonesim.io.anatomy import delta_e, load_table, neighbours

    table = load_table()
    assert delta_e(got["chorda_tympani"], got["facial_nerve"]) >= table.min_delta_e
    adj = neighbours(vol.labels, 8, vol.spacing_mm, table.neighbour_mm)
    cols = [got[n] for n in P.PARTS]
    for a, b in zip(*np.nonzero(np.triu(adj))):
        assert delta_e(cols[a], cols[b]) >= table.min_delta_e, (P.PARTS[a], P.PARTS[b])
    # the automatic view: the same as the phantom's, on the same anatomy
    assert_looks_at_mastoid(case.surgical_view, vol.labels, vol.origin_mm, "left")
    np.testing.assert_allclose(case.camera.focal_mm, phantom_case.camera.focal_mm,
                               atol=1e-9)
    info = C.case_info(case)
    assert info["warnings"] == [] and info["orientation"] == {"code": "PIR",
                                                              "source": "declared"}
    assert info["camera"]["source"] == "anatomy" and info["camera"]["notes"]
    assert info["colors"]["bone"] == {"rgb": [255, 255, 255], "source": "label"}


def test_model_draws_the_resolved_colours(their_stack):
    from bonesim.io.loading import load_model

    model = load_model(str(their_manifest(their_stack)), "cutting-5mm")
    case = model.case
    assert model.structures == case.structures
    for s, st in enumerate(model.structures, start=1):
        assert tuple(model.colors[s]) == st.display_color
    assert tuple(model.colors[6]) != THEIR_COLORS["chorda_tympani"]
    assert tuple(model.colors[5]) == THEIR_COLORS["facial_nerve"]
    assert case.camera_source == "anatomy" and "view" in case._derived


def test_a_right_ear_made_by_mirroring(tmp_path, phantom_vol):
    """The phantom's slices read with an R first letter: the anatomy lands
    mirrored in LPS, a right ear; declared right it is consistent."""
    VOL.write_label_stack(tmp_path / "slices", phantom_vol.labels,
                          [THEIR_COLORS[n] for n in P.PARTS], orientation="LPS")
    right = C.load_case(their_manifest(tmp_path, side="right", orientation="RPS"))
    vol = right.load_volume()
    np.testing.assert_array_equal(vol.labels, phantom_vol.labels[::-1])
    assert (np.array(right.camera.focal_mm) - right.camera.eye_mm)[0] > 0  # looks +x
    assert_looks_at_mastoid(right.surgical_view, vol.labels, vol.origin_mm, "right")
    assert C.case_info(right)["warnings"] == []
    # the same slices declared a left ear: the layout says otherwise
    wrong = C.load_case(their_manifest(tmp_path, side="left", orientation="RPS"))
    warnings = C.case_info(wrong)["warnings"]
    assert len(warnings) == 1 and "lateral" in warnings[0]
    assert 'orientation = "LPS"' in warnings[0] and 'side = "right"' in warnings[0]


def test_undeclared_orientation_is_assumed(tmp_path, phantom_vol, capsys):
    from bonesim.cli.main import main

    VOL.write_label_stack(tmp_path / "slices", phantom_vol.labels,
                          [THEIR_COLORS[n] for n in P.PARTS])
    path = their_manifest(tmp_path, orientation=None)
    case = C.load_case(path)
    assert case.orientation == ("LPS", "assumed")
    assert main(["case-info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "orientation: LPS, assumed: the manifest declares none" in out
    assert "patient frame: LPS" in out and "camera (derived from the anatomy)" in out
    assert "monitor: Facial nerve, Chorda tympani\n" in out
    assert "warning:" not in out


@pytest.mark.parametrize("code", ["SAR", "PIL", "LPS"])
def test_export_with_orientation_reloads_identical(tmp_path, phantom_case, phantom_vol,
                                                   code):
    m = C.export_case(phantom_case, "label-stack", tmp_path / code, orientation=code)
    text = m.read_text()
    assert f'orientation = "{code}"' in text and "[camera]" not in text
    back = C.load_case(m)
    assert back.orientation == (code, "declared")
    vol = back.load_volume()
    np.testing.assert_array_equal(vol.labels, phantom_vol.labels)
    np.testing.assert_allclose(vol.origin_mm, phantom_vol.origin_mm, atol=1e-9)
    assert _colors(back, vol) == _colors(phantom_case, phantom_vol)
    np.testing.assert_allclose(back.camera.focal_mm, phantom_case.camera.focal_mm,
                               atol=1e-9)


def test_export_keeps_declared_colours_camera_and_monitor_flags(tmp_path, phantom_vol):
    VOL.write_label_stack(tmp_path / "slices", phantom_vol.labels,
                          [THEIR_COLORS[n] for n in P.PARTS])
    path = their_manifest(tmp_path, orientation=None)
    text = path.read_text().replace(
        'name = "labyrinth"', 'name = "labyrinth"\ndisplay_color = [10, 200, 10]'
    ).replace('name = "chorda_tympani"', 'name = "chorda_tympani"\nmonitor = false')
    path.write_text(text + '\n[camera]\neye_mm = [100, 0, 0]\nfocal_mm = [0, 0, 0]\n'
                           'up = [0, 0, 1]\n')
    case = C.load_case(path)
    for fmt in ("nrrd", "label-stack"):
        back = C.load_case(C.export_case(case, fmt, tmp_path / fmt))
        vol = back.load_volume()
        assert _colors(back, vol) == _colors(case, vol)
        assert back.camera == case.camera and back.camera_source == "manifest"
        assert [s.name for s in back.structures if s.monitor] == ["facial_nerve"]
        lab = back.structures[P.PARTS.index("labyrinth")]
        assert lab.display_color == (10, 200, 10) and lab.color_source == "manifest"


def test_cli_export_orientation(tmp_path, capsys):
    from bonesim.cli.main import main

    assert main(["case-export", "phantom", "--format", "label-stack", "--orientation",
                 "ail", str(tmp_path / "a")]) == 0
    assert 'orientation = "AIL"' in (tmp_path / "a" / "case.toml").read_text()
    capsys.readouterr()
    assert main(["case-export", "phantom", "--format", "nrrd", "--orientation", "AIL",
                 str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "label stacks only" in err[0]
    assert main(["case-export", "phantom", "--format", "label-stack", "--orientation",
                 "AIX", str(tmp_path / "c")]) == 2
    assert "'X' is not one of" in capsys.readouterr().err


def test_case_info_shows_a_progress_bar(tmp_path, monkeypatch, capsys, phantom_vol):
    """case-info hands a progress callback to the volume reader (which calls it
    while a big stack loads) and draws it on stderr."""
    from bonesim.cli.main import main

    def fake_load_volume(fmt, path, *, kinds, progress=None, **kw):
        for k in range(1, 5):
            progress(k, 4, "reading slices")
        return VOL.CaseVolume(phantom_vol.labels, 0.5, phantom_vol.origin_mm, "fake")

    monkeypatch.setattr(case_records, "load_volume", fake_load_volume)
    (tmp_path / "slices").mkdir()
    assert main(["case-info", str(their_manifest(tmp_path))]) == 0
    out, err = capsys.readouterr()
    assert "reading slices [" in err and "100%" in err and "4/4" in err
    assert "case: theirs" in out


# ------------------------------------------------------ 3D Slicer segmentations
SEGMENTS = [("Bone", (0.9, 0.85, 0.75)), ("Sigmoid Sinus", (0.0, 0.0, 1.0)),
            ("Facial nerve", (1.0, 1.0, 0.0)), ("Chorda_tympani", (1.0, 0.5, 0.0)),
            ("Stapes", (0.2, 0.8, 0.8)), ("Thing", (0.5, 0.5, 0.5))]


def write_seg(path, labels, segments=SEGMENTS, spacing=0.5, origin=(0.0, 0.0, 0.0)):
    """A one-layer Slicer segmentation: voxel value s is segment s - 1."""
    import nrrd

    hdr = {"space": "left-posterior-superior", "space directions": np.eye(3) * spacing,
           "space origin": np.asarray(origin, float), "kinds": ["domain"] * 3}
    for i, (name, rgb) in enumerate(segments):
        hdr.update({f"Segment{i}_ID": f"Segment_{i + 1}", f"Segment{i}_Name": name,
                    f"Segment{i}_Color": " ".join(map(str, rgb)),
                    f"Segment{i}_LabelValue": str(i + 1), f"Segment{i}_Layer": "0"})
    nrrd.write(str(path), labels, hdr, index_order="F")
    return path


SEG_CASE = """
[case]
name = "slicer"
side = "left"

[volume]
format = "seg-nrrd"
path = "seg.seg.nrrd"
"""


def test_seg_nrrd_structures_from_the_file(tmp_path):
    lab = np.zeros((6, 6, 6), np.uint8)
    for s in range(1, 7):
        lab[s - 1, :, :3] = s
    write_seg(tmp_path / "seg.seg.nrrd", lab)
    (tmp_path / "case.toml").write_text(SEG_CASE)
    case = C.load_case(tmp_path)
    assert case.names == tuple(n for n, _ in SEGMENTS)
    assert [s.kind for s in case.structures] == ["bone", "soft", "critical", "critical",
                                                 "critical", "critical"]
    assert [s.name for s in case.structures if s.monitor] == ["Facial nerve",
                                                              "Chorda_tympani"]
    assert [s.color_source for s in case.structures] == ["segment"] * 6
    assert case.structures[1].display_color == (0, 0, 255)
    assert [s.segment for s in case.structures] == [n for n, _ in SEGMENTS]
    assert case.orientation == (None, "file")
    # a .seg.nrrd given as the label map of a label-only NRRD case
    (tmp_path / "case.toml").write_text(SEG_CASE.replace(
        'format = "seg-nrrd"\npath = "seg.seg.nrrd"', 'format = "nrrd"\nlabels = '
        '"seg.seg.nrrd"'))
    again = C.load_case(tmp_path)
    assert again.volume.format == "seg-nrrd" and again.names == case.names


def test_seg_nrrd_structures_named_in_the_manifest(tmp_path):
    write_seg(tmp_path / "seg.seg.nrrd", np.zeros((4, 4, 4), np.uint8))
    text = SEG_CASE + """
[[structures]]
name = "bone"
segment = "Segment_1"

[[structures]]
name = "VII"
segment = "facial_nerve"
monitor = false
display_color = [1, 2, 3]

[[structures]]
name = "sinus"
segment = "sigmoid sinus"
kind = "critical"
"""
    (tmp_path / "case.toml").write_text(text)
    case = C.load_case(tmp_path)
    b, vii, sinus = case.structures
    assert (b.segment, b.kind, b.display_color) == ("Bone", "bone", (230, 217, 191))
    assert (vii.segment, vii.kind, vii.monitor, vii.display_color, vii.color_source) == \
        ("Facial nerve", "critical", False, (1, 2, 3), "manifest")
    assert (sinus.segment, sinus.kind) == ("Sigmoid Sinus", "critical")


def test_seg_nrrd_case_loads(tmp_path):
    lab = np.zeros((6, 6, 6), np.uint8)
    for s in range(1, 7):
        lab[s - 1, :, :3] = s
    write_seg(tmp_path / "seg.seg.nrrd", lab)
    (tmp_path / "case.toml").write_text(SEG_CASE)
    case = C.load_case(tmp_path)
    vol = case.load_volume()
    assert C.case_info(case)["counts"] == {n: 18 for n, _ in SEGMENTS}
    np.testing.assert_array_equal(vol.labels, lab)


SEG_BAD = [
    ('[[structures]]\nname = "x"\nsegment = "Nope"\n', "no segment 'Nope' in seg.seg.nrrd; "
     "its segments: 'Bone', 'Sigmoid Sinus'", "structures[0]"),
    ('[[structures]]\nname = "a"\nsegment = "Bone"\n[[structures]]\nname = "b"\n'
     'segment = "bone"\n', "segment 'Bone' already used by 'a'", "structures[1]"),
    ('[[structures]]\nname = "Sigmoid Sinus"\n', "no structure of kind 'bone'",
     "structures"),
    ('[[structures]]\nname = "Bone"\nanatomy = "elbow"\n', "'anatomy' must be one of",
     "structures[0]"),
]


@pytest.mark.parametrize("extra, fragment, field", SEG_BAD)
def test_seg_nrrd_manifest_errors(tmp_path, extra, fragment, field):
    write_seg(tmp_path / "seg.seg.nrrd", np.zeros((4, 4, 4), np.uint8))
    (tmp_path / "case.toml").write_text(SEG_CASE + extra)
    with pytest.raises(BonesimError) as e:
        C.load_case(tmp_path)
    assert fragment in str(e.value) and str(tmp_path / "case.toml") in str(e.value)
    assert e.value.field == field


def test_seg_nrrd_without_a_bone_segment(tmp_path):
    write_seg(tmp_path / "seg.seg.nrrd", np.zeros((4, 4, 4), np.uint8),
              segments=SEGMENTS[1:3])
    (tmp_path / "case.toml").write_text(SEG_CASE)
    with pytest.raises(BonesimError, match="no segment of seg.seg.nrrd reads as bone "
                       r"\(segments: 'Sigmoid Sinus', 'Facial nerve'\); add "
                       r"\[\[structures\]\]"):
        C.load_case(tmp_path)


# ------------------------------------------------- orientation / anatomy keys
STACK = [('format = "nrrd"\npath = "ct.nrrd"',
          'format = "label-stack"\npath = "planes"\nsize_mm = [2, 2, 2]'),
         ("label = 1", "color = [1, 1, 1]"), ("label = 2", "color = [2, 2, 2]")]
ORIENTATION_BAD = [
    (STACK + [("size_mm = [2, 2, 2]", 'size_mm = [2, 2, 2]\norientation = "PLX"')],
     "orientation 'PLX': 'X' is not one of L, R, P, A, S, I"),
    (STACK + [("size_mm = [2, 2, 2]", 'size_mm = [2, 2, 2]\norientation = "LRS"')],
     "names the L/R axis more than once"),
    (STACK + [("size_mm = [2, 2, 2]", 'size_mm = [2, 2, 2]\norientation = "LP"')],
     "must be three letters"),
    (STACK + [("size_mm = [2, 2, 2]", "size_mm = [2, 2, 2]\norientation = 3")],
     "orientation must be a string"),
    ([("voxel_mm = 0.5", 'voxel_mm = 0.5\norientation = "LPS"')],
     "'orientation' does not apply to format 'nrrd': NRRD files carry their own "
     "orientation"),
    ([('format = "nrrd"\npath = "ct.nrrd"', 'format = "phantom"'),
      ('name = "nerve"', 'name = "facial_nerve"'),
      ("voxel_mm = 0.5", 'voxel_mm = 0.5\norientation = "LPS"')],
     "the phantom is generated in the patient frame"),
    ([("label = 2", 'label = 2\nsegment = "Nerve"')],
     "'segment' applies only to structures of a 3D Slicer segmentation"),
    ([("label = 2", 'label = 2\nanatomy = "spleen"')], "'anatomy' must be one of"),
]


@pytest.mark.parametrize("replace, fragment", ORIENTATION_BAD)
def test_orientation_and_anatomy_errors(tmp_path, replace, fragment):
    path = write_case(tmp_path, replace=replace)
    with pytest.raises(BonesimError) as e:
        C.load_case(path)
    msg = str(e.value)
    assert str(path) in msg and fragment in msg and "\n" not in msg, msg


def test_camera_is_optional_and_the_anatomy_key_overrides(tmp_path):
    tiny_volume(tmp_path)
    text = GOOD[:GOOD.index("[camera]")]
    c = C.load_case(write_case(tmp_path, text=text.replace(
        'name = "nerve"', 'name = "nerve"\nanatomy = "stapes"')))
    assert c.declared_camera is None and c.camera_source == "anatomy"
    nerve = c.structures[1]
    assert nerve.anatomy == "stapes" and nerve.role == "ossicles" and not nerve.monitor
    assert c.camera.up[2] > 0.8                 # derived from the tiny volume


# ------------------------------------------------------------ native resolution
def test_native_voxel_in_the_manifest_and_as_an_override(tmp_path):
    from bonesim.io.volumes import write_nrrd

    data = np.full((8, 8, 8), -1000, np.int16)
    data[2:6, 2:6, 2:6] = 1500
    write_nrrd(tmp_path / "ct.nrrd", data, 0.25, (0, 0, 0))
    path = write_case(tmp_path, replace=[("voxel_mm = 0.5", 'voxel_mm = "native"')])
    c = C.load_case(path)
    assert c.volume.voxel_mm == "native"
    vol = c.load_volume()
    assert vol.spacing_mm == 0.25 and vol.shape == (8, 8, 8)
    assert vol.native is None and vol.hu.dtype == np.int16      # one grid, no float copy
    # --voxel-mm: a number or native, over whatever the manifest says
    half = C.load_case(path, voxel_mm=0.5)
    assert half.volume.voxel_mm == 0.5 and half.load_volume().shape == (4, 4, 4)
    assert half.load_volume().native.labels.shape == (8, 8, 8)
    assert C.load_case(half) is half                            # a case is taken as it is
    back = C.load_case(half, voxel_mm="native")
    assert back.volume.voxel_mm == "native" and back.load_volume().spacing_mm == 0.25
    assert C.load_case(path, voxel_mm="0.125").volume.voxel_mm == 0.125  # command line
    with pytest.raises(BonesimError) as e:
        c.with_voxel_mm("fine")
    assert e.value.field == "--voxel-mm" and "or \"native\"" in str(e.value)
    with pytest.raises(BonesimError, match="got 0.001"):
        c.with_voxel_mm(0.001)


def test_phantom_native_is_its_manifest_voxel(tmp_path, phantom_case):
    # the bundled phantom gives 0.5 mm: "native" keeps it
    assert phantom_case.with_voxel_mm("native").volume.voxel_mm == 0.5
    assert phantom_case.with_voxel_mm(1.0).volume.voxel_mm == 1.0
    # a phantom manifest asking for "native" gets the generator's default
    text = phantom_case.manifest.read_text().replace("voxel_mm = 0.5",
                                                     'voxel_mm = "native"')
    text = text.replace("[[structures]]", "[camera]\neye_mm = [120, 0, 0]\nfocal_mm = "
                        "[20, 0, 0]\nup = [0, 0, 1]\n\n[[structures]]", 1)
    (tmp_path / "case.toml").write_text(text)
    c = C.load_case(tmp_path)
    assert c.volume.voxel_mm == "native" and c.with_voxel_mm("native") == c
    assert c.load_volume().spacing_mm == P.DEFAULT_VOXEL_MM


def test_load_model_at_another_voxel():
    from bonesim.io.loading import load_model

    m = load_model("phantom", "cutting-5mm", voxel_mm=1.0)
    assert m.grid.spacing_mm == 1.0 and m.case.volume.voxel_mm == 1.0
    assert m.grid.shape == (52, 52, 52)
    assert m.clearance.spacing_mm.tolist() == [1.0, 1.0, 1.0]   # the grid is the source
