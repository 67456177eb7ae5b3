"""A large fragment's contact samples and mass, measured in bounded slices.

:func:`bonesim.engine.rigid_set.body_samples` measures a fragment when it is
first woken (touched by the stopped tool, or grabbed): every voxel of its box
is read, with its 26 neighbours for the surface. For a 512,000-voxel
fragment that is more than half a second, all in one haptic period. A
fragment whose voxel box holds more cells than ``[rigid] voxels_per_step`` of
``bonesim/data/slicing.toml`` is therefore measured by a :class:`MeasureJob`
instead: :meth:`bonesim.engine.rigid_set.RigidSet.advance` scans its box a
slice per world step (at most that many solid voxels, at most eight times as
many cells), in the same ``(i, j, k)`` order as :func:`body_samples`,
accumulating

* the voxel count and the first and second moments of the voxel centres
  (body frame [mm]), from which mass [kg], centre of mass [mm] and inertia
  about it [kg mm^2] follow (the same quantities as
  :func:`~bonesim.engine.rigid_set.mass_properties`, summed in another order:
  equal to rounding);
* the surface voxels and their outward normals, in scan order, from which the
  contact samples are taken exactly as :func:`body_samples` takes them.

Until its measurement is complete the fragment stays put (a push leaves it
where it is; a grab is refused with a line saying so); then it wakes as any
fragment. The slices are a fixed number of voxels per step, so a run's rigid
motion stays a function of its inputs (and replay applies the recorded poses
anyway). The measurement is of the voxels as the slices read them: bone
drilled off the fragment after its slice is still counted (as it was, before,
for bone drilled after the wake).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.rigid import BONE_DENSITY_KG_MM3, empty_side, solid_at

__all__ = ["MeasureJob", "needs_slices", "measure_budget", "stride"]


def stride(n: int, keep: int) -> np.ndarray:
    """``keep`` of ``n`` indices, evenly spread (all when ``n <= keep``): the
    contact samples a fragment keeps of its surface voxels."""
    if n <= keep:
        return np.arange(n)
    return (np.arange(keep) * n) // keep


def measure_budget() -> int:
    """Solid voxels a world step may measure (``[rigid] voxels_per_step``)."""
    from bonesim.engine.slicing import voxels_per_step

    return voxels_per_step("rigid")


def needs_slices(state, b: int) -> bool:
    """Whether body ``b``'s box holds more cells than a step may measure."""
    bd = state.bounds[b].astype(np.int64)
    return int(np.prod(bd[3:] - bd[:3] + 1)) > measure_budget()


@njit(cache=True, nogil=True)
def _measure_slice(keys, vals, body, density, bid, lo, hi, cursor, budget, origin, spacing,
                   mom, surf_ijk, surf_nrm):
    # cursor: next cell of the box (i, j, k order), surface voxels so far
    ny = hi[1] - lo[1] + 1
    nz = hi[2] - lo[2] + 1
    n_box = (hi[0] - lo[0] + 1) * ny * nz
    c = cursor[0]
    ns = cursor[1]
    solid = 0
    cells = 0
    while c < n_box and solid < budget and cells < 8 * budget:
        i = lo[0] + c // (ny * nz)
        r = c - (i - lo[0]) * ny * nz
        j = lo[1] + r // nz
        k = lo[2] + r - (j - lo[1]) * nz
        c += 1
        cells += 1
        if not solid_at(keys, vals, body, density, bid, i, j, k):
            continue
        solid += 1
        x = origin[0] + spacing * i
        y = origin[1] + spacing * j
        z = origin[2] + spacing * k
        mom[0] += 1.0
        mom[1] += x
        mom[2] += y
        mom[3] += z
        mom[4] += x * x
        mom[5] += x * y
        mom[6] += x * z
        mom[7] += y * y
        mom[8] += y * z
        mom[9] += z * z
        gx, gy, gz, face = empty_side(keys, vals, body, density, bid, i, j, k)
        gn = math.sqrt(gx * gx + gy * gy + gz * gz)
        if face and gn > 0.0:
            surf_ijk[ns, 0], surf_ijk[ns, 1], surf_ijk[ns, 2] = i, j, k
            surf_nrm[ns, 0], surf_nrm[ns, 1], surf_nrm[ns, 2] = gx / gn, gy / gn, gz / gn
            ns += 1
    cursor[0] = c
    cursor[1] = ns
    return c >= n_box


class MeasureJob:
    """The measurement of body ``b`` under way (module docstring).

    Attributes
    ----------
    body : int
    done : bool
        The whole box is scanned.
    result : dict or None
        When done: :func:`~bonesim.engine.rigid_set.body_samples`'s dict.
    """

    def __init__(self, state, b: int):
        self.body = int(b)
        bd = state.bounds[b].astype(np.int64)
        self.lo, self.hi = bd[:3].copy(), bd[3:].copy()
        n_box = int(np.prod(self.hi - self.lo + 1))
        self.cursor = np.zeros(2, np.int64)
        self.mom = np.zeros(10)
        # pages are touched as the slices write them, not now
        self.surf_ijk = np.empty((n_box, 3), np.int64)
        self.surf_nrm = np.empty((n_box, 3))
        self.done = False
        self.result = None

    @property
    def progress(self) -> float:
        """Share of the box scanned."""
        return float(self.cursor[0]) / float(np.prod(self.hi - self.lo + 1))

    def advance(self, state, budget: int, max_samples: int) -> bool:
        """One slice; True when the measurement is complete (``result`` set).

        Raises
        ------
        ValueError
            The body holds no bone (when the scan ends).
        """
        g = state.grid
        self.done = bool(_measure_slice(g.keys, g.vals, state.body, g.density,
                                        np.uint8(self.body), self.lo, self.hi, self.cursor,
                                        int(budget), g.origin_mm, float(g.spacing_mm),
                                        self.mom, self.surf_ijk, self.surf_nrm))
        if self.done:
            self.result = self._finish(g, max_samples)
            self.surf_ijk = self.surf_nrm = None
        return self.done

    def _finish(self, g, max_samples: int) -> dict:
        m = self.mom
        n = int(m[0])
        if n == 0:
            raise ValueError(f"rigid: body {self.body} holds no bone")
        vm = BONE_DENSITY_KG_MM3 * g.spacing_mm ** 3
        mass = vm * n
        com = m[1:4] / n
        sxx = np.array([[m[4], m[5], m[6]], [m[5], m[7], m[8]], [m[6], m[8], m[9]]]) / n
        cov = sxx - np.outer(com, com)
        inertia = mass * (np.trace(cov) * np.eye(3) - cov)
        inertia += np.eye(3) * mass * g.spacing_mm ** 2 / 6.0
        ns = int(self.cursor[1])
        s_idx = stride(ns, max_samples)
        nrm = self.surf_nrm[s_idx].copy()
        centres = g.origin_mm + g.spacing_mm * self.surf_ijk[s_idx].astype(np.float64)
        smp = centres + 0.5 * g.spacing_mm * nrm
        return {"smp": smp, "nrm": nrm, "mass_kg": mass, "com_mm": com, "inertia": inertia,
                "voxels": n}
