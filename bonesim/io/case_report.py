"""Text output of ``bonesim case-info`` and the load progress bar of the case
commands."""
from __future__ import annotations

__all__ = ["LoadProgress", "monitor_line", "print_case_info"]


def table(rows: list[dict], cols: list[str]) -> None:
    """Print ``rows`` as left-aligned columns ``cols`` under a header line."""
    widths = [max(len(c), *(len(str(r.get(c, ""))) for r in rows)) for c in cols]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)))
    for r in rows:
        print("  ".join(str(r.get(c, "")).ljust(w) for c, w in zip(cols, widths)))


class LoadProgress:
    """``progress(done, total, what)`` callback drawing one bar per stage on
    stderr (:class:`bonesim.progress.ProgressBar`)."""

    def __init__(self, stream=None):
        self.stream = stream
        self.bar = None
        self.what = None

    def __call__(self, done, total, what="loading") -> None:
        from bonesim.progress import ProgressBar

        if self.bar is None or what != self.what or int(total) != self.bar.total:
            self.close()
            self.bar = ProgressBar(int(total), label=str(what), stream=self.stream)
            self.what = what
        self.bar.update(int(done))

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


_ORIENTATION_TEXT = {
    "declared": "{code}, declared in the manifest",
    "file": "read from the file's header",
    "assumed": "{code}, assumed: the manifest declares none (add orientation = "
               "\"...\" to [volume] if the stack is not stored in LPS)",
    "generated": "{code}, generated in the patient frame",
}


def _rgb_text(rgb) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def monitor_line(monitored, available=(), shown=None) -> str:
    """``monitor: Facial nerve, Chorda tympani (also available, off:
    Vestibular nerve)``: the nerves the monitor watches and those it could,
    by their clinical names (``shown``: code name -> clinical name)."""
    shown = shown or {}
    on = ", ".join(shown.get(n, n) for n in monitored) or "none"
    rest = ", ".join(shown.get(n, n) for n in available)
    return f"monitor: {on}" + (f" (also available, off: {rest})" if rest else "")


def print_case_info(info: dict) -> None:
    """Print :func:`bonesim.io.case.case_info`'s summary as text (stdout)."""
    f = info["frame"]
    lateral = "+x" if info["side"] == "left" else "-x"
    print(f"case: {info['name']} ({info['side']} ear)")
    if info["description"]:
        print(f"description: {info['description']}")
    print(f"manifest: {info['manifest']}")
    print(f"patient frame: {f['name']} [{f['units']}]: +x {f['x']}, +y {f['y']}, "
          f"+z {f['z']}; lateral for this ear is {lateral}")
    o = info["orientation"]
    print("orientation: " + _ORIENTATION_TEXT[o["source"]].format(code=o["code"]))
    print(f"volume: {info['format']}, {info['source']}")
    print(f"grid: {' x '.join(map(str, info['grid']))} voxels of {info['voxel_mm']:g} mm, "
          f"origin {[round(v, 3) for v in info['origin_mm']]} mm, extent "
          f"{[round(v, 3) for v in info['extent_mm']]} mm")
    c = info["camera"]
    how = "derived from the anatomy" if c["source"] == "anatomy" else "from the manifest"
    print(f"camera ({how}): eye {c['eye_mm']} mm, focal {c['focal_mm']} mm, "
          f"up {c['up']}")
    for note in c.get("notes", []):
        print(f"  {note}")
    lm = info.get("landmarks")
    if lm:
        print("landmarks (confidence: labelled, split from a merged label, found from "
              "geometry, estimated):")
        for name, m in lm["landmarks"].items():
            p = ", ".join(f"{v:.1f}" for v in m["point_mm"])
            print(f"  {name.replace('_', ' '):16s} [{p}] mm  {m['confidence']:9s} "
                  f"{m['source']}")
        for m in lm["missing"]:
            print(f"  missing: {m}")
        for n in lm["notes"]:
            print(f"  {n}")
    shown = info.get("display_names", {})
    off = info.get("monitor_available", [])
    rows = [{"structure": n, "shown as": shown.get(n, n), "kind": info["kinds"][n],
             "voxels": info["counts"][n],
             "colour": f"{_rgb_text(info['colors'][n]['rgb'])} "
                       f"({info['colors'][n]['source']})",
             "monitor": "yes" if n in info["monitored"] else "off" if n in off else ""}
            for n in info["counts"]]
    print(f"structures ({info['total']} voxels in all):")
    table(rows, ["structure", "shown as", "kind", "voxels", "colour", "monitor"])
    print(monitor_line(info["monitored"], off, shown))
    for w in info["warnings"]:
        print(f"warning: {w}")
