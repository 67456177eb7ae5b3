"""The cohort report (metrics.report) on a small synthetic cohort scored serially."""
from __future__ import annotations

import base64
import copy
import io
import re
import struct

import numpy as np
import pytest

from metrics.cohort_result import METRIC_COLUMNS
from tests.metrics.cohort_fixtures import score_serially

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
ODD_ID = "<E&1>"
ODD_ERROR = "run /data/X9.h5: <script>alert(1)</script> & unreadable"


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    """3 + 3 synthetic runs of 8 s, scored once, with an odd participant id and an
    injected error line."""
    from metrics.synth import synth_cohort

    folder = tmp_path_factory.mktemp("cohort")
    synth_cohort(folder, 3, 3, seed=1, duration_s=8.0)
    result = score_serially(folder)
    result.table.loc[0, "participant"] = ODD_ID
    result.errors.append(ODD_ERROR)
    return result


@pytest.fixture(scope="module")
def report(scored, tmp_path_factory):
    """The report and the PNG copies of its images."""
    from metrics.report import write_report

    out = tmp_path_factory.mktemp("report")
    path = write_report(scored, out / "report.html", png_dir=out / "png")
    return path.read_text(encoding="utf-8"), out / "png"


def _png_size(data: bytes) -> tuple:
    assert data[:8] == PNG_MAGIC
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def test_the_page_is_self_contained_and_its_images_are_pngs(report):
    import matplotlib.image as mpimg

    page, _ = report
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    refs = re.findall(r"""(?:src|href)\s*=\s*["']([^"']*)""", page, flags=re.IGNORECASE)
    assert refs, "no image at all"
    assert not [r for r in refs if not r.startswith("data:image/png;base64,")]
    assert not re.search(r"<script|<link|@import|url\(", page, flags=re.IGNORECASE)
    assert "http://" not in page and "https://" not in page
    imgs = re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(imgs) == len(re.findall(r"<img\b", page)) >= 5
    for b64 in imgs:
        data = base64.b64decode(b64, validate=True)
        w, h = _png_size(data)
        assert 200 <= w <= 2000 and 150 <= h <= 2000
        assert 2_000 < len(data) < 1_500_000
        px = mpimg.imread(io.BytesIO(data), format="png")      # decodes fully
        assert px.shape[:2] == (h, w) and np.ptp(px) > 0        # not a blank image


def test_every_section_group_size_metric_and_error_is_there(report, scored):
    page, png_dir = report
    for heading in ("1. Cohort", "2. Scores by group", "3. Instructor score against the metrics",
                    "4. Force against distance to the Chorda tympani",
                    "5. Visibility at removal", "6. Statistics of every metric", "7. Runs",
                    "Naive Bayes training sets"):
        assert heading in page, heading
    for g in ("expert", "novice"):
        assert re.search(rf'<td class="l">{g}</td><td>3</td><td>3</td>', page), g
    for m in METRIC_COLUMNS:
        assert f">{m}<" in page, m
    assert "SYNTHETIC TEST DATA" in page
    # the injected error, escaped
    assert ODD_ERROR not in page and "<script>" not in page
    assert "run /data/X9.h5: &lt;script&gt;alert(1)&lt;/script&gt; &amp; unreadable" in page
    # the group plots of the key metrics, the scatter plots and the force plot
    names = {p.name for p in png_dir.glob("*.png")}
    assert {"group_visible_fraction.png", "group_nb_score.png", "scatter_visible_fraction.png",
            "scatter_nb_score.png", "forces.png"} <= names
    # the visibility views: rendered, or a note says why not
    assert len([n for n in names if n.startswith("visibility_")]) == 2 or \
        page.count("view not rendered") == 2
    # each run's training set is listed under the scored run
    for f in scored.nb_trained_on:
        assert f'title="{f}"' in page


def test_strings_are_escaped_and_nan_reads_na(report, scored):
    page, _ = report
    assert ODD_ID not in page
    assert "&lt;E&amp;1&gt;" in page
    assert "nan" not in re.sub(r"<[^>]*>", " ", page).lower().split()
    assert ">n/a<" in page                         # e.g. drilled_mm3: no values at all
    assert np.isnan(scored.meta["wall_s"]) and "<dt>wall_s</dt><dd>n/a</dd>" in page


def test_significant_p_values_are_highlighted(report, scored):
    page, _ = report
    row = scored.stats.set_index("metric").loc["nb_score"]
    assert row["p_t"] < 0.05                        # the score separates the groups
    line = next(r for r in page.split("<tr>") if r.startswith('<td class="l">nb_score<'))
    assert 'class="sig"' in line


def test_without_notes_meta_flags_synthetic_and_bad_runs_get_a_note(scored, tmp_path):
    from metrics.report import write_report

    res = copy.copy(scored)
    res.table = scored.table.drop(columns=["notes"])
    res.errors = []
    res.meta = dict(scored.meta)
    page = write_report(res, tmp_path / "a.html", visibility_runs=[]).read_text()
    assert "SYNTHETIC TEST DATA" not in page
    assert "Errors: none" in page
    res.meta["synthetic"] = True
    page = write_report(res, tmp_path / "b.html",
                        visibility_runs=[tmp_path / "<missing>.h5"]).read_text()
    assert "SYNTHETIC TEST DATA" in page
    assert "&lt;missing&gt;.h5: view not rendered" in page


def test_a_table_without_the_run_columns_is_refused(scored, tmp_path):
    from metrics.report import write_report

    res = copy.copy(scored)
    res.table = scored.table.drop(columns=["group"])
    with pytest.raises(ValueError, match="group"):
        write_report(res, tmp_path / "x.html")


def test_a_cohort_without_statistics_or_forces_still_reports(scored, tmp_path):
    import pandas as pd

    from metrics.report import write_report

    res = copy.copy(scored)
    res.table = scored.table[scored.table.group == "novice"].reset_index(drop=True)
    res.stats = pd.DataFrame()
    res.force_tables = {}
    res.nb_trained_on = {}
    page = write_report(res, tmp_path / "c.html", visibility_runs=[]).read_text()
    assert "Not drawn: no force tables with a group." in page
    assert "No run to show." in page
    assert re.search(r'<td class="l">novice</td><td>3</td>', page)
    assert "<td>n/a</td>" in page


def test_group_plots_draw_one_point_per_participant_over_faint_sessions():
    """The statistics' unit: each participant's mean is one solid point; the
    sessions are a faint layer on their participant's vertical; the group
    mean and interval are over the participants' means."""
    from types import SimpleNamespace

    import pandas as pd

    from metrics.report import _group_plot

    t = pd.DataFrame({"participant": ["E1"] * 3 + ["E2"] * 3 + ["N1"] * 2 + ["N2"],
                      "group": ["expert"] * 6 + ["novice"] * 3,
                      "session": [1, 2, 3, 1, 2, 3, 1, 2, 1.0],
                      "m": [1.0, 2.0, 3.0, 5.0, 5.0, np.nan, 10.0, 12.0, 20.0]})
    fig = _group_plot(SimpleNamespace(table=t, stats=None), "m", ["expert", "novice"], True)
    ax = fig.axes[0]
    from matplotlib.collections import PathCollection

    dots = [c for c in ax.collections if isinstance(c, PathCollection)]
    faint = [np.asarray(c.get_offsets()) for c in dots if c.get_alpha() < 0.5]
    solid = [np.asarray(c.get_offsets()) for c in dots if c.get_alpha() >= 0.5]
    # expert: 5 finite sessions, 2 people (means 2 and 5); novice: 3 sessions, 2 people
    assert [len(p) for p in faint] == [5, 3]
    assert sorted(solid[0][:, 1]) == [2.0, 5.0] and sorted(solid[1][:, 1]) == [11.0, 20.0]
    # a participant's sessions share the participant's x
    for f, s in zip(faint, solid):
        assert set(np.round(f[:, 0], 12)) == set(np.round(s[:, 0], 12))
    labels = [tk.get_text() for tk in ax.get_xticklabels()]
    assert labels == ["expert\n(2 people, 5 runs)", "novice\n(2 people, 3 runs)"]
    # the square is the mean of the participants' means, not of the runs
    sq = [ln.get_ydata()[0] for ln in ax.lines if ln.get_marker() == "s"]
    assert sq == pytest.approx([3.5, 15.5])
    import matplotlib.pyplot as plt

    plt.close(fig)
