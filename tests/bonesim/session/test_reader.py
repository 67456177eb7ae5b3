"""Damaged session files: cut short, zeroed, left open, empty, not HDF5, newer
schema. Each reads its readable part or gives one clear line, and nothing
waits on a file no writer holds."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest

from bonesim.session import schema, writer
from bonesim.cli.main import main
from bonesim.errors import BonesimError
from bonesim.session.writer import SessionWriter
from bonesim.session.header import make_header
from bonesim.session.replay import verify
from bonesim.session.reader import damage_notice, read_session, repair_session
from bonesim.session.disk_guard import lookup3
from bonesim.session.salvage import read_superblock
from bonesim.runtime.simulate import run_trajectory
from tests.bonesim.runtime.test_record import model, traj  # noqa: F401 (fixtures: an 8 s demo run)

#: Rows per compacted chunk in these tests (an 8 s run spans 16 chunks).
SMALL_CHUNKS = 512


@pytest.fixture(scope="module")
def compacted(model, traj, tmp_path_factory):
    """A closed, compacted 8 s recording in chunks of SMALL_CHUNKS rows."""
    path = tmp_path_factory.mktemp("damaged") / "run.h5"
    mp = pytest.MonkeyPatch()
    mp.setattr(writer, "COMPACT_CHUNK_ROWS", SMALL_CHUNKS)
    try:
        run_trajectory(model, traj, surface=False, record=path, header=make_header(model))
    finally:
        mp.undo()
    return path


def _cut(src, dst, size):
    shutil.copy(src, dst)
    os.truncate(dst, size)
    return dst


# ------------------------------------------------------------------ checksum
def test_lookup3_matches_jenkins_and_hdf5():
    # Bob Jenkins' own test vectors (lookup3.c, driver5)
    assert lookup3(b"") == 0xDEADBEEF
    assert lookup3(b"", 0xDEADBEEF) == 0xBD5B7DDE
    assert lookup3(b"Four score and seven years ago") == 0x17770551
    assert lookup3(b"Four score and seven years ago", 1) == 0xCD628161


def test_superblock_checksum_and_cleared_flags(model, tmp_path):
    w = SessionWriter(tmp_path / "live.h5", make_header(model), compact=False)
    w.append("samples", {"t_s": np.arange(10) * 1e-3})
    w.flush()
    sb = read_superblock(tmp_path / "live.h5")
    assert sb.version == 3 and sb.flags != 0              # open for SWMR writing
    assert int.from_bytes(sb.raw[-4:], "little") == lookup3(sb.raw[:-4])
    clean = sb.cleared()
    assert clean[11] == 0 and int.from_bytes(clean[-4:], "little") == lookup3(clean[:-4])
    w.close()


# ------------------------------------------------------------------ cut short
def test_cut_short_reads_one_consistent_prefix(compacted, tmp_path):
    whole = read_session(compacted)
    assert whole.damage is None and whole.complete
    size = compacted.stat().st_size
    with h5py.File(compacted, "r") as f:     # the recorded case comes first
        start = sum(f["model"][k].id.get_storage_size() for k in f["model"])
    seen = []
    for frac in (0.35, 0.6, 0.85, 0.97):
        cut = start + int((size - start) * frac)
        s = read_session(_cut(compacted, tmp_path / f"c{frac}.h5", cut))
        assert s.carries_model              # a file cut short still rebuilds its model
        assert not s.complete and "cut short" in s.damage and s.readable
        n = len(s.samples["t_s"])
        seen.append(n)
        # a prefix of the whole: the same rows, every stream to one moment
        for k, a in s.samples.items():
            np.testing.assert_array_equal(a, whole.samples[k][:n])
        m = len(s.removals["t_s"])
        np.testing.assert_array_equal(s.removals["ijk"], whole.removals["ijk"][:m])
        assert m == 0 or s.removals["t_s"][-1] <= s.samples["t_s"][-1]
        report = verify(s)                 # replaying the prefix gives its removals
        assert report["identical"], report
        # ... but it is not the run the file declares: not ok, and it says so
        assert not report["ok"] and "readable" in report["short"]
        assert report["samples_checked"] == n < report["samples_declared"]
        assert damage_notice(s).startswith(f"{s.path}: damaged (cut short")
    assert seen == sorted(seen) and seen[0] < seen[-1] < len(whole.samples["t_s"])


_NEVER_HANGS = textwrap.dedent("""
    import os, shutil, sys
    from bonesim.errors import BonesimError
    from bonesim.session.reader import read_session
    src, out = sys.argv[1], sys.argv[2]
    size = os.path.getsize(src)
    for cut in sorted({0, 4, 8, 47, 48, 100, 1000, 4096} | set(range(1, size, size // 40))):
        shutil.copy(src, out)
        os.truncate(out, cut)
        try:
            s = read_session(out)
            print(cut, "read", len(s.samples["t_s"]), s.damage is not None)
        except BonesimError as exc:
            msg = str(exc)
            assert "\\n" not in msg and msg.startswith(out), msg
            print(cut, "error", msg)
""")


def test_every_cut_reads_or_says_why_and_never_hangs(compacted, tmp_path):
    res = subprocess.run([sys.executable, "-c", _NEVER_HANGS, str(compacted),
                          str(tmp_path / "cut.h5")], capture_output=True, text=True,
                         timeout=240)
    assert res.returncode == 0, res.stderr[-2000:]
    lines = [ln.split(" ", 2) for ln in res.stdout.splitlines()]
    assert len(lines) > 40
    by_cut = {int(c): (what, rest) for c, what, rest in lines}
    assert by_cut[0] == ("error", f"{tmp_path / 'cut.h5'}: empty file (0 bytes): nothing "
                                  "was recorded in it")
    assert by_cut[4][0] == "error" and "not an HDF5 file" in by_cut[4][1]
    reads = [int(r.split()[0]) for w, r in by_cut.values() if w == "read"]
    assert reads and max(reads) > 0                       # most cuts keep something


# ------------------------------------------------------------------ zeroed
def test_zeroed_blocks_read_or_say_why(compacted, tmp_path):
    whole = read_session(compacted)
    size = compacted.stat().st_size
    outcomes = set()
    for frac in (0.1, 0.3, 0.5, 0.7, 0.9):
        p = tmp_path / f"z{frac}.h5"
        shutil.copy(compacted, p)
        with open(p, "r+b") as f:
            f.seek(int(size * frac))
            f.write(bytes(min(4096, size // 10)))
        try:
            s = read_session(p)
        except BonesimError as exc:
            assert str(exc).startswith(str(p)) and "\n" not in str(exc)
            outcomes.add("error")
            continue
        n = len(s.samples["t_s"])
        for k, a in s.samples.items():
            if s.damage is None:
                np.testing.assert_array_equal(a, whole.samples[k])
        outcomes.add("damaged" if s.damage else "intact")
        if s.damage:
            report = verify(s)
            assert not report["ok"] and report["short"]
            if n == 0:                            # the /samples group itself is lost
                assert "nothing to verify" in report["short"]
            else:                                 # what is readable replays identically
                assert report["identical"] and n <= len(whole.samples["t_s"])
    assert "damaged" in outcomes


# ------------------------------------------------------------- live files
def test_raw_file_cut_short_and_writer_left_it_open(model, tmp_path):
    """A live writer's raw (uncompressed) file, copied while it grew."""
    w = SessionWriter(tmp_path / "live.h5", make_header(model), compact=False)
    t = np.arange(20000) * 1e-3
    for r0 in range(0, len(t), 2500):
        w.append("samples", {"t_s": t[r0:r0 + 2500], "drill": np.ones(2500, np.uint8)})
        w.flush()
    shutil.copy(tmp_path / "live.h5", tmp_path / "open.h5")      # as a crash leaves it
    w.close()
    s = read_session(tmp_path / "open.h5")
    assert not s.complete and "left open" in s.damage
    np.testing.assert_array_equal(s.samples["t_s"], t)
    cut = _cut(tmp_path / "open.h5", tmp_path / "open_cut.h5",
               int((tmp_path / "open.h5").stat().st_size * 0.6))
    s = read_session(cut)
    assert "cut short" in s.damage and "left open" in s.damage
    n = len(s.samples["t_s"])
    assert 0 < n < len(t)
    np.testing.assert_array_equal(s.samples["t_s"], t[:n])


# --------------------------------------------------------- other bad files
def test_empty_not_hdf5_and_newer_schema(model, tmp_path):
    (tmp_path / "empty.h5").write_bytes(b"")
    with pytest.raises(BonesimError, match=r"empty\.h5: empty file \(0 bytes\)"):
        read_session(tmp_path / "empty.h5")
    (tmp_path / "text.h5").write_text("t_s,x\n0,1\n")
    with pytest.raises(BonesimError, match=r"text\.h5: not an HDF5 file"):
        read_session(tmp_path / "text.h5")
    with SessionWriter(tmp_path / "new.h5", make_header(model), compact=False):
        pass
    with h5py.File(tmp_path / "new.h5", "r+") as f:
        f.attrs["schema"] = schema.SCHEMA_VERSION + 1
    with pytest.raises(BonesimError, match="newer than this bonesim reads"):
        read_session(tmp_path / "new.h5")


# ------------------------------------------------------------------ repair
def test_repair_writes_the_readable_part_as_a_clean_file(compacted, tmp_path, capsys):
    cut = _cut(compacted, tmp_path / "cut.h5", int(compacted.stat().st_size * 0.6))
    damaged = read_session(cut)
    fixed = repair_session(cut, tmp_path / "fixed.h5")
    assert fixed.damage is None and fixed.complete
    assert fixed.repaired == {"from": str(cut), "damage": damaged.damage}
    for k, a in damaged.samples.items():
        np.testing.assert_array_equal(fixed.samples[k], a)
    np.testing.assert_array_equal(fixed.removals["ijk"], damaged.removals["ijk"])
    assert fixed.header == damaged.header and verify(fixed)["ok"]
    with pytest.raises(BonesimError, match="must be a new file"):
        repair_session(cut, cut)
    assert main(["sessions", "repair", str(cut), str(tmp_path / "again.h5"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["complete"] and info["repaired_from"]["from"] == str(cut)
    assert main(["sessions", "repair", str(cut), str(tmp_path / "again.h5")]) == 2
    assert "exists" in capsys.readouterr().err


# --------------------------------------------------------------------- CLI
def test_commands_on_a_damaged_file_say_so_in_one_line(compacted, tmp_path):
    folder = tmp_path / "sessions"
    folder.mkdir()
    shutil.copy(compacted, folder / "good.h5")
    cut = _cut(compacted, folder / "cut.h5", int(compacted.stat().st_size * 0.6))
    (folder / "empty.h5").write_bytes(b"")

    def run(*args):
        return subprocess.run([sys.executable, "-m", "bonesim", *args],
                              capture_output=True, text=True, timeout=180)

    info = run("sessions", "info", str(cut))
    assert info.returncode == 1 and "damage: cut short" in info.stdout
    assert "readable: samples" in info.stdout and "Traceback" not in info.stderr
    assert info.stderr.strip().count("\n") == 0 and "damaged (cut short" in info.stderr
    rep = run("replay", "--verify", str(cut))
    # what it holds replays identically, but less than the run it declares: non-zero
    assert rep.returncode == 1 and "identical" in rep.stdout and "checked" in rep.stdout
    lines = rep.stderr.strip().splitlines()
    assert len(lines) == 2 and "damaged (cut short" in lines[0]
    assert "not verified in full" in lines[1] and "Traceback" not in rep.stderr
    lst = run("sessions", "list", str(folder), "--json")
    rows = {os.path.basename(r["file"]): r for r in json.loads(lst.stdout)["sessions"]}
    assert rows["good.h5"]["damage"] is None and rows["cut.h5"]["damage"]
    assert "empty file" in rows["empty.h5"]["error"]
    bad = run("sessions", "info", str(folder / "empty.h5"))
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0
    assert "empty file" in bad.stderr and "Traceback" not in bad.stderr


def test_playback_of_a_damaged_file_ends_with_its_readable_part(compacted, tmp_path):
    from bonesim.session.playback import Player

    cut = _cut(compacted, tmp_path / "cut.h5", int(compacted.stat().st_size * 0.6))
    s = read_session(cut)
    p = Player(s, surface=False)
    p.seek(float(s.samples["t_s"][0]))
    before = p.grid.density.copy()
    p.seek(float(s.samples["t_s"][-1]))
    emptied = (before > 0) & (p.grid.density == 0)
    # the tissue at the end lost exactly the removals kept, nothing more
    kept = {tuple(v) for v in s.removals["ijk"].tolist()}
    assert int(emptied.sum()) == len(kept) > 0
    assert all(p.grid.density_at(*v) == 0 for v in kept)
