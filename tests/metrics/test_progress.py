"""Learning curves (metrics.progress) on a table with known slopes."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from metrics.progress import draw_progress, improvement


def _table():
    rows = []
    for g, slope in (("expert", 0.0), ("novice", 0.1)):
        for q in range(4):
            for s in (1, 2, 3):
                rows.append({"participant": f"{g}{q}", "group": g, "session": float(s),
                             "visible_fraction": (0.95 if g == "expert" else 0.5)
                             + slope * s + 0.01 * q,
                             "force_close_n": (1.5 if g == "expert" else 3.3) - slope * s})
    return pd.DataFrame(rows)


def test_improvement_is_oriented_by_the_better_direction():
    df = _table()
    up = improvement(df, "visible_fraction", +1)
    down = improvement(df, "force_close_n", -1)
    assert up["novice"] == pytest.approx(0.1) and down["novice"] == pytest.approx(0.1)
    assert up["expert"] == pytest.approx(0.0, abs=1e-12) and up["improving"] == 1.0
    assert set(up["participants"]) == {f"{g}{q}" for g in ("expert", "novice")
                                       for q in range(4)}


def test_draw_progress_writes_a_png(tmp_path):
    from PIL import Image

    out = draw_progress(_table(), tmp_path / "p.png")
    assert set(out["metrics"]) == {"visible_fraction", "force_close_n"}
    img = np.asarray(Image.open(out["png"]))
    assert img.shape[0] > 200 and img.shape[1] > 400 and np.ptp(img) > 0
    with pytest.raises(ValueError, match="no values over sessions"):
        draw_progress(_table(), tmp_path / "q.png", metrics=["nb_score"])
