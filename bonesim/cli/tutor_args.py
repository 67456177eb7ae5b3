"""The ``bonesim tutor`` subcommands' arguments (keygen, serve, join,
playback); their handlers are :mod:`bonesim.cli.tutor`, imported only when
run."""
from __future__ import annotations

__all__ = ["tutor_parsers"]

#: ``--device`` of ``tutor join`` and ``tutor playback``.
TRAINEE_DEVICE_HELP = ("the trainee's device, driven by the tutoring law through the "
                       "safety layer of 'bonesim run --device' (a force-feedback backend: "
                       "touch, simulated-hand; forces start once the stylus is held still, "
                       "then ramp in). Default: a simulated hand that picks up the stylus "
                       "at the instructor's tool")


def _trainee_window_args(p) -> None:
    """The trainee's window options (``tutor join`` and ``tutor playback``)."""
    p.add_argument("--headless", action="store_true",
                   help="no window (default without a display)")
    p.add_argument("--offscreen", action="store_true",
                   help="render the window offscreen (--frames frames, or until the "
                        "session ends) and save the last frame")
    p.add_argument("--frames", type=int, help="window: stop after this many frames")
    p.add_argument("--screenshot", metavar="FILE.png", help="window: save the last frame")
    p.add_argument("--size", type=int, nargs=2, default=[1280, 720], metavar=("W", "H"),
                   help="window size in pixels (default 1280 720)")


def tutor_parsers(sub, _lazy, DEFAULT_CASE: str, DEFAULT_BURR: str) -> None:
    """Add ``bonesim tutor ...`` to the subcommands ``sub``; ``_lazy(module,
    name)`` makes a handler imported only when run."""
    from bonesim.net.packets import DEFAULT_KEY_HELP, DEFAULT_PORT

    def _tutor(name: str):
        return _lazy("bonesim.cli.tutor", name)

    s = sub.add_parser(
        "tutor", help="networked haptic tutoring and haptic playback",
        description="Haptic tutoring: the instructor drills (serve) and the trainee's "
                    "device follows with F = K_p (P_instructor - P_trainee) + F_instructor "
                    "(join), or follows a recorded session (playback). Packets are "
                    "authenticated with a shared key (keygen).")
    t = s.add_subparsers(dest="tutor_cmd", metavar="ACTION", required=True)
    k = t.add_parser("keygen", help="write a new random shared key file")
    k.add_argument("file", help="key file to create (hex text, owner-only)")
    k.add_argument("--force", action="store_true", help="overwrite an existing file")
    k.set_defaults(func=_tutor("cmd_keygen"))

    v = t.add_parser("serve", help="run the instructor's simulator and stream it to trainees",
                     description="Run the haptic loop (window with the mouse, or a scripted "
                                 "trajectory) and stream tool pose, force, drill state and "
                                 "voxel removals over UDP to every trainee that joins.")
    v.add_argument("--case", default=DEFAULT_CASE, help="case name or case.toml path")
    v.add_argument("--burr", default=DEFAULT_BURR, help="burr name or file")
    v.add_argument("--trajectory", metavar="FILE.csv",
                   help="scripted instructor (headless default: the demo mastoidectomy)")
    v.add_argument("--headless", action="store_true", help="no window (default without a "
                                                           "display)")
    v.add_argument("--duration", type=float, metavar="S",
                   help="stop after S seconds (headless default: the trajectory's length)")
    v.add_argument("--host", default="0.0.0.0", help="address to listen on (default all)")
    v.add_argument("--port", type=int, default=DEFAULT_PORT,
                   help=f"UDP port (default {DEFAULT_PORT})")
    v.add_argument("--device", metavar="NAME",
                   help="the instructor's hand: any backend 'bonesim run --device' takes "
                        "(touch, spacemouse, simulated-hand, ...), behind the same safety "
                        "layer (default: the mouse in the window, the demo trajectory "
                        "headless)")
    v.add_argument("--record", metavar="FILE.h5",
                   help="record the instructor's session (its header keeps the device's "
                        "capability record)")
    v.add_argument("--no-sound", action="store_true", help="window: no audio process")
    v.add_argument("--key-file", metavar="FILE", help=DEFAULT_KEY_HELP)
    v.add_argument("--json", action="store_true", help="print the summary as JSON")
    v.set_defaults(func=_tutor("cmd_serve"))

    j = t.add_parser("join", help="follow an instructor with this trainee's device",
                     description="Join an instructor and run the trainee's 1 kHz servo on "
                                 "the trainee's device (--device; default a simulated "
                                 "hand). A window shows "
                                 "the bone as the instructor drills it, the instructor's "
                                 "tool and your hand (headless without a display); at the "
                                 "end it prints packets, drops by reason, latency and "
                                 "tracking error beside the ideal follower's.")
    j.add_argument("host", help="instructor's address")
    j.add_argument("--port", type=int, default=DEFAULT_PORT,
                   help=f"UDP port (default {DEFAULT_PORT})")
    j.add_argument("--case", help="load this case instead of the one the instructor names")
    j.add_argument("--device", metavar="NAME", help=TRAINEE_DEVICE_HELP)
    j.add_argument("--record", metavar="FILE.json",
                   help="write the trainee's session record: a header as a recording's "
                        "(case, model, the trainee device's capability record) and the "
                        "summary (tracking against the ideal follower, packets, device)")
    _trainee_window_args(j)
    j.add_argument("--duration", type=float, metavar="S",
                   help="stop after S seconds (default: when the instructor stops)")
    j.add_argument("--timeout", type=float, default=10.0, metavar="S",
                   help="give up if the instructor does not answer within S seconds")
    j.add_argument("--key-file", metavar="FILE", help=DEFAULT_KEY_HELP)
    j.add_argument("--json", action="store_true", help="print the statistics as JSON")
    j.set_defaults(func=_tutor("cmd_join"))

    b = t.add_parser("playback", help="drive the trainee's device from a recorded session",
                     description="Feed a recorded session through the tutoring controller "
                                 "to the trainee's device (--device; default a simulated "
                                 "hand) in real time, in a window as for "
                                 "'tutor join' (headless without a display); the force "
                                 "ramps out when the recording ends.")
    b.add_argument("file", help="session file (.h5)")
    b.add_argument("--device", metavar="NAME", help=TRAINEE_DEVICE_HELP)
    b.add_argument("--speed", type=float, default=1.0, help="playback speed (default 1)")
    b.add_argument("--start", type=float, default=0.0, metavar="S",
                   help="start S seconds into the recording")
    b.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    b.add_argument("--score", metavar="RUN.h5",
                   help="the trainee's own recorded run of the case: score its force "
                        "against this recording's force profile (force-trajectory "
                        "alignment: residual after and before warping time)")
    b.add_argument("--record", metavar="FILE.json",
                   help="write the trainee's session record: a header as a recording's "
                        "(case, model, the trainee device's capability record) and the "
                        "summary (tracking against the ideal follower, packets, device)")
    _trainee_window_args(b)
    b.add_argument("--json", action="store_true", help="print the statistics as JSON")
    b.set_defaults(func=_tutor("cmd_playback"))
