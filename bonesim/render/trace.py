"""The nerve monitor's scrolling trace, docked beside the scene's 3D view.

What the technician at the facial-nerve monitor watches, beside the
surgeon's view: one lane per monitored nerve (:mod:`bonesim.runtime.monitor`),
stacked top to bottom in a panel at the top of the scene's side column
(:meth:`bonesim.render.scene.Scene.text_rect`), so that it never covers the
drilling field. A scene without a side column (``Scene(panel=False)``) gets
the panel over the top-right corner of the view instead.

In each lane

* the firing rate of the last ``window_s`` seconds as a polyline in the
  nerve's colour; time runs left to right, the newest sample at the right
  edge; the rate is drawn on a square-root scale from 0 to ``max_hz`` (so
  the resting few spikes per second are visible and a 400/s burst fits);
* every spike as a short vertical tick in a strip along the lane's bottom
  (at most one tick per pixel column);
* a faint dashed line at the resting rate ``baseline_hz``;
* a label in the nerve's colour: its clinical name (``Facial nerve``,
  :func:`bonesim.io.anatomy.clinical_name`), burr-to-nerve distance
  (``d 2.3 mm``; ``d > 10 mm`` at 10 mm or farther, infinite included) and
  rate (``45/s``) of the newest sample (:func:`format_label`). Closer than
  ``warn_mm`` the lane turns red and the label starts with ``WARNING``.
  Fields are two spaces apart, one where the lane is narrow; the font (as
  the HUD's, scaled to the window) shrinks so that the longest label of
  its kind fits, and so does not change with the digits.

Mapping (pixels, origin bottom-left; :meth:`MonitorTrace.plot_rect` gives
lane ``c``'s plot area ``(px0, py0, px1, py1)``)::

    x(t)    = px1 - (now - t) / window_s * (px1 - px0)
    y(rate) = py0 + sqrt(min(max(rate, 0), max_hz) / max_hz) * (py1 - py0)

Layout (:meth:`MonitorTrace.rect`, window pixels). In a side column: the
column's width less :data:`MARGIN_PX` on each side, :data:`MARGIN_PX` from
its top. Over the view: :data:`MARGIN_PX` from the top and right edges,
``0.35`` of the window's width (150 to 560 px). Lanes of ``0.15`` of the
height (36 to 110 px). The panel ends above the bottom
:data:`BOTTOM_CLEAR_PX` pixels of the view (where the playback timeline
lives; :data:`MARGIN_PX` in a side column) and, when the scene's HUD text
reaches under the panel, above the HUD; lanes shrink to fit. Where keeping
clear of the HUD would make lanes lower than :data:`MIN_LANE_PX` (tiny
windows) the panel overlaps it; it never enters the bottom rows (it is not
drawn when it cannot fit at all).

The overlay is built like :class:`bonesim.render.playback.TimelineBar`:
2-D actors in pixel coordinates, fed from numpy arrays in one go, direct
RGBA cell colours. Call :meth:`MonitorTrace.update` once per frame (it also
follows window resizes).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkRenderingCore import vtkActor2D, vtkPolyDataMapper2D, vtkTextActor

from bonesim.io.anatomy import clinical_name
from bonesim.runtime.monitor import HISTORY_S

__all__ = ["MonitorTrace", "format_label", "PANEL_RGBA", "LANE_RGBA", "WARN_RGBA",
           "BASELINE_RGBA", "MARGIN_PX", "BOTTOM_CLEAR_PX", "MIN_LANE_PX", "FAR_MM",
           "TRACE", "TICK", "BASELINE"]

#: Panel background, lane background and a warning lane's background (RGBA 0-255).
PANEL_RGBA = (8, 10, 14, 170)
LANE_RGBA = (30, 34, 42, 140)
WARN_RGBA = (175, 25, 20, 200)
#: Dashed resting-rate line (RGBA 0-255).
BASELINE_RGBA = (200, 200, 200, 110)
#: Distance of the panel from the window's top and right edges [px].
MARGIN_PX = 8
#: The panel stays above this many bottom rows (the playback timeline) [px].
BOTTOM_CLEAR_PX = 40
#: Gap kept between the panel and the HUD text [px].
HUD_GAP_PX = 6
#: Smallest lane height before the panel gives up avoiding the HUD [px].
MIN_LANE_PX = 14
#: Padding inside the panel and gap between lanes [px].
PAD_PX = 3
LANE_GAP_PX = 2
#: Distances at or beyond this (or infinite) read ``d > 10 mm`` [mm].
FAR_MM = 10.0
#: Cell kinds of :attr:`MonitorTrace.foreground` (cell array ``kind``).
TRACE, TICK, BASELINE = 0, 1, 2
#: Width of a Courier glyph per pixel of font size (to fit labels in a lane).
_GLYPH_EM = 0.6


def format_label(name: str, dist_mm: float | None, rate_hz: float | None,
                 warn_mm: float, sep: str = "  ") -> str:
    """Text of a lane's label.

    Parameters
    ----------
    name : str
        The nerve.
    dist_mm : float or None
        Burr surface to the nerve [mm] (None: no data; negative: inside).
    rate_hz : float or None
        Firing rate [spikes/s] (None: no data).
    warn_mm : float
        Closer than this the label starts with ``WARNING`` [mm].
    sep : str
        Between the fields.
    """
    if dist_mm is None or rate_hz is None:
        return f"{name}{sep}no signal"
    d = float(dist_mm)
    if math.isnan(d):
        ds = "d ?"
    elif d >= FAR_MM:
        ds = f"d > {FAR_MM:.0f} mm"
    else:
        ds = f"d {max(d, 0.0):.1f} mm"
    r = float(rate_hz)
    rs = "?/s" if not math.isfinite(r) else f"{max(r, 0.0):.0f}/s"
    text = sep.join((name, ds, rs))
    return (f"WARNING{sep}" + text) if d < warn_mm else text


def _quads_points(q: np.ndarray) -> np.ndarray:
    """(n, 4) rectangles ``x0, y0, x1, y1`` -> (4 n, 3) float32 corners."""
    pts = np.zeros((len(q), 4, 3), np.float32)
    pts[:, 0, :2] = q[:, [0, 1]]
    pts[:, 1, :2] = q[:, [2, 1]]
    pts[:, 2, :2] = q[:, [2, 3]]
    pts[:, 3, :2] = q[:, [0, 3]]
    return pts.reshape(-1, 3)


def _set_cells(pd: vtkPolyData, pts: np.ndarray, sizes: np.ndarray, rgba: np.ndarray,
               extra: dict, polys: bool) -> None:
    """Fill ``pd`` with cells of ``sizes`` points each, laid out in order in
    ``pts`` ((n, 3) float32), coloured by ``rgba`` ((cells, 4) uint8)."""
    points = vtkPoints()
    points.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(pts, np.float32),
                                              deep=True))
    offs = np.zeros(len(sizes) + 1, np.int64)
    np.cumsum(sizes, out=offs[1:])
    conn = np.arange(int(offs[-1]), dtype=np.int64)
    cells = vtkCellArray()
    cells.SetData(numpy_support.numpy_to_vtkIdTypeArray(offs, deep=True),
                  numpy_support.numpy_to_vtkIdTypeArray(conn, deep=True))
    pd.Initialize()
    pd.SetPoints(points)
    if polys:
        pd.SetPolys(cells)
    else:
        pd.SetLines(cells)
    col = numpy_support.numpy_to_vtk(np.ascontiguousarray(rgba, np.uint8), deep=True)
    col.SetName("rgba")
    cd = pd.GetCellData()
    cd.SetScalars(col)
    for name, values in extra.items():
        a = numpy_support.numpy_to_vtk(np.ascontiguousarray(values, np.uint8), deep=True)
        a.SetName(name)
        cd.AddArray(a)
    pd.Modified()


def _overlay(pd: vtkPolyData, line_width: float | None = None) -> vtkActor2D:
    mapper = vtkPolyDataMapper2D()
    mapper.SetInputData(pd)
    mapper.SetColorModeToDirectScalars()
    mapper.SetScalarModeToUseCellData()
    mapper.ScalarVisibilityOn()
    actor = vtkActor2D()
    actor.SetMapper(mapper)
    actor.PickableOff()
    if line_width is not None:
        actor.GetProperty().SetLineWidth(line_width)
    return actor


class _Layout(NamedTuple):
    panel: tuple            # (x0, y0, x1, y1) [px]
    lh: int                 # lane height [px]
    font: int               # label font size [px]
    label_h: int            # label strip at a lane's top [px]
    tick_h: int             # spike strip at a lane's bottom [px]
    lanes: list             # per lane (x0, y0, x1, y1) [px]
    plots: list             # per lane (px0, py0, px1, py1) [px]


class MonitorTrace:
    """Scrolling trace of the nerve monitor, in the scene's side column (or
    over the top-right corner of its view without one).

    Parameters
    ----------
    scene : Scene
        Its renderer receives the overlay; its window size sets the layout;
        its ``hud_actor`` (if any) is kept clear of.
    names : sequence of str
        The monitored nerves, one lane each (top to bottom); their labels
        show the clinical names (:attr:`titles`).
    colors : (k, 3) array_like
        Their display colours, RGB 0-255.
    window_s : float
        Time span shown [s].
    max_hz : float
        Rate at the top of a lane [spikes/s].
    warn_mm : float
        Closer than this the lane warns [mm].
    baseline_hz : float
        Resting rate, drawn as a dashed line [spikes/s] (None or <= 0: none).

    Attributes
    ----------
    background : vtkPolyData
        Panel and lane rectangles (cell array ``rgba``).
    foreground : vtkPolyData
        Line cells with cell arrays ``rgba``, ``kind`` (:data:`TRACE`,
        :data:`TICK`, :data:`BASELINE`) and ``lane``.
    labels : list of vtkTextActor
        One per lane.
    titles : list of str
        The nerves' clinical names, as the labels show them.
    now : float
        Loop time at the right edge in the last drawing [s].
    warning : (k,) bool
        Lanes warning in the last drawing.
    """

    def __init__(self, scene, names, colors, *, window_s: float = HISTORY_S,
                 max_hz: float = 400.0, warn_mm: float = 1.0,
                 baseline_hz: float | None = 4.0):
        names = [str(n) for n in names]
        if not names:
            raise ValueError("MonitorTrace needs at least one nerve name")
        if len(names) > 255:
            raise ValueError(f"at most 255 nerves, got {len(names)}")
        try:
            col = np.asarray(colors, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"colors must be a (k, 3) array of 0-255 values, got {colors!r}")
        if col.ndim != 2 or col.shape[1] != 3:
            raise ValueError(f"colors must have shape (k, 3) (RGB 0-255), got {col.shape}")
        if col.shape[0] != len(names):
            raise ValueError(f"{len(names)} names but {col.shape[0]} colors")
        if not (np.all(np.isfinite(col)) and col.min() >= 0 and col.max() <= 255):
            raise ValueError("colors must be RGB values from 0 to 255")
        for key, v in (("window_s", window_s), ("max_hz", max_hz)):
            if not (isinstance(v, (int, float, np.number)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{key} must be a finite number > 0, got {v!r}")
        if not (isinstance(warn_mm, (int, float, np.number)) and not math.isnan(warn_mm)):
            raise ValueError(f"warn_mm must be a number, got {warn_mm!r}")
        self.scene = scene
        self.names = names
        self.titles = [clinical_name(n) for n in names]
        self.colors = np.rint(col).astype(np.uint8)
        self.window_s = float(window_s)
        self.max_hz = float(max_hz)
        self.warn_mm = float(warn_mm)
        self.baseline_hz = None if baseline_hz is None or not baseline_hz > 0 \
            else float(baseline_hz)
        self.now = 0.0
        self.warning = np.zeros(self.k, bool)
        self._visible = True
        self._hist = None
        self._styles: dict = {}
        self._bg_key = None
        self.background = vtkPolyData()
        self.foreground = vtkPolyData()
        self._bg_actor = _overlay(self.background)
        self._fg_actor = _overlay(self.foreground, 1.0)
        # 2-D props go into the scene's text renderer (its side column);
        # geometry is built in window pixels and shifted by the actors'
        # positions into that renderer's viewport
        self._ren = getattr(scene, "text_renderer", scene.renderer)
        self._origin = (0, 0)
        self._ren.AddViewProp(self._bg_actor)
        self._ren.AddViewProp(self._fg_actor)
        self.labels = []
        for c in range(self.k):
            ta = vtkTextActor()
            tp = ta.GetTextProperty()
            tp.SetFontFamilyToCourier()
            tp.SetBold(True)
            tp.SetFontSize(10)
            tp.SetColor(*(self.colors[c] / 255.0))
            tp.SetVerticalJustificationToTop()
            tp.SetJustificationToLeft()
            ta.PickableOff()
            ta.SetInput("")
            self._ren.AddViewProp(ta)
            self.labels.append(ta)
        self.update({"now": 0.0})

    @property
    def k(self) -> int:
        """Number of nerves (lanes)."""
        return len(self.names)

    # ------------------------------------------------------------ layout
    def size(self) -> tuple[int, int]:
        """Window width, height [px] ((0, 0) once the scene is closed)."""
        rw = self.scene.render_window
        if rw is None:
            return 0, 0
        w, h = rw.GetSize()
        return int(w), int(h)

    def _host(self) -> tuple[tuple[int, int, int, int], bool]:
        """The pixel rectangle the panel lives in (window coordinates) and
        whether it is a side column of its own."""
        w, h = self.size()
        sc = self.scene
        if getattr(sc, "panel_renderer", None) is not None and sc.render_window is not None:
            return tuple(int(v) for v in sc.text_rect()), True
        return (0, 0, w, h), False

    def _hud_box(self):
        """Pixel box ``(x0, y0, x1, y1)`` of the scene's HUD text (window
        coordinates), or None."""
        hud = getattr(self.scene, "hud_actor", None)
        if hud is None or not hud.GetVisibility() or not (hud.GetInput() or ""):
            return None
        bb = [0.0] * 4
        hud.GetBoundingBox(self._ren, bb)
        px, py = hud.GetPosition()
        ox, oy = self._host()[0][:2]
        return ox + px + bb[0], oy + py + bb[2], ox + px + bb[1], oy + py + bb[3]

    def _layout(self) -> "_Layout | None":
        """Panel, lanes and plot areas for the current window size (None
        when the window is too small to hold the panel)."""
        w, h = self.size()
        k = self.k
        (hx0, hy0, hx1, hy1), column = self._host()
        if column:
            pw = hx1 - hx0 - 2 * MARGIN_PX
        else:
            pw = min(max(round(0.35 * w), 150), 560, w - 2 * MARGIN_PX)
        x1 = hx1 - MARGIN_PX
        x0 = x1 - pw
        y1 = hy1 - MARGIN_PX
        hard = hy0 + (MARGIN_PX if column else BOTTOM_CLEAR_PX)
        soft = hard
        hud = self._hud_box()
        if hud is not None and hud[2] >= x0 - HUD_GAP_PX and hud[1] < y1:
            soft = max(hard, int(math.ceil(hud[3])) + HUD_GAP_PX)
        fixed = (k - 1) * LANE_GAP_PX + 2 * PAD_PX
        lh = min(max(round(0.15 * h), 36), 110)
        if y1 - (k * lh + fixed) < soft:
            lh = max((y1 - soft - fixed) // k, MIN_LANE_PX)
        if y1 - (k * lh + fixed) < hard:
            lh = (y1 - hard - fixed) // k
        if pw < 20 or lh < 4:
            return None
        font = min(max(round(h / 40.0), 8), 15)
        label_h = min(font + 4, lh // 2)
        tick_h = min(max(round(0.18 * lh), 2), 10)
        lanes, plots = [], []
        for c in range(k):
            top = y1 - PAD_PX - c * (lh + LANE_GAP_PX)
            lane = (x0 + PAD_PX, top - lh, x1 - PAD_PX, top)
            lanes.append(lane)
            plots.append((lane[0] + 2, lane[1] + tick_h + 2, lane[2] - 2,
                          max(lane[3] - label_h, lane[1] + tick_h + 3)))
        return _Layout((x0, y1 - (k * lh + fixed), x1, y1), lh, font, label_h, tick_h,
                       lanes, plots)

    def _need_layout(self) -> "_Layout":
        lay = self._layout()
        if lay is None:
            raise ValueError("the window is too small for the monitor trace")
        return lay

    def _lane(self, c: int) -> int:
        if not 0 <= c < self.k:
            raise IndexError(f"lane {c} of {self.k}")
        return c

    def rect(self) -> tuple[int, int, int, int] | None:
        """The panel's pixel rectangle ``(x0, y0, x1, y1)`` for the current
        window size (origin bottom-left); None when the window is too small
        to hold it."""
        lay = self._layout()
        return None if lay is None else lay.panel

    def lane_rect(self, c: int) -> tuple[int, int, int, int]:
        """Pixel rectangle of nerve ``c``'s lane (lane 0 at the top)."""
        return self._need_layout().lanes[self._lane(c)]

    def plot_rect(self, c: int) -> tuple[int, int, int, int]:
        """Pixel rectangle ``(px0, py0, px1, py1)`` of lane ``c``'s rate plot:
        below the label, above the spike ticks (see the module docstring for
        the mapping)."""
        return self._need_layout().plots[self._lane(c)]

    def tick_span(self, c: int) -> tuple[int, int]:
        """Rows ``(y0, y1)`` of lane ``c``'s spike ticks [px]."""
        lay = self._need_layout()
        y0 = lay.lanes[self._lane(c)][1] + 1
        return y0, y0 + lay.tick_h

    def x_of(self, t, now: float) -> np.ndarray:
        """Pixel column of loop time(s) ``t`` [s] with ``now`` at the right
        edge (not clipped; earlier than ``now - window_s`` is left of the plot)."""
        return self._x(self._need_layout(), t, now)

    def y_of(self, rate, c: int) -> np.ndarray:
        """Pixel row of rate(s) ``rate`` [spikes/s] in lane ``c`` (square-root
        scale, clipped to 0 .. ``max_hz``)."""
        return self._y(self._need_layout(), rate, self._lane(c))

    def _x(self, lay, t, now):
        px0, _, px1, _ = lay.plots[0]
        return px1 - (float(now) - np.asarray(t, float)) / self.window_s * (px1 - px0)

    def _y(self, lay, rate, c):
        _, py0, _, py1 = lay.plots[c]
        r = np.minimum(np.fmax(np.asarray(rate, float), 0.0), self.max_hz)   # NaN -> 0
        return py0 + np.sqrt(r / self.max_hz) * (py1 - py0)

    # ------------------------------------------------------------ drawing
    @property
    def visible(self) -> bool:
        return self._visible

    def set_visible(self, on: bool) -> None:
        """Show or hide the whole trace (redrawn from the last history when shown)."""
        self._visible = bool(on)
        if self._visible and self._hist is not None:
            self.update(self._hist)
        else:
            self._show(False)

    def _show(self, on: bool) -> None:
        for a in [self._bg_actor, self._fg_actor] + self.labels:
            a.SetVisibility(on)

    def text(self) -> str:
        """The label text shown now, one line per lane ("" when hidden)."""
        if not self._visible or not self._bg_actor.GetVisibility():
            return ""
        return "\n".join(a.GetInput() or "" for a in self.labels)

    def update(self, hist: dict) -> None:
        """Redraw from a history (as :meth:`bonesim.runtime.monitor.MonitorView.history`).

        Parameters
        ----------
        hist : dict
            ``now`` (loop time [s]), ``t_s`` (m,), ``rate`` (m, k) [spikes/s],
            ``dist`` (m, k) [mm], ``spike_t`` (s,) [s], ``spike_nerve`` (s,);
            missing arrays count as empty. The right edge is the latest of
            ``now`` and the newest time given (the history may have been
            read while the monitor wrote). The labels show the last row.
        """
        k = self.k
        t = np.asarray(hist.get("t_s", ()), np.float64).reshape(-1)
        m = t.shape[0]
        rate = np.asarray(hist.get("rate", np.zeros((m, k))), np.float64)
        dist = np.asarray(hist.get("dist", np.full((m, k), np.inf)), np.float64)
        if rate.size == 0:
            rate = rate.reshape(0, k)
        if dist.size == 0:
            dist = dist.reshape(0, k)
        if rate.shape != (m, k) or dist.shape != (m, k):
            raise ValueError(f"history of {m} times needs rate and dist of shape "
                             f"({m}, {k}), got {rate.shape} and {dist.shape}")
        st = np.asarray(hist.get("spike_t", ()), np.float64).reshape(-1)
        sn = np.asarray(hist.get("spike_nerve", np.zeros(st.shape[0], np.uint8))).reshape(-1)
        if sn.shape != st.shape:
            raise ValueError(f"{st.shape[0]} spike times but {sn.shape[0]} spike nerves")
        now = float(hist.get("now", 0.0))
        for a in (t, st):
            fin = a[np.isfinite(a)]
            if fin.size:
                now = max(now, float(fin.max()))
        self.now = now
        self._hist = hist
        if m:
            last_d = dist[-1]
            self.warning = np.nan_to_num(last_d, nan=np.inf) < self.warn_mm
        else:
            self.warning = np.zeros(k, bool)
        if not self._visible:
            return
        lay = self._layout()
        if lay is None:
            self._show(False)
            return
        self._show(True)
        origin = self._host()[0][:2]
        if origin != self._origin:
            self._origin = origin
            for a in (self._bg_actor, self._fg_actor):
                a.SetPosition(-origin[0], -origin[1])
        self._draw(lay, t, rate, dist, st, sn, now)

    def _draw(self, lay: _Layout, t, rate, dist, st, sn, now) -> None:
        k = self.k
        m = t.shape[0]
        # backgrounds: panel, then one rectangle per lane (rebuilt on change only)
        key = (lay.panel, tuple(lay.lanes), tuple(self.warning.tolist()))
        if key != self._bg_key:
            q = np.array([lay.panel] + lay.lanes, float)
            bg = np.empty((k + 1, 4), np.uint8)
            bg[0] = PANEL_RGBA
            bg[1:] = np.where(self.warning[:, None], np.array(WARN_RGBA, np.uint8),
                              np.array(LANE_RGBA, np.uint8))
            _set_cells(self.background, _quads_points(q), np.full(k + 1, 4), bg,
                       {"lane": np.r_[255, np.arange(k)]}, polys=True)
            self._bg_key = key

        # foreground, drawn in this order: baseline dashes, spike ticks, traces
        chunks = []                 # (points (n, 2), sizes, rgba (cells, 4), kind, lane)
        px0, _, px1, _ = lay.plots[0]
        span = px1 - px0
        t_lo = now - self.window_s
        if self.baseline_hz is not None:
            dash = max(3, span // 40)
            starts = np.arange(px0, px1 - 1, 2 * dash, dtype=float)
            nd = len(starts)
            seg = np.empty((k, nd, 2, 2))
            seg[:, :, 0, 0] = starts
            seg[:, :, 1, 0] = np.minimum(starts + dash, px1)
            yb = np.floor([self._y(lay, self.baseline_hz, c) for c in range(k)]) + 0.5
            seg[:, :, :, 1] = yb[:, None, None]
            chunks.append((seg.reshape(-1, 2), np.full(k * nd, 2),
                           np.tile(np.array(BASELINE_RGBA, np.uint8), (k * nd, 1)),
                           BASELINE, np.repeat(np.arange(k), nd)))
        sk = (st >= t_lo) & (st <= now) & (sn >= 0) & (sn < k)
        if sk.any():                # one tick per (lane, pixel column)
            base = 1 << 24
            col = np.floor(px1 - (now - st[sk]) / self.window_s * span).astype(np.int64)
            key = np.unique(sn[sk].astype(np.int64) * base + col)
            tl, tc = np.divmod(key, base)
            ty0 = np.array([ln[1] + 1 for ln in lay.lanes], float)[tl]
            seg = np.empty((len(key), 2, 2))
            seg[:, :, 0] = (tc + 0.5)[:, None]
            seg[:, 0, 1] = ty0
            seg[:, 1, 1] = ty0 + lay.tick_h
            rgba = np.empty((len(key), 4), np.uint8)
            rgba[:, :3] = self.colors[tl]
            rgba[:, 3] = 220
            chunks.append((seg.reshape(-1, 2), np.full(len(key), 2), rgba, TICK, tl))
        keep = (t >= t_lo) & (t <= now)
        n = int(np.count_nonzero(keep))
        if n:
            xs = self._x(lay, t[keep], now)
            if n == 1:                  # one sample: a short stub ending at it
                xs = np.array([xs[0] - 2.0, xs[0]])
            for c in range(k):
                ys = self._y(lay, rate[keep, c], c)
                ys = np.repeat(ys, 2) if n == 1 else ys
                chunks.append((np.column_stack([xs, ys]), np.array([len(xs)]),
                               np.array([[*self.colors[c], 255]], np.uint8), TRACE,
                               np.array([c])))
        if chunks:
            xy = np.concatenate([ch[0] for ch in chunks])
            sizes = np.concatenate([ch[1] for ch in chunks])
            rgba = np.concatenate([ch[2] for ch in chunks])
            kind = np.concatenate([np.full(len(ch[1]), ch[3], np.uint8) for ch in chunks])
            lane = np.concatenate([ch[4] for ch in chunks]).astype(np.uint8)
        else:
            xy, sizes = np.zeros((0, 2)), np.zeros(0, np.int64)
            rgba, kind, lane = np.zeros((0, 4), np.uint8), np.zeros(0), np.zeros(0)
        p3 = np.zeros((len(xy), 3), np.float32)
        p3[:, :2] = xy
        _set_cells(self.foreground, p3, sizes, rgba, {"kind": kind, "lane": lane},
                   polys=False)
        width = 2.0 if lay.lh >= 60 else 1.0
        if self._fg_actor.GetProperty().GetLineWidth() != width:
            self._fg_actor.GetProperty().SetLineWidth(width)

        # labels: the last row's distance and rate
        for c, ta in enumerate(self.labels):
            lx0, _, lx1, ly1 = lay.lanes[c]
            warn = bool(self.warning[c])
            sep, fs = self._label_style(c, lx1 - lx0 - 6, min(lay.font, lay.label_h), warn)
            text = format_label(self.titles[c], dist[-1, c] if m else None,
                                rate[-1, c] if m else None, self.warn_mm, sep)
            if ta.GetInput() != text:
                ta.SetInput(text)
            tp = ta.GetTextProperty()
            if tp.GetFontSize() != fs:
                tp.SetFontSize(fs)
            at = (lx0 + 3 - self._origin[0], ly1 - 1 - self._origin[1])
            if ta.GetPosition() != at:
                ta.SetPosition(*at)

    def _label_style(self, c: int, room: int, font: int, warn: bool) -> tuple[str, int]:
        """Field separator and font size of lane ``c``'s label: the longest
        label of its kind (warning or not) fits in ``room`` pixels, so the
        size does not jump with the digits."""
        key = (c, room, font, warn)
        got = self._styles.get(key)
        if got is None:
            d = 0.0 if warn else FAR_MM
            w = math.inf if warn else -math.inf
            for sep in ("  ", " "):
                n = len(format_label(self.titles[c], d, self.max_hz, w, sep))
                if n * _GLYPH_EM * font <= room:
                    break
            got = (sep, max(6, min(font, int(room / (_GLYPH_EM * n)))))
            if len(self._styles) > 64:
                self._styles.clear()
            self._styles[key] = got
        return got
