"""The window's keys for fragments and plates send the loop's commands."""
from __future__ import annotations

from bonesim.apps.simulator import RIGID_ACTIONS, App
from bonesim.render.window import ACTIONS, DEFAULT_KEYS
from bonesim.runtime import rigid_commands as rc


class FakeLoop:
    def __init__(self):
        self.sent = []
        self.status = {"burr": 0}
        self.control = {}

    def send(self, cls, **kw):
        self.sent.append((cls, kw))


def test_rigid_keys_send_grab_release_place_affix_distract():
    assert set(RIGID_ACTIONS) <= set(ACTIONS)
    keys = {a: k for k, a in DEFAULT_KEYS.items() if a in RIGID_ACTIONS}
    assert set(keys) == set(RIGID_ACTIONS)
    app = App.__new__(App)
    app.loop, app.recorder = FakeLoop(), None
    for action in ("grab_toggle", "grab_toggle", "place_plate", "place_plate", "affix_plate",
                   "distract_more", "distract_more", "distract_less"):
        assert app.on_key(action)
    sent = app.loop.sent
    assert [c for c, _ in sent] == [rc.GrabBody, rc.ReleaseBody, rc.PlacePlate, rc.PlacePlate,
                                    rc.AffixPlate, rc.Distract, rc.Distract, rc.Distract]
    assert [kw["plate"] for c, kw in sent if c is rc.PlacePlate] == [0, 1]
    assert [kw["length_mm"] for c, kw in sent if c is rc.Distract] == [0.5, 1.0, 0.5]
