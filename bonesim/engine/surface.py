"""Hybrid voxel / triangle bone surface: the vertices *are* surface voxels.

This module keeps a triangle mesh of the bone with one vertex per surface
voxel of a :class:`bonesim.engine.grid.Grid`, and updates it in time
proportional to the number of voxels the drill removed. The mesh's topology
comes from the voxels (below); each vertex is drawn near its voxel's
centre, moved along its normal onto a smoothed density's level set
(:mod:`bonesim.engine.normals`), so the drawn surface is smooth while the
physics keeps its voxels.

Definitions
-----------
Voxels are addressed by integer ``(i, j, k)`` along the case frame's
``(x, y, z)`` axes; voxel ``(i, j, k)`` has its centre at
``origin_mm + spacing_mm * (i, j, k)`` [mm].

Occupied voxel
    density > 0. Voxels in bricks the grid did not allocate are empty.
Surface voxel
    an occupied voxel with at least one empty voxel among its 26 neighbours.
    Each surface voxel carries exactly one vertex.
Vertex position, normal, colour
    defined in :mod:`bonesim.engine.shading`: the normal from a Gaussian-derivative
    density gradient over the 7x7x7 voxels around the vertex, the position
    the voxel's centre moved along it onto the level set of the smoothed
    density (within a fraction of a voxel), the colour the structure's
    display colour, blended toward that of a non-bone structure where the
    bone over it is thin (the bone labels are given to :meth:`Surface.build`).
Cell
    the 2x2x2 block of voxels ``m + {0, 1}^3`` named by its minimum corner
    ``m``. Corner ``c`` (0..7) of a cell is the voxel ``m + (c >> 2 & 1,
    c >> 1 & 1, c & 1)``, so corner order is lexicographic ``(i, j, k)``
    order. The cell's *code* is the 8-bit mask of its occupied corners.
Triangle
    three corners of one cell (any three corners of a cell are pairwise
    26-adjacent); a cell has 56 such triples.
Qualifying triple
    triple ``T`` of cell ``C`` *qualifies in C* when its three corners are
    occupied, every occupied corner of ``C`` off ``T``'s plane lies on one
    side of that plane (the "-" side), and at least one *empty* corner of
    ``C`` lies strictly on the other side (the "+" side): ``T`` is a face of
    the convex hull of ``C``'s occupied corners that looks at empty space
    inside ``C``. Its normal points to "+", out of the bone. If no occupied
    corner lies off the plane and empty corners lie on both sides (a sheet
    one voxel thick), "+" is the side whose normal has its first non-zero
    component (in ``x, y, z`` order) *negative*; this matches the rule for
    sheets lying in a cell face below.
Coplanar quads
    when the plane of ``T`` holds four corners of the cell (the six faces and
    the six diagonal rectangles) and all four are occupied, only the two
    triangles that contain the quad's diagonal through its lowest corner
    (lexicographic ``(i, j, k)``) may qualify. The lowest corner is a global
    property of the four voxels, so the two cells sharing a face agree.
Each triangle once
    a triple lying in a face shared by cells ``L`` (below, along the face's
    axis) and ``U = L + e_axis`` is emitted once if it qualifies in either;
    it is *owned* by ``L`` and oriented as in ``L`` if it qualifies there,
    otherwise owned by and oriented as in ``U``. (Qualifying in ``L`` means
    ``L``'s far half is empty, so a face sheet gets the normal ``-e_axis``.)
    All other triples belong to their only cell. The identity of a triangle
    is ``(owner cell, triple id, orientation)``. Every corner of a qualifying
    triple is 26-adjacent to an empty corner of the owner, hence is a surface
    voxel with a vertex; the kernels check this and report a violation.
Winding
    vertices are stored counter-clockwise seen from the "+" side, so the
    right-hand normal ``(b - a) x (c - a)`` points out of the bone.

Implementation
--------------
Everything the kernels need about the 56 triples is precomputed at import,
from the geometric definition above, into a 256-entry table: for each code,
the (at most four) qualifying triples with their orientation. Ownership of
face triples adds one test per axis: a triple in ``C``'s minimum face along
``a`` is dropped from ``C`` when the four voxels just below that face are
empty (then it qualifies in, and belongs to, the lower cell). So the
triangles a cell owns depend only on its own code and on those 3 x 4 voxels.

Full tessellation (:meth:`Surface.build`) works per brick, in parallel: the
occupancy of every brick is packed into bits once, then each brick and its
one-voxel halo are gathered into 10x10 rows of 10 bits (surface voxels, cell
codes and the ownership tests are shifts and ANDs of rows,
:mod:`bonesim.engine.surface_build`); bricks whose
box is all bone or whose brick-plus-upper-halo is all empty are skipped. A
first pass counts vertices and owned triangles per brick (keeping each
brick's surface voxels as 64 bytes of bits), prefix sums give every brick
its output ranges, a second pass gives the vertices their slots, voxels,
positions, normals and colours and writes the voxel -> vertex map
(:meth:`bonesim.engine.shading.Shader.shade_all`, one pass over the
bricks, along runs of bricks in x), a third writes triangles (their
corners' slots read from a per-brick copy of the map) and fills the spare
records, and one serial pass links the vertex -> triangle lists. Each
parallel pass hands its work items (a few bricks, or a run) to the threads
one at a time (:mod:`bonesim.engine.work_items`), and each item writes only
its own outputs, so the result is the same bits whatever the number of
threads and whoever ran what.

Incremental update (:meth:`Surface.update`): a removed voxel that is empty
now is a *source*. Only cells containing a source change code, and besides
them only the cells whose minimum face has a source just below it (their
ownership test reads it): 20 cells per source can change what they own.
Only the 26 neighbours of a source can join or leave the surface (and every
occupied neighbour of an empty voxel is a surface voxel). For each affected
cell the kernel compares the triangles it owns now (found through the owner
lists below) with those it should own, drops the difference, drops the
vertices of emptied voxels, creates the vertices of voxels that became
surface and adds the new triangles; then
:meth:`bonesim.engine.shading.Shader.refresh` recomputes the position, normal and colour of
every vertex the removed and touched voxels can have changed. The old triangles come from the mesh
itself, not from a guess of the old occupancy, so extra entries (voxels
listed twice, still bone, already empty before the batch, or never bone)
are harmless; what must hold is that every voxel whose density changed
since the last update is listed.

The update runs on dense copies of a window around the removed voxels
(:mod:`bonesim.engine.surface_window`): sets of voxels and cells are bit rows (one
uint64 per row of the window along k), obtained from the inputs by a few
shifts and ORs, and visited in (i, j, k) order; the densities, occupancy
and vertex slots of the window are gathered once. Removed voxels spread far
apart, or over more than 64 voxels along k, are tiled into several windows
(:mod:`bonesim.engine.surface_tiles`, which says why the result is the same). The
cost is proportional to the number of input voxels.

Vertex -> triangles map: every live triangle ``t`` is threaded on three
singly linked lists, one per corner. ``vhead[v]`` is the first triangle of
vertex ``v``'s list, and if ``tri[t, s] == v`` the next one is
``tnext[t, s]`` (``-1`` ends the list). A vertex lies in 8 cells that own at
most 4 triangles each, so a list has at most 32 entries. Adding a triangle
is O(1), removing it walks the lists of its corners (the update removes all
dead triangles of a list in one walk). A second, private list per vertex
(the *owner list*) holds only the triangles whose first vertex ``tri[t, 0]``
it is; since the first vertex is the owner cell's corner ``c0`` of the
triple, the triangles a cell owns are on the owner lists of its corners
0..5. The lists are built in one pass after a full tessellation.

Storage: everything the update reads about a triangle slot (corners, key,
list links) is one 32-byte row of a ``(tcap, 8)`` int32 array, and the two
list heads of a vertex share an 8-byte row, so a step along a list touches
one cache line; ``tri``, ``tri_key``, ``tnext`` and ``vhead`` are views of
these rows.

Voxel -> vertex map: ``vmap`` is an int32 array shaped like the grid's bricks
``(n_bricks, 512)``, ``-1`` where a voxel has no vertex.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bonesim.engine.grid import (BRICK, BRICK_SHIFT, BRICK_VOXELS, Grid,
                                 find_brick, voxel_offset)
from bonesim.engine.shading import GRAD_EPS, Shader, ShadingParams, bone_labels
from bonesim.engine.surface_build import CHUNK, build_count, build_prepare, build_triangles
from bonesim.engine.surface_tables import (CORNER_OFFSETS, MAX_PER_CELL, RESHADE_REACH, TRIPLE_CORNERS,
                                           N_STATS, qualifying_triples,
                                           S_CELLS, S_ERR, S_NEED_T, S_NEED_V, S_STATUS,
                                           S_T_ADD, S_T_DEL, S_V_ADD, S_V_DEL, TR_FILL, TR_KEY,
                                           TR_NEXT, TR_ONEXT, TR_WIDTH, T_ALIVE, T_HW, VR_HEAD,
                                           VR_OHEAD, V_ALIVE, V_HW, link_all,
                                           orient_of, triangles_of_vertex)
from bonesim.engine.surface_tiles import COORD_LIMIT, TILE_SHIFT, WINDOW_MIN_VOXELS, update_tiles
from bonesim.engine.surface_window import N_ROWSETS
from bonesim.engine.work_items import new_counter, workers

__all__ = ["Surface", "CanonicalSurface", "GRAD_EPS", "RESHADE_REACH", "warmup",
           "qualifying_triples", "CORNER_OFFSETS", "TRIPLE_CORNERS"]

# ----------------------------------------------------------------------------
# Python front end
# ----------------------------------------------------------------------------


_NO_VOXELS = np.zeros((0, 3), dtype=np.int32)    # kernels never write their inputs


def _as_ijk(a, name):
    """Validate an (n, 3) array of integer voxel coordinates -> int32 C array.

    int32 (n, 3) arrays take a short path: copied as they are, their range
    is checked by :func:`bonesim.engine.surface_tiles._update` (status 4 / 5)."""
    if a is None:
        return _NO_VOXELS
    if type(a) is np.ndarray and a.dtype == np.int32 and a.ndim == 2 and a.shape[1] == 3:
        return a.copy(order="C")
    arr = np.asarray(a)
    if arr.size == 0:
        return np.zeros((0, 3), dtype=np.int32)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise TypeError(f"{name} must hold integer voxel coordinates, got {arr.dtype}")
    if np.abs(arr).max() >= COORD_LIMIT:
        raise ValueError(f"{name} has voxel coordinates beyond +-{COORD_LIMIT}")
    # always a fresh, writable C array: read-only or strided inputs would
    # make numba compile another specialisation of every kernel
    return np.array(arr, dtype=np.int32, order="C", copy=True)


def _as_colors(colors):
    c = np.asarray(colors)
    if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] < 1:
        raise ValueError(f"colors must have shape (n_labels + 1, 3), got {c.shape}")
    if not np.issubdtype(c.dtype, np.integer) or c.min() < 0 or c.max() > 255:
        raise ValueError("colors must be integers in [0, 255]")
    return np.array(c, dtype=np.uint8, order="C", copy=True)


def _initial_capacity(n):
    return int(max(64, n + n // 4))


def _grown(arr, cap, fill):
    out = np.full((cap,) + arr.shape[1:], fill, dtype=arr.dtype)
    out[:arr.shape[0]] = arr
    return out


@dataclass(eq=False)
class CanonicalSurface:
    """Order-independent form of a :class:`Surface`, for equality tests.

    Attributes
    ----------
    ijk : (n, 3) int32
        Vertex voxels, sorted lexicographically.
    pos, nrm : (n, 3) float32
        Position [mm] and unit normal of each vertex, in ``ijk`` order.
    col : (n, 4) uint8
        RGBA colour of each vertex.
    tris : (m, 9) int32
        Oriented triangles as the voxel coordinates of their three corners in
        winding order, rotated so the lexicographically smallest corner comes
        first; rows sorted lexicographically.
    """

    ijk: np.ndarray
    pos: np.ndarray
    nrm: np.ndarray
    col: np.ndarray
    tris: np.ndarray

    def differences(self, other, atol=0.0, pos_atol=0.0):
        """Human-readable list of what differs from ``other`` (empty if equal).

        ``atol`` is the tolerance on normals, ``pos_atol`` on positions [mm]
        (colours, voxels and triangles are exact).
        """
        out = []
        if not np.array_equal(self.ijk, other.ijk):
            a = {tuple(r) for r in self.ijk.tolist()}
            b = {tuple(r) for r in other.ijk.tolist()}
            out.append(f"vertices differ: only here {sorted(a - b)[:5]}, "
                       f"only there {sorted(b - a)[:5]}")
            return out
        if pos_atol == 0:
            bad = np.flatnonzero((self.pos != other.pos).any(axis=1))
        else:
            bad = np.flatnonzero((np.abs(self.pos - other.pos) > pos_atol).any(axis=1))
        if bad.size:
            out.append(f"positions differ at {self.ijk[bad[:5]].tolist()}")
        if atol == 0:
            bad = np.flatnonzero((self.nrm != other.nrm).any(axis=1))
        else:
            bad = np.flatnonzero((np.abs(self.nrm - other.nrm) > atol).any(axis=1))
        if bad.size:
            out.append(f"normals differ at {self.ijk[bad[:5]].tolist()}")
        bad = np.flatnonzero((self.col != other.col).any(axis=1))
        if bad.size:
            out.append(f"colours differ at {self.ijk[bad[:5]].tolist()}")
        if not np.array_equal(self.tris, other.tris):
            a = {tuple(r) for r in self.tris.tolist()}
            b = {tuple(r) for r in other.tris.tolist()}
            out.append(f"triangles differ: {len(self.tris)} vs {len(other.tris)}; "
                       f"only here {sorted(a - b)[:3]}, only there {sorted(b - a)[:3]}")
        return out

    def __eq__(self, other):
        if not isinstance(other, CanonicalSurface):
            return NotImplemented
        return not self.differences(other)


class Surface:
    """Triangle surface of a :class:`~bonesim.engine.grid.Grid` with one vertex per
    surface voxel, kept up to date as voxels are removed.

    Build one with :meth:`build`; then call :meth:`update` after each batch
    of removed voxels. See the module docstring for the definitions.

    Vertex and triangle data live in arrays with spare capacity; a slot is
    in use when ``alive[v]`` (vertices) / ``tri_key[t] >= 0`` (triangles);
    free slots hold stale data. Freed slots are reused, and when an update
    needs more room the arrays are replaced by larger copies (amortised
    doubling), so re-read the attributes after :meth:`update` rather than
    keeping references. Use :meth:`arrays` for compact copies. A surface is
    not safe to update from two threads at once, nor to read while updating.

    Attributes
    ----------
    pos : (vcap, 3) float32
        Vertex positions [mm] (case frame): the voxel's centre moved
        ``shift`` voxels along the normal, onto the smoothed density's level
        set (:mod:`bonesim.engine.normals`).
    nrm : (vcap, 3) float32
        Unit vertex normals (pointing out of the bone).
    shift : (vcap,) float32
        Each vertex's offset from its voxel's centre along its normal
        [voxels] (the thin-bone rays measure from there).
    col : (vcap, 4) uint8
        Vertex RGBA colours.
    ijk : (vcap, 3) int32
        Voxel of each vertex.
    alive : (vcap,) uint8
        1 for slots holding a vertex.
    tri : (tcap, 3) int32
        Vertex slots of each triangle, counter-clockwise seen from outside
        (a view of the packed triangle records, like ``tri_key``, ``tnext``
        and ``vhead``: not C-contiguous).
    tri_key : (tcap,) int32
        ``2 * triple_id + flip`` for live triangles (``-1`` for free slots);
        with the owner cell (``ijk[tri[t, 0]] - CORNER_OFFSETS[TRIPLE_CORNERS[
        key >> 1, 0]]``) it is the triangle's identity.
    vmap : (n_bricks, 512) int32
        Vertex slot of each grid voxel (same layout as ``grid.density``), -1
        for none.
    tflip : (tcap,) uint8
        1 where a triangle is drawn ``(tri[t, 0], tri[t, 2], tri[t, 1])``:
        its face normal ``(b - a) x (c - a)`` points against the sum of its
        corners' normals (where the surface folds within a voxel or two).
        Drawn so, OpenGL's front face always agrees with the normals
        (:mod:`bonesim.render.meshbuf`). Kept for every live triangle: set
        at :meth:`build` (as each triangle is made), and by :meth:`update` for every triangle of a
        vertex it moved or turned.
    vhead : (vcap,) int32, tnext : (tcap, 3) int32
        Vertex -> triangle lists (see module docstring); use
        :meth:`triangles_of`.
    colors : (n_labels + 1, 3) uint8
        The structure colour table given to :meth:`build`.
    shader : bonesim.engine.shading.Shader
        Computes the positions, normals and colours (its ``bone`` mask, ``tint_on`` and
        ``params`` say how).
    """

    def __init__(self, keys, vals, colors, nbr, vmap, pos, nrm, shift, col, ijk, alive, vrec,
                 vfree, trec, tfree, tflip, cnt, origin_mm, spacing_mm, shader):
        self._keys = keys
        self._vals = vals
        self.colors = colors
        self._nbr = nbr
        self.vmap = vmap
        self.pos = pos
        self.nrm = nrm
        self.shift = shift
        self.col = col
        self.ijk = ijk
        self.alive = alive
        self._vrec = vrec
        self._vfree = vfree
        self._trec = trec
        self._tfree = tfree
        self.tflip = tflip
        self._cnt = cnt
        self._origin = np.asarray(origin_mm, dtype=np.float64)
        self._spacing = float(spacing_mm)
        self._record_views()
        # the update's window size limit and tile size (tests set -1 / small
        # tiles to exercise the tiling on small grids)
        self._win_limit = WINDOW_MIN_VOXELS
        self._tile_shift = TILE_SHIFT
        self._stats = np.zeros(N_STATS, dtype=np.int64)
        self._grow_scratch(4096, 256)
        self.shader = shader

    # ------------------------------------------------------------------ build
    @classmethod
    def build(cls, grid: Grid, colors, *, bone=None,
              shading: ShadingParams | None = None) -> "Surface":
        """Tessellate and shade ``grid`` from scratch.

        Parameters
        ----------
        grid : Grid
            The bone; its ``density``/``label`` arrays are read, not kept.
        colors : (n_labels + 1, 3) uint8 array_like
            Display RGB of each structure index (row 0 for label 0); must
            cover every label present in the grid.
        bone : (n_labels + 1,) bool or 0/1 array_like, optional
            Which labels are bone (:func:`bonesim.engine.shading.bone_labels` of the
            model's structures); thin bone over the other structures takes
            on their colour. None (default): no tint.
        shading : ShadingParams, optional
            Normal smoothing and tint thresholds; default: the shipped
            ``bonesim/data/shading.toml``.

        Returns
        -------
        Surface
        """
        if not isinstance(grid, Grid):
            raise TypeError(f"grid must be a bonesim.engine.grid.Grid, got {type(grid).__name__}")
        colors = _as_colors(colors)
        if grid.label.size and int(grid.label.max()) >= colors.shape[0]:
            raise ValueError(f"colors has {colors.shape[0]} rows but the grid uses "
                             f"label {int(grid.label.max())}")
        return cls._build(grid, colors, bone, shading)

    @classmethod
    def _build(cls, grid, colors, bone, shading) -> "Surface":
        # the parallel kernels' work items are handed out one at a time, not
        # split in equal parts up front: a thread that the OS (a loaded
        # machine) holds back does not hold the build back; each item writes
        # its own outputs, so the result does not depend on who ran what
        n_b = grid.n_bricks
        nw = workers()
        nbr = np.empty((n_b, 27), dtype=np.int32)
        om = np.empty((n_b, BRICK), dtype=np.int64)
        build_prepare(grid.keys, grid.vals, grid.bricks, grid.density_ro, nbr, om, new_counter(),
                      nw)
        shader = Shader(grid, nbr, colors, bone, shading)
        nv = np.empty(n_b, dtype=np.int64)
        nt = np.empty(n_b, dtype=np.int64)
        srf = np.empty((n_b, BRICK * BRICK), dtype=np.uint8)
        build_count(om, nbr, nv, nt, srf, new_counter(), nw)
        voff = np.zeros(n_b + 1, dtype=np.int64)
        np.cumsum(nv, out=voff[1:])
        toff = np.zeros(n_b + 1, dtype=np.int64)
        np.cumsum(nt, out=toff[1:])
        n_v = int(voff[-1])
        n_t = int(toff[-1])
        vcap = _initial_capacity(n_v)
        tcap = _initial_capacity(n_t)
        vmap = np.empty((n_b, BRICK_VOXELS), dtype=np.int32)
        pos = np.zeros((vcap, 3), dtype=np.float32)
        nrm = np.zeros((vcap, 3), dtype=np.float32)
        col = np.zeros((vcap, 4), dtype=np.uint8)
        ijk = np.zeros((vcap, 3), dtype=np.int32)
        shift = np.zeros(vcap, dtype=np.float32)
        # slots, voxels and shading of the vertices in one pass, before the
        # triangles are made, so that each triangle's drawn winding is found
        # as it is written (its corners' data in cache)
        shader.shade_all(grid, srf, voff, vmap, ijk, pos, nrm, shift, col)
        trec = np.empty((tcap, TR_WIDTH), dtype=np.int32)
        tflip = np.zeros(tcap, dtype=np.uint8)
        err = np.zeros(max(1, (n_b + CHUNK - 1) // CHUNK), dtype=np.int64)
        vrec = np.empty((vcap, 2), dtype=np.int32)
        alive = np.empty(vcap, dtype=np.uint8)
        # the triangles, the spare triangle rows (TR_FILL), vrec (-1) and alive
        build_triangles(om, nbr, toff, vmap, pos, nrm, trec, tflip, err, vrec, alive, n_v,
                        new_counter(), nw)
        if err.sum():
            raise RuntimeError("surface: a qualifying triangle has a corner without vertex")
        link_all(trec, vrec, n_t)
        cnt = np.array([n_v, 0, n_t, 0, n_v, n_t], dtype=np.int64)
        return cls(grid.keys, grid.vals, colors, nbr, vmap, pos, nrm, shift, col, ijk, alive, vrec,
                   np.zeros(vcap, dtype=np.int32), trec, np.zeros(tcap, dtype=np.int32), tflip,
                   cnt, grid.origin_mm, grid.spacing_mm, shader)

    @classmethod
    def of_model(cls, model, grid: Grid | None = None,
                 shading: ShadingParams | None = None) -> "Surface":
        """:meth:`build` with a model's colours and bone labels (structures of
        kind ``"bone"``), so thin bone shows the structures beneath.

        Parameters
        ----------
        model : bonesim.engine.model.Model
        grid : Grid, optional
            The tissue to tessellate (a state's or a replica); default the
            model's initial grid.
        shading : ShadingParams, optional
            As for :meth:`build`.
        """
        return cls.build(model.grid if grid is None else grid, model.colors,
                         bone=bone_labels(model.structures), shading=shading)

    # ----------------------------------------------------------------- update
    def update(self, grid: Grid, removed, touched=None) -> dict:
        """Re-tessellate after voxels were removed from ``grid``.

        Work is proportional to the number of voxels given, not to the
        surface: cells around removed voxels are re-evaluated, vertices
        created for voxels that became surface and dropped for removed ones,
        and the positions, normals and colours the changes can reach are recomputed
        (:meth:`bonesim.engine.shading.Shader.refresh`).

        Parameters
        ----------
        grid : Grid
            The grid this surface was built from (or a copy sharing its hash
            table), in its new state.
        removed : (n, 3) int array_like
            Voxels ``(i, j, k)`` whose density was set to 0 since the last
            update. Duplicates are harmless.
        touched : (m, 3) int array_like, optional
            Voxels whose density was lowered but stayed > 0.

        Returns
        -------
        dict
            ``vertices_added``, ``vertices_removed``, ``triangles_added``,
            ``triangles_removed``, ``vertices_reshaded``, ``cells_visited``.
        """
        if not isinstance(grid, Grid):
            raise TypeError(f"grid must be a bonesim.engine.grid.Grid, got {type(grid).__name__}")
        if grid.density.shape != self.vmap.shape or not (
                grid.keys is self._keys or np.array_equal(grid.keys, self._keys)):
            raise ValueError("update() needs the grid this surface was built from")
        removed = _as_ijk(removed, "removed")
        touched = _as_ijk(touched, "touched")
        stats = self._stats
        resume = False
        while True:
            update_tiles(grid.keys, grid.vals, grid.density, self._origin, self._spacing,
                    removed, touched, self._win_limit, self._tile_shift, resume,
                    self.vmap, self.pos, self.ijk, self.alive, self._vrec, self._vfree,
                    self._trec, self._tfree, self._cnt, stats,
                    self._sf32, self._si32, self._su8, self._su64)
            st = stats.tolist()
            status = st[S_STATUS]
            if status == 0:
                break
            if status == 1:
                self._grow(st[S_NEED_V], st[S_NEED_T])
            elif status == 2:
                self._grow_scratch(st[S_NEED_V], st[S_NEED_T])
            else:
                name = "removed" if status == 4 else "touched"
                raise ValueError(f"{name} has voxel coordinates beyond +-{COORD_LIMIT}")
            resume = True
        if st[S_ERR]:
            raise RuntimeError(f"surface update found {st[S_ERR]} inconsistencies")
        n_shaded = self.shader.refresh(grid, self.vmap, self.pos, self.nrm, self.shift, self.col,
                                       removed, touched, self._orient)
        return {"vertices_added": st[S_V_ADD], "vertices_removed": st[S_V_DEL],
                "triangles_added": st[S_T_ADD], "triangles_removed": st[S_T_DEL],
                "vertices_reshaded": n_shaded, "cells_visited": st[S_CELLS]}

    def _orient(self, vlist):
        """Drawn winding of the triangles of the vertices a refresh moved
        (new triangles' corners are all among them)."""
        orient_of(self._vrec, self._trec, vlist, self.pos, self.nrm, self.tflip)

    def _grow_scratch(self, vol, nrows):
        """Scratch of the update for windows of ``vol`` voxels, ``nrows`` rows."""
        cur = getattr(self, "_sf32", None)
        if cur is None or cur.shape[0] < vol:
            v = vol if cur is None else max(vol, 2 * cur.shape[0])
            self._sf32 = np.zeros(v, dtype=np.float32)
            self._si32 = np.zeros(3 * v, dtype=np.int32)
            self._su8 = np.zeros(2 * v, dtype=np.uint8)
        cur = getattr(self, "_su64", None)
        if cur is None or cur.shape[0] < N_ROWSETS * nrows:
            n = nrows if cur is None else max(nrows, 2 * cur.shape[0] // N_ROWSETS)
            self._su64 = np.zeros(N_ROWSETS * n, dtype=np.uint64)

    def _record_views(self):
        """Public views of the packed vertex / triangle records."""
        self.vhead = self._vrec[:, VR_HEAD]
        self._ohead = self._vrec[:, VR_OHEAD]
        self.tri = self._trec[:, 0:3]
        self.tri_key = self._trec[:, TR_KEY]
        self.tnext = self._trec[:, TR_NEXT:TR_NEXT + 3]
        self._onext = self._trec[:, TR_ONEXT]

    def _grow(self, need_v, need_t):
        if need_v > 0:
            cap = max(2 * self.pos.shape[0], self.pos.shape[0] + need_v)
            self.pos = _grown(self.pos, cap, 0)
            self.nrm = _grown(self.nrm, cap, 0)
            self.shift = _grown(self.shift, cap, 0)
            self.col = _grown(self.col, cap, 0)
            self.ijk = _grown(self.ijk, cap, 0)
            self.alive = _grown(self.alive, cap, 0)
            self._vrec = _grown(self._vrec, cap, -1)
            self._vfree = _grown(self._vfree, cap, 0)
        if need_t > 0:
            cap = max(2 * self.tri.shape[0], self.tri.shape[0] + need_t)
            old = self._trec
            self._trec = np.empty((cap, TR_WIDTH), dtype=np.int32)
            self._trec[:old.shape[0]] = old
            self._trec[old.shape[0]:] = TR_FILL
            self._tfree = _grown(self._tfree, cap, 0)
            self.tflip = _grown(self.tflip, cap, 0)
        self._record_views()

    # ---------------------------------------------------------------- queries
    @property
    def n_vertices(self) -> int:
        """Number of live vertices (= surface voxels)."""
        return int(self._cnt[V_ALIVE])

    @property
    def n_triangles(self) -> int:
        """Number of live triangles."""
        return int(self._cnt[T_ALIVE])

    @property
    def vertex_slots(self) -> np.ndarray:
        """Indices of the live vertex slots, ascending."""
        return np.flatnonzero(self.alive[:self._cnt[V_HW]])

    @property
    def triangle_slots(self) -> np.ndarray:
        """Indices of the live triangle slots, ascending."""
        return np.flatnonzero(self.tri_key[:self._cnt[T_HW]] >= 0)

    def vertex_at(self, i: int, j: int, k: int) -> int:
        """Vertex slot of voxel ``(i, j, k)``, or -1 if it is not a surface voxel."""
        b = int(find_brick(self._keys, self._vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                           k >> BRICK_SHIFT))
        return -1 if b < 0 else int(self.vmap[b, voxel_offset(i, j, k)])

    def triangles_of(self, v: int) -> np.ndarray:
        """Triangle slots containing vertex slot ``v`` (int32 array)."""
        if not (0 <= v < self.alive.shape[0]) or not self.alive[v]:
            raise IndexError(f"no live vertex in slot {v}")
        out = np.empty(4 * MAX_PER_CELL * 2, dtype=np.int32)
        n = triangles_of_vertex(self.vhead, self.tri, self.tnext, v, out)
        if n > out.shape[0]:
            out = np.empty(n, dtype=np.int32)
            triangles_of_vertex(self.vhead, self.tri, self.tnext, v, out)
        return out[:n].copy()

    def triangle_owner(self, t: int):
        """Identity ``((i, j, k) of the owner cell, triple id, flip)`` of live triangle ``t``."""
        key = int(self.tri_key[t])
        if key < 0:
            raise IndexError(f"no live triangle in slot {t}")
        c0 = TRIPLE_CORNERS[key >> 1, 0]
        cell = self.ijk[self.tri[t, 0]] - CORNER_OFFSETS[c0]
        return tuple(int(x) for x in cell), key >> 1, key & 1

    # ----------------------------------------------------------------- export
    def arrays(self):
        """Compact copies of the mesh.

        Returns
        -------
        pos : (n, 3) float32
            Vertex positions [mm].
        nrm : (n, 3) float32
            Unit vertex normals.
        col : (n, 4) uint8
            RGBA vertex colours.
        tris : (m, 3) int32
            Vertex indices (into the arrays above) of each triangle,
            counter-clockwise seen from outside the bone.
        """
        vs = self.vertex_slots
        remap = np.full(self.alive.shape[0], -1, dtype=np.int32)
        remap[vs] = np.arange(vs.size, dtype=np.int32)
        tris = remap[self.tri[self.triangle_slots]]
        return self.pos[vs].copy(), self.nrm[vs].copy(), self.col[vs].copy(), tris

    def canonical(self) -> CanonicalSurface:
        """Order-independent form (see :class:`CanonicalSurface`); two surfaces
        are the same mesh iff their canonical forms compare equal."""
        vs = self.vertex_slots
        ijk = self.ijk[vs]
        order = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
        rank = np.full(self.alive.shape[0], -1, dtype=np.int64)
        rank[vs[order]] = np.arange(vs.size)
        tr = rank[self.tri[self.triangle_slots]]
        if tr.size:
            first = np.argmin(tr, axis=1)
            rows = np.arange(tr.shape[0])[:, None]
            tr = tr[rows, (first[:, None] + np.arange(3)[None, :]) % 3]
            tr = tr[np.lexsort((tr[:, 2], tr[:, 1], tr[:, 0]))]
        ijk_s = ijk[order]
        tris = ijk_s[tr].reshape(-1, 9).astype(np.int32)
        return CanonicalSurface(ijk_s.copy(), self.pos[vs][order], self.nrm[vs][order],
                                self.col[vs][order], tris)


def warmup() -> None:
    """Compile (or load from the cache) every kernel of this module and of
    :mod:`bonesim.engine.shading` on a tiny grid (bone over another structure)."""
    lab = np.zeros((6, 6, 6), dtype=np.uint8)
    lab[1:5, 1:5, 1:5] = 1
    lab[1:5, 1:5, 1] = 2
    grid = Grid.from_dense(lab)
    surf = Surface.build(grid, np.array([[0, 0, 0], [200, 200, 180], [60, 80, 220]],
                                        dtype=np.uint8), bone=[0, 1, 0])
    b = grid.brick_index(2, 2, 1)
    grid.density[b, voxel_offset(2, 2, 1)] = 0.0
    b = grid.brick_index(2, 2, 2)
    grid.density[b, voxel_offset(2, 2, 2)] = 0.5
    surf.update(grid, np.array([[2, 2, 1]], dtype=np.int32), np.array([[2, 2, 2]]))
    surf._win_limit = -1                    # tiles, as for spread-out inputs
    b = grid.brick_index(3, 2, 1)
    grid.density[b, voxel_offset(3, 2, 1)] = 0.0
    surf.update(grid, np.array([[3, 2, 1]], dtype=np.int32))
    surf.triangles_of(int(surf.vertex_slots[0]))
