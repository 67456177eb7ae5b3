"""One consumer-side copy of the tissue, changed only by the tissue-event stream.

Every consumer that shows or measures the tissue away from the haptic step
(the window's surface, the simulate command, playback, the tutored trainee,
the recorder's visibility judge, the nerve monitor) keeps a
:class:`TissueReplica`: a private :class:`~bonesim.engine.model.State` of the model
(grid density, body ids, poses) that changes only by applying tissue events
(:mod:`bonesim.engine.events`) in order, with its cursor into the stream and its
epoch (case resets seen). Applying the stream the haptic loop published
gives the loop's tissue exactly, at every reset and at the end; that is what
the tests check.

A replica that *follows* a live state (in this process, or the haptic loop's
shared memory) drains its tissue ring and also its ``touched`` shading
hints: a touched voxel takes the live density, unless that is already 0 (its
removal is still on its way through the ring). With ``surface=True`` the
replica keeps a :class:`~bonesim.engine.surface.Surface` in step: incremental
updates for removals, a rebuild after a reset.

Surfaces per body
-----------------
While the case is one body (no ``SPLIT`` since the last reset) the replica
keeps ONE surface, ``surface``, over its whole grid, as it always did; a
``POSE`` of body 0 moves it as a whole (:meth:`TissueReplica.body_matrix`).
From the first split on, every living body has a surface of only its own
voxels, in its own frame (:mod:`bonesim.engine.body_surfaces`):
:attr:`TissueReplica.body_surfaces` maps body id -> surface, and
:meth:`TissueReplica.body_matrix` gives the pose that places each in the case
frame. ``surface`` is then body 0's: the same object, updated in place (the
voxels that left body 0 are removed from it), so a window drawing it keeps
its buffers. A reset goes back to one surface.
"""
from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
from numba import njit

from bonesim.engine import events
from bonesim.engine.body_surfaces import BodySurfaces
from bonesim.engine.bodies import is_identity, set_pose, split_body
from bonesim.engine.grid import BRICK_SHIFT, find_brick, sync_replica, voxel_offset
from bonesim.engine.kernel_args import read_only
from bonesim.engine.model import Model, clear_touched, make_state, reset_state
from bonesim.engine.rigid_set import track_plates

__all__ = ["REPLICA_RING_CAPACITY", "Changes", "TissueReplica"]

#: A replica's own rings are never written; they are kept minimal.
REPLICA_RING_CAPACITY = 16
_NO_IJK = np.zeros((0, 3), np.int32)


class Changes(NamedTuple):
    """What one :meth:`TissueReplica.apply` changed.

    Attributes
    ----------
    removed : (n, 3) int32
        Voxels removed since the last reset in the batch (body frames), in order.
    touched : (m, 3) int32
        Voxels whose density was synced from the live state (shading hints).
    reset : bool
        The batch held a case reset (the tissue was put back first).
    injuries : dict
        The batch's contacts and injuries since its last reset
        (:func:`bonesim.engine.events.injuries`).
    bodies : tuple of int
        Bodies created or moved by the batch.
    n_events : int
        Events applied.
    split : (s, 3) int32
        Voxels that ``SPLIT`` events of the batch (since its last reset)
        moved to another body, in order: they left their body's surface.
    """

    removed: np.ndarray
    touched: np.ndarray
    reset: bool
    injuries: dict
    bodies: tuple
    n_events: int
    split: np.ndarray = _NO_IJK

    @property
    def changed(self) -> np.ndarray:
        """(n, 3) int32: ``removed`` and ``split`` together, the voxels that
        left a body's surface (give them to ``Scene.update_bodies``)."""
        if not len(self.split):
            return self.removed
        return np.concatenate((self.removed, self.split))


@njit(cache=True, nogil=True)
def _remove(keys, vals, density, label, ijk, removed_by_label):
    for q in range(ijk.shape[0]):
        i, j, k = ijk[q, 0], ijk[q, 1], ijk[q, 2]
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        if b >= 0:
            off = voxel_offset(i, j, k)
            if density[b, off] > 0.0:
                density[b, off] = 0.0
                removed_by_label[label[b, off]] += 1


class TissueReplica:
    """A consumer's copy of the tissue (see the module docstring).

    Parameters
    ----------
    model : Model
    source : State, optional
        A live state to follow (:meth:`drain`); None for a replica fed by
        :meth:`apply` (playback, a tutored trainee, tests).
    surface : bool
        Keep a :class:`~bonesim.engine.surface.Surface` in step.
    snapshot : bool
        With a ``source``: start from a copy of its tissue now and read its
        ring from now on (a consumer joining a running loop); else start
        from the initial tissue and read the ring from record 0.

    Attributes
    ----------
    state : State
        The replica's tissue: ``state.grid`` (density), ``state.body``,
        ``state.pose``, ``state.removed_by_label``.
    epoch : int
        Case resets applied.
    burr : int
        The burr index last announced.
    applied : int
        Events applied so far.
    surface : Surface or None
        The surface of the whole grid while the case is one body; body 0's
        surface after a split (see :attr:`body_surfaces`).
    update_s : list of float
        Time each surface update took [s] (all bodies of a batch together).
    """

    def __init__(self, model: Model, source=None, *, surface: bool = False,
                 snapshot: bool = True):
        self.model = model
        self.source = source
        self.state = make_state(model, ring_capacity=REPLICA_RING_CAPACITY)
        self.epoch = 0
        self.burr = 0
        self.applied = 0
        self.cursor = self.touched = None
        #: plates and distractors: slot -> (catalogue index, pose, host body or
        #: -1), from ``PLATE`` events (:func:`bonesim.engine.rigid_set.track_plates`)
        self.plates = {}
        if source is not None:
            # cursors first, then the snapshot: whatever the haptic side
            # changes after the cursors were set is drained later (applying a
            # removal the snapshot already shows is harmless)
            start = None if snapshot else 0
            g, live = self.state.grid, source.grid
            if g.keys is not live.keys and not (np.array_equal(g.keys, live.keys)
                                                and np.array_equal(g.vals, live.vals)):
                raise ValueError("the replica's model and the followed state have "
                                 "different brick tables (not the same case)")
            self.cursor = events.Cursor(source.tissue, start)
            self.touched = events.Cursor(source.touched, start)
            if snapshot:
                self._copy_from(source)
        self.surface = None
        self._bodies: BodySurfaces | None = None   # after a split
        self._main_rev = 0                         # changes of the one-body surface
        self.update_s: list[float] = []
        if surface:
            self._rebuild_surface()

    # ------------------------------------------------------------------ state
    @property
    def grid(self):
        """The replica's grid (density changes only through events)."""
        return self.state.grid

    def _copy_from(self, src) -> None:
        st = self.state
        for name in ("body", "pose", "pose_m", "alive", "bounds", "removed_by_label"):
            getattr(st, name)[:] = getattr(src, name)
        st.grid.density[:] = src.grid.density
        st._one_body = int(st.alive.sum()) == 1 and bool(st.alive[0]) \
            and is_identity(st.pose[0])

    def _several_bodies(self) -> bool:
        return bool(self.state.alive[1:].any())

    def _rebuild_surface(self) -> None:
        from bonesim.engine.surface import Surface

        self._main_rev += 1
        if self._several_bodies():
            self._bodies = BodySurfaces.build(self.model, self.state)
            self.surface = self._bodies.surfaces[0]
        else:
            self._bodies = None
            self.surface = Surface.of_model(self.model, self.grid)   # thin bone shows the tint

    # ------------------------------------------------------------- bodies
    @property
    def body_surfaces(self) -> dict:
        """Body id -> :class:`~bonesim.engine.surface.Surface` of the living bodies.

        Each surface holds only its body's voxels, in the body's own frame
        (vertex of voxel ``(i, j, k)`` at ``origin + spacing * (i, j, k)``
        [mm]); :meth:`body_matrix` places it in the case frame. While the
        case is one body: ``{0: surface}``. Empty without a surface.
        """
        if self.surface is None:
            return {}
        if self._bodies is None:
            return {0: self.surface}
        return dict(self._bodies.surfaces)

    @property
    def body_grids(self) -> dict:
        """Body id -> the grid each body's surface was built from (body frame;
        the replica's lattice). While the case is one body: ``{0: grid}``."""
        if self._bodies is None:
            return {0: self.grid} if self.surface is not None else {}
        return dict(self._bodies.grids)

    @property
    def body_revisions(self) -> dict:
        """Body id -> a number that grows whenever that body's surface
        changes (built or updated), for viewers that redraw only what changed."""
        if self._bodies is None:
            return {0: self._main_rev} if self.surface is not None else {}
        return dict(self._bodies.revision)

    def body_matrix(self, b: int) -> np.ndarray:
        """Body ``b``'s pose as a (4, 4) float64 matrix ``[[R, t], [0, 1]]``:
        body frame -> case frame, ``t`` [mm]."""
        if not 0 <= b < len(self.state.alive) or not self.state.alive[b]:
            raise ValueError(f"body {b} does not exist")
        m = np.eye(4)
        m[:3, :] = self.state.pose_m[b]
        return m

    def reset(self, epoch: int | None = None, surface: bool = True) -> None:
        """Back to the model's initial tissue (one body, identity pose).

        Parameters
        ----------
        epoch : int, optional
            The epoch now (default: one more).
        surface : bool
            Rebuild the surface now (False: the caller applies more events
            with ``surface=False`` and then calls :meth:`rebuild_surface`).
        """
        reset_state(self.model, self.state, rings=False)
        self.epoch = self.epoch + 1 if epoch is None else int(epoch)
        self._bodies = None
        self.plates.clear()
        if self.surface is not None and surface:
            self._rebuild_surface()

    def rebuild_surface(self) -> None:
        """Tessellate the replica's tissue from scratch (after applying events
        with ``surface=False``)."""
        if self.surface is not None:
            self._rebuild_surface()

    # ------------------------------------------------------------------ apply
    def apply(self, ev: dict, touched=None, surface: bool = True, live=None) -> Changes:
        """Apply tissue events in order.

        Parameters
        ----------
        ev : dict of str -> ndarray
            Tissue-event columns (:data:`bonesim.engine.events.TISSUE_FIELDS`).
        touched : (m, 3) int, optional
            Shading hints to sync from the followed live state.
        surface : bool
            Update the surface (False: leave it to :meth:`rebuild_surface`).
        live : bonesim.engine.grid.Grid, optional
            Where the touched voxels' densities are read (default: the
            followed state's grid), e.g. a copy taken when the events were
            drained while the state stepped on.

        Returns
        -------
        Changes
        """
        kinds = np.asarray(ev["kind"])
        n = len(kinds)
        st = self.state
        g = st.grid
        removed, bodies, did_reset, after = [], [], False, 0
        split_ijk, split_src, grown = [], [], set()
        starts = np.concatenate(([0], np.flatnonzero(np.diff(kinds)) + 1, [n])) if n \
            else np.zeros(1, np.int64)
        for a, b in zip(starts[:-1], starts[1:]):
            k = int(kinds[a])
            if k == events.REMOVED:
                ijk = np.ascontiguousarray(ev["ijk"][a:b], dtype=np.int32)
                _remove(g.keys, g.vals, g.density, g.label, read_only(ijk),
                        st.removed_by_label)
                removed.append(ijk)
            elif k == events.RESET:
                reset_state(self.model, st, rings=False)
                self.plates.clear()
                self.epoch = int(ev["n"][b - 1])
                removed, did_reset, after = [], True, b
                split_ijk, split_src, grown = [], [], set()
            elif k == events.BURR:
                self.burr = int(ev["n"][b - 1])
            elif k == events.SPLIT:
                # one split is a block of records of one new body
                dst_col = ev["body"][a:b]
                cuts = np.concatenate(([0], np.flatnonzero(np.diff(dst_col)) + 1,
                                       [b - a])) + a
                for c0, c1 in zip(cuts[:-1], cuts[1:]):
                    dst, src = int(ev["body"][c0]), int(ev["value"][c0, 0])
                    ijk = np.ascontiguousarray(ev["ijk"][c0:c1], dtype=np.int32)
                    self._split(src, dst, ijk)
                    split_ijk.append(ijk)
                    split_src.append(np.full(len(ijk), src, np.int64))
                    grown.add(dst)
                    if dst not in bodies:
                        bodies.append(dst)
            elif k == events.PLATE:
                track_plates({f: ev[f][a:b] for f in ("kind", "body", "n", "value", "label")},
                             self.plates)
            elif k == events.POSE:
                for q in range(a, b):
                    bod = int(ev["body"][q])
                    set_pose(st, bod, ev["value"][q])
                    if bod not in bodies:
                        bodies.append(bod)
        self.applied += n
        rem = np.concatenate(removed) if removed else _NO_IJK
        tch = _NO_IJK if touched is None else \
            np.ascontiguousarray(touched, dtype=np.int32).reshape(-1, 3)
        if live is None and self.source is not None:
            live = self.source.grid
        if len(tch) and live is not None:
            sync_replica(g, live, _NO_IJK, tch, check=False)
        spl = np.concatenate(split_ijk) if split_ijk else _NO_IJK
        if self.surface is not None and surface:
            if did_reset:
                self._rebuild_surface()
                if self._bodies is None and (len(rem) or len(tch)):
                    self._update_surface(rem, tch)
            elif self._bodies is not None or len(spl):
                t0 = time.perf_counter()
                if self._bodies is None:                  # the first split
                    self._bodies = BodySurfaces.take_over(
                        self.model, st, self.surface, np.concatenate((rem, spl)), tch)
                else:
                    self._bodies.update(st, rem, tch, spl,
                                        np.concatenate(split_src) if split_src else (),
                                        grown)
                self.surface = self._bodies.surfaces[0]
                self.update_s.append(time.perf_counter() - t0)
            elif len(rem) or len(tch):
                self._update_surface(rem, tch)
        since = {f: a[after:] for f, a in ev.items()}
        return Changes(rem, tch, did_reset, events.injuries(since), tuple(bodies), n, spl)

    def _split(self, src: int, dst: int, ijk) -> None:
        # a block continuing a body created earlier in the stream grows it
        split_body(self.state, src, ijk, dst, grow=bool(self.state.alive[dst]))

    def _update_surface(self, rem, tch) -> None:
        t0 = time.perf_counter()
        self.surface.update(self.grid, rem, tch)
        self._main_rev += 1
        self.update_s.append(time.perf_counter() - t0)

    def drain(self) -> Changes:
        """Apply everything the followed state published since the last call."""
        if self.source is None:
            raise ValueError("this replica follows no live state; feed it with apply()")
        ev = self.cursor.drain()
        tch = self.touched.drain()["ijk"]
        # clear the flags before reading densities: a voxel the haptic side
        # lowers again after this point is published again, never lost
        if len(tch):
            clear_touched(self.source, tch)
        return self.apply(ev, tch)
