"""The device commands: ``bonesim devices`` (what backends exist, what is
connected, what each needs) and ``bonesim run --device NAME``'s option."""
from __future__ import annotations

from bonesim.cli.output import print_json

__all__ = ["cmd_devices", "cmd_calibrate", "device_parsers", "device_option"]


def cmd_devices(args) -> int:
    from bonesim.devices.config import config_path
    from bonesim.devices.registry import backend_names, describe

    rows = [describe(n) for n in backend_names()]
    if args.json:
        print_json({"config": str(config_path()), "backends": rows})
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


def cmd_calibrate(args) -> int:
    from bonesim.devices.registry import backend_names, make_device
    from bonesim.errors import BonesimError

    if args.device != "adu100-handle":
        known = ", ".join(n for n in backend_names() if n != "adu100-handle")
        raise BonesimError(f"{args.device!r} needs no calibration (only adu100-handle does; "
                           f"the others: {known})", field="DEVICE")
    from bonesim.devices.adu100 import run_calibration

    def ask(prompt: str) -> None:
        try:
            input(prompt + " ")
        except EOFError:
            raise BonesimError("calibration asks you to move the handle: run it in a "
                               "terminal", field="DEVICE") from None

    handle = make_device(args.device, pedal_ok=True)
    cal = run_calibration(handle, ask, open_deg=args.open_deg, closed_deg=args.closed_deg)
    for ch, o, c, od, cd in zip(cal["channels"], cal["open"], cal["closed"],
                                cal["open_deg"], cal["closed_deg"]):
        print(f"analog input {ch}: {o:.0f} counts = {od:g} deg, {c:.0f} counts = {cd:g} deg")
    print(f"stored for ADU100 {cal['serial']} in {cal['path']}")
    return 0


def device_parsers(sub) -> None:
    """Add ``bonesim devices`` and ``bonesim calibrate`` to the subcommands ``sub``."""
    from bonesim.devices.adu100 import DEFAULT_CLOSED_DEG, DEFAULT_OPEN_DEG

    s = sub.add_parser("devices", help="list the device backends, what is connected and "
                                       "what each needs")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=cmd_devices)
    s = sub.add_parser("calibrate", help="calibrate a device with on-screen prompts "
                                         "(adu100-handle: open fully, then close fully)")
    s.add_argument("device", metavar="DEVICE", help="backend name (adu100-handle)")
    s.add_argument("--open-deg", type=float, nargs="+", default=list(DEFAULT_OPEN_DEG),
                   metavar="DEG", help="angle of each channel fully open [deg] (default "
                   + " ".join(f"{x:g}" for x in DEFAULT_OPEN_DEG) + ")")
    s.add_argument("--closed-deg", type=float, nargs="+", default=list(DEFAULT_CLOSED_DEG),
                   metavar="DEG", help="angle of each channel fully closed [deg] (default "
                   + " ".join(f"{x:g}" for x in DEFAULT_CLOSED_DEG) + ")")
    s.set_defaults(func=cmd_calibrate)


def device_option(s) -> None:
    """``--device NAME`` for ``bonesim run``."""
    from bonesim.devices.registry import DEFAULT_DEVICE

    s.add_argument("--device", default=DEFAULT_DEVICE, metavar="NAME",
                   help=f"input device backend (default {DEFAULT_DEVICE}; "
                        "'bonesim devices' lists them)")
    s.add_argument("--pedal", nargs="?", const="pedal", default=None, metavar="NAME",
                   help="drill on/off and speed from a USB foot pedal ([devices.pedal] in "
                        "the device config), or from another auxiliary backend "
                        "(adu100-handle: the instrumented handle's lever)")
