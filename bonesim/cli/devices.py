"""The device commands: ``bonesim devices`` (what backends exist, what is
connected, what each needs) and ``bonesim run --device NAME``'s option."""
from __future__ import annotations

import json

__all__ = ["cmd_devices", "device_parsers", "device_option"]


def cmd_devices(args) -> int:
    from bonesim.devices.config import config_path
    from bonesim.devices.registry import backend_names, describe

    rows = [describe(n) for n in backend_names()]
    if args.json:
        print(json.dumps({"config": str(config_path()), "backends": rows}, indent=2))
        return 0
    w = max(len(r["name"]) for r in rows)
    for r in rows:
        conn = ", ".join(r["connected"]) if r["connected"] else "none connected"
        print(f"{r['name'].ljust(w)}  {r['what']}")
        print(f"{''.ljust(w)}  connected: {conn}")
        if r["library"] != "ok":
            print(f"{''.ljust(w)}  library: {r['library']}")
        print(f"{''.ljust(w)}  needs: {r['needs']}")
    print(f"settings and calibrations: {config_path()}")
    return 0


def device_parsers(sub) -> None:
    """Add ``bonesim devices`` to the subcommands ``sub``."""
    s = sub.add_parser("devices", help="list the device backends, what is connected and "
                                       "what each needs")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=cmd_devices)


def device_option(s) -> None:
    """``--device NAME`` for ``bonesim run``."""
    from bonesim.devices.registry import DEFAULT_DEVICE

    s.add_argument("--device", default=DEFAULT_DEVICE, metavar="NAME",
                   help=f"input device backend (default {DEFAULT_DEVICE}; "
                        "'bonesim devices' lists them)")
    s.add_argument("--pedal", action="store_true",
                   help="drill on/off and speed from a USB foot pedal ([devices.pedal] in "
                        "the device config)")
