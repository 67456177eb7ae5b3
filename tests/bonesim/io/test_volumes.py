"""Readers, writers, labelling and resampling of CT volumes (bonesim.io.volumes)."""
from __future__ import annotations


import nibabel as nib
import nrrd
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

from bonesim.io import volumes as V
from bonesim.errors import BonesimError

SHAPE = (6, 5, 4)
SPACING = 0.5
ORIGIN = np.array([-3.0, 2.0, 10.0])
KINDS = ("bone", "soft", "critical")


def asymmetric(shape=SHAPE) -> np.ndarray:
    """A volume whose every flip / permutation differs: value = 100 i + 10 j + k."""
    i, j, k = np.indices(shape)
    return (100 * i + 10 * j + k).astype(np.int16)


def lps_points(shape, spacing, origin):
    return origin + spacing * np.stack(np.indices(shape), -1)


# ----------------------------------------------------------- orientation
def test_nifti_ras_affine_loads_into_lps(tmp_path):
    lps = asymmetric()
    # the same anatomy stored RAS-ordered: i runs toward the right (-x), j anterior
    ras_data = lps[::-1, ::-1, :]
    last = ORIGIN + SPACING * (np.array(SHAPE) - 1)           # LPS corner
    aff = np.diag([SPACING, SPACING, SPACING, 1.0])
    aff[:3, 3] = [-last[0], -last[1], ORIGIN[2]]               # RAS coordinates
    nib.save(nib.Nifti1Image(ras_data, aff), tmp_path / "v.nii.gz")
    raw = V.read_nifti(tmp_path / "v.nii.gz")
    np.testing.assert_array_equal(raw.data, lps)
    np.testing.assert_allclose(raw.spacing_mm, SPACING)
    np.testing.assert_allclose(raw.origin_mm, ORIGIN)


def test_nifti_writer_roundtrip(tmp_path):
    lps = asymmetric()
    V.write_nifti(tmp_path / "w.nii.gz", lps, SPACING, ORIGIN)
    raw = V.read_nifti(tmp_path / "w.nii.gz")
    np.testing.assert_array_equal(raw.data, lps)
    np.testing.assert_allclose(raw.origin_mm, ORIGIN)
    # nibabel sees the file as RAS: its x axis runs toward the right
    assert nib.aff2axcodes(nib.load(tmp_path / "w.nii.gz").affine) == ("L", "P", "S")


def test_nifti_intensities_keep_their_type_unless_scaled(tmp_path):
    lps = asymmetric()
    V.write_nifti(tmp_path / "w.nii.gz", lps, SPACING, ORIGIN)
    assert V.read_nifti(tmp_path / "w.nii.gz").data.dtype == np.int16   # no float copy
    img = nib.load(tmp_path / "w.nii.gz")
    scaled = nib.Nifti1Image(np.asarray(img.dataobj), img.affine, img.header)
    scaled.header.set_slope_inter(2.0, -1024.0)
    nib.save(scaled, tmp_path / "s.nii.gz")
    raw = V.read_nifti(tmp_path / "s.nii.gz")
    assert raw.data.dtype == np.float32
    np.testing.assert_array_equal(raw.data, lps * 2.0 - 1024.0)
    assert V.read_nifti(tmp_path / "s.nii.gz", scaled=False).data.dtype == np.int16


@pytest.mark.parametrize("space", ["right-anterior-superior", "RAS"])
def test_nrrd_ras_space_loads_into_lps(tmp_path, space):
    lps = asymmetric()
    ras_data = lps[::-1, ::-1, :]
    last = ORIGIN + SPACING * (np.array(SHAPE) - 1)
    hdr = {"space": space, "space directions": np.eye(3) * SPACING,
           "space origin": np.array([-last[0], -last[1], ORIGIN[2]])}
    nrrd.write(str(tmp_path / "v.nrrd"), ras_data, hdr)
    raw = V.read_nrrd(tmp_path / "v.nrrd")
    np.testing.assert_array_equal(raw.data, lps)
    np.testing.assert_allclose(raw.origin_mm, ORIGIN)


def test_nrrd_permuted_axes_and_lps(tmp_path):
    lps = asymmetric()
    stored = lps.transpose(2, 0, 1)               # file axes: z, x, y
    dirs = np.zeros((3, 3))
    dirs[0, 2] = dirs[1, 0] = dirs[2, 1] = SPACING
    nrrd.write(str(tmp_path / "p.nrrd"), stored,
               {"space": "left-posterior-superior", "space directions": dirs,
                "space origin": ORIGIN})
    raw = V.read_nrrd(tmp_path / "p.nrrd")
    np.testing.assert_array_equal(raw.data, lps)
    np.testing.assert_allclose(raw.origin_mm, ORIGIN)


def test_nrrd_writer_roundtrip_and_spacings_only(tmp_path):
    lps = asymmetric()
    V.write_nrrd(tmp_path / "w.nrrd", lps, SPACING, ORIGIN)
    raw = V.read_nrrd(tmp_path / "w.nrrd")
    np.testing.assert_array_equal(raw.data, lps)
    np.testing.assert_allclose(raw.origin_mm, ORIGIN)
    nrrd.write(str(tmp_path / "s.nrrd"), lps, {"spacings": [0.5, 0.6, 0.7]})
    raw = V.read_nrrd(tmp_path / "s.nrrd")
    np.testing.assert_allclose(raw.spacing_mm, [0.5, 0.6, 0.7])


def test_nrrd_missing_spacing(tmp_path):
    nrrd.write(str(tmp_path / "n.nrrd"), asymmetric())
    with pytest.raises(BonesimError, match="missing spacing") as e:
        V.read_nrrd(tmp_path / "n.nrrd")
    assert "n.nrrd" in str(e.value)


def test_oblique_volume_snaps_with_warning(tmp_path):
    a = np.radians(10.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    aff = np.eye(4)
    aff[:3, :3] = rot * SPACING
    nib.save(nib.Nifti1Image(asymmetric(), aff), tmp_path / "o.nii")
    with pytest.warns(V.ObliqueWarning, match="oblique"):
        raw = V.read_nifti(tmp_path / "o.nii")
    np.testing.assert_array_equal(raw.data, asymmetric()[::-1, ::-1, :])
    np.testing.assert_allclose(raw.spacing_mm, SPACING)


# ------------------------------------------------------------------ DICOM
def dicom_slice(path, pixels, z, slope=1.0, intercept=0.0, instance=1,
                spacing=(0.5, 0.5), series="1.2.3"):
    meta = FileMetaDataset()
    uid = generate_uid()
    meta.MediaStorageSOPClassUID = CTImageStorage
    meta.MediaStorageSOPInstanceUID = uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, uid
    ds.SeriesInstanceUID = series
    ds.Modality = "CT"
    ds.InstanceNumber = instance
    ds.ImagePositionPatient = [1.0, 2.0, float(z)]
    ds.ImageOrientationPatient = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    if spacing is not None:
        ds.PixelSpacing = list(spacing)
    ds.Rows, ds.Columns = pixels.shape
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.RescaleSlope = slope
    ds.RescaleIntercept = intercept
    ds.PixelData = np.ascontiguousarray(pixels.astype(np.uint16)).tobytes()
    ds.save_as(path, enforce_file_format=True)


def test_dicom_sorted_by_position_with_rescale(tmp_path):
    rng = np.random.default_rng(1)
    n = 7
    stored = rng.integers(0, 3000, size=(n, 4, 5))           # (slice, rows, cols)
    names = [f"{c}.dcm" for c in rng.permutation(list("abcdefg"))]
    for k in range(n):
        # file names shuffled, instance numbers reversed: only position counts
        dicom_slice(tmp_path / names[k], stored[k], z=-5.0 + 0.5 * k, slope=2.0,
                    intercept=-1024.0, instance=n - k)
    raw = V.read_dicom_series(tmp_path)
    want = (stored * 2.0 - 1024.0).transpose(2, 1, 0)        # -> (cols, rows, slices)
    np.testing.assert_array_equal(raw.data, want.astype(np.float32))
    np.testing.assert_allclose(raw.spacing_mm, 0.5)
    np.testing.assert_allclose(raw.origin_mm, [1.0, 2.0, -5.0])


def test_dicom_writer_roundtrip(tmp_path):
    hu = asymmetric().astype(np.float32) - 1000
    V.write_dicom_series(tmp_path / "ct", hu, SPACING, ORIGIN)
    raw = V.read_dicom_series(tmp_path / "ct")
    np.testing.assert_array_equal(raw.data, hu)
    np.testing.assert_allclose(raw.origin_mm, ORIGIN)


def _series(folder, n=4, shape=(4, 5), **kw):
    folder.mkdir()
    for k in range(n):
        dicom_slice(folder / f"s{k}.dcm", np.full(shape, 1500), z=0.5 * k, **kw)


def test_dicom_errors(tmp_path):
    with pytest.raises(BonesimError, match="not found") as e:
        V.read_dicom_series(tmp_path / "nope")
    assert "nope" in str(e.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(BonesimError, match="no DICOM files"):
        V.read_dicom_series(tmp_path / "empty")

    _series(tmp_path / "garbage")
    (tmp_path / "garbage" / "notes.dcm").write_text("not a dicom file")
    with pytest.raises(BonesimError, match="unreadable DICOM slice") as e:
        V.read_dicom_series(tmp_path / "garbage")
    assert "notes.dcm" in str(e.value)

    _series(tmp_path / "mixed")
    dicom_slice(tmp_path / "mixed" / "odd.dcm", np.zeros((8, 8)), z=9.0)
    with pytest.raises(BonesimError, match="mixed slice sizes") as e:
        V.read_dicom_series(tmp_path / "mixed")
    assert "8x8" in str(e.value) and "4x5" in str(e.value)

    _series(tmp_path / "nospacing", spacing=None)
    with pytest.raises(BonesimError, match="missing spacing.*PixelSpacing"):
        V.read_dicom_series(tmp_path / "nospacing")

    _series(tmp_path / "gap", n=5)
    (tmp_path / "gap" / "s2.dcm").unlink()
    with pytest.raises(BonesimError, match="inconsistent slice spacing") as e:
        V.read_dicom_series(tmp_path / "gap")
    assert "gap" in str(e.value)

    _series(tmp_path / "one", n=1)
    with pytest.raises(BonesimError, match="missing spacing.*single slice"):
        V.read_dicom_series(tmp_path / "one")


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(BonesimError, match="NRRD file not found") as e:
        V.read_nrrd(tmp_path / "ct.nrrd")
    assert "ct.nrrd" in str(e.value)
    with pytest.raises(BonesimError, match="NIfTI file not found"):
        V.read_nifti(tmp_path / "ct.nii.gz")
    (tmp_path / "bad.nii").write_bytes(b"\0" * 10)
    with pytest.raises(BonesimError, match="unreadable NIfTI") as e:
        V.read_nifti(tmp_path / "bad.nii")
    assert "bad.nii" in str(e.value)
    (tmp_path / "bad.nrrd").write_text("NRRD0004\ntype: what\n\n")
    with pytest.raises(BonesimError, match="unreadable NRRD"):
        V.read_nrrd(tmp_path / "bad.nrrd")


# ------------------------------------------------------------ label stacks
COLORS = [(230, 220, 200), (40, 60, 220), (250, 230, 40)]


def write_planes(folder, planes, names=None, mode="RGB"):
    folder.mkdir(exist_ok=True)
    for k, p in enumerate(planes):
        name = names[k] if names else f"plane{k + 1}.png"
        Image.fromarray(np.asarray(p, dtype=np.uint8), mode=mode).save(folder / name)


def index_planes(nz=12, ny=3, nx=4):
    """Slice k carries structure 1 at pixel (row 0, col 0) only if k is even, etc."""
    lab = np.zeros((nx, ny, nz), np.uint8)
    lab[0, 0, :] = 1
    lab[1, 0, ::2] = 2
    lab[np.arange(nz) % nx, 2, np.arange(nz)] = 3    # a marker that moves with k
    return lab


def test_label_stack_natural_sort_and_orientation(tmp_path):
    lab = index_planes()
    V.write_label_stack(tmp_path / "st", lab, COLORS)
    names = sorted(p.name for p in (tmp_path / "st").iterdir())
    assert names[:3] == ["plane1.png", "plane10.png", "plane11.png"]  # lexical != natural
    raw = V.read_label_stack(tmp_path / "st", "*.png", (2.0, 1.5, 6.0), COLORS)
    np.testing.assert_array_equal(raw.data, lab)
    np.testing.assert_allclose(raw.spacing_mm, 0.5)
    np.testing.assert_allclose(raw.origin_mm, -(np.array(lab.shape) - 1) * 0.25)
    # image columns run along x and rows along y
    img = np.asarray(Image.open(tmp_path / "st" / "plane2.png"))
    assert img.shape == (3, 4, 3)
    assert tuple(img[2, 1]) == COLORS[2]


def test_natural_key():
    names = ["plane10.png", "plane2.png", "plane1.png", "Plane03.png"]
    assert sorted(names, key=V.natural_key) == ["plane1.png", "plane2.png",
                                                 "Plane03.png", "plane10.png"]


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, 10_000), min_size=1, max_size=30, unique=True))
def test_natural_key_orders_numbers(nums):
    names = [f"plane{n}.png" for n in nums]
    got = sorted(names, key=V.natural_key)
    assert got == [f"plane{n}.png" for n in sorted(nums)]


def _stray_stack(folder):
    plane = np.zeros((3, 4, 4), np.uint8)
    plane[0, 0, :3] = COLORS[0]
    plane[0, 1, :3] = COLORS[0]
    plane[0, 2, :3] = (228, 221, 199)          # anti-aliased near-bone
    plane[1, 0, :3] = (41, 61, 218)            # near-sinus
    plane[1, 1, :3] = (41, 61, 218)
    plane[2, 3, :3] = (90, 90, 90)             # alpha 0: background whatever colour
    plane[..., 3] = 255
    plane[2, 3, 3] = 0
    write_planes(folder, [plane, plane], mode="RGBA")


def test_label_stack_unknown_colours(tmp_path):
    _stray_stack(tmp_path / "st")
    size = (2.0, 1.5, 1.0)
    with pytest.raises(BonesimError) as e:
        V.read_label_stack(tmp_path / "st", "*.png", size, COLORS)
    msg = str(e.value)
    assert "st" in msg and "2 colour(s) match no structure" in msg
    assert "RGB(41, 61, 218) x 4 voxels" in msg and "RGB(228, 221, 199) x 2 voxels" in msg

    near = V.read_label_stack(tmp_path / "st", "*.png", size, COLORS, "nearest").data
    assert near[2, 0, 0] == 1 and near[0, 1, 0] == 2 and near[1, 1, 1] == 2
    assert near[3, 2, 0] == 0                                   # transparent
    back = V.read_label_stack(tmp_path / "st", "*.png", size, COLORS, "background").data
    assert back[2, 0, 0] == 0 and back[0, 1, 0] == 0 and back[0, 0, 0] == 1
    assert np.count_nonzero(back) == 4 and np.count_nonzero(near) == 10


def test_label_stack_errors(tmp_path):
    with pytest.raises(BonesimError, match="label-stack folder not found"):
        V.read_label_stack(tmp_path / "nope", "*.png", (1, 1, 1), COLORS)
    (tmp_path / "none").mkdir()
    with pytest.raises(BonesimError, match="no images match pattern"):
        V.read_label_stack(tmp_path / "none", "*.png", (1, 1, 1), COLORS)
    write_planes(tmp_path / "mixed", [np.zeros((3, 4, 3)), np.zeros((3, 4, 3))])
    write_planes(tmp_path / "mixed", [np.zeros((5, 4, 3))], names=["plane3.png"])
    with pytest.raises(BonesimError, match="mixed slice sizes") as e:
        V.read_label_stack(tmp_path / "mixed", "*.png", (1, 1, 1), COLORS)
    assert "4x5 px" in str(e.value) and "plane3.png" in str(e.value)
    write_planes(tmp_path / "bad", [np.zeros((3, 4, 3))])
    (tmp_path / "bad" / "plane2.png").write_bytes(b"\x89PNG truncated")
    with pytest.raises(BonesimError, match="unreadable slice image") as e:
        V.read_label_stack(tmp_path / "bad", "*.png", (1, 1, 1), COLORS)
    assert "plane2.png" in str(e.value)


# ------------------------------------------------------------- labelling
def test_threshold_and_label_map():
    hu = np.array([-1000, 200, 300, 1500, 40, 1500], np.float32).reshape(6, 1, 1)
    lm = np.array([0, 0, 0, 0, 12, 7], np.int32).reshape(6, 1, 1)
    out = V.labels_from_intensity(hu, lm, KINDS, (None, 12, 7), 300.0, "ct.nrrd")
    np.testing.assert_array_equal(out.ravel(), [0, 0, 1, 1, 2, 3])


def test_label_map_unknown_values():
    lm = np.array([0, 1, 9, 9, 4], np.int32).reshape(5, 1, 1)
    with pytest.raises(BonesimError) as e:
        V.labels_from_intensity(None, lm, KINDS, (1, 2, 3), 300.0, "ct.nrrd",
                                "labels.nrrd")
    msg = str(e.value)
    assert msg.startswith("labels.nrrd") and "9 (2 voxels)" in msg and "4 (1 voxels)" in msg


def test_no_bone_after_threshold():
    hu = np.full((3, 3, 3), 100.0, np.float32)
    with pytest.raises(BonesimError, match="no bone after thresholding") as e:
        V.labels_from_intensity(hu, None, KINDS, (), 300.0, "scan.nii")
    assert "scan.nii" in str(e.value) and "300" in str(e.value)


def test_label_map_grid_mismatch(tmp_path):
    V.write_nrrd(tmp_path / "ct.nrrd", np.full(SHAPE, 1500, np.int16), SPACING, ORIGIN)
    V.write_nrrd(tmp_path / "lab.nrrd", np.zeros(SHAPE, np.uint8), SPACING, ORIGIN + 1)
    with pytest.raises(BonesimError, match="label map grid differs") as e:
        V.load_volume("nrrd", tmp_path / "ct.nrrd", kinds=KINDS,
                      labels_path=tmp_path / "lab.nrrd")
    assert "lab.nrrd" in str(e.value)


# ------------------------------------------------------------- resampling
def test_resample_identity_is_untouched():
    data = asymmetric()
    out, origin = V.resample_isotropic(data, (0.5, 0.5, 0.5), ORIGIN, 0.5, order=1)
    assert out is data
    np.testing.assert_array_equal(origin, ORIGIN)


def test_load_volume_identity_skips_resampling(tmp_path, monkeypatch):
    V.write_nrrd(tmp_path / "ct.nrrd", np.full(SHAPE, 1500, np.int16), SPACING, ORIGIN)
    import scipy.ndimage

    def boom(*a, **k):
        raise AssertionError("resampling called for an isotropic volume")
    monkeypatch.setattr(scipy.ndimage, "affine_transform", boom)
    vol = V.load_volume("nrrd", tmp_path / "ct.nrrd", kinds=KINDS, voxel_mm=SPACING)
    assert vol.shape == SHAPE and (vol.labels == 1).all()


def test_resample_labels_nearest_and_intensity_linear():
    lab = np.zeros((4, 4, 2), np.uint8)
    lab[:2] = 1
    lab[2:] = 3
    out, origin = V.resample_isotropic(lab, (1.0, 1.0, 1.0), (0, 0, 0), 0.5, order=0)
    assert out.shape == (8, 8, 4) and out.dtype == np.uint8
    assert set(np.unique(out)) == {1, 3}                       # no blended labels
    assert (out[:4] == 1).all() and (out[4:] == 3).all()
    np.testing.assert_allclose(origin, -0.25)
    ramp = np.broadcast_to(np.arange(6, dtype=np.float32)[:, None, None] * 10,
                           (6, 3, 3)).copy()
    fine, origin = V.resample_isotropic(ramp, (1.0, 1.0, 1.0), (0, 0, 0), 0.5, order=1)
    x = origin[0] + 0.5 * np.arange(fine.shape[0])
    inner = (x >= 0) & (x <= 5)
    np.testing.assert_allclose(fine[inner, 1, 1], 10 * x[inner], atol=1e-4)


def test_anisotropic_volume_resampled(tmp_path):
    nrrd.write(str(tmp_path / "a.nrrd"), np.full((4, 4, 2), 1500, np.int16),
               {"space": "left-posterior-superior",
                "space directions": np.diag([0.5, 0.5, 1.0]),
                "space origin": np.zeros(3)})
    vol = V.load_volume("nrrd", tmp_path / "a.nrrd", kinds=KINDS, voxel_mm=0.5)
    assert vol.shape == (4, 4, 4) and vol.hu.shape == (4, 4, 4)
    np.testing.assert_allclose(vol.origin_mm, [0, 0, -0.25])


def test_case_volume_checks():
    with pytest.raises(ValueError):
        V.CaseVolume(np.zeros((2, 2, 2), np.int32), 0.5, (0, 0, 0), "x")
    v = V.CaseVolume(np.ones((2, 2, 2), np.uint8), 0.5, (0, 0, 0), "x")
    assert v.counts(2).tolist() == [0, 8, 0]
    np.testing.assert_allclose(v.index_to_mm([1, 0, 1]), [0.5, 0, 0.5])


# ----------------------------------------------- big stacks, fast resampling
@settings(max_examples=300, deadline=None)
@given(shape=st.tuples(*[st.integers(1, 9)] * 3),
       spacing=st.tuples(*[st.sampled_from([0.1, 0.19, 0.25, 0.3, 0.5, 0.7, 1.0, 1.3])] * 3),
       voxel=st.sampled_from([0.2, 0.25, 0.5, 0.6]))
def test_nearest_resampling_matches_scipy(shape, spacing, voxel):
    import scipy.ndimage

    data = (np.arange(np.prod(shape)) % 251).astype(np.uint8).reshape(shape)
    got, origin = V.resample_isotropic(data, spacing, (1.0, 2.0, 3.0), voxel, order=0)
    sp = np.asarray(spacing)
    if np.allclose(sp, voxel):
        assert got is data
        return
    out_shape = tuple(int(n) for n in np.maximum(1, np.round(np.array(shape) * sp / voxel)))
    scale = voxel / sp
    ref = scipy.ndimage.affine_transform(data, scale, offset=0.5 * scale - 0.5,
                                         output_shape=out_shape, order=0, mode="nearest",
                                         prefilter=False)
    np.testing.assert_array_equal(got, ref)
    assert got.flags.c_contiguous
    np.testing.assert_allclose(origin, np.array([1.0, 2.0, 3.0]) - sp / 2 + voxel / 2)


def test_label_stack_threads_progress_and_image_modes(tmp_path):
    lab = index_planes(nz=9, ny=5, nx=7)
    V.write_label_stack(tmp_path / "st", lab, COLORS, orientation="PRI")
    calls = []
    one = V.read_label_stack(tmp_path / "st", "*.png", (1, 2, 3), COLORS, orientation="PRI",
                             threads=1)
    many = V.read_label_stack(tmp_path / "st", "*.png", (1, 2, 3), COLORS,
                              orientation="PRI", threads=3,
                              progress=lambda *a: calls.append(a))
    np.testing.assert_array_equal(one.data, lab)
    np.testing.assert_array_equal(many.data, lab)
    assert many.data.flags.c_contiguous
    assert sorted(c[0] for c in calls) == list(range(1, 10))
    assert {c[1:] for c in calls} == {(9, "decoding slices")}
    # palette and RGBA slices (as other tools save them) read the same
    from PIL import Image

    for mode in ("P", "RGBA"):
        out = tmp_path / mode
        out.mkdir()
        for f in sorted((tmp_path / "st").iterdir()):
            im = Image.open(f).convert("RGB")
            (im.convert("P", palette=Image.Palette.ADAPTIVE) if mode == "P" else
             im.convert(mode)).save(out / f.name)
        raw = V.read_label_stack(out, "*.png", (1, 2, 3), COLORS, orientation="PRI")
        np.testing.assert_array_equal(raw.data, lab)


def test_ct_with_a_cropped_slicer_segmentation(tmp_path):
    hu = np.full(SHAPE, -1000, np.int16)
    hu[:3] = 1500
    V.write_nrrd(tmp_path / "ct.nrrd", hu, SPACING, ORIGIN)
    seg = np.zeros((2, 2, 2), np.uint8)
    seg[0] = 1                                          # nerve, overrides bone
    seg[1, 0] = 2                                       # sinus, in the air
    V.write_seg_nrrd(tmp_path / "s.seg.nrrd", seg, ["nerve", "sinus"],
                     [(255, 255, 0), (0, 0, 255)], SPACING, ORIGIN + SPACING * np.array([2, 1, 1]))
    vol = V.load_volume("nrrd", tmp_path / "ct.nrrd", kinds=KINDS,
                        labels_path=tmp_path / "s.seg.nrrd", voxel_mm=SPACING,
                        segment_names=[None, "sinus", "nerve"])
    want = np.where(hu >= 300, 1, 0).astype(np.uint8)
    want[2, 1:3, 1:3] = 3
    want[3, 1, 1:3] = 2
    np.testing.assert_array_equal(vol.labels, want)


# ------------------------------------------------------------ native resolution
def test_engine_voxel_of_native_is_the_finest_spacing():
    assert V.engine_voxel_mm("native", (0.19, 0.19, 0.19)) == 0.19
    assert V.engine_voxel_mm("native", (0.19, 0.2, 0.5)) == 0.19
    assert V.engine_voxel_mm(0.5, (0.19, 0.19, 0.19)) == 0.5
    with pytest.raises(ValueError, match="native"):
        V.engine_voxel_mm("fine", (1, 1, 1))


def test_native_label_stack_holds_its_labels_once(tmp_path):
    lab = index_planes()
    V.write_label_stack(tmp_path / "st", lab, COLORS)
    kw = dict(kinds=KINDS, colors=COLORS, size_mm=np.array(lab.shape) * 0.19)
    vol = V.load_volume("label-stack", tmp_path / "st", voxel_mm="native", **kw)
    assert vol.spacing_mm == pytest.approx(0.19) and vol.shape == lab.shape
    np.testing.assert_array_equal(vol.labels, lab)
    assert vol.native is None                           # the engine grid is the source's
    assert vol.native_labels.labels is vol.labels
    # the same number as voxel_mm: the same, one array
    same = V.load_volume("label-stack", tmp_path / "st", voxel_mm=0.19, **kw)
    assert same.native is None and same.spacing_mm == vol.spacing_mm
    fine = V.load_volume("label-stack", tmp_path / "st", voxel_mm=0.095, **kw)
    assert fine.native is not None and fine.native.labels.shape == lab.shape
    assert fine.shape == tuple(2 * n for n in lab.shape)


def test_native_of_anisotropic_slices_is_their_finest_spacing(tmp_path):
    """0.2 mm pixels, 0.5 mm slices: "native" is 0.2 mm; the slice axis is
    resampled (nearest), the source kept for distances."""
    lab = index_planes()                                  # (nx, ny, nz) = (4, 3, 12)
    V.write_label_stack(tmp_path / "st", lab, COLORS)
    size = np.array(lab.shape) * np.array([0.2, 0.2, 0.5])
    vol = V.load_volume("label-stack", tmp_path / "st", kinds=KINDS, colors=COLORS,
                        size_mm=size, voxel_mm="native")
    assert vol.spacing_mm == pytest.approx(0.2)
    assert vol.shape == (4, 3, 30)                        # 12 slices * 0.5 / 0.2
    np.testing.assert_allclose(vol.extent_mm, size, atol=0.1)
    np.testing.assert_array_equal(vol.native.labels, lab)
    np.testing.assert_allclose(vol.native.spacing_mm, [0.2, 0.2, 0.5])
    np.testing.assert_array_equal(vol.labels[:, :, 0], lab[:, :, 0])


def test_native_ct_keeps_its_intensities_without_a_float_copy(tmp_path):
    hu = asymmetric() * 3 - 200                           # int16, some >= 300
    V.write_nrrd(tmp_path / "ct.nrrd", hu.astype(np.int16), 0.25, ORIGIN)
    vol = V.load_volume("nrrd", tmp_path / "ct.nrrd", kinds=KINDS, voxel_mm="native")
    assert vol.spacing_mm == 0.25 and vol.native is None
    assert vol.hu.dtype == np.int16                       # the source's type
    np.testing.assert_array_equal(vol.hu, hu)
    np.testing.assert_array_equal(vol.labels, np.where(hu >= 300, 1, 0))
    # resampled intensities keep the type too (rounded)
    half = V.load_volume("nrrd", tmp_path / "ct.nrrd", kinds=KINDS, voxel_mm=0.5)
    assert half.hu.dtype == np.int16 and half.native.labels.shape == SHAPE


def test_label_map_lookup_in_slabs(monkeypatch):
    """Slab by slab, a label map is looked up as a whole one would be: big,
    negative, float and bool values included."""
    import bonesim.io.resample as R

    monkeypatch.setattr(R, "SLAB_VOXELS", 3)
    rng = np.random.default_rng(5)
    lm = rng.choice([0, 12, 7, 70000], size=(5, 2, 3)).astype(np.int64)
    hu = rng.normal(300, 200, size=lm.shape).astype(np.float32)
    with pytest.raises(BonesimError, match=r"1 value\(s\) no structure claims: 7 \("):
        V.labels_from_intensity(hu, lm, KINDS, (None, 12, 70000), 300.0, "ct.nrrd")
    lm[lm == 7] = -3
    with pytest.raises(BonesimError, match=r"-3 \("):
        V.labels_from_intensity(hu, lm, KINDS, (None, 12, 70000), 300.0, "ct.nrrd")
    lm[lm == -3] = 0
    want = np.where(hu >= 300, 1, 0)
    want[lm == 12] = 2
    want[lm == 70000] = 3
    np.testing.assert_array_equal(
        V.labels_from_intensity(hu, lm, KINDS, (None, 12, 70000), 300.0, "x"), want)
    small = np.where(lm == 70000, 0, lm)
    np.testing.assert_array_equal(
        V.labels_from_intensity(hu, small.astype(np.float32), KINDS, (None, 12, 1), 300.0,
                                "x"), np.where(small == 12, 2, np.where(hu >= 300, 1, 0)))
    np.testing.assert_array_equal(
        V.labels_from_intensity(None, small == 12, KINDS, (1, None, None), 300.0, "x"),
        (small == 12).astype(np.uint8))
    with pytest.raises(BonesimError, match="non-integer"):
        V.labels_from_intensity(hu, small + 0.5, KINDS, (None, 12, 1), 300.0, "x")


def test_dicom_hu_stay_whole_numbers_in_int16(tmp_path):
    """The usual CT (whole rescale) reads as int16; a fractional rescale, or
    HU beyond int16, as float32, with the same values."""
    stored = np.arange(20).reshape(4, 5) * 150
    for name, slope, icpt, big in (("whole", 1.0, -1024.0, False),
                                   ("fraction", 0.5, -1024.0, False),
                                   ("beyond", 1.0, 0.0, True)):
        (tmp_path / name).mkdir()
        for k in range(3):
            px = stored + (60000 if big and k == 2 else 0)
            dicom_slice(tmp_path / name / f"s{k}.dcm", px, z=0.5 * k, slope=slope,
                        intercept=icpt)
        raw = V.read_dicom_series(tmp_path / name)
        want = np.stack([stored + (60000 if big and k == 2 else 0) for k in range(3)]
                        ).astype(np.float64) * slope + icpt
        assert raw.data.dtype == (np.int16 if name == "whole" else np.float32), name
        np.testing.assert_array_equal(raw.data, want.transpose(2, 1, 0))
        assert raw.data.flags.c_contiguous
