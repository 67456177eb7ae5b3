"""Commands into the haptic loop: registration, the ring (order, overflow,
unknown kinds), and Reset / SetBurr / SetTool and a command defined here
carried out by a running loop."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.runtime import commands
from bonesim.engine import events
from bonesim.io.burrs import load_burr
from bonesim.runtime.child import BASE_STATUS, record_dtype
from bonesim.runtime.commands import (N_ARGS, Command, CommandOverflow, CommandQueue,
                                      CommandSender, LoopContext, Reset, SetBurr, SetTool,
                                      UnknownCommand, command_class)
from bonesim.engine.grid import voxel_offset
from bonesim.runtime.haptic_loop import STATUS, HapticLoop
from bonesim.io.loading import load_model
from tests.bonesim.fakes import FakeBurr, block_model, wait_for

#: Far above the phantom's bone: the null device touches nothing [mm].
AWAY_MM = (0.0, 0.0, 60.0)


class Carve(Command):
    """A new command in one small class: empty one voxel of the tissue."""

    kind, name = 901, "test_carve"

    @classmethod
    def encode(cls, ijk) -> np.ndarray:
        ijk = np.asarray(ijk)
        if ijk.shape != (3,):
            raise ValueError(f"ijk must be 3 voxel indices, got shape {ijk.shape}")
        return cls.pack(ijk)

    @classmethod
    def apply(cls, ctx, args) -> None:
        i, j, k = (int(a) for a in args[:3])
        g = ctx.state.grid
        b = g.brick_index(i, j, k)
        if b < 0:
            raise ValueError(f"voxel {(i, j, k)} is in no brick")
        g.density[b, voxel_offset(i, j, k)] = 0.0


class Record(Command):
    """Notes its first argument in the context (for the ordering test)."""

    kind, name = 902, "test_record"

    @classmethod
    def encode(cls, value: float) -> np.ndarray:
        return cls.pack(value)

    @classmethod
    def apply(cls, ctx, args) -> None:
        if args[0] < 0:
            raise ValueError("negative values are refused")
        ctx.seen.append(float(args[0]))


def _ring(capacity: int = 8) -> events.Ring:
    fields = events.OTHER_RINGS["commands"][1]
    return events.Ring.create(capacity, **fields)


def _ctx() -> LoopContext:
    status = np.zeros((), record_dtype(BASE_STATUS, STATUS))
    model, state = block_model()
    model = model.with_burrs([FakeBurr(radius_mm=1.0)])      # burrs 0 and 1
    ctx = LoopContext(model=model, state=state, device=None, coupling=None, status=status)
    ctx.seen = []
    return ctx


# ---------------------------------------------------------------- registry
def test_defining_a_subclass_registers_it_and_clashes_are_refused():
    assert command_class("test_carve") is Carve and command_class(901) is Carve
    assert Reset in commands.registered() and Carve in commands.registered()
    with pytest.raises(ValueError, match="kind 1 is taken by bonesim.runtime.commands.Reset"):
        type("Clash", (Command,), {"kind": 1, "name": "clash"})
    with pytest.raises(ValueError, match="name 'reset' is taken"):
        type("Clash", (Command,), {"kind": 990, "name": "reset"})
    with pytest.raises(ValueError, match="kind must be an int in 1..65535"):
        type("Zero", (Command,), {"kind": 0, "name": "zero"})
    with pytest.raises(UnknownCommand, match="unknown command kind 4242"):
        command_class(4242)
    with pytest.raises(UnknownCommand, match="unknown command kind 'teleport'"):
        command_class("teleport")


def test_encode_validates_where_the_command_is_sent():
    np.testing.assert_array_equal(SetBurr.encode(index=2)[:2], [2.0, 0.0])
    assert SetBurr.encode(index=2).shape == (N_ARGS,) and N_ARGS >= 17
    assert SetTool.encode(tool="drill")[0] == 0.0
    with pytest.raises(ValueError, match="unknown tool 'laser'"):
        SetTool.encode(tool="laser")
    with pytest.raises(ValueError, match="non-negative integer"):
        SetBurr.encode(index=-1)
    with pytest.raises(TypeError, match="'reset' takes no parameters"):
        Reset.encode(hard=True)
    with pytest.raises(ValueError, match=f"at most {N_ARGS}"):
        Carve.pack(np.zeros(N_ARGS + 1))


# -------------------------------------------------------------------- ring
def test_commands_are_applied_in_order_and_counted():
    ring, ctx = _ring(), _ctx()
    sender = CommandSender(ring, ctx.status)
    queue = CommandQueue(ring, [Record, SetBurr])
    seqs = [sender.send("test_record", value=v) for v in (3.0, 1.0, 2.0)]
    seqs.append(sender.send(SetBurr, index=1))
    assert seqs == [0, 1, 2, 3] and sender.pending == 4
    assert queue.poll(ctx) == 4 and queue.poll(ctx) == 0
    assert ctx.seen == [3.0, 1.0, 2.0] and ctx.state.burr == 1
    assert ctx.status["commands_applied"] == 4 and sender.pending == 0
    for v in range(20):                        # wraps the ring of 8 several times
        sender.send(Record, value=float(v))
        queue.poll(ctx)
    assert ctx.seen[3:] == [float(v) for v in range(20)]


def test_taking_decodes_into_world_commands_handed_to_the_world_step():
    from bonesim.engine import world_commands as wc
    from bonesim.engine.model import Sample
    from bonesim.engine.world import world_step

    ring, ctx = _ring(), _ctx()
    sender = CommandSender(ring, ctx.status)
    queue = CommandQueue(ring, [Record, SetBurr, SetTool, Reset])
    empty = queue.take(ctx)
    assert empty == () and queue.take(ctx) is empty         # nothing pending: no new tuple
    sender.send(SetBurr, index=1)
    sender.send(Record, value=5.0)
    sender.send(SetTool, tool="cutplane")
    sender.send(Reset)
    sender.send(SetBurr, index=9)
    cmds = queue.take(ctx)
    assert [type(c) for c in cmds[:1] + cmds[2:]] == [wc.SetBurr, wc.SetTool, wc.Reset,
                                                        wc.SetBurr]
    assert ctx.status["commands_read"] == 5 and ctx.state.burr == 0   # not applied yet
    world_step(ctx.model, ctx.state, Sample(0.25, np.array([0.0, 0.0, 60.0]),
                                            np.array([0.0, 0.0, -1.0]), False, 1.0, 1),
               cmds, queue.failed)
    queue.settle(ctx)
    st = ctx.state
    assert (st.burr, st.tool, st.epoch) == (1, 1, 1) and ctx.seen == [5.0]
    assert ctx.status["epoch"] == 1 and ctx.status["tool"] == 1
    assert ctx.status["commands_applied"] == 4 and ctx.status["commands_rejected"] == 1
    assert ctx.status["command_error"].item() == b"#4: set_burr: burr index 9 out of range 0..1"
    ev = st.tissue.read(0)
    assert ev["kind"].tolist() == [events.BURR, events.RESET]
    assert (ev["t_s"] == 0.25).all() and st.n_steps == 1


def test_a_full_ring_is_reported_and_nothing_is_overwritten():
    ring, ctx = _ring(4), _ctx()
    sender = CommandSender(ring, ctx.status)
    queue = CommandQueue(ring, [Record])
    for v in range(4):
        sender.send(Record, value=float(v))
    with pytest.raises(CommandOverflow, match="not taken the 4 commands"):
        sender.send(Record, value=99.0)
    queue.poll(ctx)
    assert ctx.seen == [0.0, 1.0, 2.0, 3.0]        # the refused one never went in
    sender.send(Record, value=4.0)                 # room again once taken
    queue.poll(ctx)
    assert ctx.seen[-1] == 4.0


def test_unknown_kinds_and_failing_commands_are_rejected_with_a_message():
    ring, ctx = _ring(), _ctx()
    sender = CommandSender(ring, ctx.status)
    queue = CommandQueue(ring, [Record, SetBurr])    # this loop does not know Carve
    sender.send(Carve, ijk=(1, 2, 3))
    sender.send(Record, value=-1.0)
    sender.send(SetBurr, index=5)                  # only 2 models
    sender.send(Record, value=7.0)                 # the loop goes on after them
    assert queue.poll(ctx) == 4
    assert ctx.seen == [7.0] and ctx.state.burr == 0
    assert ctx.status["commands_rejected"] == 3 and ctx.status["commands_applied"] == 1
    assert ctx.status["command_error"].item() == b"#2: set_burr: burr index 5 out of range 0..1"
    ctx2 = _ctx()
    CommandQueue(ring, [Record]).poll(ctx2)         # from record 0 again
    assert ctx2.status["command_error"].item().startswith(b"#2:")
    assert ctx2.status["commands_rejected"] == 3


# ------------------------------------------------------- a running loop
@pytest.fixture(scope="module")
def model():
    return load_model("phantom", "cutting-5mm")


def _bone_voxel(grid) -> tuple:
    b, off = np.argwhere(grid.density > 0)[0]
    i0, j0, k0 = (int(c) * 8 for c in grid.bricks[b])
    return i0 + (off >> 6), j0 + ((off >> 3) & 7), k0 + (off & 7)


@pytest.mark.slow
def test_reset_burr_tool_and_a_new_command_through_a_running_loop(model):
    ijk = _bone_voxel(model.grid)
    b = model.grid.brick_index(*ijk)
    with HapticLoop(model, burrs=[load_burr("diamond-3mm")],
                    device=("null", AWAY_MM, (0.0, 0.0, -1.0))) as loop:
        st = loop.status
        assert st["epoch"] == 0 and st["burr"] == 0 and st["tool"] == 0
        # the command defined in this file travels to the loop and is carried out
        loop.send("test_carve", ijk=ijk)
        assert wait_for(lambda: loop.state.grid.density[b, voxel_offset(*ijk)] == 0.0)
        loop.set_burr(1)
        loop.set_tool("drill")
        assert wait_for(lambda: st["burr"] == 1 and st["commands_applied"] == 3)
        assert st["tool"] == 0
        n_samples = loop.samples.count
        epoch = loop.reset()
        assert epoch == 1 and wait_for(lambda: st["epoch"] == 1)
        # the reset restored the carved voxel; the sample ring kept counting
        assert loop.state.grid.density[b, voxel_offset(*ijk)] == model.grid.density[
            b, voxel_offset(*ijk)]
        assert loop.samples.count >= n_samples
        first_new = loop.samples.count
        assert wait_for(lambda: loop.samples.count >= first_new + 5)
        smp = loop.samples.read(first_new, first_new + 5)
        assert (smp["epoch"] == 1).all() and (smp["burr"] == 1).all()
        # a bad burr sent raw is refused by the loop, which says why and goes on
        loop.send(SetBurr, index=7)
        assert wait_for(lambda: st["commands_rejected"] == 1)
        assert b"burr index 7 out of range 0..1" in st["command_error"].item()
        assert st["burr"] == 1 and st["commands_applied"] == 4
        with pytest.raises(IndexError, match="out of range"):
            loop.set_burr(2)
        # a command registered after the loop started is not sent to it

        class Late(Command):
            kind, name = 903, "test_late"

        with pytest.raises(UnknownCommand, match="does not know command 'test_late'"):
            loop.send(Late)
        assert loop.running
    # ... and it does not stop later loops from starting (it cannot travel to them)
    with HapticLoop(model, device=("null", AWAY_MM, (0.0, 0.0, -1.0))) as loop:
        with pytest.raises(UnknownCommand, match="inside a function"):
            loop.send("test_late")
        loop.send(Carve, ijk=ijk)
        assert wait_for(lambda: loop.status["commands_applied"] == 1)
