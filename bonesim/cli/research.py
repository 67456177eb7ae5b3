"""The research commands' arguments: ``bonesim cohort synth``, ``bonesim
metrics run``, ``bonesim metrics cohort``, ``bonesim metrics progress``,
``bonesim metrics export``, ``bonesim metrics limits`` and ``bonesim metrics
view``.

Their handlers live with the research metrics (:mod:`metrics.cli`, beside the
package) and are named here by module path only: the simulator never imports
the metrics, and a machine that only drills never loads scipy's statistics,
Dask or pandas. A command that runs research code itself (``bonesim
assess``, ``bonesim dataset`` of many runs) gets its module through
:func:`research_module`, by name too; every import made from a string is
listed beside the import-linter contracts in ``pyproject.toml``
(``[tool.bonesim.string-imports]``), and ``tests/bonesim/test_layers.py``
checks that each resolves.
"""
from __future__ import annotations

__all__ = ["research_module", "research_parsers"]


def research_module(name: str, needed_for: str):
    """The research module ``name`` (``metrics.*``), imported by name.

    Parameters
    ----------
    name : str
        Dotted module name, e.g. ``"metrics.assessment"``.
    needed_for : str
        What asked for it (``"bonesim assess"``), for the error line.

    Raises
    ------
    BonesimError
        One line when the research package (or a library it needs) is not
        installed.
    """
    import importlib

    from bonesim.errors import BonesimError

    try:
        return importlib.import_module(name)
    except ImportError as exc:
        raise BonesimError(f"{needed_for} needs the research package (metrics/, beside "
                           f"bonesim): {exc}") from None


def research_parsers(sub, _lazy) -> None:
    """Add the research commands to the ``bonesim`` subcommands ``sub``;
    ``_lazy(module, name)`` makes a handler imported only when run."""
    s = sub.add_parser("cohort", help="research cohorts of recorded runs")
    csub = s.add_subparsers(dest="cohort_cmd", metavar="ACTION", required=True)
    cs = csub.add_parser("synth", help="record a synthetic cohort of expert-like and "
                         "novice-like scripted runs (test data) and its participants.csv")
    cs.add_argument("--experts", type=int, default=6, metavar="N", help="expert-like runs")
    cs.add_argument("--novices", type=int, default=6, metavar="M", help="novice-like runs")
    cs.add_argument("--out", required=True, metavar="DIR", help="an empty folder")
    cs.add_argument("--seed", type=int, default=0, help="seed of every draw")
    cs.add_argument("--duration", type=float, default=180.0, metavar="S",
                    help="length of each run [s] (default 180)")
    cs.add_argument("--case", default="phantom", help="case name or case.toml path")
    cs.add_argument("--sessions", type=int, default=1, metavar="K",
                    help="sessions per participant (default 1)")
    cs.add_argument("--behaviours", metavar="FILE.toml",
                    help="behaviour parameters (default metrics/synth.toml)")
    cs.add_argument("--json", action="store_true", help="print JSON")
    cs.set_defaults(func=_lazy("metrics.cli", "cmd_cohort_synth"))

    s = sub.add_parser("metrics", help="research metrics of recorded runs")
    msub = s.add_subparsers(dest="metrics_cmd", metavar="ACTION", required=True)
    mr = msub.add_parser("run", help="every metric of one run")
    mr.add_argument("file", help="session file (.h5)")
    mr.add_argument("--expert", action="append", metavar="FILE.h5",
                    help="an expert run of the same case for the final product (repeatable)")
    mr.add_argument("--force-profile", metavar="FILE.h5",
                    help="an expert run whose force is the target profile to align to")
    mr.add_argument("--structure", help="structure of the force-versus-distance table "
                    "(default chorda_tympani)")
    mr.add_argument("--json", action="store_true", help="print JSON")
    mr.set_defaults(func=_lazy("metrics.cli", "cmd_metrics_run"))
    mc = msub.add_parser("cohort", help="score a cohort of runs on a Dask cluster: a table "
                         "of every metric per run and the group statistics")
    mc.add_argument("sessions", metavar="DIR_OR_GLOB",
                    help="a folder of session files (*.h5) or a glob pattern")
    mc.add_argument("--participants", required=True, metavar="CSV",
                    help="participants table: id, group (expert/novice), instructor_score")
    mc.add_argument("--out", metavar="FILE", help="write the table (.parquet or .csv)")
    mc.add_argument("--report", metavar="FILE.html", help="write the HTML report")
    mc.add_argument("--scheduler", metavar="ADDRESS",
                    help="a running Dask scheduler (default: a local cluster)")
    mc.add_argument("--workers", type=int, default=2, metavar="N",
                    help="worker processes of the local cluster (default 2)")
    mc.add_argument("--structure", default="chorda_tympani",
                    help="structure of the force tables (default chorda_tympani)")
    mc.add_argument("--design", metavar="FILE.toml",
                    help="statistical design: primary metrics, corrections, exclusions "
                    "(default metrics/design.toml)")
    mc.add_argument("--exports", metavar="DIR",
                    help="write stats.csv, runs.csv and provenance.json here")
    mc.add_argument("--cache", metavar="DIR",
                    help="keep per-run results here by file content, bonesim version and "
                    "code; unchanged runs are read back instead of scored (default: none)")
    mc.add_argument("--ratings", metavar="CSV",
                    help="instructors' scores (participant,session,rater,score): "
                    "between-rater ICC and the simulator's score against them")
    mc.add_argument("--ratings-against", default="assess_total", metavar="COLUMN",
                    help="the simulator's column on the raters' scale (default assess_total)")
    mc.add_argument("--json", action="store_true", help="print the summary as JSON")
    mc.set_defaults(func=_lazy("metrics.cli", "cmd_metrics_cohort"))
    mp = msub.add_parser("progress", help="learning curves: each participant's metrics "
                         "session by session against the experts' band (PNG)")
    mp.add_argument("sessions", metavar="DIR_OR_GLOB",
                    help="a folder of session files (*.h5) or a glob pattern")
    mp.add_argument("--participants", required=True, metavar="CSV",
                    help="participants table with a session (or file) per run")
    mp.add_argument("--out", default="progress.png", metavar="FILE.png",
                    help="picture to write (default progress.png)")
    mp.add_argument("--metric", action="append", metavar="NAME",
                    help="metric to draw (repeatable; default the primary ones and more)")
    mp.add_argument("--cache", metavar="DIR",
                    help="per-run results kept by file content, bonesim version and code "
                    "(default ~/.cache/bonesim/runs): unchanged runs are not scored again")
    mp.add_argument("--no-cache", action="store_true", help="score every run, keep nothing")
    mp.add_argument("--workers", type=int, default=2, metavar="N",
                    help="worker processes scoring the runs (default 2)")
    mp.add_argument("--json", action="store_true", help="print JSON")
    mp.set_defaults(func=_lazy("metrics.cli", "cmd_metrics_progress"))
    mx = msub.add_parser("export", help="a run's per-voxel visibility as NRRD on the "
                         "case grid and its removals as Parquet, with provenance")
    mx.add_argument("file", help="session file (.h5)")
    mx.add_argument("--out", required=True, metavar="DIR", help="folder to write into")
    mx.add_argument("--participants", metavar="CSV",
                    help="participants table (its hash goes in the provenance)")
    mx.add_argument("--json", action="store_true", help="print JSON")
    mx.set_defaults(func=_lazy("metrics.cli", "cmd_metrics_export"))
    ml = msub.add_parser("limits", help="learn per-distance force and speed limits from "
                         "expert runs, for the window's live warnings (run --force-limits)")
    ml.add_argument("sessions", metavar="DIR_OR_GLOB",
                    help="a folder of session files (*.h5) or a glob pattern")
    ml.add_argument("--participants", metavar="CSV",
                    help="participants table choosing the experts (default: each "
                    "session's recorded group)")
    ml.add_argument("--out", required=True, metavar="FILE.toml", help="limits file to write")
    ml.add_argument("--structure", default="chorda_tympani",
                    help="structure the distances are measured to (default chorda_tympani)")
    ml.add_argument("--percentile", type=float, default=95.0,
                    help="of the expert rows per bin (default 95)")
    ml.add_argument("--json", action="store_true", help="print JSON")
    ml.set_defaults(func=_lazy("metrics.cli", "cmd_metrics_limits"))
    mv = msub.add_parser("view", help="a run's removals coloured by visibility (green "
                         "seen, red hidden) with chosen structures, in a window to turn "
                         "about; a PNG without a display or with --png")
    mv.add_argument("file", help="session file (.h5)")
    mv.add_argument("--structure", action="append", metavar="NAME",
                    help="structure to show (repeatable; default every non-bone one)")
    mv.add_argument("--png", metavar="FILE.png", help="write the view to this picture")
    mv.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                    help="window or picture size [px] (default 1024 768)")
    mv.add_argument("--frames", type=int, metavar="N",
                    help="close the window after N frames (default: when you quit)")
    mv.set_defaults(func=_lazy("metrics.cli", "cmd_metrics_view"))
