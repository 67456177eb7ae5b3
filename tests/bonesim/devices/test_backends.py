"""Device backends and the virtual coupling of the mouse/keyboard device."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.devices.interface import Device
from bonesim.devices.mouse import MOUSE_CAPS, SharedInputDevice, VirtualCoupling
from bonesim.devices.null import NullDevice
from bonesim.devices.scripted import ScriptedDevice
from bonesim.engine.device_caps import SCRIPTED, DeviceCaps
from bonesim.engine.model import Sample, step
from bonesim.io.trajectory import Trajectory
from tests.bonesim.fakes import FakeBurr, block_model


def _line(n=11):
    t = np.linspace(0, 1, n)
    pos = np.stack([t * 10, np.zeros(n), np.zeros(n)], axis=1)
    return Trajectory(t_s=t, pos_mm=pos, axis=np.tile([0, 0, -1.0], (n, 1)),
                      drill=t > 0.5, speed_rpm=np.full(n, 1000.0),
                      direction=np.ones(n, np.int8))


def test_backends_implement_the_interface():
    for dev in (NullDevice(), ScriptedDevice(_line()),
                SharedInputDevice(np.zeros(3), np.array([0.0, 0.0, -1.0]))):
        assert isinstance(dev, Device)
        dev.open()
        r = dev.read(0.0)
        assert r.pos_mm.shape == (3,) and np.isclose(np.linalg.norm(r.axis), 1.0)
        dev.write_force(np.zeros(3))
        dev.close()
    assert MOUSE_CAPS.max_force_n == np.inf and SCRIPTED.rate_hz > 0


def test_scripted_device_interpolates_and_carries_drill_state():
    dev = ScriptedDevice(_line())
    r = dev.read(0.25)
    np.testing.assert_allclose(r.pos_mm, [2.5, 0, 0])
    assert r.drill is False and dev.read(0.8).drill is True
    assert dev.finished(1.5) and not dev.finished(0.5)
    looping = ScriptedDevice(_line(), loop=True)
    np.testing.assert_allclose(looping.read(1.25).pos_mm, [2.5, 0, 0])


def test_shared_input_device_reads_the_window_target():
    pos, axis = np.zeros(3), np.zeros(3)
    dev = SharedInputDevice(pos, axis)
    pos[:] = (1, 2, 3)                          # the window writes the shared views
    axis[:] = (0, 0, 2)
    r = dev.read(0.0)
    np.testing.assert_allclose(r.pos_mm, [1, 2, 3])
    np.testing.assert_allclose(r.axis, [0, 0, 1])
    assert r.drill is None                      # drill state comes from the keys


@pytest.mark.parametrize("bad", [dict(max_force_n=0), dict(max_stiffness_n_per_mm=-1),
                                 dict(workspace_mm=(1, 2))])
def test_caps_are_validated(bad):
    args = dict(name="x", max_force_n=3.0, workspace_mm=(1, 1, 1), max_stiffness_n_per_mm=1)
    args.update(bad)
    with pytest.raises(ValueError):
        DeviceCaps(**args)


def test_virtual_coupling_rests_on_bone_and_advances_as_bone_goes():
    """Pushing the mouse 2 mm into bone: the tool stops at the surface with the
    bone pushing back as hard as the spring pulls; with the drill on it sinks."""
    m, s = block_model(burr=FakeBurr(radius_mm=1.5))
    top = 20 * 0.5 - 0.25                                # top face [mm]
    vc = VirtualCoupling(stiffness_n_per_mm=1.0, damping_ns_per_mm=0.02)
    target = np.array([10.0, 10.0, top + 1.5 - 2.0])    # 2 mm below the surface
    vc.reset([10.0, 10.0, top + 3.0])
    f = np.zeros(3)
    forces, hand = [], []
    for n in range(1500):
        pos = vc.update(target, f, 1e-3)
        f = step(m, s, Sample(n * 1e-3, pos, np.array([0, 0, -1.0]), False, 0.0)).copy()
        forces.append(f[2])
        hand.append(vc.hand_force_n(target))
    rest = vc.pos[2]
    assert top + 1.5 - 0.6 < rest < top + 1.5             # resting, barely penetrating
    # on average the bone pushes back as hard as the hand pushes
    assert np.mean(forces[-500:]) == pytest.approx(np.mean(hand[-500:]), rel=0.05)
    for n in range(1500, 4000):
        pos = vc.update(target, f, 1e-3)
        f = step(m, s, Sample(n * 1e-3, pos, np.array([0, 0, -1.0]), True, 60000.0)).copy()
    assert s.n_removed > 0 and vc.pos[2] < rest - 0.3   # drilled its way down


def test_virtual_coupling_limits_speed():
    vc = VirtualCoupling(max_speed_mm_s=100.0)
    vc.reset([0, 0, 0])
    p = vc.update([1000.0, 0, 0], np.zeros(3), 1e-3)
    assert np.linalg.norm(p) == pytest.approx(0.1)
