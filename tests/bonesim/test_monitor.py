"""Nerve monitor: which structures, the activity law, distance lookups, spikes,
the monitor process, clicks and the network console."""
from __future__ import annotations

import pytest

from bonesim import case as C
from bonesim.errors import BonesimError
from tests.bonesim.test_case import tiny_volume, write_case


# --------------------------------------------------------- monitored structures
def test_phantom_monitors_facial_nerve_and_chorda():
    c = C.load_case("phantom")
    assert [s.name for s in c.structures if s.monitor] == ["facial_nerve", "chorda_tympani"]
    assert C.case_info(c)["monitored"] == ["facial_nerve", "chorda_tympani"]


def test_monitor_flag_default_roundtrip_and_errors(tmp_path):
    tiny_volume(tmp_path)
    c = C.load_case(write_case(tmp_path))
    assert not any(s.monitor for s in c.structures)          # default: not monitored
    c = C.load_case(write_case(tmp_path, replace=[("label = 2", "label = 2\nmonitor = true")]))
    assert [s.name for s in c.structures if s.monitor] == ["nerve"]
    back = C.load_case(C.export_case(c, "nrrd", tmp_path / "out"))
    assert [s.monitor for s in back.structures] == [False, True]
    for repl, fragment in [(("label = 2", 'label = 2\nmonitor = "yes"'),
                            "'monitor' must be true or false, got 'yes'"),
                           (("label = 1", "label = 1\nmonitor = true"),
                            "'monitor' = true on a structure of kind 'bone'")]:
        path = write_case(tmp_path, replace=[repl])
        with pytest.raises(BonesimError) as e:
            C.load_case(path)
        assert fragment in str(e.value) and str(path) in str(e.value)
        assert e.value.field == ("structures[1]" if "yes" in repl[1] else "structures[0]")
