"""Before and after a minute of the demo plan, side by side, on the phantom
and on a label-stack case (as another simulator hands one over), against
stored references.

Each reference (``images/showcase_*.png``, 960 x 300) is the headless main
job's view (:class:`bonesim.apps.showcase.Showcase`) as the plan starts and 60 s
of drilling later: the opened mastoid, the thinned bone over the sinus and
the facial nerve tinted their colours, the little dust the suction leaves,
the HUD and the nerve monitor. Regenerate with ``BONESIM_UPDATE_IMAGES=1``
(see ``test_images.py``) and look at them.
"""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.io import case as C
from bonesim.io import phantom as P
from bonesim.io import volumes as VOL
from bonesim.apps.showcase import Showcase
from tests.bonesim.render.test_images import check
from tests.bonesim.io.test_case import THEIR_COLORS, their_manifest

SIZE = (480, 300)
DRILL_S = 60.0
#: The plan's start that the runs drill (the burr reaches the bone in seconds).
PLANNED_S = 90.0


@pytest.fixture(scope="module")
def label_stack_case(tmp_path_factory):
    """The phantom as PIR label slices in another simulator's colours, at
    0.25 mm in-plane pixels, with a manifest of [case], [volume] and
    [[structures]] only (no camera, colours or monitor flags)."""
    folder = tmp_path_factory.mktemp("their_case")
    labels = C.load_case("phantom").load_volume().labels
    fine = np.repeat(np.repeat(labels, 2, axis=1), 2, axis=2)
    VOL.write_label_stack(folder / "slices", fine, [THEIR_COLORS[n] for n in P.PARTS],
                          orientation="PIR")
    return their_manifest(folder)


def before_after(case) -> tuple[np.ndarray, dict]:
    with Showcase(case, "cutting-5mm", size=SIZE, seconds=PLANNED_S) as sh:
        t_on = float(sh.samples.t_s[np.flatnonzero(sh.samples.drill)[0]])
        assert t_on + DRILL_S < sh.end_s
        sh.advance(sh.start_s)
        before = sh.image()
        sh.advance(t_on + DRILL_S)
        after = sh.image()
        summary = sh.summary()
        summary["monitored"] = list(sh.monitor.names) if sh.monitor is not None else []
    return np.concatenate([before, after], axis=1), summary


@pytest.mark.parametrize("which", ["phantom", "label_stack"])
def test_before_and_after_a_minute_of_drilling(which, label_stack_case, gl_info, tmp_path):
    case = "phantom" if which == "phantom" else label_stack_case
    img, summary = before_after(case)
    assert img.shape == (SIZE[1], 2 * SIZE[0], 3)
    # what the picture shows is what happened: bone drilled, nothing else,
    # and the nerves are monitored without a flag in the manifest
    assert summary["voxels_removed"] > 3000 and summary["injuries"] == []
    assert set(summary["removed_by_structure"]) == {"bone"}
    assert summary["monitored"] == ["facial_nerve", "chorda_tympani"]
    before, after = img[:, :SIZE[0]], img[:, SIZE[0]:]
    assert np.abs(before.astype(int) - after.astype(int)).mean() > 2.0
    check(f"showcase_{which}", img, tmp_path)
