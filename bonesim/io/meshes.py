"""Triangle-mesh files: binary PLY and VTK XML PolyData (.vtp), by hand.

Both writers take the arrays of :meth:`bonesim.engine.surface.Surface.arrays`:

* ``pos`` (n, 3) vertex positions [mm], case frame, axis order ``(x, y, z)``;
* ``tris`` (m, 3) integer vertex indices per triangle, counter-clockwise seen
  from outside;
* ``nrm`` (n, 3) optional unit vertex normals;
* ``col`` (n, 3) or (n, 4) optional uint8 RGB(A) vertex colours.

Files are written with numpy only (no VTK import: only ``bonesim/render/``
may import VTK). The readers are small and read what the writers write (and
similar files), which is what the tests and round trips need.

* PLY: ``format binary_little_endian 1.0``; vertex properties ``x y z``
  (float), ``nx ny nz`` (float), ``red green blue alpha`` (uchar); faces as
  ``property list uchar int vertex_indices``.
* VTP: ``VTKFile type="PolyData" version="1.0" header_type="UInt64"``, every
  DataArray ``format="binary"`` (base64 of a UInt64 byte count followed by
  the little-endian data, one stream); points Float32, normals
  ``Normals`` Float32, colours ``RGBA`` UInt8, polys as Int64
  ``connectivity`` / ``offsets``.
"""
from __future__ import annotations

import base64
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError

__all__ = ["write_mesh", "write_ply", "write_vtp", "read_ply", "read_vtp", "MESH_SUFFIXES"]

#: Suffixes understood by :func:`write_mesh`.
MESH_SUFFIXES = (".ply", ".vtp")


def _check(pos, tris, nrm, col):
    pos = np.asarray(pos)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"pos must have shape (n, 3), got {pos.shape}")
    pos = np.ascontiguousarray(pos, dtype="<f4")
    if not np.isfinite(pos).all():
        raise ValueError("pos holds non-finite coordinates")
    n = pos.shape[0]
    tris = np.asarray(tris)
    if tris.size == 0:
        tris = np.zeros((0, 3), dtype=np.int64)
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise ValueError(f"tris must have shape (m, 3), got {tris.shape}")
    if not np.issubdtype(tris.dtype, np.integer):
        raise ValueError(f"tris must hold integer vertex indices, got {tris.dtype}")
    if tris.size and (tris.min() < 0 or tris.max() >= n):
        raise ValueError(f"tris index vertices outside [0, {n})")
    if nrm is not None:
        nrm = np.asarray(nrm)
        if nrm.shape != (n, 3):
            raise ValueError(f"nrm must have shape ({n}, 3), got {nrm.shape}")
        nrm = np.ascontiguousarray(nrm, dtype="<f4")
    if col is not None:
        col = np.asarray(col)
        if col.ndim != 2 or col.shape[0] != n or col.shape[1] not in (3, 4):
            raise ValueError(f"col must have shape ({n}, 3) or ({n}, 4), got {col.shape}")
        if not np.issubdtype(col.dtype, np.integer) or (col.size and (col.min() < 0
                                                                       or col.max() > 255)):
            raise ValueError("col must hold integers in [0, 255]")
        if col.shape[1] == 3:
            col = np.concatenate([col, np.full((n, 1), 255)], axis=1)
        col = np.ascontiguousarray(col, dtype=np.uint8)
    return pos, tris, nrm, col


# ------------------------------------------------------------------------ PLY
def write_ply(path, pos, tris, nrm=None, col=None) -> Path:
    """Write a binary little-endian PLY file.

    Parameters
    ----------
    path : str or Path
        Output file.
    pos : (n, 3) float array_like
        Vertex positions [mm].
    tris : (m, 3) int array_like
        Vertex indices of each triangle.
    nrm : (n, 3) float array_like, optional
        Unit vertex normals.
    col : (n, 3) or (n, 4) uint8 array_like, optional
        Vertex colours (alpha 255 when only RGB is given).

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    pos, tris, nrm, col = _check(pos, tris, nrm, col)
    n, m = pos.shape[0], tris.shape[0]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if nrm is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if col is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")]
    vert = np.empty(n, dtype=fields)
    for a, name in enumerate("xyz"):
        vert[name] = pos[:, a]
    if nrm is not None:
        for a, name in enumerate(("nx", "ny", "nz")):
            vert[name] = nrm[:, a]
    if col is not None:
        for a, name in enumerate(("red", "green", "blue", "alpha")):
            vert[name] = col[:, a]
    face = np.empty(m, dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"] = 3
    face["v"] = tris
    ply_type = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment bonesim surface",
              f"element vertex {n}"]
    header += [f"property {ply_type[t]} {name}" for name, t in fields]
    header += [f"element face {m}", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())
    return path


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
              "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
              "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply(path) -> dict:
    """Read a triangle mesh from a binary little-endian PLY file.

    Returns
    -------
    dict
        ``pos`` (n, 3) float32 and ``tris`` (m, 3) int64; ``nrm`` (n, 3)
        float32 and ``col`` (n, 3 or 4) uint8 when the file has them.
    """
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise BonesimError("not a PLY file", path)
    body = data.index(b"\n", end) + 1
    elements = []
    fmt = None
    for line in data[:end].decode("ascii", "replace").splitlines():
        w = line.split()
        if not w:
            continue
        if w[0] == "format":
            fmt = w[1]
        elif w[0] == "element":
            elements.append((w[1], int(w[2]), []))
        elif w[0] == "property":
            if w[1] == "list":
                elements[-1][2].append((w[4], ("list", _PLY_TYPES[w[2]], _PLY_TYPES[w[3]])))
            else:
                elements[-1][2].append((w[2], _PLY_TYPES[w[1]]))
    if fmt != "binary_little_endian":
        raise BonesimError(f"PLY format {fmt!r} is not supported (binary_little_endian only)",
                           path)
    out = {}
    off = body
    for name, count, props in elements:
        lists = [p for p in props if isinstance(p[1], tuple)]
        if not lists:
            dt = np.dtype([(p, "<" + t) for p, t in props])
            arr = np.frombuffer(data, dtype=dt, count=count, offset=off)
            off += dt.itemsize * count
            if name == "vertex":
                out["pos"] = np.stack([arr[a] for a in "xyz"], axis=1).astype(np.float32)
                if "nx" in arr.dtype.names:
                    out["nrm"] = np.stack([arr[a] for a in ("nx", "ny", "nz")],
                                          axis=1).astype(np.float32)
                chans = [c for c in ("red", "green", "blue", "alpha") if c in arr.dtype.names]
                if len(chans) >= 3:
                    out["col"] = np.stack([arr[c] for c in chans], axis=1).astype(np.uint8)
            continue
        if name != "face" or len(props) != 1:
            raise BonesimError(f"PLY element {name!r} is not supported", path)
        _, (_, tcount, tidx) = props[0]
        dt = np.dtype([("n", "<" + tcount), ("v", "<" + tidx, (3,))])
        arr = np.frombuffer(data, dtype=dt, count=count, offset=off)
        if count and (arr["n"] != 3).any():
            raise BonesimError("PLY faces that are not triangles are not supported", path)
        off += dt.itemsize * count
        out["tris"] = arr["v"].astype(np.int64).reshape(-1, 3)
    out.setdefault("tris", np.zeros((0, 3), np.int64))
    if "pos" not in out:
        raise BonesimError("PLY file has no vertex element", path)
    return out


# ------------------------------------------------------------------------ VTP
def _b64(arr) -> str:
    raw = np.ascontiguousarray(arr).tobytes()
    return base64.b64encode(np.uint64(len(raw)).astype("<u8").tobytes() + raw).decode("ascii")


def write_vtp(path, pos, tris, nrm=None, col=None) -> Path:
    """Write VTK XML PolyData (``.vtp``), inline base64 binary arrays.

    Parameters are those of :func:`write_ply`. Normals go to the point-data
    array ``Normals`` (set as the active normals), colours to ``RGBA`` (the
    active scalars; 4 UInt8 components, drawn directly as colours by VTK
    when colour mapping is off).

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    pos, tris, nrm, col = _check(pos, tris, nrm, col)
    n, m = pos.shape[0], tris.shape[0]
    conn = tris.astype("<i8").reshape(-1)
    offs = (3 * np.arange(1, m + 1)).astype("<i8")

    def arr(attrs, data):
        a = " ".join(f'{k}="{v}"' for k, v in attrs.items())
        return f'        <DataArray {a} format="binary">\n          {_b64(data)}\n        </DataArray>'

    pd_attrs = []
    pd = []
    if nrm is not None:
        pd_attrs.append('Normals="Normals"')
        pd.append(arr({"type": "Float32", "Name": "Normals", "NumberOfComponents": 3}, nrm))
    if col is not None:
        pd_attrs.append('Scalars="RGBA"')
        pd.append(arr({"type": "UInt8", "Name": "RGBA", "NumberOfComponents": 4}, col))
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" '
             'header_type="UInt64">',
             "  <PolyData>",
             f'    <Piece NumberOfPoints="{n}" NumberOfVerts="0" NumberOfLines="0" '
             f'NumberOfStrips="0" NumberOfPolys="{m}">',
             f'      <PointData {" ".join(pd_attrs)}>'.replace(" >", ">"),
             *pd,
             "      </PointData>",
             "      <Points>",
             arr({"type": "Float32", "Name": "Points", "NumberOfComponents": 3}, pos),
             "      </Points>",
             "      <Polys>",
             arr({"type": "Int64", "Name": "connectivity"}, conn),
             arr({"type": "Int64", "Name": "offsets"}, offs),
             "      </Polys>",
             "    </Piece>",
             "  </PolyData>",
             "</VTKFile>", ""]
    path.write_text("\n".join(lines), encoding="ascii")
    return path


_VTK_TYPES = {"Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2", "Int32": "i4",
              "UInt32": "u4", "Int64": "i8", "UInt64": "u8", "Float32": "f4",
              "Float64": "f8"}


def read_vtp(path) -> dict:
    """Read a triangle mesh from a ``.vtp`` file with inline binary or ascii
    arrays (no compression, no appended data) -- what :func:`write_vtp` writes.

    Returns
    -------
    dict
        As :func:`read_ply`.
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise BonesimError(f"not a VTK XML file ({exc})", path) from None
    if root.tag != "VTKFile" or root.get("type") != "PolyData":
        raise BonesimError("not a VTK XML PolyData file", path)
    if root.get("compressor"):
        raise BonesimError("compressed .vtp files are not supported", path)
    order = "<" if root.get("byte_order", "LittleEndian") == "LittleEndian" else ">"
    head = order + ("u8" if root.get("header_type") == "UInt64" else "u4")

    def values(el):
        dt = np.dtype(order + _VTK_TYPES[el.get("type")])
        text = (el.text or "").strip()
        if el.get("format") == "ascii":
            out = np.array(text.split(), dtype=dt)
        elif el.get("format") == "binary":
            raw = base64.b64decode("".join(text.split()))
            hsize = np.dtype(head).itemsize
            nbytes = int(np.frombuffer(raw[:hsize], dtype=head)[0])
            out = np.frombuffer(raw[hsize:hsize + nbytes], dtype=dt)
        else:
            raise BonesimError(f"DataArray format {el.get('format')!r} is not supported", path)
        ncomp = int(el.get("NumberOfComponents", "1"))
        return out.reshape(-1, ncomp) if ncomp > 1 else out

    piece = root.find("PolyData/Piece")
    if piece is None:
        raise BonesimError("PolyData has no Piece", path)
    out = {"pos": values(piece.find("Points/DataArray")).astype(np.float32).reshape(-1, 3)}
    for el in piece.findall("PointData/DataArray"):
        if el.get("Name") == "Normals":
            out["nrm"] = values(el).astype(np.float32)
        elif el.get("Name") == "RGBA":
            out["col"] = values(el).astype(np.uint8)
    polys = {el.get("Name"): values(el) for el in piece.findall("Polys/DataArray")}
    conn = polys.get("connectivity", np.zeros(0, np.int64)).astype(np.int64)
    offs = polys.get("offsets", np.zeros(0, np.int64)).astype(np.int64)
    if len(offs) and not (np.diff(np.r_[0, offs]) == 3).all():
        raise BonesimError("polygons that are not triangles are not supported", path)
    out["tris"] = conn.reshape(-1, 3)
    return out


# ---------------------------------------------------------------------- both
def write_mesh(path, pos, tris, nrm=None, col=None) -> Path:
    """Write a mesh, the format chosen by the file suffix (``.ply`` or ``.vtp``).

    Raises
    ------
    BonesimError
        For any other suffix.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return write_ply(path, pos, tris, nrm=nrm, col=col)
    if suffix == ".vtp":
        return write_vtp(path, pos, tris, nrm=nrm, col=col)
    raise BonesimError(f"unknown mesh format {path.suffix or '(no suffix)'!r}; "
                       f"use one of {', '.join(MESH_SUFFIXES)}", path)
