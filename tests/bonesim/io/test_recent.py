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


def test_a_byte_budget_drops_the_oldest_and_keeps_nothing_too_large():
    r = Recent(4, max_bytes=10, nbytes=len)
    assert r.put("a", b"xxxx") and r.put("b", b"yyyy")
    assert r.nbytes == 8
    assert r.put("c", b"zzzz")                     # 12 > 10: a goes
    assert r.get("a") is None and r.get("b") == b"yyyy" and r.nbytes == 8
    assert not r.put("d", b"q" * 11)               # alone too large: not kept
    assert r.get("d") is None and len(r) == 2
    assert r.put("c", b"zz") and r.nbytes == 6     # replaced under its key
    assert Recent(1).nbytes == 0 and not Recent(0).put("e", b"")
