"""Text of the head-up display and of the help overlay (no VTK here).

:func:`format_hud` turns the dictionary the app passes to
:meth:`bonesim.render.scene.Scene.set_hud` into short lines, a label column
and a value, to fit the side panel (about 28 characters wide). Recognised
keys (all optional; units in the names):

===================  ====================================================
``case``             case name
``burr``             burr name (e.g. ``cutting-5mm``; shown only when it
                     says more than kind and diameter)
``burr_kind``        ``cutting`` / ``diamond``
``burr_diameter_mm`` burr diameter [mm]
``tool``             ``burr``, ``suction`` or ``irrigation`` (shown
                     unless ``burr``)
``irrigation``       bool, irrigation water running (shown when on)
``drill``            bool, drill running
``direction``        +1 / -1 (or ``"forward"`` / ``"reverse"``)
``speed_rpm``        spindle speed [rpm]
``force_n``          applied force magnitude [N]
``depth_mm``         tissue between the burr and the eye [mm]
                     (:func:`bonesim.physics.sightline.depth_below_surface_mm`);
                     None: not shown
``haptic_hz``        haptic loop rate [Hz]
``frame_hz``         frame rate [Hz] (default: measured by the scene)
``elapsed_s``        run time [s]
``injuries``         count, list of structure names (shown by their
                     clinical names, :func:`bonesim.io.anatomy.clinical_name`),
                     or text
``visible``          ``(visible, judged)``: removals the eye could see since the
                     case reset, of those judged (the recorder's voxel
                     visibility, :mod:`bonesim.physics.visibility`); shown as a
                     percentage once any is judged; None: not shown
``force_limit``      ``{"structure", "count", "warning"}``: the live force
                     limits near a structure (:class:`bonesim.physics.force_limits.ForceWatch`):
                     steps over a limit so far, and the latest
                     :class:`~bonesim.physics.force_limits.LimitWarning` while it
                     is recent (else None); None: not shown
``device``           ``(name, state)`` or ``(name, state, rejected)`` of a
                     real device behind the safety layer; ``state`` one of
                     :data:`DEVICE_STATE_TEXT`'s keys (``unplugged``: the mouse
                     drives); ``rejected``: bad samples so far
``message``          free text (status, warnings), one paragraph a line,
                     wrapped (continuations indented by two spaces)
===================  ====================================================

Any other key is shown as ``key: value``. Structures are named by their
clinical names (``facial_nerve`` shows as ``Facial nerve``), whichever name
the app passes.
"""
from __future__ import annotations

import textwrap

from bonesim.io.anatomy import clinical_name

__all__ = ["DEVICE_STATE_TEXT", "KNOWN", "LABEL_W", "WRAP_CHARS", "WRAP_INDENT", "format_hud", "format_help"]

KNOWN = ("case", "burr", "burr_kind", "burr_diameter_mm", "tool", "irrigation", "drill",
         "direction",
         "speed_rpm", "force_n", "depth_mm", "haptic_hz", "frame_hz", "elapsed_s",
         "injuries", "visible", "force_limit", "message", "device")
#: How each device state (:data:`bonesim.devices.safety.STATES`) reads on the HUD.
DEVICE_STATE_TEXT = {"active": "", "waiting": "hold still", "ramping": "forces in",
                     "unplugged": "UNPLUGGED - mouse"}
#: Width of the label column [characters].
LABEL_W = 7
#: Messages wrap at this many characters; continuation lines are indented.
WRAP_CHARS = 28
WRAP_INDENT = "  "


def _num(v, fmt):
    try:
        return format(float(v), fmt)
    except (TypeError, ValueError):
        return str(v)


def _direction(v) -> str:
    if isinstance(v, str):
        return "REV" if v.lower().startswith("rev") else "FWD"
    try:
        return "REV" if float(v) < 0 else "FWD"
    except (TypeError, ValueError):
        return str(v)


def _injuries(v) -> str:
    if v is None:
        return "none"
    if isinstance(v, (list, tuple)):
        if not v:
            return "none"
        names = [clinical_name(str(x)) for x in v]
        text = ", ".join(names[:3]) + (f" +{len(names) - 3}" if len(names) > 3 else "")
        return f"{len(names)} ({text})"
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return "none" if v == 0 else str(int(v))
    return str(v)


def _line(label: str, value: str) -> str:
    return f"{label.ljust(LABEL_W - 1)} {value}"


def _burr_line(info: dict) -> str:
    parts = []
    if "burr_kind" in info:
        parts.append(str(info["burr_kind"]))
    if "burr_diameter_mm" in info:
        parts.append(_num(info["burr_diameter_mm"], ".1f") + " mm")
    name = str(info["burr"]) if "burr" in info else None
    if name is not None:
        plain = ""
        try:
            plain = f"{info.get('burr_kind', '')}-{float(info['burr_diameter_mm']):g}mm"
        except (KeyError, TypeError, ValueError):
            pass
        if not parts or name.replace(" ", "").lower() != plain.lower():
            parts.append(f"({name})" if parts else name)
    return _line("burr", " ".join(parts))


def _depth(v) -> str:
    d = float(v)
    return "in view" if d <= 0 else f"{d:.1f} mm under bone"


def _force_limit(v: dict) -> list:
    name = clinical_name(str(v.get("structure", "")))
    w = v.get("warning")
    if w is None:
        n = int(v.get("count", 0))
        state = "ok" if n == 0 else f"{n:,} over"
        return [_line("limit", f"{name}: {state}")]
    if w.quantity == "force_n":
        text = f"{w.value:.2f} > {w.limit:.2f} N"
    elif w.quantity == "approach_mm":           # closer than any expert came
        text = f"{w.value:.1f} < {w.limit:.1f} mm"
    else:
        text = f"{w.value:,.0f} > {w.limit:,.0f} rpm"
    return [_line("LIMIT!", text), f"{WRAP_INDENT}{w.distance_mm:.1f} mm from {name}"]


def _device(v) -> str:
    if isinstance(v, str):
        return v
    name, state = str(v[0]), str(v[1])
    text = DEVICE_STATE_TEXT.get(state, state)
    out = f"{name} {text}".strip()
    if len(v) > 2 and int(v[2]) > 0:
        out += f" ({int(v[2])} bad)"
    return out


def format_hud(info: dict, measured_frame_hz: float | None = None) -> str:
    """Lines of the HUD for ``info`` (see the module docstring).

    Parameters
    ----------
    info : dict
        Values to show.
    measured_frame_hz : float, optional
        Shown as the frame rate when ``info`` has no ``frame_hz``.

    Returns
    -------
    str
        Newline-separated text.
    """
    lines = []
    if "case" in info:
        lines.append(_line("case", str(info["case"])))
    if info.get("device") is not None:
        lines.append(_line("device", _device(info["device"])))
    if str(info.get("tool", "burr")) != "burr":
        lines.append(_line("tool", str(info["tool"])))
    if info.get("irrigation"):
        lines.append(_line("water", "on"))
    if any(k in info for k in ("burr", "burr_kind", "burr_diameter_mm")):
        lines.append(_burr_line(info))
    drill = []
    if "drill" in info:
        drill.append("ON" if info["drill"] else "off")
    if "direction" in info:
        drill.append(_direction(info["direction"]))
    if "speed_rpm" in info:
        drill.append(_num(info["speed_rpm"], ",.0f") + " rpm")
    if drill:
        lines.append(_line("drill", " ".join(drill)))
    if "force_n" in info:
        lines.append(_line("force", _num(info["force_n"], ".2f") + " N"))
    if info.get("depth_mm") is not None:
        lines.append(_line("depth", _depth(info["depth_mm"])))
    if "haptic_hz" in info:
        lines.append(_line("haptic", _num(info["haptic_hz"], ".0f") + " Hz"))
    fr = info.get("frame_hz", measured_frame_hz)
    if fr is not None:
        lines.append(_line("frame", _num(fr, ".0f") + " Hz"))
    if "elapsed_s" in info:
        lines.append(_line("time", _num(info["elapsed_s"], ".1f") + " s"))
    if "injuries" in info:
        lines.append(_line("injury", _injuries(info["injuries"])))
    seen = info.get("visible")
    if seen is not None and seen[1] > 0:
        lines.append(_line("seen", f"{100.0 * seen[0] / seen[1]:.0f} % of {seen[1]:,}"))
    if info.get("force_limit") is not None:
        lines += _force_limit(info["force_limit"])
    for k, v in info.items():
        if k not in KNOWN:
            lines.append(f"{k}: {v}")
    if info.get("message"):
        for para in str(info["message"]).splitlines():
            lines += textwrap.wrap(para, WRAP_CHARS, subsequent_indent=WRAP_INDENT) or [para]
    return "\n".join(lines)


def format_help(keys: dict, mouse_lines=()) -> str:
    """Help overlay text: one ``key(s)  action`` line per action.

    Parameters
    ----------
    keys : dict
        Key symbol -> action name (as :data:`bonesim.render.window.DEFAULT_KEYS`).
    mouse_lines : sequence of str
        Extra lines describing the mouse.
    """
    by_action: dict = {}
    for sym, action in keys.items():
        by_action.setdefault(action, []).append(_pretty_key(sym))
    width = max((len(" / ".join(v)) for v in by_action.values()), default=0)
    out = ["keys"]
    for action, syms in by_action.items():
        out.append(f"  {' / '.join(syms).ljust(width)}  {action.replace('_', ' ')}")
    if mouse_lines:
        out.append("mouse")
        out += [f"  {ln}" for ln in mouse_lines]
    return "\n".join(out)


_PRETTY = {"space": "Space", "plus": "+", "equal": "=", "minus": "-", "KP_Add": "keypad +",
           "KP_Subtract": "keypad -", "BackSpace": "Backspace", "Escape": "Esc",
           "Prior": "PgUp", "Next": "PgDn"}


def _pretty_key(sym: str) -> str:
    return _PRETTY.get(sym, sym)
