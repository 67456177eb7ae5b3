"""``--voxel-mm`` on the commands that load a case (``run``, ``demo``,
``simulate``, ``trajectory``, ``case-info``, ``case-export``).

The option reads a case at another engine voxel than its manifest's
``[volume] voxel_mm``: a number of mm, or ``native`` for the source's own
spacing (:meth:`bonesim.io.case.Case.with_voxel_mm`). Applied once, before
the command runs, it turns ``args.case`` into the loaded case; every command
passes a case on to :func:`bonesim.io.case.load_case` and
:func:`bonesim.io.loading.load_model`, which take a name or a case alike.
"""
from __future__ import annotations

import argparse

from bonesim.errors import BonesimError

__all__ = ["voxel_option", "apply_voxel_mm"]


def _voxel_mm_arg(text: str):
    """``--voxel-mm``'s value: a number of mm or ``native``."""
    from bonesim.io.case_records import check_voxel_mm

    try:
        return check_voxel_mm(text)
    except BonesimError as exc:
        raise argparse.ArgumentTypeError(exc.message) from None


def voxel_option(parser) -> None:
    """Add ``--voxel-mm MM|native`` to a command's parser."""
    parser.add_argument("--voxel-mm", type=_voxel_mm_arg, metavar="MM|native",
                        help="engine voxel edge [mm], or 'native' for the source's own "
                             "spacing (its finest axis; the phantom keeps its manifest's); "
                             "overrides the case's [volume] voxel_mm")


def apply_voxel_mm(args) -> None:
    """With ``--voxel-mm``, replace ``args.case`` (a name or path) by the
    loaded case at that voxel; without it, leave ``args`` as it is."""
    if getattr(args, "voxel_mm", None) is not None:
        from bonesim.io.case import load_case

        args.case = load_case(args.case, voxel_mm=args.voxel_mm)
