"""``bonesim monitor HOST``: the nerve monitor's remote console
(:func:`bonesim.net.monitor_link.run_console`) and its closing summary."""
from __future__ import annotations

from bonesim.cli.output import print_json

__all__ = ["cmd_monitor"]


def cmd_monitor(args) -> int:
    """Run the console; print the link's statistics (JSON with ``--json``)."""
    from bonesim.net.monitor_link import run_console

    s = run_console(args)
    if args.json:
        print_json(s)
        return 0
    lat = s["latency_ms"]
    print(f"{s['data']} packets ({s['lost']} lost, {s['loss_fraction'] * 100:.2f} %), "
          f"{s['spikes']} spikes; latency p50 {lat.get('p50')} ms, p99 {lat.get('p99')} "
          f"ms; link lost {s['link_lost']} time(s)"
          + ("; server ended the session" if s["byes"] else ""))
    return 0
