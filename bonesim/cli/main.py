"""The ``bonesim`` command line: the parser and ``main``.

The commands live by group: :mod:`bonesim.cli.cases` (cases and burrs),
:mod:`bonesim.cli.drilling` (simulate, trajectory, demo, run),
:mod:`bonesim.cli.sessions` (sessions, replay, playback; arguments in
:mod:`bonesim.cli.session_args`), :mod:`bonesim.cli.tutor` (tutoring),
:mod:`bonesim.cli.research` (metrics, cohort), :mod:`bonesim.cli.dataset`,
:mod:`bonesim.cli.assess`, :mod:`bonesim.cli.devices`, :mod:`bonesim.cli.monitor`
and :mod:`bonesim.cli.warmup`. Every subcommand has ``--help``. Bad input (a missing case, a malformed
manifest, a broken trajectory) is reported as one line naming the file and the
problem, with exit status 2; no traceback.
"""
from __future__ import annotations

import argparse
import sys

from bonesim.io.burrs import DEFAULT_BURR
from bonesim.cli.assess import assess_parsers
from bonesim.cli.bounds import check_options
from bonesim.cli.cases import case_parsers
from bonesim.cli.devices import device_parsers
from bonesim.cli.drilling import DEFAULT_CASE, drilling_parsers
from bonesim.cli.output import print_json
from bonesim.cli.research import research_parsers
from bonesim.cli.session_args import session_parsers
from bonesim.cli.tutor_args import tutor_parsers
from bonesim.cli.voxel import apply_voxel_mm
from bonesim.cli.warmup import cmd_warmup
from bonesim.errors import BonesimError

__all__ = ["cmd_bench", "build_parser", "main"]


def _lazy(module: str, name: str):
    """A command handler ``<module>.<name>``, imported only when run
    (keeps the CLI light)."""
    def run(args) -> int:
        import importlib

        return getattr(importlib.import_module(module), name)(args)
    return run


def cmd_bench(args) -> int:
    from bonesim.bench.suite import run_benchmarks

    results = run_benchmarks(only=args.only, quick=args.quick)
    if args.json:
        print_json(results)
    else:
        for name, r in results.items():
            print(f"{name:34s} {r['value']:>12.4g} {r['unit']}")
    return 0


# ---------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="bonesim",
        description="Temporal-bone drilling simulator: cases, burrs, headless runs, "
                    "benchmarks.")
    from bonesim import __version__
    from bonesim.net.packets import DEFAULT_KEY_HELP as KEY_HELP
    from bonesim.net.packets import MONITOR_PORT
    p.add_argument("--version", action="version", version=f"bonesim {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    case_parsers(sub)
    drilling_parsers(sub)

    s = sub.add_parser(
        "monitor", help="remote nerve-monitor console (the monitoring technician's)",
        description="Join a simulator that serves its nerve monitor (bonesim run "
                    "--monitor-port) and show, for every monitored nerve, the burr's "
                    "distance, the firing rate and a warning below the warning distance, "
                    "with a click per spike on the sound device. Packets are authenticated "
                    "with the shared key ('bonesim tutor keygen FILE').")
    s.add_argument("host", help="the simulator's address")
    s.add_argument("--port", type=int, default=MONITOR_PORT,
                   help=f"UDP port (default {MONITOR_PORT})")
    s.add_argument("--key-file", metavar="FILE", help=KEY_HELP)
    s.add_argument("--duration", type=float, metavar="S",
                   help="stop after S seconds (default: when the simulator stops)")
    s.add_argument("--timeout", type=float, default=10.0, metavar="S",
                   help="give up if the simulator does not answer within S seconds")
    s.add_argument("--no-sound", action="store_true", help="no clicks")
    s.add_argument("--wav", metavar="FILE.wav", help="record the clicks")
    s.add_argument("--every", type=float, default=1.0, metavar="S",
                   help="without a terminal: print the readings every S seconds "
                        "(0: only the summary)")
    s.add_argument("--json", action="store_true", help="print the statistics as JSON")
    s.set_defaults(func=_lazy("bonesim.cli.monitor", "cmd_monitor"))

    session_parsers(sub, _lazy)

    tutor_parsers(sub, _lazy, DEFAULT_CASE, DEFAULT_BURR)

    research_parsers(sub, _lazy)
    assess_parsers(sub, _lazy)
    device_parsers(sub)

    s = sub.add_parser("warmup", help="compile the numba kernels now (setup does it), so "
                                      "that the first run starts at once")
    s.add_argument("--json", action="store_true", help="print seconds per part as JSON")
    s.add_argument("--jobs", type=int, default=None,
                   help="compiling processes (default 2, or 1 on a one-core machine)")
    s.set_defaults(func=cmd_warmup)

    s = sub.add_parser("bench", help="run the performance benchmarks")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.add_argument("--only", action="append", metavar="NAME",
                   help="run only this benchmark (repeatable)")
    s.add_argument("--quick", action="store_true",
                   help="fewer repetitions (for smoke tests; figures are noisier)")
    s.set_defaults(func=cmd_bench)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)   # for provenance records
    try:
        check_options(args)                  # numbers within their physical bounds
        apply_voxel_mm(args)
        return int(args.func(args) or 0)
    except BonesimError as exc:
        print(f"bonesim: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("bonesim: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:                 # output piped into head, less, ...
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
