"""Slicer segmentation headers: the segment table and its errors."""
from __future__ import annotations

import nrrd
import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.segmentation import read_seg_segments


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
