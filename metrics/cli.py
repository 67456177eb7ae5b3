"""Handlers of the research commands of ``bonesim`` (``bonesim cohort ...``).

``bonesim``'s command line (:mod:`bonesim.cli.main`) names these handlers by
module path and imports them only when run, so the simulator never imports
the metrics.
"""
from __future__ import annotations

import json
import sys

__all__ = ["cmd_cohort_synth"]


def cmd_cohort_synth(args) -> int:
    """``bonesim cohort synth``: record a synthetic cohort (:mod:`metrics.synth`)."""
    from bonesim.errors import BonesimError
    from bonesim.progress import ProgressBar
    from metrics.synth import PARTICIPANTS_CSV, synth_cohort

    bar = ProgressBar(max(args.experts + args.novices, 1), "recording")
    try:
        paths = synth_cohort(args.out, args.experts, args.novices, seed=args.seed,
                             case=args.case, duration_s=args.duration,
                             progress=lambda done, _n: bar.update(done))
    except ValueError as exc:
        raise BonesimError(f"cohort synth: {exc}") from None
    bar.close()
    out = {"sessions": [str(p) for p in paths],
           "participants": str(paths[0].parent / PARTICIPANTS_CSV),
           "synthetic": True}
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"{len(paths)} synthetic runs ({args.experts} expert-like, {args.novices} "
              f"novice-like, {args.duration:g} s each) in {paths[0].parent}; participants "
              f"in {out['participants']}", file=sys.stdout)
    return 0
