"""Command-line numbers checked against their physical bounds
(``bonesim/data/limits.toml``, :mod:`bonesim.io.limits`) right after parsing,
before any command runs: a window of 100000 x 100000 px, ``--frames -5`` or
``--duration nan`` is refused in one line naming the option, never taken on
to an allocation, a crash or a run that never ends.
"""
from __future__ import annotations

from bonesim.io.limits import check

__all__ = ["OPTION_BOUNDS", "check_options"]

#: Option destination -> the quantity of ``limits.toml`` bounding it.
OPTION_BOUNDS = {
    "size": "window_px", "frames": "frames", "fps": "rate_hz",
    "duration": "duration_s", "seconds": "duration_s", "timeout": "duration_s",
    "every": "duration_s", "start": "duration_s", "end": "duration_s", "at": "duration_s",
    "speed": "speed_factor", "oversample": "oversample", "workers": "workers",
    "port": "port", "monitor_port": "port", "experts": "count", "novices": "count",
    "stereo": "baseline_mm", "eye_separation_mm": "baseline_mm", "zoom": "zoom",
    "percentile": "percentile",
}


def _option(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def check_options(args) -> None:
    """Check every numeric option of a parsed command line against its bounds.

    Parameters
    ----------
    args : argparse.Namespace
        Options that are None, strings (``--stereo anaglyph``) or absent are
        left alone; numbers and lists of numbers (``--size W H``) are checked.

    Raises
    ------
    bonesim.errors.BonesimError
        Naming the option, its value, the bounds and why.
    """
    for dest, name in OPTION_BOUNDS.items():
        value = getattr(args, dest, None)
        values = value if isinstance(value, (list, tuple)) else [value]
        for v in values:
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                check(name, v, field=_option(dest), what="")
