"""Commands into the haptic loop: one small class each, sent through a ring.

The window (or any single producer in the parent) changes what the haptic
loop does between two steps by appending fixed-size records to the loop's
``commands`` ring (:data:`bonesim.engine.events.OTHER_RINGS`): ``kind`` (uint16),
``seq`` (the producer's running number) and ``args``
(:data:`~bonesim.engine.events.COMMAND_ARGS` float64: room for a body id and a 4x4
rigid pose). The loop takes every pending record before its next step, in
order, and runs the command's :meth:`Command.apply` on its
:class:`LoopContext`.

A command is one subclass of :class:`Command` with a unique ``kind`` and
``name``; defining the class registers it::

    class Nudge(Command):
        kind, name = 100, "nudge"

        @classmethod
        def encode(cls, dz_mm: float = 0.0):
            return cls.pack(dz_mm)

        @classmethod
        def apply(cls, ctx, args):
            ...

The haptic loop takes every command registered in the parent when it starts
(the classes travel to its process by reference). Continuous inputs (the
mouse's target pose, drill on/off, speed, direction) are not commands: they
are a stream, the loop's shared ``control`` fields.

Shipped: :class:`Reset` (the case back; the event counters keep running so
that consumers in other processes miss nothing), :class:`SetBurr`,
:class:`SetTool`, :class:`SplitBox` (the voxels of a body inside a box become
a new body) and :class:`MoveBody` (place a body at a rigid pose). Commands
that change the tissue publish it as tissue events (:mod:`bonesim.engine.events`)
at the time of the step they precede, so recorders, replicas and replay
see them. Quitting is the process protocol's (:mod:`bonesim.runtime.child`).
"""
from __future__ import annotations

import numpy as np

from bonesim.engine import events
from bonesim.engine.bodies import publish_pose, publish_split_box, validate_pose
from bonesim.engine.cut_plane import publish_cut_record, quantize_size
from bonesim.errors import BonesimError
from bonesim.engine.model import reset_state

__all__ = ["N_ARGS", "MAX_KIND", "TOOLS", "ERROR_TEXT_BYTES", "UnknownCommand",
           "CommandOverflow", "Command", "command_class", "registered", "LoopContext",
           "CommandSender", "CommandQueue", "Reset", "SetBurr", "SetTool", "SplitBox",
           "MoveBody", "CutPlane"]

#: Arguments per command record.
N_ARGS = events.COMMAND_ARGS
#: Largest command kind (the ring stores it as uint16); 0 is never a kind.
MAX_KIND = (1 << 16) - 1
#: Tools the loop knows (:class:`SetTool`): the drill, and the cut plane
#: (:class:`CutPlane`; the tool's pose is the plane's, a key applies a stroke).
TOOLS = ("drill", "cutplane")
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
    def apply(cls, ctx: "LoopContext", args: np.ndarray) -> None:
        """Carry the command out in the loop, between two steps. ``args`` is
        a view into the ring: copy what must outlive the call. Raise to
        reject it (the loop counts and reports the message)."""
        raise NotImplementedError(f"command {cls.name!r} has no apply()")


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
    """What a command may read and change in the haptic loop.

    Attributes
    ----------
    model : Model
        The loop's model; its burr table (:attr:`Model.burrs`) holds the
        burrs the loop can switch to.
    state : State
        The loop's tissue state (shared memory).
    burr : int
        Current burr index; the next step uses it.
    epoch : int
        Case resets so far.
    tool : int
        Current tool index into :data:`TOOLS`.
    device, coupling : object
        The haptic device and the mouse's virtual coupling (None without).
    t_s : float
        Time of the step the commands precede [s] (their events' time).
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
        self.burr = 0
        self.epoch = 0
        self.tool = 0

    def applied(self, command: type, args: np.ndarray, seq: int) -> None:
        """Called after each applied command (the hook for publishing
        commands as tissue events): counts it in ``commands_applied``."""
        self.status["commands_applied"] += 1

    def rejected(self, kind: int, seq: int, message: str) -> None:
        """Called for a command that is unknown or whose apply raised:
        counts it in ``commands_rejected`` and keeps the message in
        ``command_error``."""
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
    """The loop's side of the ring: takes and applies pending commands.

    Parameters
    ----------
    ring : events.Ring
        The ``commands`` ring.
    known : iterable of Command subclasses
        The commands this loop carries out (others are rejected).
    """

    def __init__(self, ring: events.Ring, known):
        self.ring = ring
        self.known = {c.kind: c for c in known}
        self.pos = 0
        self._head = ring.head
        self._mask = ring.capacity - 1

    def poll(self, ctx: LoopContext) -> int:
        """Apply every pending command in order; returns how many were taken.
        Without pending commands this is one integer comparison."""
        head = int(self._head[0])
        if head == self.pos:
            return 0
        f = self.ring.fields
        n = head - self.pos
        for q in range(self.pos, head):
            i = q & self._mask
            kind = int(f["kind"][i])
            seq = int(f["seq"][i])
            cls = self.known.get(kind)
            if cls is None:
                ctx.rejected(kind, seq, f"unknown command kind {kind}")
            else:
                args = f["args"][i]
                try:
                    cls.apply(ctx, args)
                except Exception as exc:           # a bad command must not stop the loop
                    ctx.rejected(kind, seq, f"{cls.name}: {exc}")
                else:
                    ctx.applied(cls, args, seq)
            self.pos = q + 1
            ctx.status["commands_read"] = self.pos
        return n


# ------------------------------------------------------------ the commands
class Reset(Command):
    """Put the case's initial tissue back; a new epoch. The event rings keep
    counting across it (consumers in other processes lose nothing)."""

    kind, name = 1, "reset"

    @classmethod
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        reset_state(ctx.model, ctx.state, rings=False)
        if ctx.coupling is not None:
            ctx.coupling.pos = None
        ctx.epoch += 1
        events.push_event(ctx.state.tissue, events.RESET, ctx.t_s, n=ctx.epoch)
        # announced before the first step of the new epoch
        ctx.status["epoch"] = ctx.epoch


class SetBurr(Command):
    """Switch to burr ``index`` (0: the model's, 1..: the loop's ``burrs``)."""

    kind, name = 2, "set_burr"

    @classmethod
    def encode(cls, index: int) -> np.ndarray:
        if int(index) != index or index < 0:
            raise ValueError(f"burr index must be a non-negative integer, got {index!r}")
        return cls.pack(index)

    @classmethod
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        b = int(args[0])
        n = len(ctx.model.burrs)
        if not 0 <= b < n:
            raise IndexError(f"burr index {b} out of range 0..{n - 1}")
        if b != ctx.burr:
            ctx.burr = b
            events.push_event(ctx.state.tissue, events.BURR, ctx.t_s, n=b)


class SetTool(Command):
    """Switch the tool (an index into :data:`TOOLS`, or its name)."""

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
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        t = int(args[0])
        if not 0 <= t < len(TOOLS):
            raise IndexError(f"tool index {t} out of range 0..{len(TOOLS) - 1}")
        ctx.tool = t
        ctx.status["tool"] = t


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
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        publish_split_box(ctx.state, int(args[0]), args[1:4].astype(np.int64),
                          args[4:7].astype(np.int64), ctx.t_s)


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
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        publish_pose(ctx.state, int(args[0]), args[1:8].copy(), ctx.t_s)
        rigid = getattr(ctx, "rigid", None)        # placed by hand: it stays put
        if rigid is not None:
            rigid.hold(int(args[0]))


class SplitPart(Command):
    """Make one part of body ``body`` a new body (the fragment finder's split,
    :mod:`bonesim.engine.fragments`): the 26-connected voxels of ``body``
    with material that hold voxel ``seed``, flood-filled inside the box ``lo
    .. hi`` (body frame, inclusive). The part was found on a replica of the
    loop's tissue; since then material can only have gone, so the loop's
    part is that part or a piece of it. The loop publishes the voxels it
    moved as ``SPLIT`` events (in ``(i, j, k)`` order, as
    :func:`~bonesim.engine.bodies.publish_split` does): replicas and replay
    move exactly those. A command of an earlier epoch (a reset came between)
    does nothing; a part larger than ``n`` voxels is refused."""

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
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        from bonesim.engine.fragments import publish_part

        if int(args[11]) != ctx.epoch:
            return                          # found before a reset: nothing of it is left
        a = args[:11].astype(np.int64)
        publish_part(ctx.state, int(a[0]), a[1:4], a[4:7], a[7:10], int(a[10]), ctx.t_s,
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
    removals and a ``CUT`` record, so replay repeats it."""

    kind, name = 21, "cut_plane"

    @classmethod
    def encode(cls, pose, width_mm: float, height_mm: float, depth_mm: float) -> np.ndarray:
        um = quantize_size(width_mm, height_mm, depth_mm)
        return cls.pack(validate_pose(pose), um)

    @classmethod
    def apply(cls, ctx: LoopContext, args: np.ndarray) -> None:
        publish_cut_record(ctx.state, ctx.model.injury, args[7:10].astype(np.int64),
                           args[0:7].copy(), ctx.t_s)
