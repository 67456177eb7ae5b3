"""Index buffers for drawing a :class:`~bonesim.engine.surface.Surface`: all live
triangles, and the *visible subset*.

No VTK here: these are numpy arrays that :mod:`bonesim.render.scene` hands
to VTK without copying, and numba kernels that fill them.

The surface keeps vertices and triangles in slot arrays with free slots
(see :class:`bonesim.engine.surface.Surface`). Vertex arrays are drawn as they are
(a free slot is simply never referenced); triangles are *compacted*: one
pass over the triangle slots writes the vertex indices of every live
triangle into a flat int32 connectivity buffer. That pass is O(triangle
slots) in a numba loop (~0.1 ms per 100,000 slots).

Winding as drawn
----------------
The surface winds each triangle by the voxels it comes from (seen from
outside the cell's empty corners); its vertex normals come from the
smoothed density. Where the surface folds within a voxel or two, the two
can disagree: a triangle whose corners' normals face the eye is then wound
away from it. OpenGL calls it back-facing, and the renderer's two-sided
lighting turns its normals around, away from the light: a dark speck, one
voxel wide, on bright bone. So every compaction writes a triangle as
``(a, c, b)`` when its face normal ``(b - a) x (c - a)`` points against
the sum of its corners' normals (the surface keeps that bit per triangle,
``Surface.tflip``, up to date as it moves vertices), and as ``(a, b, c)``
otherwise: the drawn winding always agrees with the shading normals.
:func:`oriented_triangles` does the same for compact arrays. (The visible
subset below still judges a face by the surface's own winding, out of the
bone: what it asks is which side of the bone a triangle is on.)

Visible subset (SPEC, "Hybrid voxel / surface data structure")
--------------------------------------------------------------
A vertex *faces the camera* when its normal points toward the eye:
``dot(n, eye - p) > 0`` for a perspective camera, ``dot(n, -d) > 0`` for a
parallel one looking along ``d``. A triangle is *visible* when at least one
of its vertices faces the camera (SPEC), or when its own face does (normal
``(b - a) x (c - a)`` as the surface winds it, out of the bone). The second test is
ours: at a drilled rim the smoothed vertex normals of a triangle seen edge-on
can all point away although the face shows, and without it the resting
picture lost those pixels. When the camera comes to rest,
:meth:`SurfaceBuffers.start_visible` copies the surface's arrays (a
snapshot) and a background thread computes the visible flag of every
triangle slot of the snapshot (numba, ``nogil``; it touches no VTK object
and not the live surface). When it is done and the camera has not moved,
:meth:`SurfaceBuffers.adopt` installs it.

The surface keeps changing while the subset is in use, so each compaction
keeps a live triangle in the subset if it was visible in the snapshot *or*
it may have changed since. Two ways to know what may have changed:

*Change marks* (fast; when the caller passes the voxels given to
``Surface.update``). A removal only re-evaluates the cells that contain the
removed voxel, so every triangle it creates has all three corners in the
3x3x3 block around that voxel; a new vertex is a neighbour of a removed
voxel. So the vertices of those blocks are *marked* (``_mark_near``, O(27)
hash look-ups per voxel), and a triangle is kept when a corner is marked.
The per-update pass then reads only the triangle slots. (Re-shading moves
and turns vertices up to ``NORMAL_RADIUS`` voxels from a removed or touched
voxel; beyond the marked block those are small changes of vertices that
already existed, and a triangle they turn toward the eye joins the subset
at the next snapshot, when the camera next comes to rest.)

*Comparison* (fallback; when the voxels are not given). A triangle is kept
when its slot lies past the snapshot's end, its key or corners differ from
the snapshot, or a corner's position or normal does (an extra O(vertex
slots) pass; ~4x slower on a 1.7-million-triangle surface).

Either way new and re-shaded geometry around the drill is always drawn, and
the subset never loses a triangle the full array would show facing the
camera at the time of the snapshot.
"""
from __future__ import annotations

import threading
import weakref

import numpy as np
from numba import njit

from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset

__all__ = ["VisibleJob", "SurfaceBuffers", "oriented_triangles", "warmup"]


@njit(cache=True, nogil=True, inline="always")
def _append(dst, n, a, b, c):
    """Write triangle ``(a, b, c)`` as the ``n``-th of the index list ``dst``;
    returns ``n + 1``."""
    dst[3 * n] = a
    dst[3 * n + 1] = b
    dst[3 * n + 2] = c
    return n + 1


@njit(cache=True, nogil=True)
def _compact(tri, key, tflip, pos, nrm, s_tri, s_key, s_pos, s_nrm, s_tvis, vdirty, with_vis,
             full, vis):
    """Write live triangles into ``full`` (and the visible ones into ``vis``).

    Returns ``(n_full, n_vis)`` triangle counts."""
    if with_vis:
        nvs = s_pos.shape[0]
        for v in range(pos.shape[0]):
            if v >= nvs:
                vdirty[v] = 1
            elif (pos[v, 0] != s_pos[v, 0] or pos[v, 1] != s_pos[v, 1]
                  or pos[v, 2] != s_pos[v, 2] or nrm[v, 0] != s_nrm[v, 0]
                  or nrm[v, 1] != s_nrm[v, 1] or nrm[v, 2] != s_nrm[v, 2]):
                vdirty[v] = 1
            else:
                vdirty[v] = 0
    nts = s_key.shape[0]
    nf = 0
    nv = 0
    for t in range(key.shape[0]):
        k = key[t]
        if k < 0:
            continue
        a = tri[t, 0]
        b = tri[t, 1]
        c = tri[t, 2]
        if tflip[t]:
            b, c = c, b
        nf = _append(full, nf, a, b, c)
        if with_vis:
            keep = False
            if t >= nts:
                keep = True
            elif (s_key[t] != k or s_tri[t, 0] != tri[t, 0] or s_tri[t, 1] != tri[t, 1]
                  or s_tri[t, 2] != tri[t, 2]):
                keep = True
            elif s_tvis[t] != 0 or vdirty[a] != 0 or vdirty[b] != 0 or vdirty[c] != 0:
                keep = True
            if keep:
                nv = _append(vis, nv, a, b, c)
    return nf, nv


@njit(cache=True, nogil=True)
def _compact_marked(tri, key, tflip, s_tvis, marked, full, vis):
    """Like :func:`_compact` with change marks: keep a live triangle in ``vis``
    when it was visible in the snapshot or a corner is marked."""
    nts = s_tvis.shape[0]
    nf = 0
    nv = 0
    for t in range(key.shape[0]):
        if key[t] < 0:
            continue
        a = tri[t, 0]
        b = tri[t, 1]
        c = tri[t, 2]
        if tflip[t]:
            b, c = c, b
        nf = _append(full, nf, a, b, c)
        if (t < nts and s_tvis[t] != 0) or marked[a] != 0 or marked[b] != 0 or marked[c] != 0:
            nv = _append(vis, nv, a, b, c)
    return nf, nv


@njit(cache=True, nogil=True)
def _compact_near(tri, key, tflip, far, with_vis, keep_near, s_tvis, marked, full, vis):
    """Like :func:`_compact_marked` for the triangles without a far corner
    (:mod:`bonesim.render.lod`); ``keep_near``: keep every one in ``vis``
    (changes not marked). Returns the counts written."""
    nts = s_tvis.shape[0]
    nf = 0
    nv = 0
    for t in range(key.shape[0]):
        if key[t] < 0:
            continue
        a = tri[t, 0]
        b = tri[t, 1]
        c = tri[t, 2]
        if far[a] != 0 or far[b] != 0 or far[c] != 0:
            continue
        keep = with_vis and (keep_near or (t < nts and s_tvis[t] != 0) or marked[a] != 0
                             or marked[b] != 0 or marked[c] != 0)
        if tflip[t]:
            b, c = c, b
        nf = _append(full, nf, a, b, c)
        if keep:
            nv = _append(vis, nv, a, b, c)
    return nf, nv


@njit(cache=True, nogil=True)
def _mark_near(keys, vals, vmap, ijk, marked):
    """Mark the vertex slots of every voxel in the 3x3x3 block around each
    voxel of ``ijk``."""
    for q in range(ijk.shape[0]):
        for di in range(-1, 2):
            i = ijk[q, 0] + di
            for dj in range(-1, 2):
                j = ijk[q, 1] + dj
                for dk in range(-1, 2):
                    k = ijk[q, 2] + dk
                    b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                                   k >> BRICK_SHIFT)
                    if b >= 0:
                        v = vmap[b, voxel_offset(i, j, k)]
                        if v >= 0 and v < marked.shape[0]:
                            marked[v] = 1


@njit(cache=True, nogil=True)
def _visible_flags(pos, nrm, tri, key, eye, dirn, parallel, vflag, tvis):
    """Facing flag per vertex slot, visible flag per triangle slot (a
    facing corner, or a facing face)."""
    for v in range(pos.shape[0]):
        if parallel:
            d = -(nrm[v, 0] * dirn[0] + nrm[v, 1] * dirn[1] + nrm[v, 2] * dirn[2])
        else:
            d = (nrm[v, 0] * (eye[0] - pos[v, 0]) + nrm[v, 1] * (eye[1] - pos[v, 1])
                 + nrm[v, 2] * (eye[2] - pos[v, 2]))
        vflag[v] = 1 if d > 0.0 else 0
    n = 0
    for t in range(key.shape[0]):
        if key[t] < 0:
            tvis[t] = 0
            continue
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        vis = (vflag[a] | vflag[b] | vflag[c]) != 0
        if not vis:
            # face normal (b - a) x (c - a) as the surface winds it (out of
            # the bone), whatever way the triangle is drawn
            ux, uy, uz = pos[b, 0] - pos[a, 0], pos[b, 1] - pos[a, 1], pos[b, 2] - pos[a, 2]
            wx, wy, wz = pos[c, 0] - pos[a, 0], pos[c, 1] - pos[a, 1], pos[c, 2] - pos[a, 2]
            fx, fy, fz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
            if parallel:
                d = -(fx * dirn[0] + fy * dirn[1] + fz * dirn[2])
            else:
                d = (fx * (eye[0] - pos[a, 0]) + fy * (eye[1] - pos[a, 1])
                     + fz * (eye[2] - pos[a, 2]))
            vis = d > 0.0
        if vis:
            tvis[t] = 1
            n += 1
        else:
            tvis[t] = 0
    return n


def oriented_triangles(pos, nrm, tris) -> np.ndarray:
    """Triangles wound as the scene draws them (module docstring, "Winding
    as drawn").

    Parameters
    ----------
    pos, nrm : (n, 3) float array_like
        Vertex positions [mm] and normals.
    tris : (m, 3) int array_like
        Vertex indices.

    Returns
    -------
    (m, 3) int32
        ``tris`` with the last two corners swapped where the face normal
        points against the sum of the corners' normals.
    """
    p = np.asarray(pos, dtype=np.float32)
    n = np.asarray(nrm, dtype=np.float32)
    t = np.array(tris, dtype=np.int32).reshape(-1, 3)
    if t.size == 0:
        return t
    a, b, c = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    face = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", face, n[t].sum(axis=1)) < 0
    t[flip, 1], t[flip, 2] = t[flip, 2], t[flip, 1].copy()
    return t


class VisibleJob:
    """One background computation of the visible subset.

    Attributes
    ----------
    tag : object
        What the caller computed it for (the camera state); compared on adopt.
    done : threading.Event
        Set when the flags are ready.
    n_visible : int
        Visible triangles in the snapshot.
    seconds : float
        Wall time of the computation [s].
    """

    def __init__(self, surface, eye, direction, parallel, tag):
        # the snapshot is taken here, on the caller's (main) thread
        self.s_pos = surface.pos.copy()
        self.s_nrm = surface.nrm.copy()
        self.s_tri = np.ascontiguousarray(surface.tri)
        self.s_key = np.ascontiguousarray(surface.tri_key)
        self.eye = np.asarray(eye, dtype=np.float64).copy()
        self.dirn = np.asarray(direction, dtype=np.float64).copy()
        self.parallel = bool(parallel)
        self.tag = tag
        self.surface_ref = weakref.ref(surface)
        self.tvis = np.zeros(self.s_key.shape[0], dtype=np.uint8)
        self.done = threading.Event()
        self.n_visible = 0
        self.seconds = 0.0
        self.error = None
        self._thread = threading.Thread(target=self._run, name="bonesim-visible",
                                        daemon=True)

    def start(self) -> "VisibleJob":
        self._thread.start()
        return self

    def _run(self):
        import time

        t0 = time.perf_counter()
        try:
            vflag = np.zeros(self.s_pos.shape[0], dtype=np.uint8)
            self.n_visible = int(_visible_flags(self.s_pos, self.s_nrm, self.s_tri,
                                                self.s_key, self.eye, self.dirn,
                                                self.parallel, vflag, self.tvis))
        except Exception as exc:   # pragma: no cover - reported by adopt()
            self.error = exc
        self.seconds = time.perf_counter() - t0
        self.done.set()

    def wait(self, timeout=None) -> bool:
        return self.done.wait(timeout)


class SurfaceBuffers:
    """Connectivity buffers of one surface (full and visible), reused across
    frames and grown by doubling.

    Attributes
    ----------
    full : (3 * cap,) int32
        Vertex slots of the live triangles, ``n_full`` of them.
    vis : (3 * cap,) int32
        The visible subset, ``n_vis`` triangles, meaningful when
        :attr:`vis_valid`.
    offsets : (cap + 1,) int32
        ``0, 3, 6, ...``: cell offsets for any prefix of either buffer.
    coarse_min_cos : float or None
        Given to the level of detail (:class:`~bonesim.render.lod.SurfaceLOD`):
        None, no second level.

    Parameters
    ----------
    coarse_min_cos : float, optional
        :attr:`coarse_min_cos`.
    """

    def __init__(self, coarse_min_cos=None):
        self.coarse_min_cos = coarse_min_cos     # the level of detail's second level
        self.full = np.zeros(0, dtype=np.int32)
        self.vis = np.zeros(0, dtype=np.int32)
        self.offsets = np.zeros(1, dtype=np.int32)
        self.n_full = 0
        self.n_vis = 0
        self._vdirty = np.zeros(0, dtype=np.uint8)
        self._marked = np.zeros(0, dtype=np.uint8)
        self.lod = None              # SurfaceLOD when the level of detail is on
        self._lod_kept = None        # the same, kept while off (its drilled blocks)
        self._marks_ok = False       # every change since the last snapshot is marked
        self._marks_job = None       # the snapshot the marks refer to
        self._job: VisibleJob | None = None      # the adopted snapshot
        self._empty_f = np.zeros((0, 3), dtype=np.float32)
        self._empty_i = np.zeros((0, 3), dtype=np.int32)
        self._empty_k = np.zeros(0, dtype=np.int16)
        self._empty_u = np.zeros(0, dtype=np.uint8)

    @property
    def vis_valid(self) -> bool:
        """A visible subset is installed."""
        return self._job is not None

    @property
    def vis_tag(self):
        return None if self._job is None else self._job.tag

    def _fit(self, n_tri_slots: int, n_vert_slots: int) -> None:
        if self.full.shape[0] < 3 * n_tri_slots:
            cap = max(n_tri_slots, 2 * self.full.shape[0] // 3, 1024)
            self.full = np.zeros(3 * cap, dtype=np.int32)
            self.vis = np.zeros(3 * cap, dtype=np.int32)
            self.offsets = np.arange(0, 3 * (cap + 1), 3, dtype=np.int32)
        if self._vdirty.shape[0] < n_vert_slots:
            n = max(n_vert_slots, 2 * self._vdirty.shape[0])
            self._vdirty = np.zeros(n, dtype=np.uint8)
            marked = np.zeros(n, dtype=np.uint8)
            marked[:self._marked.shape[0]] = self._marked
            self._marked = marked

    def sync(self, surface, removed=None, touched=None) -> tuple[int, int]:
        """Recompute both index lists from ``surface``'s current arrays.

        Parameters
        ----------
        surface : Surface
        removed, touched : (n, 3) int array_like, optional
            The voxels given to ``Surface.update`` since the last call (all
            of them). With them the visible subset is kept by change marks;
            without them (None) by comparison with the snapshot. Pass empty
            arrays when nothing changed.

        Returns
        -------
        (n_full, n_vis) : triangle counts (``n_vis`` is 0 without a subset).
        """
        self._fit(surface.tri_key.shape[0], surface.pos.shape[0])
        changed = None if removed is None and touched is None else np.concatenate(
            [np.asarray(x, dtype=np.int32).reshape(-1, 3) for x in (removed, touched)
             if x is not None])
        if self.lod is not None:
            self.lod.sync(surface, changed)
        elif changed is not None and len(changed):
            # off: the drilled blocks are still followed, for when it is on again
            self._lod_obj().mark_drilled(surface, changed)
        if removed is None and touched is None:
            self._marks_ok = False
        elif self._marks_ok:
            keys, vals = _surface_table(surface)
            for ijk in (removed, touched):
                if ijk is not None and len(ijk):
                    _mark_near(keys, vals, surface.vmap,
                               np.ascontiguousarray(ijk, dtype=np.int32).reshape(-1, 3),
                               self._marked)
        return self._compact(surface)

    def _compact(self, surface):
        job = self._job
        if job is not None and job.surface_ref() is not surface:
            self._job = job = None
        lod = self.lod
        if lod is not None:
            marks = job is not None and self._marks_ok and self._marks_job is job
            nf, nv = _compact_near(surface.tri, surface.tri_key, surface.tflip, lod.far,
                                   job is not None, not marks,
                                   job.tvis if job is not None else self._empty_u,
                                   self._marked, self.full, self.vis)
            ff, nff, fv, nfv = lod.far_lists(
                surface, job, job.eye if job is not None else np.zeros(3),
                job.dirn if job is not None else np.zeros(3),
                bool(job.parallel) if job is not None else False)
            self.full[3 * nf:3 * (nf + nff)] = ff[:3 * nff]
            nf += nff
            if job is not None:
                self.vis[3 * nv:3 * (nv + nfv)] = fv[:3 * nfv]
                nv += nfv
        elif job is None:
            nf, nv = _compact(surface.tri, surface.tri_key, surface.tflip, surface.pos,
                              surface.nrm, self._empty_i, self._empty_k, self._empty_f,
                              self._empty_f,
                              self._empty_u, self._vdirty, False, self.full, self.vis)
        elif self._marks_ok and self._marks_job is job:
            nf, nv = _compact_marked(surface.tri, surface.tri_key, surface.tflip, job.tvis,
                                     self._marked, self.full, self.vis)
        else:
            nf, nv = _compact(surface.tri, surface.tri_key, surface.tflip, surface.pos,
                              surface.nrm, job.s_tri, job.s_key, job.s_pos, job.s_nrm, job.tvis,
                              self._vdirty, True, self.full, self.vis)
        self.n_full, self.n_vis = int(nf), int(nv)
        return self.n_full, self.n_vis

    def set_lod(self, surface, on: bool, near_box=None, mid_box=None) -> bool:
        """Draw ``surface`` with the level of detail of :mod:`bonesim.render.lod`
        (``on``), the near box ``near_box`` (block range, see
        :meth:`~bonesim.render.lod.SurfaceLOD.near_blocks`; None: everything
        far but the drilled blocks) at full detail, the far vertices outside
        ``mid_box`` (None: none) at the second level when the buffers were
        made with ``coarse_min_cos``; recomputes the lists
        when anything changed. The drilled blocks are followed by
        :meth:`sync` (from the removed and touched voxels) whether the
        level of detail is on or off, until another surface is given.

        Returns
        -------
        bool
            Whether the lists changed (push them again).
        """
        if not on:
            if self.lod is None:
                return False
            self.lod.release()           # kept for its drilled blocks only
            self.lod = None
        else:
            box, mid = (None if b is None else (np.asarray(b[0], dtype=np.int64),
                                                np.asarray(b[1], dtype=np.int64))
                        for b in (near_box, mid_box))
            if self.lod is None or self.lod._surface is not surface:
                if self.lod is None:
                    self.lod = self._lod_obj()
                self.lod.rebuild(surface, box, mid)
            else:
                if _same_box(self.lod.near_box, box) and _same_box(self.lod.mid_box, mid):
                    return False
                self.lod.set_box(box, mid)
        self._fit(surface.tri_key.shape[0], surface.pos.shape[0])
        self._compact(surface)
        return True

    def _lod_obj(self):
        """The :class:`~bonesim.render.lod.SurfaceLOD`, kept while the level
        of detail is off so that the blocks drilled meanwhile stay known."""
        if self._lod_kept is None:
            from bonesim.render.lod import SurfaceLOD

            self._lod_kept = SurfaceLOD(self.coarse_min_cos)
        return self._lod_kept

    @property
    def marks_in_use(self) -> bool:
        """The installed subset is maintained by change marks (fast path)."""
        return self._job is not None and self._marks_ok and self._marks_job is self._job

    def start_visible(self, surface, eye, direction, parallel=False, tag=None) -> VisibleJob:
        """Snapshot ``surface`` and compute its visible subset in a thread.

        Parameters
        ----------
        surface : Surface
        eye : (3,) float
            Camera position [mm].
        direction : (3,) float
            Unit view direction (used for parallel projection).
        parallel : bool
            Parallel projection.
        tag : object
            Returned with the job; :meth:`adopt` callers compare it with the
            current camera state.
        """
        job = VisibleJob(surface, eye, direction, parallel, tag)
        # changes from here on are marked against this snapshot
        self._fit(surface.tri_key.shape[0], surface.pos.shape[0])
        self._marked[:] = 0
        self._marks_ok = True
        self._marks_job = job
        return job.start()

    def adopt(self, job: VisibleJob, surface) -> bool:
        """Install a finished job's subset and recompute the lists.

        Returns False (and installs nothing) if the job failed or was made
        for another surface."""
        if (not job.done.is_set() or job.error is not None
                or job.surface_ref() is not surface):
            return False
        self._job = job
        self._compact(surface)
        return True

    def invalidate(self) -> None:
        """Drop the visible subset (the camera moved)."""
        self._job = None
        self.n_vis = 0


def _same_box(a, b) -> bool:
    """Two block ranges (or None) are the same."""
    if a is None or b is None:
        return a is None and b is None
    return bool(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]))


def _surface_table(surface):
    """The brick hash table ``(keys, vals)`` of the grid a surface was built
    from (the surface keeps it to address its voxel -> vertex map)."""
    return surface._keys, surface._vals


def warmup() -> None:
    """Compile (or load from the cache) this module's kernels: both
    compactions, the change marks and the visible flags, and those of the
    level of detail (:mod:`bonesim.render.lod`), on a tiny surface."""
    from bonesim.engine.grid import Grid
    from bonesim.engine.surface import Surface

    lab = np.zeros((6, 6, 6), dtype=np.uint8)
    lab[1:5, 1:5, 1:5] = 1
    grid = Grid.from_dense(lab)
    surface = Surface.build(grid, np.array([[0, 0, 0], [200, 200, 180]], dtype=np.uint8))
    buf = SurfaceBuffers()
    buf.sync(surface)                                   # no subset yet
    eye = np.array([2.0, 2.0, 20.0])
    job = buf.start_visible(surface, eye, np.array([0.0, 0.0, -1.0]))
    job.wait()
    if not buf.adopt(job, surface):
        raise RuntimeError(f"meshbuf warm-up: the visible subset failed ({job.error!r})")
    none = np.zeros((0, 3), dtype=np.int32)
    buf.sync(surface, np.array([[2, 2, 4]], dtype=np.int32), none)   # by change marks
    buf.sync(surface)                                   # by comparison
    # the level of detail (bonesim.render.lod): representatives, far flags,
    # far lists with and without a subset, near compaction, change follow-up
    box = (np.zeros(3, np.int64), np.zeros(3, np.int64))
    buf.set_lod(surface, True, box)
    job = buf.start_visible(surface, eye, np.array([0.0, 0.0, -1.0]))
    job.wait()
    buf.adopt(job, surface)
    grid.density[grid.brick_index(2, 2, 3), voxel_offset(2, 2, 3)] = 0.0
    surface.update(grid, np.array([[2, 2, 3]], dtype=np.int32))
    buf.sync(surface, np.array([[2, 2, 3]], dtype=np.int32), none)
    buf.set_lod(surface, True, None)
    buf.set_lod(surface, False)
    # the drilled blocks: followed while off, then a block turned fine
    # outside the near box (another surface: none drilled yet)
    surface = Surface.build(grid, np.array([[0, 0, 0], [200, 200, 180]], dtype=np.uint8))
    buf.set_lod(surface, True, None)
    for off, ijk in ((False, (3, 3, 4)), (True, (3, 2, 4))):
        if off:
            buf.set_lod(surface, False)
        grid.density[grid.brick_index(*ijk), voxel_offset(*ijk)] = 0.0
        surface.update(grid, np.array([ijk], dtype=np.int32))
        buf.sync(surface, np.array([ijk], dtype=np.int32), none)
