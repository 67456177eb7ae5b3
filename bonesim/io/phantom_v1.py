"""Generation 1 of the procedural phantom, frozen: the bundled case ``phantom@1``.

This is the phantom generator as it was at commit 15854c3 (``bonesim/phantom.py``
then), before the outer cortex was reshaped as a temporal bone seen from lateral
(generation 2, :mod:`bonesim.io.phantom`). It is kept unchanged, only moved into
today's package layout, so that recordings made on it rebuild the very model
they were recorded with: a session's recorded model hash
(:func:`bonesim.session.header.model_sha256`) finds ``phantom@1``
(``ct_cases/phantom/versions/v1/case.toml``, ``generation = 1``), and
:func:`bonesim.io.phantom.phantom_volume` hands generation 1 to this module.
Do not change a constant or a line of the geometry below: any change breaks
those recordings (``tests/bonesim/io/test_phantom_v1.py`` checks the labels
and intensities against hashes taken from the code at 15854c3).

The generator as it described itself:

Procedural phantom of a LEFT temporal bone, built from primitives.

Frame and layout
----------------
Positions are in the case frame (LPS, [mm]): ``+x`` toward the patient's left
(for a left ear that is **lateral**, so the mastoid cortex faces ``+x``),
``+y`` posterior, ``+z`` superior. The grid is centred on the frame origin: a
``size_mm`` box of ``voxel_mm`` voxels with voxel ``(0, 0, 0)`` at
``-(n - 1) * voxel_mm / 2`` on each axis.

Anatomy (all constants below, in mm)
------------------------------------
* **Bone**: a rounded block (super-ellipsoid) with a mastoid tip below and
  behind, and the petrous ridge running medially and anteriorly. Its lateral
  surface (the mastoid cortex) lies near ``x = +19``.
* **Cranial fossae**: above the tegmen plane (``z > TEGMEN_Z_MM``) and medial
  to a squamous plate lies the middle fossa; behind a posteromedial plane lies
  the posterior fossa. Each is lined by a dura layer ``DURA_MM`` thick (soft);
  the rest of the fossae is empty.
* **Sigmoid sinus** (soft): a thick tube grooving the posterior mastoid, from
  the transverse sinus (posterior-superior) down and medially to the jugular
  bulb.
* **Air**: the external auditory canal (a tube entering from lateral,
  anterior-inferior), the middle ear and epitympanum, the mastoid antrum
  (anterior-superior in the mastoid, ~11 mm deep to the cortex) with the
  aditus joining it to the epitympanum, and many random air cells in the
  mastoid. Air cells keep ``CORTEX_MM`` of bone to the outside and to the
  fossae, and ``CELL_CLEARANCE_MM`` to nerves, sinus, labyrinth and the
  ear spaces.
* **Facial nerve** (critical): tympanic segment from the geniculate ganglion
  (anterior-medial) back under the lateral canal to the second genu, then the
  vertical mastoid segment down to the stylomastoid foramen, ~13 mm deep
  (medial) to the mastoid cortex.
* **Chorda tympani** (critical): leaves the mastoid segment at
  ``CHORDA_BRANCH_Z_MM`` and runs up and forward into the middle ear.
* **Labyrinth** (critical): vestibule plus three semicircular canals (tori) in
  mutually perpendicular planes, medial to the antrum.
* **Ossicles** (critical): malleus, incus and stapes in the middle ear.

Only the air cells and the bone's HU texture depend on the seed; the named
structures are fixed, so trajectories can rely on :data:`LANDMARKS_MM`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from bonesim.io.volumes import CaseVolume

__all__ = ["GENERATION", "PARTS", "LANDMARKS_MM", "DEFAULT_SEED", "DEFAULT_VOXEL_MM",
           "DEFAULT_SIZE_MM", "PhantomParts", "Canvas", "build_phantom", "phantom_volume",
           "lateral_surface_x_mm"]

#: The phantom generation this module builds (see :data:`bonesim.io.phantom.GENERATIONS`).
GENERATION = 1

PARTS = ("bone", "sigmoid_sinus", "posterior_fossa_dura", "middle_fossa_dura",
         "facial_nerve", "chorda_tympani", "labyrinth", "ossicles")
"""Structure names the phantom can paint (the default manifest order)."""

DEFAULT_SEED = 0
DEFAULT_VOXEL_MM = 0.5
DEFAULT_SIZE_MM = (52.0, 52.0, 52.0)

# ------------------------------------------------------------ bone envelope
BLOCK_CENTER_MM = (2.0, 2.0, -2.0)
BLOCK_SEMI_MM = (18.0, 22.0, 18.0)
BLOCK_EXPONENT = 3.0           # super-ellipsoid exponent: a rounded box
TIP_CENTER_MM = (12.0, 8.0, -16.0)
TIP_SEMI_MM = (7.0, 8.0, 9.0)
PETROUS_AXIS_MM = ((-5.0, -5.0, 0.0), (-21.0, -17.0, 2.0))
PETROUS_RADII_MM = (8.0, 5.0)  # at the base and at the apex

# ----------------------------------------------------------- cranial fossae
TEGMEN_Z_MM = 11.0             # floor of the middle fossa
SQUAMA_MM = 3.0                # lateral bony plate above the tegmen
PF_POINT_MM = (0.0, 12.0, 0.0)  # a point on the posterior fossa's bony wall
PF_NORMAL = (-1.0, 1.2, 0.0)   # points into the posterior fossa (posteromedial)
DURA_MM = 1.5

# ---------------------------------------------------------------- air spaces
EAC_AXIS_MM = ((30.0, -13.0, -4.0), (8.5, -13.0, -4.0))
EAC_RADIUS_MM = 4.0
MIDDLE_EAR_CENTER_MM = (6.0, -12.5, -2.0)
MIDDLE_EAR_SEMI_MM = (3.0, 4.5, 5.0)
EPITYMPANUM_CENTER_MM = (6.0, -11.5, 3.5)
EPITYMPANUM_SEMI_MM = (2.5, 3.5, 2.5)
ANTRUM_CENTER_MM = (8.0, -1.0, 6.0)
ANTRUM_RADIUS_MM = 3.5
ADITUS_AXIS_MM = (ANTRUM_CENTER_MM, (6.0, -10.0, 4.0))
ADITUS_RADIUS_MM = 1.5
AIR_REGION_CENTER_MM = (11.5, 7.0, -5.0)   # ellipsoid the cell centres fall in
AIR_REGION_SEMI_MM = (7.0, 10.0, 12.0)
AIR_CELL_CANDIDATES = 400
AIR_CELL_RADIUS_MM = (0.8, 2.2)            # uniform range
CORTEX_MM = 2.0                            # bone kept between cells and outside
CELL_CLEARANCE_MM = 1.0                    # bone kept around protected parts

# ----------------------------------------------------------------- structures
SINUS_PATH_MM = ((2.0, 26.0, 14.0), (6.0, 19.0, 6.0), (7.0, 16.0, -3.0),
                 (5.0, 13.0, -11.0), (1.0, 8.0, -16.0), (-2.0, 5.0, -18.0))
SINUS_RADIUS_MM = 3.5
JUGULAR_BULB_MM = (-2.0, 5.0, -18.0)
JUGULAR_BULB_RADIUS_MM = 4.5
FACIAL_PATH_MM = ((-1.0, -16.0, 1.0),      # geniculate ganglion
                  (4.0, -4.0, -0.5),       # second genu
                  (5.0, -3.0, -3.0),
                  (5.8, -2.3, -12.0),
                  (6.6, -1.6, -21.0))      # stylomastoid foramen (below the bone)
FACIAL_RADIUS_MM = 0.9
CHORDA_BRANCH_Z_MM = -12.0
CHORDA_PATH_MM = ((7.2, -5.0, -8.0), (8.2, -8.3, -3.5), (8.0, -11.0, -0.5))
CHORDA_RADIUS_MM = 0.5
VESTIBULE_MM = (-2.5, -9.0, 1.5)
VESTIBULE_RADIUS_MM = 2.0
SCC_MAJOR_MM = 3.2                         # canal arc radius
SCC_MINOR_MM = 0.8                         # canal (bony labyrinth) radius
SCC_MM = {                                 # centre, plane normal
    "lateral": ((-1.0, -6.75, 3.0), (0.0, 0.0, 1.0)),
    "superior": ((-2.5, -9.0, 4.2), (-1.0, -1.0, 0.0)),
    "posterior": ((-3.0, -5.5, -1.0), (1.0, -1.0, 0.0)),
}
OSSICLE_SPHERES_MM = (((6.5, -13.0, 3.5), 1.3),    # malleus head
                      ((6.0, -10.8, 3.5), 1.1))    # incus body
OSSICLE_RODS_MM = (((6.8, -13.0, 2.5), (8.5, -13.0, -3.5), 0.5),   # malleus handle
                   ((6.0, -10.8, 3.5), (6.5, -8.5, 4.0), 0.5),     # incus short proc.
                   ((6.0, -10.8, 3.0), (5.5, -10.5, -1.0), 0.5),   # incus long proc.
                   ((5.3, -10.5, -1.3), (3.2, -10.5, -1.3), 0.5))  # stapes

# ------------------------------------------------------------- intensities
HU_AIR = -1000.0
HU_BONE = 1500.0
HU_BONE_SD = 150.0           # spread of the smooth bone texture
HU_TEXTURE_MM = 4.0          # correlation length of that texture
HU_BY_PART = {"sigmoid_sinus": 50.0, "posterior_fossa_dura": 40.0,
              "middle_fossa_dura": 40.0, "facial_nerve": 40.0,
              "chorda_tympani": 40.0, "labyrinth": 10.0, "ossicles": 1200.0}


def _point_on_path(path, z):
    """Point of a polyline (descending in z) at height ``z`` [mm]."""
    p = np.asarray(path, float)
    for a, b in zip(p[:-1], p[1:]):
        if min(a[2], b[2]) <= z <= max(a[2], b[2]) and a[2] != b[2]:
            t = (z - a[2]) / (b[2] - a[2])
            return a + t * (b - a)
    raise ValueError(f"path does not reach z = {z}")


def lateral_surface_x_mm(y_mm: float, z_mm: float) -> float:
    """x [mm] of the bone block's lateral surface (mastoid cortex) at (y, z).

    Valid on the block itself (not on the mastoid tip below ``z = -18``);
    returns the block centre's x where (y, z) misses the block.
    """
    c, s, p = BLOCK_CENTER_MM, BLOCK_SEMI_MM, BLOCK_EXPONENT
    f = abs((y_mm - c[1]) / s[1]) ** p + abs((z_mm - c[2]) / s[2]) ** p
    return float(c[0] + s[0] * max(1.0 - f, 0.0) ** (1.0 / p))


LANDMARKS_MM = {
    "mastoid_cortex": (lateral_surface_x_mm(4.0, -3.0), 4.0, -3.0),
    "antrum": ANTRUM_CENTER_MM,
    "facial_second_genu": FACIAL_PATH_MM[1],
    "facial_mastoid_mid": tuple(float(v) for v in _point_on_path(FACIAL_PATH_MM, -8.0)),
    "sigmoid_sinus_lateral": (SINUS_PATH_MM[2][0] + SINUS_RADIUS_MM,
                              *SINUS_PATH_MM[2][1:]),   # lateral wall of the sinus
    "lateral_canal": SCC_MM["lateral"][0],
    "eac_medial_end": EAC_AXIS_MM[1],
}
"""Named points for trajectory generators (case frame, mm)."""


@dataclass
class PhantomParts:
    """Boolean masks of the phantom's parts on its grid (axes x, y, z).

    Attributes
    ----------
    masks : dict of str -> (nx, ny, nz) bool
        One mask per name in :data:`PARTS`, as painted (later parts win, so
        masks do not overlap).
    envelope : (nx, ny, nz) bool
        Outer bone shape before any air space was carved (fossae excluded).
    air_cells : (nx, ny, nz) bool
        Random mastoid air cells (antrum and ear spaces excluded).
    hu : (nx, ny, nz) float32
        Intensities [HU].
    origin_mm : (3,) float64
        Centre of voxel (0, 0, 0) [mm].
    spacing_mm : float
        Voxel edge [mm].
    """

    masks: dict
    envelope: np.ndarray
    air_cells: np.ndarray
    hu: np.ndarray
    origin_mm: np.ndarray
    spacing_mm: float


class Canvas:
    """Voxel-centre coordinates of the grid and painting into sub-boxes."""

    def __init__(self, shape, spacing_mm: float):
        self.shape = tuple(int(n) for n in shape)
        self.h = float(spacing_mm)
        self.origin = -(np.asarray(self.shape, float) - 1) * self.h / 2
        self.axes = [(self.origin[a] + self.h * np.arange(n)).astype(np.float32)
                     for a, n in enumerate(self.shape)]

    def empty(self) -> np.ndarray:
        return np.zeros(self.shape, dtype=bool)

    def box(self, lo, hi):
        """Slices and broadcast coordinates of voxel centres inside [lo, hi]."""
        sl = []
        for a in range(3):
            i0 = int(np.ceil((lo[a] - self.origin[a]) / self.h))
            i1 = int(np.floor((hi[a] - self.origin[a]) / self.h)) + 1
            sl.append(slice(max(i0, 0), min(i1, self.shape[a])))
        if any(s.stop <= s.start for s in sl):
            return None
        x = self.axes[0][sl[0]][:, None, None]
        y = self.axes[1][sl[1]][None, :, None]
        z = self.axes[2][sl[2]][None, None, :]
        return tuple(sl), x, y, z

    def full(self):
        return self.box(self.origin, self.origin + self.h * (np.asarray(self.shape) - 1))

    def ellipsoid(self, mask, c, semi):
        c, semi = np.asarray(c, float), np.asarray(semi, float)
        b = self.box(c - semi, c + semi)
        if b is None:
            return
        sl, x, y, z = b
        mask[sl] |= (((x - c[0]) / semi[0]) ** 2 + ((y - c[1]) / semi[1]) ** 2
                     + ((z - c[2]) / semi[2]) ** 2) <= 1.0

    def sphere(self, mask, c, r):
        self.ellipsoid(mask, c, (r, r, r))

    def capsule(self, mask, a, b, r0, r1=None):
        """Tube from ``a`` to ``b`` with round ends; radius ``r0`` -> ``r1``."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        r1 = r0 if r1 is None else r1
        rmax = max(r0, r1)
        bx = self.box(np.minimum(a, b) - rmax, np.maximum(a, b) + rmax)
        if bx is None:
            return
        sl, x, y, z = bx
        d = b - a
        L2 = float(d @ d)
        px, py, pz = x - a[0], y - a[1], z - a[2]
        t = np.clip((px * d[0] + py * d[1] + pz * d[2]) / L2, 0.0, 1.0)
        dist2 = (px - t * d[0]) ** 2 + (py - t * d[1]) ** 2 + (pz - t * d[2]) ** 2
        r = r0 + (r1 - r0) * t
        mask[sl] |= dist2 <= r * r

    def polyline(self, mask, pts, r):
        for a, b in zip(pts[:-1], pts[1:]):
            self.capsule(mask, a, b, r)

    def torus(self, mask, c, normal, R, r):
        c = np.asarray(c, float)
        n = np.asarray(normal, float)
        n = n / np.linalg.norm(n)
        b = self.box(c - (R + r), c + (R + r))
        if b is None:
            return
        sl, x, y, z = b
        px, py, pz = x - c[0], y - c[1], z - c[2]
        h = px * n[0] + py * n[1] + pz * n[2]
        rho = np.sqrt(np.maximum(px * px + py * py + pz * pz - h * h, 0.0))
        mask[sl] |= (rho - R) ** 2 + h * h <= r * r


def _envelope(cv: Canvas):
    """Bone shape, middle-fossa and posterior-fossa masks and dura layers."""
    sl, x, y, z = cv.full()
    c, s, p = np.asarray(BLOCK_CENTER_MM), np.asarray(BLOCK_SEMI_MM), BLOCK_EXPONENT
    fx = np.abs((x - c[0]) / s[0]) ** p
    fyz = np.abs((y - c[1]) / s[1]) ** p + np.abs((z - c[2]) / s[2]) ** p
    shape = (fx + fyz) <= 1.0
    cv.ellipsoid(shape, TIP_CENTER_MM, TIP_SEMI_MM)
    cv.capsule(shape, *PETROUS_AXIS_MM, *PETROUS_RADII_MM)
    # lateral surface of the block at (y, z): x where the super-ellipsoid ends
    x_surf = c[0] + s[0] * np.maximum(1.0 - fyz, 0.0) ** (1.0 / p)
    above = z - TEGMEN_Z_MM                                 # > 0 above the tegmen
    medial = (x_surf - SQUAMA_MM) - x                       # > 0 medial to squama
    mid = (above > 0) & (medial > 0)
    mid_depth = np.minimum(above, medial)                   # depth into the fossa
    n = np.asarray(PF_NORMAL, float)
    n /= np.linalg.norm(n)
    q = np.asarray(PF_POINT_MM, float)
    pf_depth = (x - q[0]) * n[0] + (y - q[1]) * n[1] + (z - q[2]) * n[2]
    post = pf_depth > 0
    mid_dura = shape & mid & (mid_depth <= DURA_MM)
    post_dura = shape & post & (pf_depth <= DURA_MM) & ~mid
    envelope = shape & ~mid & ~post
    return envelope, mid_dura, post_dura


def _air_cells(cv: Canvas, rng, envelope, protected):
    """Random spheres in the mastoid that keep their distance to the outside."""
    c = np.asarray(AIR_REGION_CENTER_MM, float)
    semi = np.asarray(AIR_REGION_SEMI_MM, float)
    # candidate centres uniform in the region ellipsoid
    u = rng.normal(size=(AIR_CELL_CANDIDATES, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u *= rng.random(AIR_CELL_CANDIDATES)[:, None] ** (1.0 / 3.0)
    centres = c + u * semi
    radii = rng.uniform(*AIR_CELL_RADIUS_MM, size=AIR_CELL_CANDIDATES)
    # distance [mm] to the nearest non-bone / protected voxel, in a padded box
    pad = CORTEX_MM + AIR_CELL_RADIUS_MM[1] + 2 * cv.h
    b = cv.box(c - semi - pad, c + semi + pad)
    if b is None:                                 # grid too small to hold the mastoid
        return cv.empty()
    sl = b[0]
    d_out = ndimage.distance_transform_edt(envelope[sl], sampling=cv.h)
    d_prot = ndimage.distance_transform_edt(~protected[sl], sampling=cv.h)
    lo = np.array([s.start for s in sl])
    idx = np.rint((centres - cv.origin) / cv.h).astype(int) - lo
    sub_shape = np.array(d_out.shape)
    inside = np.all((idx >= 0) & (idx < sub_shape), axis=1)
    snap = cv.h * np.sqrt(3.0) / 2          # centre rounded to a voxel moves this far
    cells = cv.empty()
    for ci, r, ok, ii in zip(centres, radii, inside, idx):
        if not ok:
            continue
        if (d_out[tuple(ii)] < r + snap + CORTEX_MM
                or d_prot[tuple(ii)] < r + snap + CELL_CLEARANCE_MM):
            continue
        cv.sphere(cells, ci, r)
    return cells & envelope


def build_phantom(seed: int = DEFAULT_SEED, voxel_mm: float = DEFAULT_VOXEL_MM,
                  size_mm=DEFAULT_SIZE_MM) -> PhantomParts:
    """Generate the phantom's part masks and intensities.

    Parameters
    ----------
    seed : int
        Seed of ``numpy.random.default_rng`` (air cells, bone texture).
    voxel_mm : float
        Isotropic voxel edge [mm].
    size_mm : (3,) float
        Grid extent ``(x, y, z)`` [mm], centred on the frame origin.

    Returns
    -------
    PhantomParts
    """
    if not voxel_mm > 0:
        raise ValueError(f"voxel_mm must be positive, got {voxel_mm}")
    shape = np.maximum(1, np.round(np.asarray(size_mm, float) / voxel_mm)).astype(int)
    cv = Canvas(shape, voxel_mm)
    rng = np.random.default_rng(seed)

    envelope, mid_dura, post_dura = _envelope(cv)

    sinus = cv.empty()
    cv.polyline(sinus, SINUS_PATH_MM, SINUS_RADIUS_MM)
    cv.sphere(sinus, JUGULAR_BULB_MM, JUGULAR_BULB_RADIUS_MM)
    facial = cv.empty()
    cv.polyline(facial, FACIAL_PATH_MM, FACIAL_RADIUS_MM)
    chorda = cv.empty()
    branch = _point_on_path(FACIAL_PATH_MM, CHORDA_BRANCH_Z_MM)
    cv.polyline(chorda, (tuple(branch),) + CHORDA_PATH_MM, CHORDA_RADIUS_MM)
    labyrinth = cv.empty()
    cv.sphere(labyrinth, VESTIBULE_MM, VESTIBULE_RADIUS_MM)
    for centre, normal in SCC_MM.values():
        cv.torus(labyrinth, centre, normal, SCC_MAJOR_MM, SCC_MINOR_MM)
    ossicles = cv.empty()
    for centre, r in OSSICLE_SPHERES_MM:
        cv.sphere(ossicles, centre, r)
    for a, b, r in OSSICLE_RODS_MM:
        cv.capsule(ossicles, a, b, r)
    ear = cv.empty()                     # air spaces of the ear proper
    cv.capsule(ear, *EAC_AXIS_MM, EAC_RADIUS_MM)
    cv.ellipsoid(ear, MIDDLE_EAR_CENTER_MM, MIDDLE_EAR_SEMI_MM)
    cv.ellipsoid(ear, EPITYMPANUM_CENTER_MM, EPITYMPANUM_SEMI_MM)
    antrum = cv.empty()
    cv.sphere(antrum, ANTRUM_CENTER_MM, ANTRUM_RADIUS_MM)
    cv.capsule(antrum, *ADITUS_AXIS_MM, ADITUS_RADIUS_MM)

    protected = sinus | facial | chorda | labyrinth | ear | ossicles
    cells = _air_cells(cv, rng, envelope, protected)

    bone = envelope & ~cells & ~ear & ~antrum
    masks = {"bone": bone, "posterior_fossa_dura": post_dura,
             "middle_fossa_dura": mid_dura, "sigmoid_sinus": sinus,
             "labyrinth": labyrinth, "facial_nerve": facial,
             "chorda_tympani": chorda, "ossicles": ossicles}
    # paint order: later parts win where they overlap
    order = ("bone", "posterior_fossa_dura", "middle_fossa_dura", "sigmoid_sinus",
             "labyrinth", "chorda_tympani", "facial_nerve", "ossicles")
    painted = np.zeros(cv.shape, dtype=np.uint8)
    for i, name in enumerate(order, start=1):
        painted[masks[name]] = i
    masks = {name: painted == i for i, name in enumerate(order, start=1)}

    # bone texture: coarse Gaussian noise interpolated onto the grid
    step = HU_TEXTURE_MM / voxel_mm
    coarse_shape = tuple(int(np.ceil(n / step)) + 2 for n in cv.shape)
    coarse = rng.normal(size=coarse_shape)
    tex = ndimage.affine_transform(coarse, np.full(3, 1.0 / step),
                                   output_shape=cv.shape, order=1, mode="nearest")
    tex /= max(float(tex.std()), 1e-6)
    hu = np.full(cv.shape, HU_AIR, dtype=np.float32)
    hu[masks["bone"]] = (HU_BONE + HU_BONE_SD * tex[masks["bone"]]).astype(np.float32)
    for name, value in HU_BY_PART.items():
        hu[masks[name]] = value
    np.rint(hu, out=hu)
    return PhantomParts(masks, envelope, cells, hu, cv.origin.copy(), cv.h)


def phantom_volume(seed: int = DEFAULT_SEED, voxel_mm: float = DEFAULT_VOXEL_MM,
                   size_mm=DEFAULT_SIZE_MM, structures=PARTS) -> CaseVolume:
    """The phantom as a :class:`~bonesim.io.volumes.CaseVolume`.

    Parameters
    ----------
    seed, voxel_mm, size_mm
        See :func:`build_phantom`.
    structures : sequence of str
        Part names in manifest order: part ``structures[s - 1]`` gets label
        ``s``. Parts not listed are left empty (label 0, HU of air).

    Returns
    -------
    CaseVolume
        ``labels`` uint8 and ``hu`` float32 on the phantom grid.
    """
    unknown = [s for s in structures if s not in PARTS]
    if unknown:
        raise ValueError(f"unknown phantom part(s) {unknown}; known: {list(PARTS)}")
    parts = build_phantom(seed, voxel_mm, size_mm)
    labels = np.zeros(parts.hu.shape, dtype=np.uint8)
    hu = parts.hu
    for s, name in enumerate(structures, start=1):
        labels[parts.masks[name]] = s
    omitted = [p for p in PARTS if p not in structures]
    for name in omitted:
        hu[parts.masks[name]] = HU_AIR
    src = f"procedural left temporal-bone phantom (seed {seed}, generation 1)"
    return CaseVolume(labels, parts.spacing_mm, parts.origin_mm, src, hu)
