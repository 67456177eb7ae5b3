"""Throw hostile inputs at every ``bonesim`` command that takes a file and
report, one row each, what happened: exit status, a traceback or not, and the
last line on stderr.

Run from a checkout (``python scripts/hostile_inputs.py [--mem-gb 3]``): every
command runs in a subprocess under an address-space cap (RLIMIT_AS) and a
time-out, so a hostile size cannot take the machine down. A row is "ok" when
the command exits non-zero with one line and no traceback.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = (ROOT / "ct_cases" / "phantom" / "case.toml").read_text()
TRAJ_HEAD = "t_s,x_mm,y_mm,z_mm,axis_x,axis_y,axis_z,drill,speed_rpm\n"
TRAJ_ROW = "{t},{x},0,0,0,0,-1,1,{rpm}\n"


def _case(d: Path, name: str, old: str, new: str, raw: bytes | None = None) -> str:
    path = d / name / "case.toml"
    path.parent.mkdir()
    path.write_bytes(raw if raw is not None else PHANTOM.replace(old, new).encode())
    return str(path)


def _traj(d: Path, name: str, rows) -> str:
    path = d / name
    path.write_text(TRAJ_HEAD + "".join(TRAJ_ROW.format(t=t, x=x, rpm=r) for t, x, r in rows))
    return str(path)


def _big_traj(d: Path, rows: int = 2_000_000) -> str:
    """A long trajectory (2 million rows, 2000 s at 1 kHz, ~90 MB) whose last
    row has a negative speed: read whole (in chunks, with progress), then refused."""
    path = d / "big.csv"
    with open(path, "w") as fh:
        fh.write(TRAJ_HEAD)
        block = 100_000
        for k in range(0, rows, block):
            fh.write("".join(f"{i / 1000:.3f},{20 + (i % 100) / 100:.2f},0,0,0,0,-1,1,60000\n"
                             for i in range(k, k + block)))
        fh.write(f"{rows / 1000:.3f},20,0,0,0,0,-1,1,-5\n")
    return str(path)


def _file(d: Path, name: str, data: bytes) -> str:
    path = d / name
    path.write_bytes(data)
    return str(path)


def cases(d: Path) -> list[tuple[str, list[str], dict]]:
    """``(row name, argv, extra environment)`` for every hostile input."""
    ok_traj = _traj(d, "ok.csv", [(0, 0, 60000), (0.01, 0, 60000)])
    binary = bytes(range(256)) * 8
    burr = ("[burr]\nkind = \"cutting\"\ndiameter_mm = {d}\n")
    rows = []
    for name, old, new in (
            ("case voxel_mm = nan", "voxel_mm = 0.5", "voxel_mm = nan"),
            ("case voxel_mm = 0.01", "voxel_mm = 0.5", "voxel_mm = 0.01"),
            ("case size_mm 5200", "size_mm = [52.0, 52.0, 52.0]", "size_mm = [5200.0, 5200.0, 5200.0]"),
            ("case size_mm inf", "size_mm = [52.0, 52.0, 52.0]", "size_mm = [inf, 52.0, 52.0]"),
            ("case seed = nan", "seed = 7", "seed = nan"),
            ("case origin_mm nan", "size_mm = [52.0", "origin_mm = [nan, 0.0, 0.0]\nsize_mm = [52.0"),
            ("case origin_mm 1e300", "size_mm = [52.0", "origin_mm = [1e300, 0.0, 0.0]\nsize_mm = [52.0"),
            ("case box_mm nan", "box_mm = [[7.0", "box_mm = [[nan")):
        slug = name.replace(" ", "_").replace("=", "").replace(".", "")
        rows.append((name, ["case-info", _case(d, slug, old, new)], {}))
        if "voxel" in name or "size" in name:
            rows.append((name + " (simulate)", ["simulate", "--case", _case(d, slug + "_s", old, new),
                                                "--trajectory", ok_traj], {}))
    rows.append(("case non-UTF-8", ["case-info", _case(d, "latin", "", "", PHANTOM.replace(
        "Procedural", "Proc\u00e9dural").encode("latin-1"))], {}))
    rows.append(("case binary", ["case-info", _case(d, "binary", "", "", binary)], {}))
    rows.append(("--voxel-mm nan", ["case-info", "phantom", "--voxel-mm", "nan"], {}))
    family = (ROOT / "burrs" / "cutting.toml").read_text()
    for d_mm in ("200.0", "1e300"):
        text = family.replace("[[burr]]\ndiameter_mm = 1.0", f"[[burr]]\ndiameter_mm = {d_mm}", 1)
        rows.append((f"burr family diameter_mm = {d_mm}", ["simulate", "--burr", _file(
            d, f"fam_{d_mm}.toml", text.encode()) + f"#cutting-{float(d_mm):g}mm",
            "--trajectory", ok_traj], {}))
    stack = d / "label-stack"                     # the phantom as a label stack
    subprocess.run([sys.executable, "-m", "bonesim", "case-export", "phantom", "--format",
                    "label-stack", str(stack)], capture_output=True,
                   env=dict(os.environ, PYTHONPATH=str(ROOT)))
    if (stack / "case.toml").is_file():
        text = (stack / "case.toml").read_text().replace('path = "planes"',
                                                         f'path = "{stack / "planes"}"')
        for name, new in (("nan", "origin_mm = [nan, 0.0, 0.0]"),
                          ("1e300", "origin_mm = [1e300, 0.0, 0.0]")):
            import re as _re

            path = d / f"stack_{name}" / "case.toml"
            path.parent.mkdir()
            path.write_text(_re.sub(r"origin_mm = \[.*\]", new, text))
            rows.append((f"label-stack origin_mm {name}", ["case-info", str(path)], {}))
            rows.append((f"label-stack origin_mm {name} (simulate)",
                         ["simulate", "--case", str(path), "--trajectory", ok_traj], {}))
    for d_mm in ("200.0", "nan", "inf", "1e300", "-1.0", "0.0"):
        rows.append((f"burr diameter_mm = {d_mm}", ["simulate", "--burr", _file(
            d, f"burr_{d_mm}.toml", (burr.format(d=d_mm)).encode()), "--trajectory", ok_traj], {}))
    rows.append(("burr non-UTF-8", ["simulate", "--burr", _file(d, "burr_latin.toml",
                 b"# \xe9\n" + burr.format(d=2.0).encode()), "--trajectory", ok_traj], {}))
    rows.append(("burr binary", ["simulate", "--burr", _file(d, "burr_bin.toml", binary),
                                 "--trajectory", ok_traj], {}))
    for name, trows in (("trajectory t = 1e12", [(0, 0, 60000), (1e12, 0, 60000)]),
                        ("trajectory x = 1e300", [(0, 0, 60000), (0.01, 1e300, 60000)]),
                        ("trajectory rpm = 1e300", [(0, 0, 60000), (0.01, 0, 1e300)]),
                        ("trajectory t = nan", [(0, 0, 60000), ("nan", 0, 60000)])):
        rows.append((name, ["simulate", "--trajectory", _traj(d, name[13:].replace(" ", "")
                                                               + ".csv", trows)], {}))
    rows.append(("trajectory non-UTF-8", ["simulate", "--trajectory", _file(
        d, "traj_latin.csv", TRAJ_HEAD.encode() + b"0,0,0,0,0,0,-1,1,6\xe90\n")], {}))
    rows.append(("trajectory binary", ["simulate", "--trajectory", _file(d, "traj.bin", binary)], {}))
    rows.append(("run --size 100000 100000", ["run", "--offscreen", "--frames", "1", "--size",
                                               "100000", "100000", "--no-sound"], {}))
    rows.append(("run --frames -5", ["run", "--offscreen", "--frames", "-5", "--no-sound"], {}))
    rows.append(("playback --size 99999x99999", ["playback", "x.h5", "--size", "99999x99999"], {}))
    rows.append(("monitor --duration -1", ["monitor", "127.0.0.1", "--duration", "-1",
                                           "--timeout", "0.5"], {}))
    rows.append(("trajectory 2e6 rows, bad last row", ["simulate", "--trajectory", _big_traj(d)], {}))
    lim = "format = \"bonesim-force-limits-1\"\n"
    for name, data in (("limits non-UTF-8", b"# \xe9\n" + lim.encode()),
                       ("limits binary", binary)):
        rows.append((name, ["run", "--offscreen", "--frames", "1", "--no-sound", "--script",
                            ok_traj, "--force-limits", _file(d, name[7:] + ".toml", data)], {}))
    for name, data in (("devices config non-UTF-8", b"# \xe9\n[devices]\n"),
                       ("devices config binary", binary),
                       ("devices config nan", b"[devices.simulated-hand]\nrest_mm = [nan, 0.0, 0.0]\n")):
        rows.append((name, ["run", "--offscreen", "--frames", "1", "--no-sound", "--device",
                            "simulated-hand"],
                     {"BONESIM_DEVICES_CONFIG": _file(d, name[15:].replace(" ", "") + ".toml", data)}))
    lim_ok = ('format = "bonesim-force-limits-1"\nstructure = "{s}"\nforce = "applied"\n'
              'percentile = 95.0\nmax_distance_mm = 4.0\nedges_mm = [0.0, 2.0, 4.0]\n'
              'force_n = [{f}, 1.0]\nspeed_rpm = [1.0, 2.0]\nn = [1, 1]\n')
    for name, data in (("limits unknown structure", lim_ok.format(s="no_such_nerve", f="1.0")),
                       ("limits negative force", lim_ok.format(s="chorda_tympani", f="-1.0"))):
        rows.append((name, ["run", "--offscreen", "--frames", "1", "--no-sound", "--script",
                            ok_traj, "--force-limits", _file(d, name[7:].replace(" ", "") + ".toml",
                                                             data.encode())], {}))
    rows.append(("participants CSV non-UTF-8", ["metrics", "cohort", str(d), "--participants",
                 _file(d, "p_latin.csv", b"file,participant,group\nx\xe9.h5,a,expert\n")], {}))
    rows.append(("participants CSV binary", ["metrics", "cohort", str(d), "--participants",
                 _file(d, "p.bin", binary)], {}))
    rows.append(("key file binary", ["monitor", "127.0.0.1", "--key-file", _file(d, "key.bin", binary),
                                     "--timeout", "0.5"], {}))
    rows.append(("key file weak", ["monitor", "127.0.0.1", "--key-file", _file(
        d, "weak.key", b"passwordpassword"), "--timeout", "0.5"], {}))
    rows.append(("key file 16 zero bytes", ["tutor", "join", "127.0.0.1", "--key-file", _file(
        d, "zero.key", bytes(16)), "--timeout", "0.5", "--headless"], {}))
    good_key = _file(d, "good.key", bytes(range(3, 255, 8)).hex().encode())
    rows.append(("tutor serve --duration nan", ["tutor", "serve", "--duration", "nan",
                                                 "--headless", "--key-file", good_key], {}))
    rows.append(("session file binary", ["sessions", "info", _file(d, "s.h5", binary)], {}))
    return rows


def run(argv, env_extra, mem_gb: float, timeout_s: float):
    cap = int(mem_gb * 2 ** 30)

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    env = dict(os.environ, PYTHONPATH=str(ROOT), **env_extra)
    env.pop("DISPLAY", None)
    try:
        p = subprocess.run([sys.executable, "-m", "bonesim", *argv], capture_output=True,
                           text=True, errors="replace", env=env, timeout=timeout_s,
                           preexec_fn=limit, cwd=tempfile.gettempdir())
    except subprocess.TimeoutExpired:
        return None, True, "TIMEOUT"
    err = [ln for ln in p.stderr.splitlines() if ln.strip()]
    return p.returncode, "Traceback" in p.stderr, (err[-1] if err else "")[:160]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mem-gb", type=float, default=3.0, help="address-space cap [GiB]")
    ap.add_argument("--timeout", type=float, default=120.0, help="per command [s]")
    ap.add_argument("-k", help="only rows whose name contains this")
    a = ap.parse_args()
    bad = 0
    with tempfile.TemporaryDirectory() as tmp:
        for name, argv, env in cases(Path(tmp)):
            if a.k and a.k not in name:
                continue
            rc, tb, last = run(argv, env, a.mem_gb, a.timeout)
            good = rc is not None and 0 < rc < 128 and not tb
            bad += not good
            print(f"{'ok ' if good else 'BAD'} | {name:32s} | rc={rc} | "
                  f"{'traceback | ' if tb else ''}{last.replace(tmp, '$T')}", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
