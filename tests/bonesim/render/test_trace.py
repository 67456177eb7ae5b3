"""The nerve monitor's trace overlay (offscreen): layout for several window
sizes, the polyline and tick geometry against the documented mapping
computed here by hand, warnings, empty and hidden traces, rendered pixels
and a reference picture (``images/trace.png``; regenerate with
``BONESIM_UPDATE_IMAGES=1``, see test_images.py)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from vtkmodules.util import numpy_support

from bonesim.render.imagecmp import compare_images, read_png
from bonesim.render.scene import Scene
from bonesim.render.trace import (BASELINE, LANE_RGBA, TICK, TRACE, WARN_RGBA, MonitorTrace,
                                  format_label)
from tests.bonesim.render import scenes
from tests.bonesim.render.test_images import check

SIZE = (320, 240)
NAMES = ["facial_nerve", "chorda_tympani"]
COLORS = [(250, 230, 40), (250, 150, 30)]
IMAGES = Path(__file__).parent / "images"


@pytest.fixture
def scene(gl_info):
    sc = Scene(size=SIZE, visible_subset=False)
    yield sc
    sc.close()


def history(now=12.0, m=600, rates=(20.0, 4.0), dists=(3.0, 6.0), spikes=((), ()),
            start=None, k=2):
    """A history as MonitorView.history returns it: ``m`` updates ending at
    ``now`` (from ``start``, default ``now - 6`` so some are older than the
    5 s window), constant rates and distances, the given spike times."""
    start = now - 6.0 if start is None else start
    t = np.linspace(start, now, m) if m else np.zeros(0)
    rate = np.tile(np.resize(np.asarray(rates, np.float32), k), (m, 1))
    dist = np.tile(np.resize(np.asarray(dists, np.float32), k), (m, 1))
    st = np.concatenate([np.asarray(s, float) for s in spikes])
    sn = np.concatenate([np.full(len(s), i, np.uint8) for i, s in enumerate(spikes)])
    order = np.argsort(st, kind="stable")
    return {"now": now, "t_s": t, "rate": rate, "dist": dist, "spike_t": st[order],
            "spike_nerve": sn[order]}


def cells(pd):
    """Cells of a polydata: list of (kind, lane, rgba, points (n, 2))."""
    pts = numpy_support.vtk_to_numpy(pd.GetPoints().GetData())[:, :2].astype(float) \
        if pd.GetNumberOfPoints() else np.zeros((0, 2))
    ca = pd.GetLines() if pd.GetNumberOfLines() else pd.GetPolys()
    offs = numpy_support.vtk_to_numpy(ca.GetOffsetsArray())
    conn = numpy_support.vtk_to_numpy(ca.GetConnectivityArray())
    cd = pd.GetCellData()
    rgba = numpy_support.vtk_to_numpy(cd.GetArray("rgba")).reshape(-1, 4)
    kind = cd.GetArray("kind")
    kind = numpy_support.vtk_to_numpy(kind) if kind is not None else np.zeros(len(rgba))
    lane = numpy_support.vtk_to_numpy(cd.GetArray("lane"))
    return [(int(kind[i]), int(lane[i]), tuple(int(v) for v in rgba[i]),
             pts[conn[offs[i]:offs[i + 1]]]) for i in range(len(offs) - 1)]


def rows(img, y):
    """Image row of pixel row ``y`` (origin bottom-left)."""
    return img.shape[0] - 1 - int(y)


# ------------------------------------------------------------------ checks
def test_bad_arguments_are_refused(scene):
    with pytest.raises(ValueError, match="2 names but 1 colors"):
        MonitorTrace(scene, NAMES, COLORS[:1])
    with pytest.raises(ValueError, match=r"shape \(k, 3\)"):
        MonitorTrace(scene, NAMES, [(1, 2, 3, 4), (1, 2, 3, 4)])
    with pytest.raises(ValueError, match="0 to 255"):
        MonitorTrace(scene, NAMES, [(250, 230, 40), (256, 0, 0)])
    with pytest.raises(ValueError, match="0 to 255"):
        MonitorTrace(scene, NAMES, [(250, 230, 40), (-1, 0, 0)])
    with pytest.raises(ValueError, match="at least one"):
        MonitorTrace(scene, [], np.zeros((0, 3)))
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="window_s"):
            MonitorTrace(scene, NAMES, COLORS, window_s=bad)
        with pytest.raises(ValueError, match="max_hz"):
            MonitorTrace(scene, NAMES, COLORS, max_hz=bad)
    tr = MonitorTrace(scene, NAMES, COLORS)
    h = history()
    h["rate"] = h["rate"][:, :1]
    with pytest.raises(ValueError, match="rate and dist of shape"):
        tr.update(h)


def test_mapping_is_the_documented_one(scene):
    tr = MonitorTrace(scene, NAMES, COLORS, window_s=5.0, max_hz=400.0)
    x0, y0, x1, y1 = tr.rect()
    for c in range(2):
        lx0, ly0, lx1, ly1 = tr.lane_rect(c)
        px0, py0, px1, py1 = tr.plot_rect(c)
        assert x0 <= lx0 < px0 < px1 < lx1 <= x1 and y0 <= ly0 < py0 < py1 < ly1 <= y1
        assert py1 - py0 >= 10 and px1 - px0 >= 100
        # time: newest at the right edge, window_s back at the left edge
        assert tr.x_of(20.0, 20.0) == pytest.approx(px1)
        assert tr.x_of(15.0, 20.0) == pytest.approx(px0)
        assert tr.x_of(18.75, 20.0) == pytest.approx(px0 + 0.75 * (px1 - px0))
        # rate: square-root scale, clipped to 0 .. max_hz
        assert tr.y_of(0.0, c) == pytest.approx(py0)
        assert tr.y_of(400.0, c) == pytest.approx(py1)
        assert tr.y_of(100.0, c) == pytest.approx(py0 + 0.5 * (py1 - py0))
        assert tr.y_of(4.0, c) == pytest.approx(py0 + 0.1 * (py1 - py0))
        assert tr.y_of(5000.0, c) == pytest.approx(py1)
        assert tr.y_of(-3.0, c) == pytest.approx(py0)
    # lane 0 on top, lanes do not overlap
    assert tr.lane_rect(0)[1] >= tr.lane_rect(1)[3]
    with pytest.raises(IndexError):
        tr.lane_rect(2)


def test_polyline_points_follow_the_rates_and_skip_older_samples(scene):
    tr = MonitorTrace(scene, NAMES, COLORS, window_s=5.0, max_hz=400.0)
    now = 30.0
    t = np.linspace(now - 7.0, now, 701) + 0.0005         # no sample on the window edge
    t[-1] = now
    r0 = (50.0 + 40.0 * np.sin(t)).astype(np.float32)
    r1 = np.where(t > now - 2.0, 900.0, 9.0).astype(np.float32)   # above max_hz: clipped
    tr.update({"now": now, "t_s": t, "rate": np.column_stack([r0, r1]),
               "dist": np.full((len(t), 2), 5.0, np.float32),
               "spike_t": np.zeros(0), "spike_nerve": np.zeros(0, np.uint8)})
    traces = [c for c in cells(tr.foreground) if c[0] == TRACE]
    assert [c[1] for c in traces] == [0, 1]
    inside = t >= now - 5.0
    assert 490 < inside.sum() < 510
    for c, rate in ((0, r0), (1, r1)):
        _, lane, rgba, pts = traces[c]
        px0, py0, px1, py1 = tr.plot_rect(c)
        tt, rr = t[inside], np.minimum(rate[inside].astype(float), 400.0)
        want_x = px1 - (now - tt) / 5.0 * (px1 - px0)
        want_y = py0 + np.sqrt(rr / 400.0) * (py1 - py0)
        assert rgba == (*COLORS[c], 255)
        assert pts.shape == (inside.sum(), 2)
        np.testing.assert_allclose(pts[:, 0], want_x, atol=1e-3)
        np.testing.assert_allclose(pts[:, 1], want_y, atol=1e-3)
        assert pts[:, 0].min() >= px0 and pts[-1, 0] == pytest.approx(px1)
    assert traces[1][3][:, 1].max() == pytest.approx(tr.plot_rect(1)[3])
    # nothing at all is drawn left of the plot (the samples older than 5 s)
    for kind, _, _, pts in cells(tr.foreground):
        assert pts[:, 0].min() >= tr.plot_rect(0)[0] - 0.5, kind


def test_right_edge_is_the_newest_time_given(scene):
    tr = MonitorTrace(scene, NAMES, COLORS)
    h = history(now=10.0)
    h["t_s"] = h["t_s"] + 0.02                 # the monitor wrote after "now" was read
    tr.update(h)
    assert tr.now == pytest.approx(10.02)
    trace = [c for c in cells(tr.foreground) if c[0] == TRACE][0][3]
    assert trace[-1, 0] == pytest.approx(tr.plot_rect(0)[2])


def test_spike_ticks_at_the_spike_times(scene):
    tr = MonitorTrace(scene, NAMES, COLORS, window_s=5.0)
    now = 12.0
    s0 = [5.0, 6.9, 7.3, 9.1, 9.1004, 11.5, 12.0]          # 5.0 and 6.9: too old
    s1 = [8.25, 10.0, 11.99]
    h = history(now=now, spikes=(s0, s1))
    h["spike_t"] = np.r_[h["spike_t"], 11.0]
    h["spike_nerve"] = np.r_[h["spike_nerve"], 7].astype(np.uint8)   # no such nerve
    tr.update(h)
    ticks = [c for c in cells(tr.foreground) if c[0] == TICK]
    px0, _, px1, _ = tr.plot_rect(0)
    want = set()
    for lane, times in ((0, s0), (1, s1)):
        for s in times:
            if s >= now - 5.0:
                want.add((lane, math.floor(px1 - (now - s) / 5.0 * (px1 - px0)) + 0.5))
    got = {(lane, float(p[0, 0])) for _, lane, _, p in ticks}
    assert got == want and len(ticks) == len(want) == 7   # 9.1 and 9.1004 share a column
    for _, lane, rgba, p in ticks:
        assert p.shape == (2, 2) and p[0, 0] == p[1, 0]   # vertical
        y0, y1 = tr.tick_span(lane)
        ly0 = tr.lane_rect(lane)[1]
        assert (p[0, 1], p[1, 1]) == (y0, y1) and ly0 < y0 < y1 <= tr.plot_rect(lane)[1]
        assert rgba[:3] == COLORS[lane]


@pytest.mark.parametrize("k", [2, 4])
def test_panel_docks_in_the_side_column_above_the_hud(scene, k):
    """With a side column the trace fills its top, above the HUD, and never
    enters the 3D view."""
    names = [f"n{i}" for i in range(k)]
    colors = [(200, 50 * i, 100) for i in range(k)]
    scene.set_hud(scenes.HUD)
    tr = MonitorTrace(scene, names, colors)
    for w, h in ((320, 240), (640, 480), (1280, 720), (500, 900), (900, 260)):
        scene.render_window.SetSize(w, h)
        scene.set_hud(scenes.HUD)
        tr.set_visible(False)
        img = scene.image()
        tr.set_visible(True)
        tr.update(history(k=k))
        cx0, _, cx1, ch = scene.panel_rect()
        assert (cx1, ch) == (w, h) and scene.view_rect()[2] == cx0
        x0, y0, x1, y1 = tr.rect()
        assert (x0, x1, y1) == (cx0 + 8, w - 8, h - 8), (w, h)
        hud = tr._hud_box()
        assert hud is not None and hud[3] < y0 and hud[0] >= cx0, (w, h, hud, tr.rect())
        shown = scene.image()
        changed = np.nonzero(np.abs(shown.astype(int) - img).max(axis=2) > 0)
        assert changed[1].min() >= cx0                   # nothing drawn in the 3D view
        assert changed[1].min() >= x0 and changed[1].max() < x1


@pytest.mark.parametrize("k", [2, 4])
def test_panel_top_right_clear_of_the_bottom_and_the_hud(gl_info, k):
    """Without a side column (Scene(panel=False)): over the view's top-right."""
    scene = Scene(size=SIZE, visible_subset=False, panel=False)
    names = [f"n{i}" for i in range(k)]
    colors = [(200, 50 * i, 100) for i in range(k)]
    scene.set_hud(scenes.HUD)
    tr = MonitorTrace(scene, names, colors)
    for w, h in ((320, 240), (400, 300), (640, 480), (1280, 720), (1920, 1080),
                 (500, 900), (900, 260), (640, 150), (1000, 120)):
        scene.render_window.SetSize(w, h)
        scene.set_hud(scenes.HUD)                        # the HUD's font follows the size
        tr.set_visible(False)
        img = scene.image()
        assert img.shape == (h, w, 3)
        tr.set_visible(True)
        tr.update(history(k=k))
        x0, y0, x1, y1 = tr.rect()
        assert (x1, y1) == (w - 8, h - 8), (w, h)
        assert y0 >= 40 and x0 >= w // 2, (w, h)
        assert x1 - x0 == min(max(round(0.35 * w), 150), 560), (w, h)
        # the HUD's text pixels (found in the picture) stay outside the panel
        ys, xs = np.nonzero(img.max(axis=2) > 120)
        assert len(xs) > 200                             # the HUD is there
        hud_top = h - 1 - ys.min()
        assert xs.max() < x0 or hud_top < y0, (w, h, xs.max(), hud_top, tr.rect())
        lanes = [tr.lane_rect(c) for c in range(k)]
        for (a, b) in zip(lanes, lanes[1:]):
            assert a[1] > b[3]                           # stacked top to bottom
        assert all(x0 < ln[0] < ln[2] < x1 and y0 < ln[1] < ln[3] < y1 for ln in lanes)
        # drawn pixels: the panel darkens the (uniform) background only in its rect
        shown = scene.image()
        changed = np.nonzero(np.abs(shown.astype(int) - img).max(axis=2) > 0)
        assert changed[1].min() >= x0 and changed[1].max() < x1
        assert h - 1 - changed[0].max() >= y0 and h - 1 - changed[0].min() < y1
    scene.close()


def test_warning_text_and_red_lane_below_warn_mm(scene):
    tr = MonitorTrace(scene, NAMES, COLORS, warn_mm=1.0)
    tr.update(history(rates=(45.2, 4.0), dists=(2.34, math.inf)))
    lines = tr.text().splitlines()
    # clinical names on screen (the code names stay in tr.names)
    assert lines[0].split() == ["Facial", "nerve", "d", "2.3", "mm", "45/s"]
    assert lines[1].split() == ["Chorda", "tympani", "d", ">", "10", "mm", "4/s"]
    assert tr.names == NAMES and tr.titles == ["Facial nerve", "Chorda tympani"]
    assert "WARNING" not in tr.text() and not tr.warning.any()
    calm = scene.image()
    tr.update(history(rates=(180.0, 4.0), dists=(0.4, 1.0)))     # 1.0 is not below 1.0
    lines = tr.text().splitlines()
    assert lines[0].startswith("WARNING") and "d 0.4 mm" in " ".join(lines[0].split())
    assert "180/s" in lines[0] and "WARNING" not in lines[1]
    assert list(tr.warning) == [True, False]
    bg = {lane: rgba for _, lane, rgba, _ in cells(tr.background)}
    assert bg[0] == WARN_RGBA and bg[1] == LANE_RGBA
    alarm = scene.image()
    # a spot in each lane between the baseline and the top, clear of the trace
    for c in range(2):
        px0, py0, px1, py1 = tr.plot_rect(c)
        x, y = (px0 + px1) // 2, int(tr.y_of(250.0, c))
        a = alarm[rows(alarm, y), x].astype(int)
        b = calm[rows(calm, y), x].astype(int)
        if c == 0:
            assert a[0] > a[1] + 60 and a[0] > a[2] + 60, a      # red
            assert abs(b[0] - b[1]) < 20, b                      # not red before
        else:
            assert abs(a[0] - a[1]) < 20 and np.array_equal(a, b), (a, b)
    # back out of range: the warning goes
    tr.update(history(dists=(1.2, 3.0)))
    assert "WARNING" not in tr.text() and not tr.warning.any()
    assert format_label("n", -0.2, 300.0, 1.0).split() == ["WARNING", "n", "d", "0.0", "mm",
                                                           "300/s"]


def test_empty_history_draws_the_panel_only(scene):
    tr = MonitorTrace(scene, NAMES, COLORS)
    tr.set_visible(False)
    bare = scene.image()
    tr.set_visible(True)
    x0, y0, x1, y1 = tr.rect()
    lx0, ly0, lx1, ly1 = tr.lane_rect(1)
    _, py0, _, py1 = tr.plot_rect(1)
    first = None
    for h in ({"now": 0.0},
              {"now": 0.0, "t_s": np.zeros(0), "rate": np.zeros((0, 2), np.float32),
               "dist": np.zeros((0, 2), np.float32), "spike_t": np.zeros(0),
               "spike_nerve": np.zeros(0, np.uint8)}):
        tr.update(h)
        kinds = {c[0] for c in cells(tr.foreground)}
        assert TRACE not in kinds and TICK not in kinds and kinds <= {BASELINE}
        assert [ln.split() for ln in tr.text().splitlines()] == [
            ["Facial", "nerve", "no", "signal"], ["Chorda", "tympani", "no", "signal"]]
        img = scene.image()
        first = img if first is None else first
        assert np.array_equal(img, first)
        # the lane background is drawn (plot area), the label is there (label strip)
        plot = np.s_[rows(img, py1 - 1):rows(img, py0) + 1, lx0 + 4:lx1 - 4]
        diff = np.abs(img[plot].astype(int) - bare[plot]).max(axis=2)
        assert (diff[:, :20] > 3).all()
        label = np.s_[rows(img, ly1 - 1):rows(img, py1) + 1, lx0:lx1]
        assert (np.abs(img[label].astype(int) - COLORS[1]) < 40).all(axis=2).sum() > 10
    # a single sample draws a stub ending at the right edge
    tr.update(history(m=1, start=12.0))
    traces = [c for c in cells(tr.foreground) if c[0] == TRACE]
    assert len(traces) == 2 and traces[0][3][-1, 0] == pytest.approx(tr.plot_rect(0)[2])


def test_hidden_trace_draws_nothing(scene):
    scene.set_hud(scenes.HUD)
    without = scene.image()
    tr = MonitorTrace(scene, NAMES, COLORS)
    tr.update(history(rates=(120.0, 30.0), spikes=([9.0, 10.0, 11.0], [10.5])))
    shown = scene.image()
    x0, y0, x1, y1 = tr.rect()
    panel = np.s_[rows(shown, y1 - 1):rows(shown, y0) + 1, x0:x1]
    assert (np.abs(shown[panel].astype(int) - without[panel]).max(axis=2) > 3).mean() > 0.9
    tr.set_visible(False)
    assert not tr.visible and tr.text() == ""
    assert np.array_equal(scene.image(), without)
    tr.update(history(rates=(300.0, 300.0)))          # updates while hidden draw nothing
    assert np.array_equal(scene.image(), without)
    tr.set_visible(True)                              # shows the last history
    assert tr.visible and "300/s" in tr.text()
    assert not np.array_equal(scene.image()[panel], without[panel])


def test_rendered_pixels_show_the_trace_and_ticks_in_the_nerve_colours(scene):
    tr = MonitorTrace(scene, NAMES, COLORS, baseline_hz=None)
    spikes = ([8.0, 9.5, 11.0], [])
    tr.update(history(rates=(100.0, 4.0), spikes=spikes))
    img = scene.image()

    def colour_rows(c, x):
        """Image rows of column x inside lane c that show nerve c's colour."""
        _, ly0, _, ly1 = tr.lane_rect(c)
        col = img[rows(img, ly1 - 1):rows(img, ly0) + 1, x].astype(int)
        near = np.abs(col - COLORS[c]).max(axis=1) < 40
        return ly1 - 1 - np.nonzero(near)[0]             # back to pixel rows (bottom-up)

    for c, rate in ((0, 100.0), (1, 4.0)):
        px0, py0, px1, py1 = tr.plot_rect(c)
        lx0, ly0, lx1, ly1 = tr.lane_rect(c)
        y = float(tr.y_of(rate, c))
        for x in np.linspace(px0 + 20, px1 - 10, 5).astype(int):
            hit = colour_rows(c, x)
            trace_rows = hit[(hit >= py0) & (hit <= py1 - 2)]
            assert len(trace_rows) >= 1 and np.abs(trace_rows - y).max() <= 1.5, (c, x, hit)
    # ticks: nerve 0's colour in the tick strip at the spike columns, not between
    y0, y1 = tr.tick_span(0)
    r = rows(img, (y0 + y1) // 2)
    for s in spikes[0]:
        x = int(math.floor(tr.x_of(s, 12.0)))
        assert np.abs(img[r, x].astype(int) - COLORS[0]).max() < 40, s
        assert np.abs(img[r, x + 6].astype(int) - COLORS[0]).max() > 100, s
    # nerve 1 had no spikes: nothing of its colour in its tick strip
    y0, y1 = tr.tick_span(1)
    px0, _, px1, _ = tr.plot_rect(1)
    strip = img[rows(img, y1 - 1):rows(img, y0) + 1, px0:px1].astype(int)
    assert (np.abs(strip - COLORS[1]).max(axis=2) < 60).sum() == 0


def test_a_burst_draws_at_most_one_tick_per_pixel_column(scene):
    """1000 samples x 2 nerves and a 400/s burst on one (about 2000 spikes)."""
    tr = MonitorTrace(scene, NAMES, COLORS)
    rng = np.random.default_rng(1)
    h = history(m=1000, start=7.0, rates=(400.0, 20.0), dists=(0.1, 2.0),
                spikes=(np.sort(rng.uniform(7.0, 12.0, 2000)), np.sort(rng.uniform(7, 12, 100))))
    tr.update(h)
    ticks = [c for c in cells(tr.foreground) if c[0] == TICK]
    px0, _, px1, _ = tr.plot_rect(0)
    assert px1 - px0 < len(ticks) <= 2 * (px1 - px0 + 1)     # many spikes, capped columns


def test_matches_reference_picture(phantom, tmp_path):
    """The phantom's drilled view (400 x 300, with the HUD) and the trace of
    a burr closing in on the facial nerve."""
    sc, _, _ = scenes.build(phantom, "drilled", visible_subset=False)
    tr = MonitorTrace(sc, NAMES, COLORS)
    t = np.linspace(7.0, 12.0, 1000)
    d = np.column_stack([4.0 - 3.4 * (t - 7.0) / 5.0, np.full_like(t, 3.0)])
    r = 4.0 + 150.0 * np.exp(-d / 0.66)
    rng = np.random.default_rng(2)
    cand = np.sort(rng.uniform(7.0, 12.0, 400))          # thinned: denser as the rate grows
    s0 = cand[rng.random(400) < np.interp(cand, t, r[:, 0]) / r[:, 0].max()]
    s1 = np.sort(rng.uniform(7.0, 12.0, 25))
    order = np.argsort(np.r_[s0, s1], kind="stable")
    tr.update({"now": 12.0, "t_s": t, "rate": r.astype(np.float32),
               "dist": d.astype(np.float32), "spike_t": np.r_[s0, s1][order],
               "spike_nerve": np.r_[np.zeros(len(s0)), np.ones(len(s1))][order].astype(np.uint8)})
    img = sc.image()
    tr.set_visible(False)
    bare = sc.image()
    assert tr.text() == ""
    tr.set_visible(True)
    sc.close()
    assert tr.text().splitlines()[0].split()[:5] == ["WARNING", "Facial", "nerve", "d", "0.6"]
    check("trace", img, tmp_path)                      # (skips after writing, if asked)
    assert not compare_images(bare, read_png(IMAGES / "trace.png"))   # the trace is what
                                                                      # the picture shows
