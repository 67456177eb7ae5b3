"""Tests of bonesim.io.meshes: PLY / VTP writers and the small readers."""
from __future__ import annotations

import base64
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.engine.grid import Grid
from bonesim.io.meshes import read_ply, read_vtp, write_mesh, write_ply, write_vtp
from bonesim.engine.surface import Surface


@pytest.fixture(scope="module")
def mesh():
    g = np.indices((10, 10, 10))
    lab = (np.sqrt(((g - 4.5) ** 2).sum(0)) <= 3.6).astype(np.uint8)
    lab[lab.shape[0] // 2:] *= 2
    surf = Surface.build(Grid.from_dense(lab, spacing_mm=0.5, origin_mm=(-2.0, 1.0, 3.5)),
                         np.array([[0, 0, 0], [230, 220, 190], [200, 50, 40]], np.uint8))
    return surf.arrays()


@pytest.mark.parametrize("suffix", [".ply", ".vtp", ".PLY"])
def test_round_trip(tmp_path, mesh, suffix):
    pos, nrm, col, tris = mesh
    path = write_mesh(tmp_path / f"surface{suffix}", pos, tris, nrm=nrm, col=col)
    back = (read_ply if suffix.lower() == ".ply" else read_vtp)(path)
    np.testing.assert_array_equal(back["pos"], pos)
    np.testing.assert_array_equal(back["nrm"], nrm)
    np.testing.assert_array_equal(back["col"], col)
    np.testing.assert_array_equal(back["tris"], tris)


@pytest.mark.parametrize("writer,reader", [(write_ply, read_ply), (write_vtp, read_vtp)])
def test_optional_attributes_and_rgb(tmp_path, mesh, writer, reader):
    pos, nrm, col, tris = mesh
    back = reader(writer(tmp_path / "a", pos, tris))
    assert "nrm" not in back and "col" not in back
    np.testing.assert_array_equal(back["tris"], tris)
    back = reader(writer(tmp_path / "b", pos, tris, col=col[:, :3]))
    np.testing.assert_array_equal(back["col"][:, :3], col[:, :3])
    assert (back["col"][:, 3] == 255).all()


@pytest.mark.parametrize("writer,reader", [(write_ply, read_ply), (write_vtp, read_vtp)])
def test_empty_mesh(tmp_path, writer, reader):
    back = reader(writer(tmp_path / "e", np.zeros((0, 3)), np.zeros((0, 3), int)))
    assert back["pos"].shape == (0, 3) and back["tris"].shape == (0, 3)


def test_ply_layout(tmp_path):
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    path = write_ply(tmp_path / "t.ply", pos, [[0, 1, 2]])
    data = path.read_bytes()
    head, body = data.split(b"end_header\n")
    assert head.startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert b"element vertex 3" in head and b"element face 1" in head
    assert b"property list uchar int vertex_indices" in head
    assert len(body) == 3 * 12 + (1 + 12)
    assert np.frombuffer(body[:36], "<f4").tolist() == pos.reshape(-1).tolist()
    assert body[36] == 3 and np.frombuffer(body[37:], "<i4").tolist() == [0, 1, 2]


def test_vtp_layout(tmp_path, mesh):
    pos, nrm, col, tris = mesh
    root = ET.parse(write_vtp(tmp_path / "t.vtp", pos, tris, nrm=nrm, col=col)).getroot()
    assert root.get("type") == "PolyData" and root.get("header_type") == "UInt64"
    piece = root.find("PolyData/Piece")
    assert int(piece.get("NumberOfPoints")) == len(pos)
    assert int(piece.get("NumberOfPolys")) == len(tris)
    assert root.find("PolyData/Piece/PointData").get("Normals") == "Normals"
    offs = [el for el in piece.findall("Polys/DataArray") if el.get("Name") == "offsets"][0]
    raw = base64.b64decode(offs.text.strip())
    assert np.frombuffer(raw[:8], "<u8")[0] == 8 * len(tris)
    np.testing.assert_array_equal(np.frombuffer(raw[8:], "<i8"), 3 * np.arange(1, len(tris) + 1))


def test_unknown_suffix_is_a_clear_error(tmp_path, mesh):
    pos, nrm, col, tris = mesh
    with pytest.raises(BonesimError, match="unknown mesh format '.stl'"):
        write_mesh(tmp_path / "x.stl", pos, tris)
    with pytest.raises(BonesimError, match="no suffix"):
        write_mesh(tmp_path / "x", pos, tris)
    assert not (tmp_path / "x.stl").exists()


def test_bad_arrays(tmp_path):
    pos = np.zeros((3, 3))
    with pytest.raises(ValueError):
        write_ply(tmp_path / "a.ply", pos, [[0, 1, 3]])
    with pytest.raises(ValueError):
        write_ply(tmp_path / "a.ply", np.zeros((3, 2)), [[0, 1, 2]])
    with pytest.raises(ValueError):
        write_vtp(tmp_path / "a.vtp", pos, [[0, 1, 2]], nrm=np.zeros((2, 3)))
    with pytest.raises(ValueError):
        write_vtp(tmp_path / "a.vtp", pos, [[0, 1, 2]], col=np.full((3, 3), 300))
    with pytest.raises(ValueError):
        write_ply(tmp_path / "a.ply", pos, [[0.0, 1.0, 2.0]])


def test_readers_reject_other_files(tmp_path):
    p = tmp_path / "n.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(BonesimError, match="not supported"):
        read_ply(p)
    q = tmp_path / "n.vtp"
    q.write_text("not xml")
    with pytest.raises(BonesimError):
        read_vtp(q)
