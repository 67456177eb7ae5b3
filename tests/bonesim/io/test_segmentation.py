"""Slicer segmentation headers: the segment table and its errors."""
from __future__ import annotations

import nrrd
import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.io import segmentation as S
from bonesim.io.segmentation import read_seg_segments


def _write(path, fields, data=None):
    data = np.zeros((2, 3, 4), np.uint8) if data is None else data
    hdr = {"space": "left-posterior-superior", "space directions": np.eye(3),
           "space origin": np.zeros(3), "kinds": ["domain"] * 3}
    hdr.update(fields)
    nrrd.write(str(path), data, hdr, index_order="F")
    return path


def test_reads_names_colours_layers_and_values(tmp_path):
    p = _write(tmp_path / "a.seg.nrrd", {
        "Segment0_ID": "Segment_1", "Segment0_Name": "Facial nerve",
        "Segment0_Color": "1 1 0", "Segment0_LabelValue": "1", "Segment0_Layer": "0",
        "Segment1_ID": "Segment_2", "Segment1_Color": "0.2 0.4 0.8",
        "Segment1_LabelValue": "3", "Segment1_Layer": "1"})
    a, b = read_seg_segments(p)
    assert (a.id, a.name, a.color, a.layer, a.label_value) == \
        ("Segment_1", "Facial nerve", (255, 255, 0), 0, 1)
    assert (b.name, b.color, b.layer, b.label_value) == ("Segment_2", (51, 102, 204), 1, 3)


@pytest.mark.parametrize("fields, words", [
    ({}, "no segments"),
    ({"Segment0_ID": "s", "Segment0_Color": "1 2"}, "Segment0_Color"),
    ({"Segment0_ID": "s", "Segment0_Layer": "x"}, "Segment0_Layer")])
def test_bad_headers_name_the_field(tmp_path, fields, words):
    p = _write(tmp_path / "b.seg.nrrd", fields)
    with pytest.raises(BonesimError, match=words):
        read_seg_segments(p)


def test_missing_and_non_nrrd_files(tmp_path):
    with pytest.raises(BonesimError, match="not found"):
        read_seg_segments(tmp_path / "none.seg.nrrd")
    bad = tmp_path / "x.seg.nrrd"
    bad.write_bytes(b"hello")
    with pytest.raises(BonesimError, match="unreadable NRRD header"):
        read_seg_segments(bad)


# ------------------------------------------------------------------ voxels
def _segments(*rows):
    """Header fields of segments given as (name, layer, label value)."""
    out = {}
    for i, (name, layer, value) in enumerate(rows):
        out.update({f"Segment{i}_ID": f"Segment_{i + 1}", f"Segment{i}_Name": name,
                    f"Segment{i}_Color": "0.5 0.5 0.5",
                    f"Segment{i}_LabelValue": str(value), f"Segment{i}_Layer": str(layer)})
    return out


def _layered(path, layers, fields, space="left-posterior-superior", origin=(0, 0, 0)):
    """A 4-D Slicer segmentation: a leading list axis of 3-D layers."""
    data = np.stack(layers, axis=0)
    hdr = {"space": space, "space directions": np.vstack([np.full(3, np.nan), np.eye(3) * 0.5]),
           "space origin": np.asarray(origin, float),
           "kinds": ["list", "domain", "domain", "domain"]}
    hdr.update(fields)
    nrrd.write(str(path), data, hdr, index_order="F")
    return path


def naive_paint(layers, rows, names, kinds):
    """Reference: for each voxel, of the structures whose segment holds it, the
    one of highest kind priority, the later on a tie."""
    shape = layers[0].shape
    out = np.zeros(shape, np.uint8)
    for ijk in np.ndindex(shape):
        best = None
        for s, (name, kind) in enumerate(zip(names, kinds)):
            _, layer, value = next(r for r in rows if r[0] == name)
            if layers[layer][ijk] == value:
                rank = (S.KIND_PRIORITY[kind], s)
                if best is None or rank > best[0]:
                    best = (rank, s + 1)
        out[ijk] = 0 if best is None else best[1]
    return out


def test_overlapping_layers_paint_by_priority(tmp_path):
    rng = np.random.default_rng(3)
    rows = [("Bone", 0, 1), ("Sinus", 0, 2), ("Facial nerve", 1, 1), ("Dura", 1, 2),
            ("Unused", 0, 3)]
    layers = [rng.integers(0, 4, (5, 4, 3)).astype(np.uint8),
              rng.integers(0, 3, (5, 4, 3)).astype(np.uint8)]
    p = _layered(tmp_path / "l.seg.nrrd", layers, _segments(*rows))
    names = ["Bone", "Dura", "Facial nerve", "Sinus"]
    kinds = ["bone", "soft", "critical", "soft"]
    raw = S.read_segmentation(p, names, kinds)
    np.testing.assert_array_equal(raw.data, naive_paint(layers, rows, names, kinds))
    unclaimed = (layers[0] == 3) & (layers[1] == 0)        # only "Unused" holds them
    assert unclaimed.any() and (raw.data[unclaimed] == 0).all()
    np.testing.assert_allclose(raw.spacing_mm, 0.5)
    # a segment ID names it as well as its name
    again = S.read_segmentation(p, ["Segment_1", "Segment_4", "Segment_3", "Segment_2"],
                                kinds)
    np.testing.assert_array_equal(again.data, raw.data)


def test_ras_segmentation_lands_in_lps(tmp_path):
    lab = np.zeros((4, 3, 2), np.uint8)
    lab[0, 0, 0] = 1                           # first voxel in file order
    p = _write(tmp_path / "r.seg.nrrd", {"space": "right-anterior-superior",
                                         **_segments(("Bone", 0, 1))}, lab)
    raw = S.read_segmentation(p, ["Bone"], ["bone"])
    # file axis 0 runs toward the right (-x), axis 1 anterior (-y): that voxel is
    # the +x, +y corner in LPS
    assert raw.data[3, 2, 0] == 1 and raw.data.sum() == 1


def test_segmentation_errors(tmp_path):
    p = _write(tmp_path / "e.seg.nrrd", _segments(("Bone", 2, 1)))
    with pytest.raises(BonesimError, match="in layer 2, but the file has 1 layer") as e:
        S.read_segmentation(p, ["Bone"], ["bone"])
    assert "e.seg.nrrd" in str(e.value) and "Segment0_Layer" in str(e.value)
    with pytest.raises(BonesimError, match="no segment 'Nerve'; its segments: 'Bone'"):
        S.read_segmentation(p, ["Nerve"], ["critical"])
    with pytest.raises(BonesimError, match="segmentation file not found"):
        S.read_segmentation(tmp_path / "none.seg.nrrd", ["Bone"], ["bone"])


def test_cropped_segmentation_on_a_ct_grid(tmp_path):
    from bonesim.io.raw_volume import RawVolume

    seg = RawVolume(np.arange(1, 7, dtype=np.uint8).reshape(1, 2, 3), np.full(3, 0.5),
                    np.array([1.0, 0.5, -1.0]), "s")
    out = S.embed_on_grid(seg, (4, 4, 6), np.full(3, 0.5), np.array([0.0, 0.0, -2.0]),
                          tmp_path / "s.seg.nrrd")
    assert out.shape == (4, 4, 6) and out.sum() == seg.data.sum()
    np.testing.assert_array_equal(out[2:3, 1:3, 2:5], seg.data)
    for origin, why in [([0.1, 0.0, -2.0], "offset"), ([0.0, 0.0, 0.0], "of a")]:
        with pytest.raises(BonesimError, match="does not lie on the volume's grid") as e:
            S.embed_on_grid(seg, (4, 4, 6), np.full(3, 0.5), np.array(origin),
                            tmp_path / "s.seg.nrrd")
        assert why in str(e.value) and "s.seg.nrrd" in str(e.value)


def test_write_seg_nrrd_is_a_slicer_segmentation(tmp_path):
    lab = np.zeros((5, 4, 3), np.uint8)
    lab[1:3, 1, :] = 1
    lab[4, 3, 2] = 2
    p = S.write_seg_nrrd(tmp_path / "w.seg.nrrd", lab, ["bone", "facial_nerve", "stapes"],
                         [(230, 217, 191), (255, 255, 0), (0, 0, 0)], 0.25, (1.0, 2.0, 3.0))
    hdr = nrrd.read_header(str(p))
    assert hdr["space"] == "left-posterior-superior"
    assert hdr["Segmentation_MasterRepresentation"] == "Binary labelmap"
    assert hdr["Segment0_Extent"] == "1 2 1 1 0 2" and hdr["Segment1_Extent"] == "4 4 3 3 2 2"
    assert hdr["Segment2_Extent"] == "0 -1 0 -1 0 -1"           # empty segment
    bone, nerve, stapes = read_seg_segments(p)
    assert (nerve.name, nerve.color, nerve.label_value, nerve.layer) == \
        ("facial_nerve", (255, 255, 0), 2, 0)
    raw = S.read_segmentation(p, ["bone", "facial_nerve", "stapes"],
                              ["bone", "critical", "critical"])
    np.testing.assert_array_equal(raw.data, lab)
    np.testing.assert_allclose(raw.origin_mm, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(raw.spacing_mm, 0.25)
