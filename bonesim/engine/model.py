"""Model / State / step: the simulator's core contract.

* :class:`Model` is immutable: the case's initial grid, the structure table
  and its material factors, the burr and its sampled stencil, the gains, the
  device's limits. It is loaded from files by :func:`bonesim.io.loading.load_model` (or built
  from arrays by :func:`make_model`).
* :class:`State` is everything a run changes: the voxel grid and its bodies,
  the rigid bodies in motion (:class:`~bonesim.engine.rigid_set.RigidSet`),
  the epoch, the current burr and tool, the tool pose, time, the last force,
  the event rings and the kernel's scratch memory.
* :func:`step` advances the state by one haptic sample (the haptic step
  alone); :func:`bonesim.engine.world.world_step` is the whole world step
  (commands, rigid motion, haptic step) that every run calls.

Feeding the same model the same samples gives a bit-identical grid and
identical events: that is what recording and replay rely on.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple, Sequence

import numpy as np
from numba import njit

from bonesim.engine import events
from bonesim.engine.bodies import (BODY_LIMIT, DEFAULT_MAX_BODIES, body_arrays_spec, init_bodies,
                                   plan_passes)
from bonesim.engine.device_caps import SCRIPTED, DeviceCaps
from bonesim.engine.grid import BRICK_SHIFT, BRICK_VOXELS, Grid, find_brick, voxel_offset
from bonesim.engine.haptics import (N_OUT, N_PARAMS, O_FX, O_FZ, O_MAG, O_TX, O_TZ, P_H3,
                                    P_INV_VOXEL_VOL, P_K_HIGH, P_K_LOW, P_K_TAN, P_MAX_FORCE, P_RADIUS,
                                    P_V_T, Stencil, block_size, haptic_kernel, make_stencil)
from bonesim.engine.haptics_budget import (Budget, BudgetState, budget_step, lattice_spacing,
                                           make_budget, make_budget_state, make_step_args,
                                           reset_budget_state)
from bonesim.engine.haptics_rows import ROWS_MIN_OVERSAMPLE, haptic_rows_kernel
from bonesim.engine.rigid import gravity_direction
from bonesim.engine.rigid_set import RIGID_SLOTS, RigidSet
from bonesim.engine.step_io import store_step, unit_pose

__all__ = ["HAPTIC_RATE_HZ", "MAX_DT_S", "DEFAULT_OVERSAMPLE", "Sample", "Model",
           "make_model", "State", "state_arrays_spec", "make_state", "reset_state",
           "step", "clear_touched"]

#: Default haptic rate [Hz].
HAPTIC_RATE_HZ = 1000.0
#: Longest step the removal integrates over [s]; a stalled loop must not
#: remove a burst of bone when it resumes.
MAX_DT_S = 0.005
#: Default burr-sampling refinement relative to the bone grid.
DEFAULT_OVERSAMPLE = 2


class Sample(NamedTuple):
    """One device sample, as fed to :func:`step`.

    Attributes
    ----------
    t_s : float
        Time [s].
    pos_mm : (3,) float64
        Tool (burr centre) position, case frame [mm].
    axis : (3,) float64
        Drill axis (unit vector, from the handle toward the burr tip).
    drill : bool
        Drill running.
    speed_rpm : float
        Spindle speed [rpm].
    direction : int
        +1 forward, -1 reverse.
    burr : int
        Index of the burr in the model's burr table (:attr:`Model.burrs`).
    """

    t_s: float
    pos_mm: np.ndarray
    axis: np.ndarray
    drill: bool
    speed_rpm: float
    direction: int = 1
    burr: int = 0


@dataclass(frozen=True)
class Model:
    """Immutable description of one simulation.

    Attributes
    ----------
    name : str
        Case name.
    structures : tuple
        Structure records (``name``, ``kind``, ``display_color``); grid label
        ``s`` is ``structures[s - 1]``.
    grid : Grid
        Initial tissue (arrays read-only; :func:`make_state` copies them).
    burrs : tuple of Burr
        The burr table: a sample's ``burr`` indexes it; burr 0 is the default
        (:attr:`burr`).
    stencils : tuple of Stencil
        Each burr's samples.
    device : DeviceCaps
        Limits of the device driving the tool.
    oversample : int
        Burr lattice refinement relative to the voxel size.
    stiff, removal : (n_labels + 1,) float64
        Material stiffness and removal factor per grid label (0 = empty).
    injury : (n_labels + 1,) uint8
        1 where touching/removing the label is an injury.
    colors : (n_labels + 1, 3) uint8
        Display colour per label.
    burr_params : tuple of (N_PARAMS,) float64
        Each burr's gains and constants for :func:`bonesim.engine.haptics.haptic_kernel`.
    max_bodies : int
        Most bone bodies a run may hold (see :mod:`bonesim.engine.bodies`).
    haptic_rate_hz : float
        Nominal step rate [Hz].
    case : object
        The loaded case manifest, or None for models built from arrays.
    clearance : bonesim.physics.clearance.Clearance or None
        Distances to every structure that is not bone, measured on the case's
        label map at its source resolution (:func:`load_model` fills it; None
        for models built from arrays, whose grid is their only label map).
    """

    name: str
    structures: tuple
    grid: Grid
    burrs: tuple
    stencils: tuple
    device: DeviceCaps
    oversample: int
    stiff: np.ndarray
    removal: np.ndarray
    injury: np.ndarray
    colors: np.ndarray
    burr_params: tuple
    max_bodies: int = DEFAULT_MAX_BODIES
    haptic_rate_hz: float = HAPTIC_RATE_HZ
    case: object = None
    clearance: object = None
    budget: Budget = None

    @property
    def spacing_mm(self) -> float:
        return self.grid.spacing_mm

    @property
    def burr(self):
        """The default burr (burr 0 of the table)."""
        return self.burrs[0]

    @property
    def stencil(self) -> Stencil:
        """The default burr's samples."""
        return self.stencils[0]

    @property
    def params(self) -> np.ndarray:
        """The default burr's kernel parameters."""
        return self.burr_params[0]

    @property
    def max_force_n(self) -> float:
        """Force limit applied by the step: the smaller of burr and device [N]."""
        return float(self.params[P_MAX_FORCE])

    def structure_name(self, label: int) -> str:
        return "none" if label == 0 else self.structures[label - 1].name

    def __setstate__(self, state: dict) -> None:
        # numpy's pickle drops the read-only flag. A model sent to another
        # process (the haptic loop, the recorder) stays immutable there, and
        # its arrays keep the types the warmed-up kernels were compiled for: a
        # writable copy made the loop compile a second haptic kernel at its
        # first step (1.8 s with a cold cache).
        self.__dict__.update(state)
        for a in (self.grid.density, self.grid.label, self.stiff, self.removal,
                  self.injury, self.colors, *self.burr_params, self.budget.occ0,
                  self.budget.thr0, *self.budget.lat):
            a.flags.writeable = False
        for st in self.stencils:
            for a in (st.offsets, st.inv_r, st.lat, st.packed, st.row_head, st.row_off,
                      st.row_sums):
                a.flags.writeable = False

    def with_burrs(self, burrs) -> "Model":
        """The same model with ``burrs`` added to its burr table (indices
        ``len(self.burrs)`` on)."""
        extra = [_burr_arrays(b, self.grid.spacing_mm, self.oversample, self.device,
                              self.budget.settings) for b in burrs]
        return replace(self, burrs=self.burrs + tuple(burrs),
                       stencils=self.stencils + tuple(e[0] for e in extra),
                       burr_params=self.burr_params + tuple(e[1] for e in extra),
                       budget=_with_burrs(self.budget, burrs, self))

    def with_burr(self, burr) -> "Model":
        """The same model whose default burr (burr 0) is ``burr``; the rest of
        the table is dropped."""
        stencil, params = _burr_arrays(burr, self.grid.spacing_mm, self.oversample,
                                       self.device, self.budget.settings)
        bud = replace(self.budget, lat=(), removal_voxels=())
        return replace(self, burrs=(burr,), stencils=(stencil,), burr_params=(params,),
                       budget=_with_burrs(bud, (burr,), self))


def _with_burrs(budget: Budget, burrs, model) -> Budget:
    return budget.with_burrs(burrs, model.grid.spacing_mm,
                             [model.device.max_force_n] * len(burrs),
                             float(np.max(model.removal)))


def _burr_arrays(burr, spacing_mm: float, oversample: int, device: DeviceCaps,
                 settings=None):
    if oversample < 1:
        raise ValueError(f"oversample must be >= 1, got {oversample}")
    if settings is None:
        from bonesim.engine.haptics_budget import load_budget_settings
        settings = load_budget_settings()
    # voxel / oversample, or the budget's finest spacing where that is finer
    h = lattice_spacing(spacing_mm, oversample, settings)
    stencil = make_stencil(burr.radius_mm, h, burr.r_max, burr.falloff)
    p = np.zeros(N_PARAMS)
    p[P_K_LOW] = burr.k_low
    p[P_K_HIGH] = burr.k_high
    p[P_V_T] = burr.n_t_fraction * stencil.volume_mm3
    p[P_K_TAN] = burr.k_tan
    p[P_MAX_FORCE] = min(burr.max_force_n, device.max_force_n)
    p[P_H3] = stencil.sample_volume_mm3
    p[P_INV_VOXEL_VOL] = 1.0 / spacing_mm ** 3
    p[P_RADIUS] = burr.radius_mm
    p.flags.writeable = False
    return stencil, p


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


def make_model(labels: np.ndarray, spacing_mm: float, structures: Sequence, burr,
               *, origin_mm=(0.0, 0.0, 0.0), density: np.ndarray | None = None,
               materials: dict | None = None, device: DeviceCaps = SCRIPTED,
               oversample: int = DEFAULT_OVERSAMPLE, name: str = "arrays",
               case=None, max_bodies: int = DEFAULT_MAX_BODIES,
               budget_settings=None) -> Model:
    """Build a :class:`Model` from a label volume.

    Parameters
    ----------
    labels : (nx, ny, nz) uint8
        Structure index per voxel (``s >= 1`` is ``structures[s - 1]``), axis
        order (x, y, z).
    spacing_mm : float
        Isotropic voxel edge [mm].
    structures : sequence
        Records with ``name``, ``kind`` ("bone" | "critical" | "soft") and
        ``display_color`` ((3,) ints 0-255).
    burr : Burr
        See :mod:`bonesim.io.burrs`.
    origin_mm : (3,) float
        Case-frame centre of voxel (0, 0, 0) [mm].
    density : (nx, ny, nz) float, optional
        Initial density (default 1 where labelled).
    materials : dict, optional
        Kind -> material (``stiffness``, ``removal``, ``injury``); default
        :func:`bonesim.engine.materials.load_materials`.
    device : DeviceCaps
        The device's limits (default: scripted, unlimited).
    oversample : int
        Burr lattice refinement (samples per voxel edge).
    max_bodies : int
        Most bone bodies a run may hold (1 .. 255).
    budget_settings : BudgetSettings, optional
        The fixed budget's limits (default: ``bonesim/data/haptics.toml``,
        :func:`bonesim.engine.haptics_budget.load_budget_settings`).
    """
    labels = np.asarray(labels)
    if not 1 <= int(max_bodies) <= BODY_LIMIT:
        raise ValueError(f"max_bodies must be in 1..{BODY_LIMIT}, got {max_bodies}")
    n = len(structures)
    if labels.size and int(labels.max()) > n:
        raise ValueError(f"label volume uses label {int(labels.max())} but only {n} "
                         "structures are defined")
    if n > 255:
        raise ValueError("at most 255 structures are supported")
    if materials is None:
        from bonesim.engine.materials import load_materials
        materials = load_materials()
    stiff = np.zeros(n + 1)
    removal = np.zeros(n + 1)
    injury = np.zeros(n + 1, dtype=np.uint8)
    colors = np.zeros((n + 1, 3), dtype=np.uint8)
    for s, st in enumerate(structures, start=1):
        if st.kind not in materials:
            raise ValueError(f"structure {st.name!r}: no material for kind {st.kind!r}")
        mat = materials[st.kind]
        stiff[s] = mat.stiffness
        removal[s] = mat.removal
        injury[s] = 1 if mat.injury else 0
        colors[s] = st.display_color
    grid = Grid.from_dense(labels, density, spacing_mm, origin_mm)
    for a in (grid.density, grid.label):
        a.flags.writeable = False
    budget = make_budget(grid, oversample, removal, budget_settings)
    stencil, params = _burr_arrays(burr, grid.spacing_mm, oversample, device, budget.settings)
    model = Model(name=name, structures=tuple(structures), grid=grid, burrs=(burr,),
                  stencils=(stencil,), device=device, oversample=int(oversample),
                  stiff=_readonly(stiff), removal=_readonly(removal),
                  injury=_readonly(injury), colors=_readonly(colors),
                  burr_params=(params,), max_bodies=int(max_bodies), case=case)
    return replace(model, budget=_with_burrs(budget, (burr,), model))


@dataclass
class State:
    """Everything a run changes.

    Attributes
    ----------
    grid : Grid
        Current tissue (density is modified in place by :func:`step`).
    touched_flag : (n_bricks, 512) uint8
        1 where a voxel sits in the touched ring unconsumed.
    body : (n_bricks, 512) uint8
        Body id per voxel (see :mod:`bonesim.engine.bodies`).
    pose : (max_bodies, 7) float64
        Body-to-case pose per body ``(tx, ty, tz [mm], qw, qx, qy, qz)``.
    pose_m : (max_bodies, 3, 4) float64
        The same poses as ``[R | t]`` matrices.
    alive : (max_bodies,) uint8
        1 for the bodies that exist.
    bounds : (max_bodies, 6) int32
        Each body's voxel box in its own frame (inclusive).
    t_s : float
        Time of the last step [s] (NaN before the first).
    pos_mm, axis : (3,) float64
        Last tool pose (case frame).
    force_n : (3,) float64
        Last force sent to the device [N].
    out : (N_OUT,) float64
        The last step's kernel output (see :mod:`bonesim.engine.haptics`), case frame.
    tissue, touched : events.Ring
        The tissue-event ring and the shading-hint ring, drained by consumers.
    removed_by_label : (n_labels + 1,) int64
        Running total of removed voxels per label.
    n_steps : int
        Steps taken.
    epoch : int
        Case resets so far (:class:`bonesim.engine.world_commands.Reset`).
    burr : int
        The current burr, an index into the model's burr table
        (:class:`~bonesim.engine.world_commands.SetBurr`); the world step uses it.
    tool : int
        The current tool, an index into
        :data:`bonesim.engine.world_commands.TOOLS`.
    rigid : RigidSet or None
        The fragments and plates in motion, stepped by
        :func:`bonesim.engine.world.world_step`; None: this run has no rigid
        motion of its own (a replay applies the recorded poses instead).
    split_jobs : list of SplitJob
        Large splits under way, first in first out, advanced by one bounded
        slice per world step (:mod:`bonesim.engine.split_jobs`); a reset
        drops them.
    cut_jobs : list of CutJob
        Cut-plane strokes under way, likewise
        (:func:`bonesim.engine.cut_plane.advance_cuts`).
    """

    grid: Grid
    touched_flag: np.ndarray
    body: np.ndarray
    pose: np.ndarray
    pose_m: np.ndarray
    alive: np.ndarray
    bounds: np.ndarray
    tissue: events.Ring
    touched: events.Ring
    removed_by_label: np.ndarray
    t_s: float = math.nan
    pos_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    force_n: np.ndarray = field(default_factory=lambda: np.zeros(3))
    out: np.ndarray = field(default_factory=lambda: np.zeros(N_OUT))
    n_steps: int = 0
    epoch: int = 0
    burr: int = 0
    tool: int = 0
    rigid: RigidSet | None = None
    split_jobs: list = field(default_factory=list)
    cut_jobs: list = field(default_factory=list)
    # kernel scratch
    _R: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    _n_vox: int = 0
    _lbrick: np.ndarray = None
    _ldens: np.ndarray = None
    _llab: np.ndarray = None
    _acc: np.ndarray = None
    _dirty: np.ndarray = None
    _contact: np.ndarray = None
    _prev_contact: np.ndarray | None = None
    _lost: np.ndarray = None
    _lab_body: np.ndarray = None
    _group: np.ndarray = None
    _pass_body: np.ndarray = None
    _pass_ident: np.ndarray = None
    #: the bone is one body at the identity pose (the step needs no pass plan)
    _one_body: bool = True
    _pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _axis: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _acc_out: np.ndarray = field(default_factory=lambda: np.zeros(N_OUT))
    _bpos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _baxis: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: the removal the fixed-budget step carries from step to step (None
    #: where the budget does not bind)
    _budget: BudgetState | None = None
    _onset_body: np.ndarray = None
    _counts: np.ndarray = field(default_factory=lambda: np.zeros(2, np.int64))
    #: the fixed-budget step's brick table and what it was filled for
    _blbrick: np.ndarray = None
    _blkey: np.ndarray = None
    _brow: np.ndarray = None
    #: (model, burr, StepArgs): the budget kernel's arguments that stay from
    #: step to step (:func:`budget_arrays`)
    _bargs: tuple | None = None

    def fit_scratch(self, model: Model) -> None:
        """Size the kernel's scratch for the largest burr of the model's table."""
        self._bargs = None
        for burr in model.burrs:
            n_vox, n_brick = block_size(burr.radius_mm, model.spacing_mm)
            if n_vox > self._n_vox:
                self._n_vox = n_vox
                self._lbrick = np.zeros((n_brick, n_brick, n_brick), dtype=np.int32)
                # the fixed-budget step reads the grid through the brick
                # table alone: no voxel block
                n3 = 1 if model.budget.binding else n_vox ** 3
                self._ldens = np.zeros(n3, dtype=np.float32)
                self._llab = np.zeros(n3, dtype=np.uint8)
                self._acc = np.zeros(n3)
                self._dirty = np.zeros(n3 + 1, dtype=np.int32)
                if model.budget.binding:
                    # the budget step's own brick table, kept from pass to
                    # pass (haptics_budget._brick_table); invalid until filled
                    self._blbrick = np.zeros((n_brick, n_brick, n_brick), dtype=np.int32)
                    self._blkey = np.zeros(5, dtype=np.int64)
        if model.budget.binding:
            n_rows = max(st.row_head.shape[0] for st in model.stencils)
            if self._brow is None or self._brow.shape[0] < n_rows:
                self._brow = np.zeros((n_rows, 3))

    @property
    def n_removed(self) -> int:
        """Voxels removed since the last reset."""
        return int(self.removed_by_label.sum())

    @property
    def n_bodies(self) -> int:
        """Bodies that exist."""
        return int(self.alive.sum())


def state_arrays_spec(model: Model, ring_capacity: int | None = None) -> list:
    """The state arrays another process may need to see, as
    ``(name, shape, dtype)``: density, touched flags, the body arrays,
    removal totals and the event rings (for :class:`bonesim.runtime.shared.SharedArrays`).
    ``ring_capacity`` overrides the rings' capacities (a power of two)."""
    n_b = model.grid.n_bricks
    spec = [("density", (n_b, BRICK_VOXELS), np.float32),
            ("touched_flag", (n_b, BRICK_VOXELS), np.uint8),
            ("removed_by_label", (len(model.structures) + 1,), np.int64)]
    spec += body_arrays_spec(n_b, model.max_bodies)
    for ring in events.RINGS:
        spec += events.ring_arrays_spec(ring, ring_capacity)
    return spec


def make_state(model: Model, arrays: dict | None = None,
               ring_capacity: int | None = None, rate_hz: float | None = None,
               rigid: bool = True) -> State:
    """A fresh state: the model's initial grid as one body, no events, time
    unset, epoch 0, burr 0, tool 0, no rigid in motion.

    Parameters
    ----------
    model : Model
    arrays : dict, optional
        Arrays laid out as :func:`state_arrays_spec` says (e.g. in shared
        memory) to hold the state; they are reset to the model's initial
        tissue and empty rings. Default: private arrays.
    ring_capacity : int, optional
        Capacity of private rings (default :data:`bonesim.engine.events.RINGS`'s).
    rate_hz : float, optional
        The rate the run is stepped at [Hz] (the rigid step's time step;
        default the model's :attr:`Model.haptic_rate_hz`).
    rigid : bool
        Give the state a :class:`~bonesim.engine.rigid_set.RigidSet` of
        :data:`~bonesim.engine.rigid_set.RIGID_SLOTS` slots (gravity from the
        model's case). False: no rigid motion (``state.rigid`` None).
    """
    if arrays is None:
        arrays = {name: np.zeros(shape, dtype=dt)
                  for name, shape, dt in state_arrays_spec(model, ring_capacity)}
    n = len(model.structures) + 1
    g0 = model.grid
    grid = Grid(g0.spacing_mm, g0.origin_mm, g0.shape, g0.keys, g0.vals, g0.bricks,
                arrays["density"], g0.label)
    st = State(grid=grid, touched_flag=arrays["touched_flag"], body=arrays["body"],
               pose=arrays["pose"], pose_m=arrays["pose_m"], alive=arrays["alive"],
               bounds=arrays["bounds"],
               tissue=events.ring_from_arrays("tissue", arrays),
               touched=events.ring_from_arrays("touched", arrays),
               removed_by_label=arrays["removed_by_label"])
    reset_state(model, st)
    st._contact = np.zeros(n, dtype=np.int64)
    st._prev_contact = np.zeros(n, dtype=np.uint8)
    st._lost = np.zeros(n, dtype=np.int64)
    st._lab_body = np.zeros(n, dtype=np.int32)
    st._group = np.zeros(model.max_bodies, dtype=np.int32)
    st._pass_body = np.zeros(model.max_bodies, dtype=np.int32)
    st._pass_ident = np.zeros(model.max_bodies, dtype=np.bool_)
    st._onset_body = np.zeros(n, dtype=np.int32)
    if model.budget.binding:
        st._budget = make_budget_state(model.budget)
    st.fit_scratch(model)
    if rigid:
        st.rigid = RigidSet(model.max_bodies, RIGID_SLOTS,
                            model.haptic_rate_hz if rate_hz is None else rate_hz,
                            gravity_direction(model))
    return st


def reset_state(model: Model, state: State, rings: bool = True) -> None:
    """Put the model's initial tissue back, in place: one body at the
    identity pose, no rigid in motion. The epoch, burr and tool are kept
    (:class:`bonesim.engine.world_commands.Reset` counts the epoch).

    Parameters
    ----------
    rings : bool
        Also empty the event rings. The haptic loop passes False: its rings
        keep counting across resets so that consumers in other processes
        never miss the records written just before one.
    """
    state.grid.density[:] = model.grid.density
    state.touched_flag[:] = 0
    init_bodies(state.body, state.pose, state.pose_m, state.alive, state.bounds,
                model.grid.shape)
    state._one_body = True
    state.split_jobs.clear()
    state.cut_jobs.clear()
    state.removed_by_label[:] = 0
    if rings:
        for ring in (state.tissue, state.touched):
            ring.reset()
    state.t_s = math.nan
    state.n_steps = 0
    state.force_n[:] = 0.0
    if state._prev_contact is not None:
        state._prev_contact[:] = 0
    if state._budget is not None:
        reset_budget_state(model.budget, state._budget)
    if state.rigid is not None:
        state.rigid.clear()


def step(model: Model, state: State, sample: Sample, burr: int | None = None) -> np.ndarray:
    """Advance ``state`` by one haptic sample (the haptic step alone: no
    commands, no rigid motion; :func:`bonesim.engine.world.world_step` is
    the whole world step).

    Computes the volume-sampled force and tangential drag, removes material
    while the drill runs, and appends removals and injuries to the state's
    tissue ring and touched voxels to its touched ring. See
    :mod:`bonesim.engine.haptics` for the model.

    Where the bone is finer than the budget's finest sample lattice
    (:mod:`bonesim.engine.haptics_budget`), the step is the fixed-budget
    step: a fixed number of samples per burr, removal doses per cell
    carried in the state and flushed within a per-step budget (also on
    steps away from the bone).

    Bodies: the tool is transformed into the frame of every body within its
    reach, one kernel pass per group of bodies that share a pose
    (:func:`bonesim.engine.bodies.plan_passes`); each pass's force is turned back
    into the case frame and the sum is clamped to the force limit. A bone
    that is one body at the identity pose takes one pass in the case frame,
    which is exactly the single-body step.

    Parameters
    ----------
    model : Model
    state : State
        Modified in place.
    sample : Sample
        Time [s], position [mm], axis, drill, speed [rpm], direction, burr.
    burr : int, optional
        The burr to step with, overriding ``sample.burr`` (the world step
        passes the state's current burr).

    Returns
    -------
    force_n : (3,) float64
        Force to render on the device [N] (a view of ``state.force_n``).
    """
    t = float(sample.t_s)
    if math.isnan(state.t_s):
        dt = 1.0 / model.haptic_rate_hz
    else:
        dt = t - state.t_s
        if not dt >= 0.0:
            raise ValueError(f"sample time {t} s precedes the previous step ({state.t_s} s)")
        dt = min(dt, MAX_DT_S)
    bi = int(getattr(sample, "burr", 0)) if burr is None else burr   # a trajectory
    # sample has no burr
    if not 0 <= bi < len(model.burrs):
        raise ValueError(f"sample at t={t} s: burr {bi} is not in the model's table of "
                         f"{len(model.burrs)}")
    burr = model.burrs[bi]
    pos, ax = state._pos, state._axis
    pos[:] = sample.pos_mm
    ax[:] = sample.axis
    if not unit_pose(pos, ax):
        raise ValueError(f"sample at t={t} s: position must be finite and axis non-zero")
    drill = bool(sample.drill)
    speed_factor = max(0.0, float(sample.speed_rpm)) / burr.default_speed_rpm
    direction = -1.0 if sample.direction < 0 else 1.0
    if state._one_body:                    # no plan, no body mask: the one-body step
        _kernel(model, state, bi, pos, ax, drill, direction, speed_factor, dt, t, -1,
                True, True)
    else:
        _step_bodies(model, state, bi, pos, ax, drill, direction, speed_factor, dt, t)
    store_step(state.removed_by_label, state._lost, state.pos_mm, pos, state.axis, ax,
               state.force_n, state.out)
    state.t_s = t
    state.n_steps += 1
    return state.force_n


def _step_bodies(model, state, bi, pos, ax, drill, direction, speed_factor, dt, t) -> None:
    """The step over several bodies: one pass per group sharing a pose."""
    g = state.grid
    n_pass = plan_passes(state.alive, state.pose, state.pose_m, state.bounds, pos,
                         model.burr_params[bi][P_RADIUS], g.origin_mm, g.spacing_mm,
                         state._group, state._pass_body, state._pass_ident)
    if n_pass == 1 and state._pass_ident[0]:
        _kernel(model, state, bi, pos, ax, drill, direction, speed_factor, dt, t, 0,
                True, True)
    elif n_pass == 0 and model.budget.binding:
        # no body within reach: a pass that samples nothing flushes the
        # carried removal
        _kernel(model, state, bi, pos, ax, drill, direction, speed_factor, dt, t, -2,
                True, True)
    elif n_pass == 0:
        state.out[:] = 0.0
        state._lost[:] = 0
        state._prev_contact[:] = 0
    else:
        _step_passes(model, state, bi, n_pass, pos, ax, drill, direction, speed_factor,
                     dt, t)


def _kernel(model, state, bi, pos, ax, drill, direction, speed_factor, dt, t, gsel,
            first, last) -> None:
    if model.budget.binding:
        # the fixed-budget step (bone finer than the finest sample lattice)
        a = state._bargs
        if a is None or a[0] is not model or a[1] != bi:
            a = state._bargs = (model, bi, make_step_args(*budget_arrays(model, state, bi)))
        owner = 0 if gsel < 0 else int(state._pass_body[gsel])
        budget_step(a[2], pos, ax, drill, direction, speed_factor, dt, t, gsel, owner, first,
                    last)
        return
    g = state.grid
    ev, tch = state.tissue.fields, state.touched.fields
    st = model.stencils[bi]
    if model.oversample >= ROWS_MIN_OVERSAMPLE:
        # fine sampling: one lookup per voxel a row of samples crosses
        haptic_rows_kernel(
            g.keys, g.vals, g.density, g.label, state.body, state.touched_flag,
            g.origin_mm, g.spacing_mm, model.stiff, model.removal, model.injury,
            st.row_head, st.row_off, st.row_sums, st.spacing_mm, model.burr_params[bi],
            pos, ax, drill, direction, speed_factor, dt, t,
            state._group, gsel, first, last, state._pos,
            state._R, state._n_vox, state._lbrick, state._ldens, state._llab,
            state._acc, state._dirty,
            state._contact, state._prev_contact, state._lost, state._lab_body,
            ev["kind"], ev["body"], ev["label"], ev["t_s"], ev["ijk"], ev["n"],
            ev["value"], state.tissue.head,
            tch["ijk"], state.touched.head, state.out)
        return
    haptic_kernel(g.keys, g.vals, g.density, g.label, state.body, state.touched_flag,
                  g.origin_mm, g.spacing_mm, model.stiff, model.removal, model.injury,
                  st.packed, st.row_off, model.burr_params[bi],
                  pos, ax, drill, direction, speed_factor, dt, t,
                  state._group, gsel, first, last, state._pos,
                  state._R, state._n_vox, state._lbrick, state._ldens, state._llab,
                  state._acc, state._dirty,
                  state._contact, state._prev_contact, state._lost, state._lab_body,
                  ev["kind"], ev["body"], ev["label"], ev["t_s"], ev["ijk"], ev["n"],
                  ev["value"], state.tissue.head,
                  tch["ijk"], state.touched.head, state.out)


def budget_arrays(model, state, bi) -> tuple:
    """The arguments of :func:`~bonesim.engine.haptics_budget.budget_kernel`
    that stay the same from step to step (the state's arrays, the model's
    tables for burr ``bi``), in the order of
    :data:`~bonesim.engine.haptics_budget.STEP_FIELDS`. The step keeps them
    in one :class:`~bonesim.engine.haptics_budget.StepArgs`
    (``state._bargs``, built again for another model or burr and cleared by
    :meth:`State.fit_scratch`)."""
    g = state.grid
    ev, tch = state.tissue.fields, state.touched.fields
    st = model.stencils[bi]
    bud, bs = model.budget, state._budget
    head = (g.keys, g.vals, g.bricks, g.density, g.label, state.body, state.touched_flag,
            g.origin_mm, g.spacing_mm, model.stiff, model.removal, model.injury,
            st.packed, st.row_head, st.row_off, st.spacing_mm, model.burr_params[bi],
            bud.lat[bi], bud.removal_voxels[bi],
            bud.cell, bud.cell.bit_length() - 1)
    tail = (state._pos, state.pose_m,
            state._R, state._blbrick, state._contact, state._prev_contact, state._lost,
            state._lab_body, state._onset_body,
            bs.dose, bs.thr, bs.occ, bs.queued, bs.rep, bs.queue, bs.qhead, state._counts,
            ev["kind"], ev["body"], ev["label"], ev["t_s"], ev["ijk"], ev["n"],
            ev["value"], state.tissue.head,
            tch["ijk"], state.touched.head, state.out, state._blkey, state._brow)
    return head + (state._group,) + tail


def _step_passes(model, state, bi, n_pass, pos, ax, drill, direction, speed_factor, dt,
                 t) -> None:
    """Several kernel passes (bodies at different poses), summed in the case frame."""
    acc = state._acc_out
    acc[:] = 0.0
    for q in range(n_pass):
        m = state.pose_m[state._pass_body[q]]
        _to_body_frame(m, pos, ax, state._bpos, state._baxis)
        _kernel(model, state, bi, state._bpos, state._baxis, drill, direction,
                speed_factor, dt, t, q, q == 0, q == n_pass - 1)
        _add_pass(m, state.out, acc)
    _clamp_total(acc, model.burr_params[bi][P_MAX_FORCE], state.out)


@njit(cache=True, nogil=True)
def _to_body_frame(m, pos, ax, bpos, baxis):
    # R^T (pos - t) and R^T ax for the body-to-case pose [R | t]
    for a in range(3):
        bpos[a] = (m[0, a] * (pos[0] - m[0, 3]) + m[1, a] * (pos[1] - m[1, 3])
                   + m[2, a] * (pos[2] - m[2, 3]))
        baxis[a] = m[0, a] * ax[0] + m[1, a] * ax[1] + m[2, a] * ax[2]


@njit(cache=True, nogil=True)
def _add_pass(m, out, acc):
    # a pass's output into the sum: force and drag turned into the case frame
    for q in range(out.shape[0]):
        if not (O_FX <= q <= O_FZ or O_TX <= q <= O_TZ):
            acc[q] += out[q]
    for a in range(3):
        acc[O_FX + a] += m[a, 0] * out[O_FX] + m[a, 1] * out[O_FX + 1] + m[a, 2] * out[O_FZ]
        acc[O_TX + a] += m[a, 0] * out[O_TX] + m[a, 1] * out[O_TX + 1] + m[a, 2] * out[O_TZ]


@njit(cache=True, nogil=True)
def _clamp_total(acc, limit, out):
    # the summed force clamped to the limit, written as the step's output
    fm = np.sqrt(acc[O_FX] ** 2 + acc[O_FX + 1] ** 2 + acc[O_FZ] ** 2)
    if fm > limit:
        for a in range(3):
            acc[O_FX + a] *= limit / fm
    if acc[O_MAG] > limit:
        acc[O_MAG] = limit
    for q in range(out.shape[0]):
        out[q] = acc[q]


def clear_touched(state: State, ijk: np.ndarray) -> None:
    """Let the touched voxels ``ijk`` (n, 3) be published again (consumer side)."""
    _clear_flags(state.grid.keys, state.grid.vals, state.touched_flag,
                 np.ascontiguousarray(ijk, dtype=np.int32))


@njit(cache=True, nogil=True)
def _clear_flags(keys, vals, flags, ijk):
    for q in range(ijk.shape[0]):
        i, j, k = ijk[q, 0], ijk[q, 1], ijk[q, 2]
        b = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        if b >= 0:
            flags[b, voxel_offset(i, j, k)] = 0
