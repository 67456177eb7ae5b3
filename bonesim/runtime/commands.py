"""Commands into the haptic loop: one small class each, sent through a ring.

The window (or any single producer in the parent) changes what the haptic
loop does between two steps by appending fixed-size records to the loop's
``commands`` ring (:data:`bonesim.engine.events.OTHER_RINGS`): ``kind`` (uint16),
``seq`` (the producer's running number) and ``args``
(:data:`~bonesim.engine.events.COMMAND_ARGS` float64: room for a body id and a 4x4
rigid pose). Before each step the loop takes every pending record, in
order, and decodes it (:meth:`Command.decode`) into a world command
(:mod:`bonesim.engine.world_commands`); it hands them to
:func:`bonesim.engine.world.world_step`, which applies them to the state as
pure state transitions before the rigid and haptic steps. Process-side
effects (the mouse coupling re-seeded at a reset; the ``status`` fields
epoch and tool) stay here, on the :class:`LoopContext`.

A command is one subclass of :class:`Command` with a unique ``kind`` and
``name``; defining the class registers it::

    class Nudge(Command):
        kind, name = 100, "nudge"

        @classmethod
        def encode(cls, body: int = 1, dz_mm: float = 0.0):
            return cls.pack(body, dz_mm)

        @classmethod
        def decode(cls, ctx, args):
            return world_commands.MoveBody(int(args[0]), ...)

A command that acts on the loop's process rather than on the state may
override :meth:`Command.apply` instead of :meth:`Command.decode`: it is
carried out on the :class:`LoopContext` in its place among the others.

The haptic loop takes every command registered in the parent when it starts
(the classes travel to its process by reference). Continuous inputs (the
mouse's target pose, drill on/off, speed, direction) are not commands: they
are a stream, the loop's shared ``control`` fields.

Shipped: :class:`Reset` (the case back; the event counters keep running so
that consumers in other processes miss nothing), :class:`SetBurr`,
:class:`SetTool`, :class:`SplitBox` (the voxels of a body inside a box become
a new body), :class:`MoveBody` (place a body at a rigid pose),
:class:`SplitPart` / :class:`ShedPart` (the fragment finder's) and
:class:`CutPlane`; the rigid commands are :mod:`bonesim.runtime.rigid_commands`'.
Commands that change the tissue publish it as tissue events
(:mod:`bonesim.engine.events`) at the time of the step they precede, so
recorders, replicas and replay see them. Quitting is the process protocol's
(:mod:`bonesim.runtime.child`).
"""
from __future__ import annotations

import numpy as np

from bonesim.engine import events
from bonesim.engine import world_commands as wc
from bonesim.engine.bodies import validate_pose
from bonesim.engine.cut_plane import quantize_size
from bonesim.engine.world import apply_commands
from bonesim.engine.world_commands import TOOLS
from bonesim.errors import BonesimError

__all__ = ["N_ARGS", "MAX_KIND", "ERROR_TEXT_BYTES", "UnknownCommand",
           "CommandOverflow", "Command", "command_class", "registered", "LoopContext",
           "CommandSender", "CommandQueue", "Reset", "SetBurr", "SetTool", "SplitBox",
           "MoveBody", "CutPlane"]

#: Arguments per command record.
N_ARGS = events.COMMAND_ARGS
#: Largest command kind (the ring stores it as uint16); 0 is never a kind.
MAX_KIND = (1 << 16) - 1
#: Size of the loop's ``command_error`` status field [bytes].
ERROR_TEXT_BYTES = 160

_BY_KIND: dict = {}
_BY_NAME: dict = {}


class UnknownCommand(BonesimError):
    """A command kind or name that no :class:`Command` subclass declares."""


class CommandOverflow(BonesimError):
    """The loop has not taken the commands already sent (ring full)."""


class Command:
    """Base of the haptic loop's commands (see the module docstring).

    Attributes
    ----------
    kind : int
        Unique, 1 .. :data:`MAX_KIND`.
    name : str
        Unique name (``loop.send("reset")``).
    """

    kind: int = 0
    name: str = ""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        kind, name = cls.kind, cls.name
        where = f"{cls.__module__}.{cls.__qualname__}"
        if not isinstance(kind, int) or not 1 <= kind <= MAX_KIND:
            raise ValueError(f"{where}: command kind must be an int in 1..{MAX_KIND}, "
                             f"got {kind!r}")
        if not isinstance(name, str) or not name:
            raise ValueError(f"{where}: command name must be a non-empty string")
        for table, key in ((_BY_KIND, kind), (_BY_NAME, name)):
            old = table.get(key)
            # the same class imported again (a re-imported test module) replaces itself
            if old is not None and (old.__module__, old.__qualname__) != (
                    cls.__module__, cls.__qualname__):
                raise ValueError(f"{where}: command {'kind' if table is _BY_KIND else 'name'} "
                                 f"{key!r} is taken by {old.__module__}.{old.__qualname__}")
        _BY_KIND[kind] = cls
        _BY_NAME[name] = cls

    @classmethod
    def pack(cls, *values) -> np.ndarray:
        """``(N_ARGS,)`` float64 arguments from leading ``values`` (zeros after).

        Raises
        ------
        ValueError
            More than :data:`N_ARGS` values.
        """
        flat = np.concatenate([np.ravel(np.asarray(v, dtype=np.float64)) for v in values]) \
            if values else np.zeros(0)
        if len(flat) > N_ARGS:
            raise ValueError(f"command {cls.name!r}: {len(flat)} arguments, at most {N_ARGS}")
        out = np.zeros(N_ARGS)
        out[:len(flat)] = flat
        return out

    @classmethod
    def encode(cls, **params) -> np.ndarray:
        """The record's ``args`` (N_ARGS,) from named parameters (in the
        parent; validate here so a bad command fails where it is sent).
        Default: a command without parameters."""
        if params:
            raise TypeError(f"command {cls.name!r} takes no parameters, got "
                            f"{sorted(params)}")
        return cls.pack()

    @classmethod
    def decode(cls, ctx: "LoopContext", args: np.ndarray):
        """The world command (:mod:`bonesim.engine.world_commands`) this
        record stands for, which :func:`bonesim.engine.world.world_step`
        applies before the next step. ``args`` is the record's own copy.
        Process-side effects that must precede the step (the mouse coupling
        re-seeded) happen here. Raise to reject the record (the loop counts
        and reports the message in its place among the others).

        Default, for a command that overrides :meth:`apply` instead: a world
        command that runs that :meth:`apply` on the loop context.
        """
        if getattr(cls.apply, "__func__", None) is Command.apply.__func__:
            raise NotImplementedError(f"command {cls.name!r} has neither decode() nor "
                                      "apply()")
        return _OnContext(cls, ctx, args)

    @classmethod
    def apply(cls, ctx: "LoopContext", args: np.ndarray) -> None:
        """Carry the command out at once, at ``ctx.t_s`` (outside a world
        step: tools and tests). A subclass may override it to act on the
        loop's process instead of defining :meth:`decode`."""
        cmd = cls.decode(ctx, np.array(args, dtype=np.float64))
        cmd.apply(ctx.model, ctx.state, ctx.t_s)
        sync = getattr(ctx, "sync", None)
        if sync is not None:
            sync()


class _OnContext(wc.WorldCommand):
    """A command acting on the loop's context (its own :meth:`Command.apply`),
    carried out in its place among the world commands."""

    __slots__ = ("cls", "ctx", "args")

    def __init__(self, cls, ctx, args):
        self.cls, self.ctx, self.args = cls, ctx, args

    def apply(self, model, state, t_s: float) -> None:
        self.ctx.t_s = t_s
        self.cls.apply(self.ctx, self.args)


class _Refusal(Exception):
    """A record refused before it could be applied (its message is complete)."""


class _Refused(wc.WorldCommand):
    """A record that is unknown or could not be decoded: refused in its place."""

    __slots__ = ("message",)

    def __init__(self, message: str):
        self.message = message

    def apply(self, model, state, t_s: float) -> None:
        raise _Refusal(self.message)


def command_class(which) -> type:
    """The :class:`Command` subclass for a kind (int), a name or a class.

    Raises
    ------
    UnknownCommand
        Naming the kind or name.
    """
    if isinstance(which, type) and issubclass(which, Command):
        if _BY_KIND.get(which.kind) is not which:
            raise UnknownCommand(f"command class {which.__qualname__} is not registered")
        return which
    table = _BY_NAME if isinstance(which, str) else _BY_KIND
    try:
        return table[which if isinstance(which, str) else int(which)]
    except (KeyError, TypeError, ValueError):
        known = ", ".join(f"{k} {c.name!r}" for k, c in sorted(_BY_KIND.items()))
        raise UnknownCommand(f"unknown command kind {which!r} (known: {known})",
                             field="kind") from None


def registered() -> tuple:
    """Every registered command class, by kind."""
    return tuple(c for _, c in sorted(_BY_KIND.items()))



class LoopContext:
    """The loop's process side, as commands see it: the state and model
    they decode for, and what is not state (device, coupling, status).

    Everything a run changes (epoch, burr, tool, rigids) is the state's
    (:class:`~bonesim.engine.model.State`).

    Attributes
    ----------
    model : Model
        The loop's model; its burr table (:attr:`Model.burrs`) holds the
        burrs the loop can switch to.
    state : State
        The loop's state (tissue in shared memory).
    device, coupling : object
        The haptic device and the mouse's virtual coupling (None without).
    t_s : float
        Time of the step the commands precede [s] (for :meth:`Command.apply`
        outside a world step).
    status : ndarray
        The loop's 0-d structured status record.
    """

    def __init__(self, model, state, device, coupling, status):
        self.model = model
        self.t_s = 0.0
        self.state = state
        self.device = device
        self.coupling = coupling
        self.status = status

    def sync(self) -> None:
        """Publish the state's epoch and tool in ``status`` (after commands)."""
        self.status["epoch"] = self.state.epoch
        self.status["tool"] = self.state.tool

    def applied(self, command: type, args: np.ndarray, seq: int) -> None:
        """Called after each applied command (the hook for publishing
        commands as tissue events): counts it in ``commands_applied``."""
        self.status["commands_applied"] += 1

    def rejected(self, kind: int, seq: int, message: str) -> None:
        """Called for a command that is unknown or whose decoding or
        application raised: counts it in ``commands_rejected`` and keeps the
        message in ``command_error``."""
        self.status["commands_rejected"] += 1
        self.status["command_error"] = f"#{seq}: {message}".encode()[:ERROR_TEXT_BYTES]


class CommandSender:
    """The producer's side of the ring (one per ring, in the parent).

    Parameters
    ----------
    ring : events.Ring
        The ``commands`` ring.
    status : ndarray
        The loop's status record; its ``commands_read`` says how many
        records the loop has taken.
    """

    def __init__(self, ring: events.Ring, status):
        self.ring = ring
        self.status = status

    @property
    def pending(self) -> int:
        """Commands sent and not yet taken by the loop."""
        return self.ring.count - int(self.status["commands_read"])

    def send(self, which, **params) -> int:
        """Encode and append one command; returns its sequence number.

        Raises
        ------
        UnknownCommand
            ``which`` names no registered command.
        CommandOverflow
            The ring holds ``capacity`` commands the loop has not taken.
        """
        cls = command_class(which)
        args = cls.encode(**params)
        if self.pending >= self.ring.capacity:
            raise CommandOverflow(f"the haptic loop has not taken the {self.pending} "
                                  f"commands already sent (ring of {self.ring.capacity}); "
                                  f"{cls.name!r} was not sent", field="commands")
        f = self.ring.fields
        seq = self.ring.count
        q = seq & (self.ring.capacity - 1)
        f["kind"][q] = cls.kind
        f["seq"][q] = seq
        f["args"][q] = args
        self.ring.head[0] += 1              # publish after the record is complete
        return seq


class CommandQueue:
    """The loop's side of the ring: takes pending records as world commands.

    Parameters
    ----------
    ring : events.Ring
        The ``commands`` ring.
    known : iterable of Command subclasses
        The commands this loop carries out (others are rejected).

    The loop calls :meth:`take` before each step, hands what it returns to
    :func:`~bonesim.engine.world.world_step` with :meth:`failed` as its
    ``on_error``, then calls :meth:`settle` when something was taken.
    """

    _NONE = ()

    def __init__(self, ring: events.Ring, known):
        self.ring = ring
        self.known = {c.kind: c for c in known}
        self.pos = 0
        self._head = ring.head
        self._mask = ring.capacity - 1
        self._taken = []
        self._failed = set()
        self._ctx = None

    def take(self, ctx: LoopContext) -> tuple:
        """Every pending record, decoded in order (an unknown or undecodable
        one becomes a command that is refused in its place). Without pending
        records this is one integer comparison and returns the same empty
        tuple."""
        head = int(self._head[0])
        if head == self.pos:
            return self._NONE
        f = self.ring.fields
        cmds = []
        self._ctx = ctx
        for q in range(self.pos, head):
            i = q & self._mask
            kind = int(f["kind"][i])
            seq = int(f["seq"][i])
            cls = self.known.get(kind)
            args = np.array(f["args"][i], dtype=np.float64)
            if cls is None:
                cmd = _Refused(f"unknown command kind {kind}")
            else:
                try:
                    cmd = cls.decode(ctx, args)
                except Exception as exc:           # refused in its place, in order
                    cmd = _Refused(f"{cls.name}: {exc}")
            self._taken.append((cls, kind, seq, args))
            cmds.append(cmd)
        self.pos = head
        ctx.status["commands_read"] = self.pos
        return tuple(cmds)

    def failed(self, i: int, exc: Exception) -> None:
        """``on_error`` for the world step: command ``i`` of the last
        :meth:`take` raised ``exc``."""
        cls, kind, seq, _ = self._taken[i]
        self._failed.add(i)
        msg = str(exc) if isinstance(exc, _Refusal) else f"{cls.name}: {exc}"
        self._ctx.rejected(kind, seq, msg)

    def settle(self, ctx: LoopContext) -> None:
        """After the world step: count the commands applied and publish the
        state's epoch and tool."""
        for i, (cls, _, seq, args) in enumerate(self._taken):
            if i not in self._failed:
                ctx.applied(cls, args, seq)
        self._taken.clear()
        self._failed.clear()
        ctx.sync()

    def poll(self, ctx: LoopContext) -> int:
        """Take and apply every pending command now, at ``ctx.t_s`` (outside
        a world step); returns how many were taken."""
        cmds = self.take(ctx)
        if not cmds:
            return 0
        apply_commands(ctx.model, ctx.state, cmds, ctx.t_s, self.failed)
        self.settle(ctx)
        return len(cmds)


# ------------------------------------------------------------ the commands
class Reset(Command):
    """Put the case's initial tissue back; a new epoch. The event rings keep
    counting across it (consumers in other processes lose nothing)."""

    kind, name = 1, "reset"

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.Reset:
        if ctx.coupling is not None:       # re-seeded where the hand is, this period
            ctx.coupling.pos = None
        return wc.Reset()


class SetBurr(Command):
    """Switch to burr ``index`` (0: the model's, 1..: the loop's ``burrs``)."""

    kind, name = 2, "set_burr"

    @classmethod
    def encode(cls, index: int) -> np.ndarray:
        if int(index) != index or index < 0:
            raise ValueError(f"burr index must be a non-negative integer, got {index!r}")
        return cls.pack(index)

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.SetBurr:
        return wc.SetBurr(int(args[0]))


class SetTool(Command):
    """Switch the tool (an index into :data:`bonesim.engine.world_commands.TOOLS`, or its name)."""

    kind, name = 3, "set_tool"

    @classmethod
    def encode(cls, tool) -> np.ndarray:
        if isinstance(tool, str):
            if tool not in TOOLS:
                raise ValueError(f"unknown tool {tool!r} (known: {', '.join(TOOLS)})")
            tool = TOOLS.index(tool)
        if int(tool) != tool or not 0 <= tool < len(TOOLS):
            raise ValueError(f"tool index {tool!r} out of range 0..{len(TOOLS) - 1}")
        return cls.pack(tool)

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.SetTool:
        return wc.SetTool(int(args[0]))


class SplitBox(Command):
    """Make the voxels of body ``body`` inside a box a new body (by hand; the
    fragment finder sends its own splits). The box is in the body's own frame,
    voxel indices ``lo .. hi`` inclusive. The new body takes the lowest free
    id and starts at its parent's pose; nothing moves."""

    kind, name = 4, "split_box"

    @classmethod
    def encode(cls, lo, hi, body: int = 0) -> np.ndarray:
        lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
        if lo.shape != (3,) or hi.shape != (3,) or (hi < lo).any():
            raise ValueError(f"split box: lo {lo.tolist()} and hi {hi.tolist()} must be "
                             "three voxel indices each with lo <= hi")
        if int(body) != body or body < 0:
            raise ValueError(f"split box: body must be a non-negative integer, got {body!r}")
        return cls.pack(body, lo, hi)

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.SplitBox:
        return wc.SplitBox(int(args[0]), tuple(args[1:4].astype(np.int64).tolist()),
                           tuple(args[4:7].astype(np.int64).tolist()))


class MoveBody(Command):
    """Place body ``body`` at ``pose`` ``(tx, ty, tz [mm], qw, qx, qy, qz)``,
    its body-to-case rigid transform."""

    kind, name = 5, "move_body"

    @classmethod
    def encode(cls, body: int, pose) -> np.ndarray:
        if int(body) != body or body < 0:
            raise ValueError(f"move body: body must be a non-negative integer, got {body!r}")
        return cls.pack(body, validate_pose(pose))

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.MoveBody:
        return wc.MoveBody(int(args[0]), args[1:8].copy())   # placed by hand: it stays put


class SplitPart(Command):
    """Make one part of body ``body`` a new body (the fragment finder's split,
    :mod:`bonesim.engine.fragments`): the 26-connected voxels of ``body``
    with material that hold voxel ``seed``, flood-filled inside the box ``lo
    .. hi`` (body frame, inclusive). The part was found on a replica of the
    loop's tissue; since then material can only have gone, so the loop's
    part is that part or a piece of it. The loop publishes the voxels it
    moved as ``SPLIT`` events (in ``(i, j, k)`` order, as
    :func:`~bonesim.engine.bodies.publish_split` does): replicas and replay
    move exactly those. A part of more than a step's split budget (``n``
    above ``[split] voxels_per_step`` of ``bonesim/data/slicing.toml``), or
    any part while such a split is under way, is moved in slices by the
    next steps, one block of ``SPLIT`` events (in fill order) per step
    (:mod:`bonesim.engine.split_jobs`). A command of an earlier epoch (a
    reset came between) does nothing; a part larger than ``n`` voxels is
    refused (in slices: the fill stops at ``n``)."""

    kind, name = 30, "split_part"
    shed = False

    @classmethod
    def encode(cls, body: int, seed, lo, hi, n: int, epoch: int) -> np.ndarray:
        seed, lo, hi = (np.asarray(v, np.int64) for v in (seed, lo, hi))
        if seed.shape != (3,) or lo.shape != (3,) or hi.shape != (3,) or (hi < lo).any() \
                or (seed < lo).any() or (seed > hi).any():
            raise ValueError(f"{cls.name}: seed {seed.tolist()} must lie in the box "
                             f"{lo.tolist()}..{hi.tolist()} (three voxel indices each)")
        for what, v in (("body", body), ("n", n), ("epoch", epoch)):
            if int(v) != v or v < (1 if what == "n" else 0):
                raise ValueError(f"{cls.name}: {what} must be a "
                                 f"{'positive' if what == 'n' else 'non-negative'} integer, "
                                 f"got {v!r}")
        return cls.pack(body, seed, lo, hi, n, epoch)

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.SplitPart:
        a = args[:12].astype(np.int64).tolist()
        return wc.SplitPart(a[0], tuple(a[1:4]), tuple(a[4:7]), tuple(a[7:10]), a[10], a[11],
                            shed=cls.shed)


class ShedPart(SplitPart):
    """As :class:`SplitPart`, but the part (a speck) is removed as dust:
    ``REMOVED`` events marked :data:`~bonesim.engine.events.REMOVED_SHED`."""

    kind, name = 31, "shed_part"
    shed = True


__all__ += ["SplitPart", "ShedPart"]


class CutPlane(Command):
    """One stroke of the cut plane (:mod:`bonesim.engine.cut_plane`): a
    rectangle at ``pose`` ``(cx, cy, cz [mm], qw, qx, qy, qz)`` (case frame;
    :func:`~bonesim.engine.cut_plane.plane_pose` builds one from a centre and a
    normal), ``width_mm`` x ``height_mm``, whose rays go ``depth_mm`` along
    its normal and remove every voxel they pass, in every body. Published as
    removals and a ``CUT`` record, so replay repeats it. A stroke larger than
    a step's budget is walked in slices by the next steps (its ``CUT`` record
    first: :mod:`bonesim.engine.cut_plane`)."""

    kind, name = 21, "cut_plane"

    @classmethod
    def encode(cls, pose, width_mm: float, height_mm: float, depth_mm: float) -> np.ndarray:
        um = quantize_size(width_mm, height_mm, depth_mm)
        return cls.pack(validate_pose(pose), um)

    @classmethod
    def decode(cls, ctx: LoopContext, args: np.ndarray) -> wc.CutStroke:
        return wc.CutStroke(args[0:7].copy(), args[7:10].astype(np.int64))
