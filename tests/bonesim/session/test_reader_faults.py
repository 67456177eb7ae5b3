"""The fault matrix of session files (issue 24): a flipped bit anywhere, a cut
anywhere, in the raw file a crash leaves and in the compacted one, is found
and named or harmless; never data silently different, never a traceback.
A corrupt header is called corrupt (never "the case files changed", never
"identical"); one bad dataset loses that dataset only; a compaction's
leftover is never read as a session; verify fails with nothing or less than
the file declares."""
from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from bonesim.cli.main import main
from bonesim.errors import BonesimError
from bonesim.session.schema import SCHEMA_VERSION
from bonesim.session.writer import compaction_temp
from bonesim.session.reader import list_sessions, read_session, repair_session, session_info
from bonesim.session.replay import coverage, verify
from tests.bonesim.session.fault_files import ROWS, cut, flip_bit, write_synthetic

#: Offsets tried per file: every byte of the first 4 KiB (superblock, root
#: object header, the header attribute) at a stride, then spread over the rest.
N_SPREAD = 110


@pytest.fixture(scope="module", params=["raw", "compacted"])
def synthetic(request, tmp_path_factory):
    path = tmp_path_factory.mktemp(request.param) / "run.h5"
    data = write_synthetic(path, compact=request.param == "compacted", chunk_rows=2048)
    return path, data


def _same_as_written(s, data) -> bool:
    for g in ("samples", "tissue", "camera"):
        got = getattr(s, g)
        for k, a in data[g].items():
            if not np.array_equal(got[k], a):
                return False
    return True


def _offsets(size: int) -> list[int]:
    head = list(range(0, min(size, 4096), 53))
    rest = np.linspace(4096, size - 1, N_SPREAD).astype(int).tolist() if size > 4096 else []
    return head + rest


def test_synthetic_file_reads_back_whole_with_checksums(synthetic):
    path, data = synthetic
    s = read_session(path)
    assert s.schema == SCHEMA_VERSION == 4 and s.complete and s.damage is None
    assert s.checksums and s.header_ok and not s.lost
    assert _same_as_written(s, data)
    with h5py.File(path, "r") as f:        # every chunked column carries Fletcher32
        for g in ("samples", "tissue", "camera", "events"):
            for name, ds in f[g].items():
                assert ds.fletcher32, f"/{g}/{name}"
        assert "header_sha256" in f.attrs


def test_every_bit_flip_is_found_or_harmless(synthetic, tmp_path):
    """One bit flipped at each of a few hundred offsets: the file reads the
    same as written, or says what is damaged, or is refused in one line."""
    path, data = synthetic
    outcomes = {"same": 0, "damage named": 0, "refused": 0}
    for q, off in enumerate(_offsets(path.stat().st_size)):
        bad = flip_bit(path, tmp_path / f"f{q}.h5", off, bit=q % 8)
        try:
            s = read_session(bad)
        except BonesimError as exc:
            assert "\n" not in str(exc)
            outcomes["refused"] += 1
            continue
        if s.damage is not None:
            outcomes["damage named"] += 1
            assert not s.complete or not s.header_ok or s.lost
        else:
            assert _same_as_written(s, data), f"flip at byte {off} changed data silently"
            assert s.header_ok and s.complete
            outcomes["same"] += 1
        bad.unlink()
    print(path.parent.name, outcomes)
    assert outcomes["damage named"] + outcomes["refused"] > 20


def _header_offset(path, needle: bytes) -> int:
    raw = path.read_bytes()
    assert raw.count(needle) == 1
    return raw.index(needle) + len(needle) - 1


@pytest.mark.parametrize("field, needle, bit", [
    ("voxel_mm", b'"voxel_mm": 0.5', 0),            # 0.5 -> 0.4
    ("oversample", b'"oversample": 2', 0),          # 2 -> 3
])
def test_a_flip_in_the_header_is_header_corruption(synthetic, tmp_path, capsys, field,
                                                   needle, bit):
    path, _ = synthetic
    bad = flip_bit(path, tmp_path / f"{field}.h5", _header_offset(path, needle), bit)
    s = read_session(bad)
    assert not s.header_ok and "header is corrupt" in s.damage
    assert s.header[field] != read_session(path).header[field]      # the flip is there
    with pytest.raises(BonesimError, match="header is corrupt") as err:
        s.burr_models()
    assert "changed since the recording" not in str(err.value)
    assert main(["sessions", "info", str(bad)]) == 1
    out = capsys.readouterr()
    assert "header_ok: False" in out.out and "header is corrupt" in out.err
    assert main(["replay", str(bad), "--verify"]) == 2
    err = capsys.readouterr().err
    assert "header is corrupt" in err and "identical" not in err
    assert main(["sessions", "repair", str(bad), str(tmp_path / f"{field}-fixed.h5")]) == 2
    assert "header is corrupt" in capsys.readouterr().err
    assert not (tmp_path / f"{field}-fixed.h5").exists()


def _chunk_offset(path, dataset: str, row: int) -> tuple[int, int]:
    with h5py.File(path, "r") as f:
        ds = f[dataset]
        info = ds.id.get_chunk_info_by_coord((row,) + (0,) * (ds.ndim - 1))
        return info.byte_offset, info.size


@pytest.mark.parametrize("dataset", ["samples/force_n", "samples/pos_mm", "tissue/ijk",
                                     "camera/eye_mm"])
def test_a_flip_in_a_chunk_is_named(synthetic, tmp_path, dataset):
    """A flipped bit in any chunk of any column fails that chunk's Fletcher32
    checksum (raw and compressed): the damage names the column and rows, and
    the readable part ends before the chunk."""
    path, data = synthetic
    with h5py.File(path, "r") as f:
        row = min(4096, f[dataset].shape[0] - 1)
        r0 = row // f[dataset].chunks[0] * f[dataset].chunks[0]
    off, size = _chunk_offset(path, dataset, row)
    bad = flip_bit(path, tmp_path / "chunk.h5", off + size // 3, 3)
    s = read_session(bad)
    assert s.damage is not None and f"/{dataset}: rows {r0:,}-" in s.damage
    assert "fail their checksum" in s.damage
    g, col = dataset.split("/")
    if dataset == "samples/force_n":
        # a column a replay does not need: that chunk's rows read as NaN, the rest goes on
        assert s.holes == ["/samples/force_n"] and "(NaN there)" in s.damage
        assert len(s.samples["t_s"]) == ROWS["samples"]
        f = s.samples["force_n"]
        step = h5py.File(path, "r")[dataset].chunks[0]
        assert np.isnan(f[r0:r0 + step]).all()
        keep = np.ones(len(f), bool)
        keep[r0:r0 + step] = False
        np.testing.assert_array_equal(f[keep], data["samples"]["force_n"][keep])
        assert "fail their checksum" in coverage(s)["short"]
        assert session_info(s)["columns_with_holes"] == ["/samples/force_n"]
        return
    assert len(getattr(s, g)["t_s"]) <= r0          # the readable part ends before it
    if g == "samples":
        assert "readable" in coverage(s)["short"]


def test_one_bad_dataset_loses_that_dataset_not_the_file(synthetic, tmp_path):
    path, data = synthetic
    with h5py.File(path, "r") as f:
        addr = h5py.h5o.get_info(f["samples/force_n"].id).addr
    bad = flip_bit(path, tmp_path / "meta.h5", addr + 12, 2)    # its object header
    s = read_session(bad)
    assert s.lost == ["/samples/force_n"] and "force_n unreadable" in s.damage
    assert np.isnan(s.samples["force_n"]).all()
    n = len(s.samples["t_s"])
    assert n == ROWS["samples"]                    # every other column reads whole
    for k, a in data["samples"].items():
        if k != "force_n":
            np.testing.assert_array_equal(s.samples[k], a)
    np.testing.assert_array_equal(s.tissue["ijk"], data["tissue"]["ijk"])
    assert session_info(s)["lost_columns"] == ["/samples/force_n"]
    with pytest.raises(BonesimError, match="force_n lost"):
        repair_session(bad, tmp_path / "meta-fixed.h5")
    assert coverage(s)["short"] == "/samples/force_n lost"


@pytest.mark.parametrize("fraction", [0.02, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99])
def test_every_cut_keeps_a_true_prefix_or_says_why(synthetic, tmp_path, fraction):
    path, data = synthetic
    size = path.stat().st_size
    bad = cut(path, tmp_path / "cut.h5", int(size * fraction))
    try:
        s = read_session(bad)
    except BonesimError as exc:
        assert "\n" not in str(exc)
        return
    assert s.damage is not None and not s.complete
    for g in ("samples", "tissue", "camera"):
        got = getattr(s, g)
        n = len(got["t_s"])
        for k, a in data[g].items():                 # what is kept is what was written
            np.testing.assert_array_equal(got[k], a[:n])
    n = len(s.samples["t_s"])
    cov = coverage(s)
    assert cov["samples_checked"] == n
    if n < ROWS["samples"]:
        assert cov["short"] is not None


def test_nothing_to_verify_fails_and_repair_refuses(synthetic, tmp_path, capsys):
    path, _ = synthetic
    bad = cut(path, tmp_path / "head.h5", 6000)
    try:
        s = read_session(bad)
    except BonesimError:
        return                                      # refused outright: also not "ok"
    assert len(s.samples["t_s"]) == 0
    report = verify(s)
    assert not report["ok"] and "nothing to verify" in report["short"]
    assert main(["replay", str(bad), "--verify", "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is False and out["samples_checked"] == 0
    assert main(["sessions", "repair", str(bad), str(tmp_path / "h.h5")]) == 2
    assert "nothing readable to repair" in capsys.readouterr().err


def test_a_compaction_leftover_is_never_read_as_a_session(synthetic, tmp_path):
    path, _ = synthetic
    folder = tmp_path / "sessions"
    folder.mkdir()
    target = folder / "run.h5"
    target.write_bytes(path.read_bytes())
    stray = compaction_temp(target)
    cut(path, stray, path.stat().st_size // 2)
    with pytest.raises(BonesimError, match="leftover of an interrupted compaction of run.h5"):
        read_session(stray)
    rows = {r["file"]: r for r in list_sessions(folder)}
    assert "leftover" in rows[str(stray)]["error"] and "error" not in rows[str(target)]


@pytest.mark.parametrize("how", ["backwards", "nan"])
def test_sample_times_out_of_order_are_damage(tmp_path, how):
    """Sample times that go backwards (or turn NaN) end the readable part
    there: named, never replayed or scored as they are."""
    path = tmp_path / "order.h5"
    data = write_synthetic(path, compact=False)
    with h5py.File(path, "r+") as f:
        f["samples/t_s"][5000] = 1.0 if how == "backwards" else np.nan
    s = read_session(path)
    assert "/samples/t_s: sample time" in s.damage and "at row 5,000" in s.damage
    assert len(s.samples["t_s"]) == 5000 and np.all(np.diff(s.samples["t_s"]) > 0)
    assert s.readable["samples"] == (5000, ROWS["samples"])
    assert coverage(s)["short"] is not None
    np.testing.assert_array_equal(s.samples["pos_mm"], data["samples"]["pos_mm"][:5000])


def _as_schema_2(src, dst):
    """``src`` rewritten as bonesim wrote files before checksums (schema 2):
    the same columns, no Fletcher32, no ``header_sha256``."""
    with h5py.File(src, "r") as f, h5py.File(dst, "w", libver="latest") as g:
        for k, v in f.attrs.items():
            if k != "header_sha256":
                g.attrs[k] = v
        g.attrs["schema"] = 2
        for name, item in f.items():
            if isinstance(item, h5py.Group):
                grp = g.create_group(name)
                for col, ds in item.items():
                    grp.create_dataset(col, data=ds[()], maxshape=(None,) + ds.shape[1:],
                                       chunks=True)
            else:
                g.create_dataset(name, data=item[()])
    return dst


def test_files_written_before_checksums_still_open(synthetic, tmp_path, capsys):
    path, data = synthetic
    old = _as_schema_2(path, tmp_path / "v2.h5")
    s = read_session(old)
    assert s.schema == 2 and not s.checksums and s.header_ok and s.damage is None
    assert s.complete and _same_as_written(s, data)
    assert main(["sessions", "info", str(old), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["checksums"] == "none (schema 2)" and info["header_ok"] is True
    fixed = repair_session(old, tmp_path / "v3.h5")       # a copy in the current schema
    assert fixed.schema == SCHEMA_VERSION and fixed.checksums and _same_as_written(fixed, data)
