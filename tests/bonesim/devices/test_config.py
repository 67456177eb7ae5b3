"""The device configuration file refuses hostile content in one line naming
the file and key (issue 24, row 6: non-UTF-8 and binary device configs gave
tracebacks; NaN settings were taken)."""
from __future__ import annotations

import pytest

from bonesim.devices.config import load_config
from bonesim.errors import BonesimError


@pytest.mark.parametrize("data, needle", [
    (b"# \xe9\n[devices]\n", "not a UTF-8 text"),
    (bytes(range(256)) * 4, "not a UTF-8 text"),
    (b"[devices.simulated-hand]\nscale = nan\n",
     r"\[devices.simulated-hand.scale\]: must be a finite number, got nan"),
    (b"[calibration.adu100-handle.default]\nopen = [1.0, inf]\n",
     r"\[calibration.adu100-handle.default.open\[1\]\]: must be a finite"),
])
def test_hostile_device_configs_give_one_line(tmp_path, data, needle):
    p = tmp_path / "devices.toml"
    p.write_bytes(data)
    with pytest.raises(BonesimError, match=needle) as err:
        load_config(p)
    assert str(err.value).startswith(str(p)) and "\n" not in str(err.value)


def test_a_good_config_still_loads(tmp_path):
    p = tmp_path / "devices.toml"
    p.write_text("[devices.simulated-hand]\nscale = 2.0\nstart = [0.0, 1.0, 2.0]\n")
    assert load_config(p)["devices"]["simulated-hand"]["scale"] == 2.0
