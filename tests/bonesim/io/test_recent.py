"""Recent: the least recently used value goes first; getting one renews it."""
from __future__ import annotations

from bonesim.io.recent import Recent


def test_least_recently_used_goes_first():
    r = Recent(2)
    r.put("a", 1)
    r.put("b", 2)
    assert r.get("a") == 1              # a is now the most recently used
    r.put("c", 3)                       # b goes
    assert r.get("b") is None and r.get("a") == 1 and r.get("c") == 3 and len(r) == 2
    r.put("a", 4)                       # kept again under the same key: replaced
    assert r.get("a") == 4 and len(r) == 2
    assert Recent(0).get("x") is None
