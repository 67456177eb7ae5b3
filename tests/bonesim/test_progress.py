"""The progress bar (bonesim.progress) and its clock format."""
from __future__ import annotations

import io

from bonesim.progress import ProgressBar, format_clock


def test_format_clock():
    assert format_clock(0) == "0:00.0" and format_clock(75.25) == "1:15.2"
    assert format_clock(59.97) == "1:00.0" and format_clock(3725) == "1:02:05"


def test_progress_bar_percent_and_eta():
    now = [100.0]
    out = io.StringIO()
    bar = ProgressBar(200, "video", stream=out, width=10, clock=lambda: now[0])
    assert bar.text(0) == "video [..........]   0%  0/200  ETA ?"
    now[0] = 110.0
    assert bar.text(50) == "video [##........]  25%  50/200  ETA 0:30.0"
    for k in range(1, 201):
        bar.update(k)
    bar.close()
    lines = out.getvalue().splitlines()          # not a terminal: one line per 10 %
    assert len(lines) == 11 and lines[-1].endswith("done in 0:10.0")
    assert " 0%" in lines[0] and "50%" in lines[5] and "100%" in lines[-1]
    tty = io.StringIO()
    tty.isatty = lambda: True
    bar = ProgressBar(4, stream=tty, width=4, min_interval_s=0.0, clock=lambda: now[0])
    for k in range(1, 5):
        bar.update(k)
    bar.close()
    assert tty.getvalue().count("\r") == 4 and tty.getvalue().endswith("\n")
    assert "\n" not in tty.getvalue()[:-1]       # redrawn in place
    assert tty.getvalue().count("done in") == 1  # the finished bar is drawn once
    cut = io.StringIO()                          # closed early: the last state drawn
    cut.isatty = lambda: True
    bar = ProgressBar(4, stream=cut, width=4, min_interval_s=0.0, clock=lambda: now[0])
    bar.update(2)
    bar.close()
    assert cut.getvalue().count("\r") == 2 and cut.getvalue().endswith(" 2/4  ETA 0:00.0\n")
