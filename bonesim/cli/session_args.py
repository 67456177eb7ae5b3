"""The session commands' arguments: ``bonesim sessions``, ``replay`` and
``playback`` (their handlers, :mod:`bonesim.cli.sessions`, are imported only
when run)."""
from __future__ import annotations

from bonesim.cli.dataset import dataset_parsers

__all__ = ["session_parsers"]


def session_parsers(sub, _lazy) -> None:
    """Add the session commands to the ``bonesim`` subparsers ``sub``
    (``_lazy(module, name)``: a handler imported when run)."""
    s = sub.add_parser("sessions", help="recorded sessions (HDF5 files)")
    ssub = s.add_subparsers(dest="sessions_cmd", metavar="ACTION", required=True)
    si = ssub.add_parser("info", help="summarize a session file (schema checked)")
    si.add_argument("file", help="session file (.h5)")
    si.add_argument("--json", action="store_true", help="print JSON")
    si.add_argument("--against-current", action="store_true",
                    help="also list what differs between the case, burr and material "
                         "files it was recorded on and today's")
    si.set_defaults(func=_lazy("bonesim.cli.sessions", "cmd_sessions_info"))
    sl = ssub.add_parser("list", help="list the session files in a folder")
    sl.add_argument("folder", nargs="?",
                    help="folder (default $BONESIM_SESSIONS or ~/.local/share/bonesim/sessions)")
    sl.add_argument("--json", action="store_true", help="print JSON")
    sl.set_defaults(func=_lazy("bonesim.cli.sessions", "cmd_sessions_list"))
    sr = ssub.add_parser("repair", help="write the readable part of a damaged session "
                         "file as a clean copy")
    sr.add_argument("file", help="damaged session file (.h5)")
    sr.add_argument("out", help="the clean copy to write (.h5, a new file)")
    sr.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    sr.add_argument("--json", action="store_true", help="print JSON")
    sr.set_defaults(func=_lazy("bonesim.cli.sessions", "cmd_sessions_repair"))
    dataset_parsers(sub, _lazy, ssub)        # bonesim dataset, bonesim sessions export

    s = sub.add_parser("replay", help="re-run a session's samples through the engine")
    s.add_argument("file", help="session file (.h5)")
    s.add_argument("--verify", action="store_true",
                   help="check that the removals and forces equal the recording bit for "
                        "bit (exit status 1 if not)")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=_lazy("bonesim.cli.sessions", "cmd_replay"))

    s = sub.add_parser(
        "playback", help="play a session back in a window with a timeline, or export it "
                         "as an H.264 video (--video)",
        description="Play a recorded session back: the tool at its recorded pose, the "
                    "bone as drilled up to the current time, HUD and timeline with "
                    "injuries. Keys: Space play/pause, +/- speed (0.25x..8x), Left/Right "
                    "-/+1 s, Down/Up -/+10 s, Home/End, click or drag on the timeline to "
                    "seek, right-drag to orbit, v back to the recorded camera, h help, "
                    "q quit. With --video it renders offscreen into an mp4 instead.")
    s.add_argument("file", help="session file (.h5)")
    s.add_argument("--video", metavar="OUT.mp4", help="export an H.264 video instead of "
                                                     "opening the window")
    s.add_argument("--fps", type=float, default=30.0, help="video frame rate (default 30)")
    s.add_argument("--size", metavar="WxH", help="window or video size in pixels "
                                                 "(default 1280x720; even for video)")
    s.add_argument("--speed", type=float, help="playback speed factor (default 1)")
    s.add_argument("--start", type=float, metavar="S", help="start at S seconds into the "
                                                            "recording")
    s.add_argument("--end", type=float, metavar="S", help="video: stop at S seconds "
                                                          "(default the end)")
    s.add_argument("--paused", action="store_true", help="window: start paused")
    s.add_argument("--offscreen", action="store_true",
                   help="no window: render --frames frames offscreen and save the last")
    s.add_argument("--frames", type=int, help="stop after this many frames")
    s.add_argument("--screenshot", metavar="FILE.png", help="save the last frame")
    s.add_argument("--no-progress", action="store_true", help="video: no progress bar")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    s.set_defaults(func=_lazy("bonesim.cli.sessions", "cmd_playback"))
