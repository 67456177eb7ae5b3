"""TOML manifests: non-UTF-8 bytes, binary files, NaN and infinity give one
line naming the file and key (issue 24, row 6), never a traceback."""
from __future__ import annotations

import math

import pytest

from bonesim.errors import BonesimError
from bonesim.tomlfile import get_number, get_vector, read_toml


@pytest.mark.parametrize("data, needle", [
    (b"# caf\xe9\nx = 1\n", r"not a UTF-8 text \(TOML\) file: byte 5 is 0xe9"),
    (bytes(range(256)) * 4, "not a UTF-8 text"),
    (b"x = 1\n\x00\x00\x00", "NUL bytes"),
    (b"x = [", "malformed TOML"),
])
def test_bad_bytes_give_one_line_naming_the_file(tmp_path, data, needle):
    p = tmp_path / "m.toml"
    p.write_bytes(data)
    with pytest.raises(BonesimError, match=needle) as err:
        read_toml(p)
    assert str(err.value).startswith(str(p)) and "\n" not in str(err.value)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_nan_and_infinity_are_refused_naming_the_key(tmp_path, value):
    path = tmp_path / "m.toml"
    with pytest.raises(BonesimError, match=r"m.toml \[volume\]: 'x' must be finite"):
        get_number({"x": value}, "x", path, "volume")
    with pytest.raises(BonesimError, match=r"'v' must hold finite numbers"):
        get_vector({"v": [0.0, value, 1.0]}, "v", path, "volume")


def test_infinity_where_it_means_something():
    assert get_number({"s": math.inf}, "s", None, "cavity", finite=False) == math.inf
    with pytest.raises(BonesimError, match="finite"):
        get_number({"s": math.nan}, "s", None, "cavity", finite=False)
