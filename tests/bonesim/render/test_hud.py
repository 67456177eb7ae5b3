"""HUD and help text."""
from __future__ import annotations

from bonesim.render.hud import format_help, format_hud
from bonesim.render.window import DEFAULT_KEYS


def test_hud_lines_with_units():
    text = format_hud({"case": "phantom", "burr": "cutting-5mm", "burr_kind": "cutting",
                       "burr_diameter_mm": 5, "drill": True, "direction": -1,
                       "speed_rpm": 60000, "force_n": 1.234, "haptic_hz": 998.6,
                       "elapsed_s": 3.21, "injuries": ["facial_nerve"]}, 59.7)
    lines = text.splitlines()
    assert lines[0] == "case   phantom"
    assert "burr   cutting 5.0 mm" in lines                  # the name says nothing more
    assert "drill  ON REV 60,000 rpm" in lines
    assert "force  1.23 N" in lines
    assert "haptic 999 Hz" in lines and "frame  60 Hz" in lines
    assert "time   3.2 s" in lines
    assert "injury 1 (Facial nerve)" in lines         # the clinical name
    assert not any(ln.startswith("depth") for ln in lines)   # no depth given
    # compact: fits the side panel
    assert max(len(ln) for ln in lines) <= 28


def test_hud_burr_name_when_it_says_more_and_depth():
    text = format_hud({"burr": "diamond-coarse", "burr_kind": "diamond",
                       "burr_diameter_mm": 3, "depth_mm": 2.345})
    assert "burr   diamond 3.0 mm (diamond-coarse)" in text.splitlines()
    assert "depth  2.3 mm under bone" in text.splitlines()
    assert "depth  in view" in format_hud({"depth_mm": 0.0})
    assert "depth" not in format_hud({"depth_mm": None})


def test_hud_frame_rate_from_info_wins_and_extras_are_listed():
    text = format_hud({"frame_hz": 30, "drill": False, "tool": "suction", "foo": 3}, 60.0)
    assert "frame  30 Hz" in text
    assert "drill  off" in text and "tool   suction" in text and "foo: 3" in text
    assert format_hud({"injuries": 0}) == "injury none"
    msg = format_hud({"message": "no audio device: sound muted, recorded to /tmp/x.wav"})
    assert len(msg.splitlines()) == 3 and max(map(len, msg.splitlines())) <= 28


def test_help_lists_every_action_once():
    text = format_help(DEFAULT_KEYS, ["right drag  orbit"])
    for action in set(DEFAULT_KEYS.values()):
        assert sum(line.strip().endswith(action.replace("_", " "))
                   for line in text.splitlines()) == 1
    assert "Space" in text and "Esc" in text and "orbit" in text


def test_hud_shows_the_running_visible_share_once_any_removal_is_judged():
    assert "seen   87 % of 1,234" in format_hud({"visible": (1074, 1234)}).splitlines()
    assert not any(ln.startswith("seen") for ln in format_hud({"visible": (0, 0)}).splitlines())
    assert not any(ln.startswith("seen")
                   for ln in format_hud({"visible": None}).splitlines())


def test_hud_force_limit_line_ok_over_and_warning():
    from bonesim.physics.force_limits import LimitWarning

    assert format_hud({"force_limit": None}) == ""
    assert format_hud({"force_limit": {"structure": "chorda_tympani", "count": 0,
                                       "warning": None}}) == "limit  Chorda tympani: ok"
    assert format_hud({"force_limit": {"structure": "chorda_tympani", "count": 1234,
                                       "warning": None}}) == \
        "limit  Chorda tympani: 1,234 over"
    w = LimitWarning(1.0, "force_n", 3.3, 2.456, 3.04)
    assert format_hud({"force_limit": {"structure": "facial_nerve", "count": 1,
                                       "warning": w}}).splitlines() == \
        ["LIMIT! 3.30 > 2.46 N", "  3.0 mm from Facial nerve"]
    w = LimitWarning(1.0, "speed_rpm", 80000.0, 60000.0, 12.0)
    assert format_hud({"force_limit": {"structure": "x", "count": 1, "warning": w}}
                      ).splitlines()[0] == "LIMIT! 80,000 > 60,000 rpm"
    w = LimitWarning(1.0, "approach_mm", 0.84, 2.5, 0.84)    # closer than any expert
    assert format_hud({"force_limit": {"structure": "x", "count": 1, "warning": w}}
                      ).splitlines()[0] == "LIMIT! 0.8 < 2.5 mm"


def test_hud_names_structures_by_their_clinical_names():
    """Code names and abbreviations from the case come out as a surgeon
    reads them; names already clinical are kept."""
    text = format_hud({"injuries": ["sigmoid_sinus", "FN", "Chorda tympani", "CN7"]})
    assert text == "injury 4 (Sigmoid sinus, Facial nerve, Chorda tympani +1)"
    from bonesim.physics.force_limits import LimitWarning

    w = LimitWarning(1.0, "force_n", 3.3, 2.456, 0.84)
    lines = format_hud({"force_limit": {"structure": "SS", "count": 1, "warning": w}}
                       ).splitlines()
    assert lines[1] == "  0.8 mm from Sigmoid sinus"         # the distance names it
    assert "_" not in "".join(lines)


def test_device_state_line_says_when_the_mouse_has_taken_over():
    from bonesim.render.hud import format_hud

    assert "device touch UNPLUGGED - mouse" in format_hud({"device": ("touch", "unplugged")})
    text = format_hud({"device": ("touch", "waiting", 3)})
    assert "touch hold still (3 bad)" in text
    assert "device" not in format_hud({"device": None, "case": "x"})
