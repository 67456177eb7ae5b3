"""Model / State / step: the simulator's core contract.

* :class:`Model` is immutable: the case's initial grid, the structure table
  and its material factors, the burr and its sampled stencil, the gains, the
  device's limits. It is loaded from files by :func:`bonesim.loading.load_model` (or built
  from arrays by :func:`make_model`).
* :class:`State` is everything a run changes: the voxel grid, the tool pose,
  time, the last force, the event rings and the kernel's scratch memory.
* :func:`step` advances the state by one haptic sample.

Feeding the same model the same samples gives a bit-identical grid and
identical events: that is what recording and replay rely on.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple, Sequence

import numpy as np
from numba import njit

from . import events
from .device_caps import SCRIPTED, DeviceCaps
from .grid import BRICK_SHIFT, BRICK_VOXELS, Grid, find_brick, voxel_offset
from .haptics import (N_OUT, N_PARAMS, P_H3, P_INV_VOXEL_VOL, P_K_HIGH, P_K_LOW,
                      P_K_TAN, P_MAX_FORCE, P_RADIUS, P_V_T, Stencil, block_size,
                      haptic_kernel, make_stencil)

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
    """

    t_s: float
    pos_mm: np.ndarray
    axis: np.ndarray
    drill: bool
    speed_rpm: float
    direction: int = 1


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
    burr : Burr
        The burr in the hand.
    stencil : Stencil
        The burr's samples.
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
    params : (N_PARAMS,) float64
        Gains and constants for :func:`bonesim.haptics.haptic_kernel`.
    haptic_rate_hz : float
        Nominal step rate [Hz].
    case : object
        The loaded case manifest, or None for models built from arrays.
    clearance : bonesim.clearance.Clearance or None
        Distances to every structure that is not bone, measured on the case's
        label map at its source resolution (:func:`load_model` fills it; None
        for models built from arrays, whose grid is their only label map).
    """

    name: str
    structures: tuple
    grid: Grid
    burr: object
    stencil: Stencil
    device: DeviceCaps
    oversample: int
    stiff: np.ndarray
    removal: np.ndarray
    injury: np.ndarray
    colors: np.ndarray
    params: np.ndarray
    haptic_rate_hz: float = HAPTIC_RATE_HZ
    case: object = None
    clearance: object = None

    @property
    def spacing_mm(self) -> float:
        return self.grid.spacing_mm

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
        st = self.stencil
        for a in (self.grid.density, self.grid.label, self.stiff, self.removal,
                  self.injury, self.colors, self.params,
                  st.offsets, st.inv_r, st.lat, st.packed):
            a.flags.writeable = False

    def with_burr(self, burr) -> "Model":
        """The same model holding another burr (new stencil and gains)."""
        stencil, params = _burr_arrays(burr, self.grid.spacing_mm, self.oversample,
                                       self.device)
        return replace(self, burr=burr, stencil=stencil, params=params)


def _burr_arrays(burr, spacing_mm: float, oversample: int, device: DeviceCaps):
    if oversample < 1:
        raise ValueError(f"oversample must be >= 1, got {oversample}")
    h = spacing_mm / oversample
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
               case=None) -> Model:
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
        See :mod:`bonesim.burrs`.
    origin_mm : (3,) float
        Case-frame centre of voxel (0, 0, 0) [mm].
    density : (nx, ny, nz) float, optional
        Initial density (default 1 where labelled).
    materials : dict, optional
        Kind -> material (``stiffness``, ``removal``, ``injury``); default
        :func:`bonesim.materials.load_materials`.
    device : DeviceCaps
        The device's limits (default: scripted, unlimited).
    oversample : int
        Burr lattice refinement (samples per voxel edge).
    """
    labels = np.asarray(labels)
    n = len(structures)
    if labels.size and int(labels.max()) > n:
        raise ValueError(f"label volume uses label {int(labels.max())} but only {n} "
                         "structures are defined")
    if n > 255:
        raise ValueError("at most 255 structures are supported")
    if materials is None:
        from .materials import load_materials
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
    stencil, params = _burr_arrays(burr, grid.spacing_mm, oversample, device)
    return Model(name=name, structures=tuple(structures), grid=grid, burr=burr,
                 stencil=stencil, device=device, oversample=int(oversample),
                 stiff=_readonly(stiff), removal=_readonly(removal),
                 injury=_readonly(injury), colors=_readonly(colors), params=params,
                 case=case)


@dataclass
class State:
    """Everything a run changes.

    Attributes
    ----------
    grid : Grid
        Current tissue (density is modified in place by :func:`step`).
    touched_flag : (n_bricks, 512) uint8
        1 where a voxel sits in the touched ring unconsumed.
    t_s : float
        Time of the last step [s] (NaN before the first).
    pos_mm, axis : (3,) float64
        Last tool pose.
    force_n : (3,) float64
        Last force sent to the device [N].
    out : (N_OUT,) float64
        The last step's kernel output (see :mod:`bonesim.haptics`).
    removed, touched, injuries : events.Ring
        Event rings drained by consumers.
    removed_by_label : (n_labels + 1,) int64
        Running total of removed voxels per label.
    n_steps : int
        Steps taken.
    """

    grid: Grid
    touched_flag: np.ndarray
    removed: events.Ring
    touched: events.Ring
    injuries: events.Ring
    removed_by_label: np.ndarray
    t_s: float = math.nan
    pos_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    force_n: np.ndarray = field(default_factory=lambda: np.zeros(3))
    out: np.ndarray = field(default_factory=lambda: np.zeros(N_OUT))
    n_steps: int = 0
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
    _pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _axis: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def fit_scratch(self, model: Model) -> None:
        """Size the kernel's scratch for the model's burr (call after a burr change)."""
        n_vox, n_brick = block_size(model.burr.radius_mm, model.spacing_mm)
        if n_vox > self._n_vox:
            self._n_vox = n_vox
            self._lbrick = np.zeros((n_brick, n_brick, n_brick), dtype=np.int32)
            self._ldens = np.zeros(n_vox ** 3, dtype=np.float32)
            self._llab = np.zeros(n_vox ** 3, dtype=np.uint8)
            self._acc = np.zeros(n_vox ** 3)
            self._dirty = np.zeros(n_vox ** 3, dtype=np.int32)


def state_arrays_spec(model: Model) -> list:
    """The state arrays another process may need to see, as
    ``(name, shape, dtype)``: density, touched flags, removal totals and the
    event rings (for :class:`bonesim.shared.SharedArrays`)."""
    n_b = model.grid.n_bricks
    spec = [("density", (n_b, BRICK_VOXELS), np.float32),
            ("touched_flag", (n_b, BRICK_VOXELS), np.uint8),
            ("removed_by_label", (len(model.structures) + 1,), np.int64)]
    for ring in events.RINGS:
        spec += events.ring_arrays_spec(ring)
    return spec


def make_state(model: Model, arrays: dict | None = None) -> State:
    """A fresh state: the model's initial grid, no events, time unset.

    Parameters
    ----------
    model : Model
    arrays : dict, optional
        Arrays laid out as :func:`state_arrays_spec` says (e.g. in shared
        memory) to hold the state; they are reset to the model's initial
        tissue and empty rings. Default: private arrays.
    """
    if arrays is None:
        arrays = {name: np.zeros(shape, dtype=dt)
                  for name, shape, dt in state_arrays_spec(model)}
    n = len(model.structures) + 1
    g0 = model.grid
    grid = Grid(g0.spacing_mm, g0.origin_mm, g0.shape, g0.keys, g0.vals, g0.bricks,
                arrays["density"], g0.label)
    st = State(grid=grid, touched_flag=arrays["touched_flag"],
               removed=events.ring_from_arrays("removed", arrays),
               touched=events.ring_from_arrays("touched", arrays),
               injuries=events.ring_from_arrays("injuries", arrays),
               removed_by_label=arrays["removed_by_label"])
    reset_state(model, st)
    st._contact = np.zeros(n, dtype=np.int64)
    st._prev_contact = np.zeros(n, dtype=np.uint8)
    st._lost = np.zeros(n, dtype=np.int64)
    st.fit_scratch(model)
    return st


def reset_state(model: Model, state: State, rings: bool = True) -> None:
    """Put the model's initial tissue back, in place.

    Parameters
    ----------
    rings : bool
        Also empty the event rings. The haptic loop passes False: its rings
        keep counting across resets so that consumers in other processes
        never miss the records written just before one.
    """
    state.grid.density[:] = model.grid.density
    state.touched_flag[:] = 0
    state.removed_by_label[:] = 0
    if rings:
        for ring in (state.removed, state.touched, state.injuries):
            ring.reset()
    state.t_s = math.nan
    state.n_steps = 0
    state.force_n[:] = 0.0
    if state._prev_contact is not None:
        state._prev_contact[:] = 0


def step(model: Model, state: State, sample: Sample) -> np.ndarray:
    """Advance ``state`` by one haptic sample.

    Computes the volume-sampled force and tangential drag, removes material
    while the drill runs, and appends removals, touched voxels and injuries
    to the state's rings. See :mod:`bonesim.haptics` for the model.

    Parameters
    ----------
    model : Model
    state : State
        Modified in place.
    sample : Sample
        Time [s], position [mm], axis, drill, speed [rpm], direction.

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
    pos = state._pos
    pos[:] = sample.pos_mm
    ax = state._axis
    ax[:] = sample.axis
    norm = math.sqrt(ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2])
    if not norm > 0.0 or not math.isfinite(norm) or not np.isfinite(pos).all():
        raise ValueError(f"sample at t={t} s: position must be finite and axis non-zero")
    ax /= norm
    drill = bool(sample.drill)
    speed_factor = max(0.0, float(sample.speed_rpm)) / model.burr.default_speed_rpm
    direction = -1.0 if sample.direction < 0 else 1.0
    g = state.grid
    st = model.stencil
    rem, tch, inj = state.removed.fields, state.touched.fields, state.injuries.fields
    haptic_kernel(g.keys, g.vals, g.density, g.label, state.touched_flag, g.origin_mm,
                  g.spacing_mm, model.stiff, model.removal, model.injury,
                  st.packed, model.params,
                  pos, ax, drill, direction, speed_factor, dt, t,
                  state._R, state._n_vox, state._lbrick, state._ldens, state._llab,
                  state._acc, state._dirty,
                  state._contact, state._prev_contact, state._lost,
                  rem["ijk"], rem["label"], rem["t_s"], state.removed.head,
                  tch["ijk"], state.touched.head,
                  inj["label"], inj["kind"], inj["t_s"], inj["pos_mm"], inj["voxels"],
                  state.injuries.head, state.out)
    state.removed_by_label += state._lost
    state.t_s = t
    state.pos_mm[:] = pos
    state.axis[:] = ax
    state.force_n[:] = state.out[:3]
    state.n_steps += 1
    return state.force_n


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
