"""Procedural phantom of a LEFT temporal bone, built from primitives.

Frame and layout
----------------
Positions are in the case frame (LPS, [mm]): ``+x`` toward the patient's left
(for a left ear that is **lateral**, so the mastoid cortex faces ``+x``),
``+y`` posterior, ``+z`` superior. The grid is centred on the frame origin: a
``size_mm`` box of ``voxel_mm`` voxels with voxel ``(0, 0, 0)`` at
``-(n - 1) * voxel_mm / 2`` on each axis.

Anatomy (all constants below, in mm)
------------------------------------
* **Bone**, its outer cortex as a surgeon sees it from lateral: the *squama*,
  a thin (``SQUAMA_MM``), slightly convex plate with a rounded upper border
  rising above the ear canal; the root of the *zygomatic process* above and
  in front of the canal, its stump cut off in front (``ANTERIOR_CUT_Y_MM``,
  the specimen's saw cut); the *temporal line* (supramastoid crest), a ridge
  running back from the zygomatic root above the antrum; the bony *external
  acoustic meatus*, an oval opening (about 7 mm wide, 9 mm high) with a rim,
  and the *spine of Henle* at its posterior-superior margin; the *mastoid*,
  whose convex, rough lateral face (the mastoid cortex, near ``x = +20``)
  narrows down and forward into the mastoid process, its tip about 2 cm below
  and 1.3 cm behind the canal. Medially, a core and the petrous pyramid
  (running medially and anteriorly) hold the ear. The shape is a smooth union
  of ellipsoids, round cones and a spherical plate (signed distance fields
  with fillets), so it has no edges but the saw cut;
  :func:`lateral_surface_x_mm` gives its lateral face.
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

Only the air cells and the bone's HU texture depend on the seed; the outer
shape (its relief included) and the named structures are fixed, so
trajectories can rely on :data:`LANDMARKS_MM`.
"""
from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from bonesim.io import phantom_v1 as _v1
# the painting canvas and the parts record are the first generation's, shared
# by every generation (the frozen module's hash test guards them)
from bonesim.io.phantom_v1 import Canvas, PhantomParts
from bonesim.io.recent import Recent
from bonesim.io.volumes import CaseVolume

__all__ = ["PARTS", "LANDMARKS_MM", "DEFAULT_SEED", "DEFAULT_VOXEL_MM", "DEFAULT_SIZE_MM",
           "GENERATIONS", "LATEST_GENERATION",
           "build_phantom", "phantom_volume", "lateral_surface_x_mm"]

PARTS = ("bone", "sigmoid_sinus", "posterior_fossa_dura", "middle_fossa_dura",
         "facial_nerve", "chorda_tympani", "labyrinth", "ossicles")
"""Structure names the phantom can paint (the default manifest order)."""

DEFAULT_SEED = 0
DEFAULT_VOXEL_MM = 0.5
DEFAULT_SIZE_MM = (52.0, 52.0, 52.0)
#: Generations of the phantom's shape still built: 1, the first phantom (a
#: rounded block; frozen in :mod:`bonesim.io.phantom_v1`, which builds it); 2,
#: the temporal bone whose posterior fossa opened behind the mastoid (the sinus
#: bulging out of the bone); 3, the posterior fossa closed by a wall of bone
#: behind the mastoid (``OCCIPITAL_*``, ``PF_TABLE_MM``) so the sinus lies
#: inside the bone. Recordings made on an older generation replay on it
#: (bundled as ``phantom@1``, ``phantom@2``).
GENERATIONS = (1, 2, 3)
LATEST_GENERATION = GENERATIONS[-1]

# ------------------------------------------------------------ outer cortex
# The bone's outer shape is the zero level of a smooth signed distance field
# [mm] (negative in bone): a smooth union of the parts below, then the saw
# cut. Solids are (centre, semi-axes) ellipsoids or (base, apex) round cones
# with radii (base, apex); positions in the case frame [mm]. Proportions
# from adult anatomy: bony meatus 8-10 mm high, 6-8 mm wide; mastoid tip
# 1.5-2 cm below the canal; spine of Henle 1-2 mm; squama a few mm thick.
CORE_CENTER_MM = (0.0, 2.0, -1.0)      # petromastoid core (medial, mostly hidden;
CORE_SEMI_MM = (17.0, 22.0, 19.0)      # the fossae carve its top and back)
TEGMEN_CENTER_MM = (1.5, 0.0, 10.0)    # roof of the core: the middle fossa's
TEGMEN_SEMI_MM = (16.5, 22.5, 4.5)     # floor (the fossa carves all above it)
PETROUS_AXIS_MM = ((-3.0, -5.0, 0.0), (-20.0, -16.5, 2.0))   # pyramid, to the apex
PETROUS_RADII_MM = (8.0, 4.5)
MASTOID_CENTER_MM = (9.5, 5.0, -1.0)   # mastoid part: a lens whose convex
MASTOID_SEMI_MM = (10.65, 19.5, 12.5)   # lateral face is the mastoid cortex
MASTOID_TIP_AXIS_MM = ((9.5, 2.0, -9.0), (13.5, -1.0, -21.0))  # process: down, forward
MASTOID_TIP_RADII_MM = (9.5, 3.4)      # tip 1.5-2 cm below the ear canal
TYMPANIC_CENTER_MM = (8.0, -12.0, -3.0)  # tympanic part around canal and middle ear
TYMPANIC_SEMI_MM = (11.0, 7.5, 7.5)
OCCIPITAL_CENTER_MM = (2.0, 18.0, 0.0)  # bone behind the mastoid (occipital and
OCCIPITAL_SEMI_MM = (14.0, 14.0, 21.0)  # mastoid parts over the sinus); the posterior
                                       # fossa is carved out of it, leaving a table
SQUAMA_POINT_MM = (18.0, -6.0, 8.0)    # a point of the squama's lateral face
SQUAMA_RADIUS_MM = 90.0                # curvature of that face (slightly convex)
SQUAMA_OUTLINE_MM = ((-4.0, 3.0), (20.5, 21.0))  # (y, z) centre and semi-axes
SQUAMA_BASE_Z_MM = 3.0                 # its lower border (at the zygomatic root)
ZYGOMA_ROOT_CENTER_MM = (18.0, -16.5, 3.8)  # root of the zygomatic process:
ZYGOMA_ROOT_SEMI_MM = (2.6, 6.0, 3.8)       # broad, above the canal
ZYGOMA_CENTER_MM = (19.5, -28.0, 3.5)  # the process, running forward;
ZYGOMA_SEMI_MM = (2.0, 15.0, 3.8)      # cut off at ANTERIOR_CUT_Y_MM
ANTERIOR_CUT_Y_MM = -24.5              # the specimen's anterior saw cut
TEMPORAL_LINE_YZ_MM = ((-9.5, 4.5), (-4.0, 6.5), (3.0, 8.0), (10.0, 9.0),
                       (16.0, 9.5))        # supramastoid crest on the cortex
TEMPORAL_LINE_RADII_MM = (1.6, 1.0)    # ridge half-width, from front to back
TEMPORAL_LINE_HEIGHT_MM = 2.0          # how far the crest stands out
EAC_OPENING_SEMI_MM = (3.3, 4.6)       # bony meatus: half-width (y), half-height (z)
EAC_OVAL_FROM_X_MM = 13.0              # the canal is oval lateral to this x
EAC_RIM_X_MM = 19.0                    # lateral rim of the bony meatus
EAC_WALL_MM = 1.8                      # its wall (tympanic ring) around the opening
EAC_COLLAR_MM = 4.0                    # depth of that collar below the rim
HENLE_ANGLE_DEG = 50.0                 # spine's place on the rim, up from posterior
HENLE_SPINE_MM = (2.5, 1.0)            # spine of Henle: length, base radius
HENLE_DIRECTION = (1.0, -0.3, -0.3)    # it points out, a little forward and down
ROUGH_MM = 0.2                         # relief of the mastoid cortex (amplitude)
ROUGH_WAVELENGTHS_MM = (3.0, 7.0)      # range of its bumps
ROUGH_WAVES = 24                       # plane waves summed for the relief
ROUGH_SEED = 1010                      # fixed: the shape does not depend on the seed
ROUGH_REGION_MM = (12.0, -8.0, 8.0)    # relief lateral of x, behind y, below z,
ROUGH_FADE_MM = 3.0                    # fading in over this distance
BLEND_MM = 3.0                         # fillet between the large parts
ROOT_BLEND_MM = 2.0                    # fillet of the zygoma, meatus, squama's base
FEATURE_BLEND_MM = 1.0                 # fillet of the crest and rims

# ----------------------------------------------------------- cranial fossae
TEGMEN_Z_MM = 11.0             # floor of the middle fossa
SQUAMA_MM = 3.0                # lateral bony plate above the tegmen
PF_POINT_MM = (0.0, 12.0, 0.0)  # a point on the posterior fossa's bony wall
PF_NORMAL = (-1.0, 1.2, 0.0)   # points into the posterior fossa (posteromedial)
PF_TABLE_MM = 3.0              # bony wall kept between the fossa and the outside
MF_TABLE_Y_MM = 13.0           # the middle fossa keeps that wall too behind this y
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


# ------------------------------------------------------- distance primitives
# Signed distances [mm], negative inside; x, y, z broadcastable float arrays.

def _sd_ellipsoid(x, y, z, c, r):
    """Ellipsoid of centre ``c`` and semi-axes ``r`` (close to a true
    distance near the surface)."""
    px, py, pz = (x - c[0]) / r[0], (y - c[1]) / r[1], (z - c[2]) / r[2]
    k0 = np.sqrt(px * px + py * py + pz * pz)
    k1 = np.sqrt((px / r[0]) ** 2 + (py / r[1]) ** 2 + (pz / r[2]) ** 2)
    return np.where(k1 > 0, k0 * (k0 - 1.0) / np.where(k1 > 0, k1, 1.0), -min(r))


def _sd_ellipse(u, v, c, r):
    """Infinite elliptic cylinder: the ellipse of centre ``c`` and semi-axes
    ``r`` in the (u, v) plane."""
    pu, pv = (u - c[0]) / r[0], (v - c[1]) / r[1]
    k0 = np.sqrt(pu * pu + pv * pv)
    k1 = np.sqrt((pu / r[0]) ** 2 + (pv / r[1]) ** 2)
    return np.where(k1 > 0, k0 * (k0 - 1.0) / np.where(k1 > 0, k1, 1.0), -min(r))


def _sd_round_cone(x, y, z, a, b, ra, rb):
    """Exact distance to the hull of the spheres (``a``, ``ra``) and (``b``, ``rb``)."""
    bax, bay, baz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    l2 = bax * bax + bay * bay + baz * baz
    rr = ra - rb
    a2 = l2 - rr * rr
    il2 = 1.0 / l2
    px, py, pz = x - a[0], y - a[1], z - a[2]
    t = px * bax + py * bay + pz * baz
    u = t - l2
    qx, qy, qz = px * l2 - bax * t, py * l2 - bay * t, pz * l2 - baz * t
    x2 = qx * qx + qy * qy + qz * qz
    y2 = t * t * l2
    z2 = u * u * l2
    k = np.sign(rr) * rr * rr * x2
    side = np.sqrt(np.maximum(x2 * a2 * il2, 0.0)) + t * rr
    return np.where(np.sign(u) * a2 * z2 > k, np.sqrt(x2 + z2) * il2 - rb,
                    np.where(np.sign(t) * a2 * y2 < k, np.sqrt(x2 + y2) * il2 - ra,
                             side * il2 - ra))


def _smin(a, b, k):
    """Smooth union: the minimum with a fillet of radius ``k`` [mm]."""
    if k <= 1e-9:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smax(a, b, k):
    """Smooth intersection (maximum with a fillet of radius ``k`` [mm])."""
    return -_smin(-a, -b, k)


# ------------------------------------------------------------- outer cortex

_SQUAMA_CENTRE = (SQUAMA_POINT_MM[0] - SQUAMA_RADIUS_MM, *SQUAMA_POINT_MM[1:])


def _squama_depth(x, y, z):
    """Depth [mm] medial to the squama's lateral face (a sphere, convex outward)."""
    c = _SQUAMA_CENTRE
    return SQUAMA_RADIUS_MM - np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)


def _sd_squama(x, y, z, inner_mm):
    """The squama: a plate from its lateral face to ``inner_mm`` medial of it,
    within its outline in the (y, z) plane."""
    d = _squama_depth(x, y, z)
    plate = np.abs(d - 0.5 * inner_mm) - 0.5 * inner_mm
    (cy, cz), (sy, sz) = SQUAMA_OUTLINE_MM
    outline = _smax(_sd_ellipse(y, z, (cy, cz), (sy, sz)), SQUAMA_BASE_Z_MM - z,
                    ROOT_BLEND_MM)
    return _smax(plate, outline, FEATURE_BLEND_MM)


def _sd_zygoma(x, y, z):
    """The zygomatic process: its broad root and the process running forward."""
    return _smin(_sd_ellipsoid(x, y, z, ZYGOMA_ROOT_CENTER_MM, ZYGOMA_ROOT_SEMI_MM),
                 _sd_ellipsoid(x, y, z, ZYGOMA_CENTER_MM, ZYGOMA_SEMI_MM), ROOT_BLEND_MM)


def _bbox_ellipsoid(c, r):
    """(lo, hi) corners [mm] of an ellipsoid's bounding box."""
    return np.subtract(c, r), np.add(c, r)


def _bbox_cone(a, b, ra, rb):
    """(lo, hi) corners [mm] of a round cone's bounding box."""
    rmax = max(ra, rb)
    return np.minimum(a, b) - rmax, np.maximum(a, b) + rmax


def _base_parts(inner_mm=SQUAMA_MM, generation=LATEST_GENERATION):
    """The large parts, each (distance function of x, y, z, bounding box lo,
    hi [mm], fillet [mm] with the parts before it); the squama is
    ``inner_mm`` thick; the occipital part from generation 3 on."""
    (cy, cz), (sy, sz) = SQUAMA_OUTLINE_MM
    sq_x = SQUAMA_POINT_MM[0]
    zr_lo, zr_hi = _bbox_ellipsoid(ZYGOMA_ROOT_CENTER_MM, ZYGOMA_ROOT_SEMI_MM)
    zp_lo, zp_hi = _bbox_ellipsoid(ZYGOMA_CENTER_MM, ZYGOMA_SEMI_MM)
    return [
        (lambda x, y, z: _sd_ellipsoid(x, y, z, CORE_CENTER_MM, CORE_SEMI_MM),
         *_bbox_ellipsoid(CORE_CENTER_MM, CORE_SEMI_MM), 0.0),
        (lambda x, y, z: _sd_ellipsoid(x, y, z, TEGMEN_CENTER_MM, TEGMEN_SEMI_MM),
         *_bbox_ellipsoid(TEGMEN_CENTER_MM, TEGMEN_SEMI_MM), BLEND_MM),
        (lambda x, y, z: _sd_round_cone(x, y, z, *PETROUS_AXIS_MM, *PETROUS_RADII_MM),
         *_bbox_cone(*PETROUS_AXIS_MM, *PETROUS_RADII_MM), BLEND_MM),
        (lambda x, y, z: _sd_ellipsoid(x, y, z, MASTOID_CENTER_MM, MASTOID_SEMI_MM),
         *_bbox_ellipsoid(MASTOID_CENTER_MM, MASTOID_SEMI_MM), BLEND_MM),
        (lambda x, y, z: _sd_ellipsoid(x, y, z, TYMPANIC_CENTER_MM, TYMPANIC_SEMI_MM),
         *_bbox_ellipsoid(TYMPANIC_CENTER_MM, TYMPANIC_SEMI_MM), BLEND_MM),
        (lambda x, y, z: _sd_round_cone(x, y, z, *MASTOID_TIP_AXIS_MM, *MASTOID_TIP_RADII_MM),
         *_bbox_cone(*MASTOID_TIP_AXIS_MM, *MASTOID_TIP_RADII_MM), BLEND_MM),
        (lambda x, y, z: _sd_squama(x, y, z, inner_mm),
         np.array([sq_x - inner_mm - (sy * sy + sz * sz) / SQUAMA_RADIUS_MM, cy - sy, cz - sz]),
         np.array([sq_x, cy + sy, cz + sz]), BLEND_MM),
        (_sd_zygoma, np.minimum(zr_lo, zp_lo), np.maximum(zr_hi, zp_hi), BLEND_MM),
    ] + ([(lambda x, y, z: _sd_ellipsoid(x, y, z, OCCIPITAL_CENTER_MM, OCCIPITAL_SEMI_MM),
           *_bbox_ellipsoid(OCCIPITAL_CENTER_MM, OCCIPITAL_SEMI_MM), BLEND_MM)]
         if generation >= 3 else [])


def _eval_points(parts, x, y, z):
    """Smooth union of ``parts`` at points (broadcastable arrays)."""
    f = np.full(np.broadcast(x, y, z).shape, 1e3)
    for fn, _, _, k in parts:
        f = _smin(f, fn(x, y, z), k)
    return np.maximum(f, ANTERIOR_CUT_Y_MM - y)


def _surface_x(parts, y, z, x_lo=-26.0, x_hi=26.0):
    """x [mm] of the most lateral zero of the field of ``parts`` in the
    columns (y, z) [mm] (arrays); NaN where a column misses the shape."""
    y = np.atleast_1d(np.asarray(y, float))[:, None]
    z = np.atleast_1d(np.asarray(z, float))[:, None]
    xs = np.arange(x_hi, x_lo, -0.25)[None, :]
    f = _eval_points(parts, xs, y, z)
    inside = f <= 0
    hit = inside.any(axis=1)
    i = np.argmax(inside, axis=1)
    lo = xs[0, i]                               # inside
    hi = xs[0, np.maximum(i - 1, 0)]            # outside
    for _ in range(30):                         # bisection to ~1e-8 mm
        mid = 0.5 * (lo + hi)
        f = _eval_points(parts, mid[:, None], y, z)[:, 0]
        lo, hi = np.where(f <= 0, mid, lo), np.where(f <= 0, hi, mid)
    return np.where(hit, 0.5 * (lo + hi), np.nan)


def _polyline_on_cortex(yz, radii, height, generation=LATEST_GENERATION):
    """3-D path of a ridge that stands ``height`` [mm] out of the cortex along
    the (y, z) points ``yz``: tube centres ``radius - height`` below it."""
    yz = np.asarray(yz, float)
    r = np.interp(np.arange(len(yz)), [0, len(yz) - 1], radii)
    x = _surface_x(_base_parts(generation=generation), yz[:, 0], yz[:, 1]) + height - r
    return np.column_stack([x, yz]), r


@functools.lru_cache(maxsize=len(GENERATIONS))
def _ridge(generation):
    """The temporal line's tube centres and radii on a generation's cortex."""
    return _polyline_on_cortex(TEMPORAL_LINE_YZ_MM, TEMPORAL_LINE_RADII_MM,
                               TEMPORAL_LINE_HEIGHT_MM, generation)
_EAC_C = EAC_AXIS_MM[0][1:]                        # (y, z) of the canal's axis
_HENLE_BASE = np.array([
    EAC_RIM_X_MM - 0.5 * HENLE_SPINE_MM[1],
    _EAC_C[0] + (EAC_OPENING_SEMI_MM[0] + 0.5 * EAC_WALL_MM) * np.cos(np.radians(HENLE_ANGLE_DEG)),
    _EAC_C[1] + (EAC_OPENING_SEMI_MM[1] + 0.5 * EAC_WALL_MM) * np.sin(np.radians(HENLE_ANGLE_DEG))])
_HENLE_TIP = _HENLE_BASE + HENLE_SPINE_MM[0] * (np.asarray(HENLE_DIRECTION)
                                               / np.linalg.norm(HENLE_DIRECTION))


def _sd_meatus(x, y, z):
    """The bony meatus: a collar of wall ``EAC_WALL_MM`` around the canal's
    lateral end, its rounded rim in the plane x = ``EAC_RIM_X_MM``."""
    sy, sz = EAC_OPENING_SEMI_MM
    w = EAC_WALL_MM
    ring = _sd_ellipse(y, z, _EAC_C, (sy + w, sz + w))
    half = 0.5 * EAC_COLLAR_MM
    return _smax(ring, np.abs(x - (EAC_RIM_X_MM - half)) - half, FEATURE_BLEND_MM)


def _feature_parts(generation=LATEST_GENERATION):
    """Small parts on the cortex, as :func:`_base_parts`: the temporal line,
    the bony meatus and the spine of Henle."""
    parts = []
    ridge_pts, ridge_r = _ridge(generation)
    for i in range(len(ridge_pts) - 1):
        a, b = tuple(ridge_pts[i]), tuple(ridge_pts[i + 1])
        ra, rb = float(ridge_r[i]), float(ridge_r[i + 1])
        parts.append((lambda x, y, z, a=a, b=b, ra=ra, rb=rb:
                      _sd_round_cone(x, y, z, a, b, ra, rb),
                      *_bbox_cone(a, b, ra, rb), FEATURE_BLEND_MM))
    sy, sz = EAC_OPENING_SEMI_MM
    w = EAC_WALL_MM
    parts.append((_sd_meatus,
                  np.array([EAC_RIM_X_MM - EAC_COLLAR_MM, _EAC_C[0] - sy - w, _EAC_C[1] - sz - w]),
                  np.array([EAC_RIM_X_MM, _EAC_C[0] + sy + w, _EAC_C[1] + sz + w]),
                  ROOT_BLEND_MM))
    a, b = tuple(_HENLE_BASE), tuple(_HENLE_TIP)
    r0 = HENLE_SPINE_MM[1]
    parts.append((lambda x, y, z: _sd_round_cone(x, y, z, a, b, r0, 0.25 * r0),
                  *_bbox_cone(a, b, r0, r0), 0.5 * FEATURE_BLEND_MM))
    return parts


def _roughness(x, y, z):
    """Relief of the mastoid cortex [mm]: a fixed sum of plane waves, faded
    out away from the mastoid's lateral face (behind the canal, below the
    temporal line)."""
    rng = np.random.default_rng(ROUGH_SEED)
    d = rng.normal(size=(ROUGH_WAVES, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lam = rng.uniform(*ROUGH_WAVELENGTHS_MM, size=ROUGH_WAVES)
    phase = rng.uniform(0, 2 * np.pi, size=ROUGH_WAVES)
    s = 0.0
    for (dx, dy, dz), l, p in zip(d, lam, phase):
        s = s + np.cos((2 * np.pi / l) * (dx * x + dy * y + dz * z) + p)
    x0, y0, z0 = ROUGH_REGION_MM
    w = (np.clip((x - x0) / ROUGH_FADE_MM, 0, 1) * np.clip((y - y0) / ROUGH_FADE_MM, 0, 1)
         * np.clip((z0 - z) / ROUGH_FADE_MM, 0, 1))
    return (ROUGH_MM * np.sqrt(2.0 / ROUGH_WAVES)) * w * s      # unit-variance sum


def _cortex_field(cv: "Canvas", inner_mm=SQUAMA_MM, relief: bool = True,
                  generation=LATEST_GENERATION) -> np.ndarray:
    """Signed distance [mm] to the outer shape on the grid (float32), the
    squama ``inner_mm`` thick, with the mastoid's relief or without.

    Each part is evaluated in its bounding box grown by more than any fillet,
    so the zero level is the one :func:`_eval_points` gives everywhere.
    """
    f = np.full(cv.shape, 1e3, dtype=np.float32)
    pad = 2 * max(BLEND_MM, ROOT_BLEND_MM, FEATURE_BLEND_MM) + cv.h
    for fn, lo, hi, k in _base_parts(inner_mm, generation) + _feature_parts(generation):
        b = cv.box(np.asarray(lo) - pad, np.asarray(hi) + pad)
        if b is None:
            continue
        sl, x, y, z = b
        f[sl] = _smin(f[sl], fn(x, y, z), k)
    x0, y0, z0 = ROUGH_REGION_MM
    far = 1e3
    b = cv.box((x0, y0, -far), (far, far, z0)) if relief else None
    if b is not None:                  # the relief can only move the surface
        sl, x, y, z = b                # where |f| is below its largest value
        sub = f[sl]
        near = np.abs(sub) <= ROUGH_MM * np.sqrt(2.0 * ROUGH_WAVES)
        xs, ys, zs = (np.broadcast_to(v, sub.shape)[near] for v in (x, y, z))
        sub[near] += _roughness(xs, ys, zs).astype(np.float32)
    sl, x, y, z = cv.full()
    return np.maximum(f, ANTERIOR_CUT_Y_MM - y)


def lateral_surface_x_mm(y_mm: float, z_mm: float) -> float:
    """The outer cortex's most lateral point in a (y, z) column.

    Parameters
    ----------
    y_mm, z_mm : float
        Position of the column in the case frame [mm].

    Returns
    -------
    float
        x [mm] of the smooth outer shape there: without the mastoid's relief
        (``ROUGH_MM`` RMS) and before the ear canal, the fossae and the air
        spaces are carved; NaN where the column misses the bone.
    """
    return float(_surface_x(_base_parts() + _feature_parts(), y_mm, z_mm)[0])


def _on_cortex(y, z):
    """The point of the smooth lateral face in the column (y, z) [mm]."""
    return (lateral_surface_x_mm(y, z), float(y), float(z))


LANDMARKS_MM = {
    "mastoid_cortex": _on_cortex(4.0, -3.0),
    "antrum": ANTRUM_CENTER_MM,
    "facial_second_genu": FACIAL_PATH_MM[1],
    "facial_mastoid_mid": tuple(float(v) for v in _point_on_path(FACIAL_PATH_MM, -8.0)),
    "sigmoid_sinus_lateral": (SINUS_PATH_MM[2][0] + SINUS_RADIUS_MM,
                              *SINUS_PATH_MM[2][1:]),   # lateral wall of the sinus
    "lateral_canal": SCC_MM["lateral"][0],
    "eac_medial_end": EAC_AXIS_MM[1],
    # the outer cortex, as a surgeon sees it from lateral
    "eac_opening": (EAC_RIM_X_MM, *_EAC_C),        # centre of the meatus, rim plane
    "henle_spine": tuple(float(v) for v in _HENLE_TIP),            # its tip
    "mastoid_tip": (MASTOID_TIP_AXIS_MM[1][0], MASTOID_TIP_AXIS_MM[1][1],
                    MASTOID_TIP_AXIS_MM[1][2] - MASTOID_TIP_RADII_MM[1]),  # lowest point
    "temporal_line": _on_cortex(-1.0, float(np.interp(     # crest top above the antrum
        -1.0, *np.transpose(TEMPORAL_LINE_YZ_MM)))),
    "zygomatic_root": ZYGOMA_ROOT_CENTER_MM,                       # inside it
    "squama": _on_cortex(SQUAMA_POINT_MM[1], TEGMEN_Z_MM + 8.0),   # its lateral face
}
"""Named points for trajectory generators (case frame, mm)."""


def _envelope(cv: Canvas, generation=LATEST_GENERATION):
    """Bone shape, middle-fossa and posterior-fossa masks and dura layers."""
    # the squama counts DURA_MM thicker so that its inner face carries dura
    field = _cortex_field(cv, SQUAMA_MM + DURA_MM, generation=generation)
    shape = field <= 0
    sl, x, y, z = cv.full()
    above = z - TEGMEN_Z_MM                                 # > 0 above the tegmen
    medial = _squama_depth(x, y, z) - SQUAMA_MM             # > 0 medial to squama
    # from generation 3 the posterior fossa stops PF_TABLE_MM inside the outer
    # shape (the skull's wall behind the mastoid, which covers the sinus); so
    # does the middle fossa within the occipital part, behind the squama
    closed = generation >= 3
    occipital = (_sd_ellipsoid(x, y, z, OCCIPITAL_CENTER_MM, OCCIPITAL_SEMI_MM)
                 <= PF_TABLE_MM) & (y > MF_TABLE_Y_MM) & closed
    to_table = np.where(occipital, -PF_TABLE_MM - field, np.inf)   # > 0 inside it
    table = to_table > 0
    mid = (above > 0) & (medial > 0) & table
    mid_depth = np.minimum(np.minimum(above, medial), to_table)
    n = np.asarray(PF_NORMAL, float)
    n /= np.linalg.norm(n)
    q = np.asarray(PF_POINT_MM, float)
    pf_depth = (x - q[0]) * n[0] + (y - q[1]) * n[1] + (z - q[2]) * n[2]
    to_wall = -PF_TABLE_MM - field if closed else np.inf   # > 0 deeper than the wall
    post = (pf_depth > 0) & (to_wall > 0)
    mid_dura = shape & mid & (mid_depth <= DURA_MM)
    post_dura = shape & post & (np.minimum(pf_depth, to_wall) <= DURA_MM) & ~mid
    envelope = shape & ~mid & ~post
    return envelope, mid_dura, post_dura


def _ear_canal(cv: Canvas, mask):
    """The external auditory canal: round medially, widening to the oval
    bony meatus laterally (semi-axes ``EAC_OPENING_SEMI_MM`` from the rim)."""
    (x0, y0, z0), (x1, _, _) = EAC_AXIS_MM
    cv.capsule(mask, (EAC_OVAL_FROM_X_MM, y0, z0), EAC_AXIS_MM[1], EAC_RADIUS_MM)
    sy, sz = EAC_OPENING_SEMI_MM
    b = cv.box((EAC_OVAL_FROM_X_MM, y0 - max(sy, EAC_RADIUS_MM), z0 - sz),
               (x0, y0 + max(sy, EAC_RADIUS_MM), z0 + sz))
    if b is None:
        return
    sl, x, y, z = b
    t = np.clip((x - EAC_OVAL_FROM_X_MM) / (EAC_RIM_X_MM - EAC_OVAL_FROM_X_MM), 0.0, 1.0)
    ry = EAC_RADIUS_MM + (sy - EAC_RADIUS_MM) * t
    rz = EAC_RADIUS_MM + (sz - EAC_RADIUS_MM) * t
    mask[sl] |= ((y - y0) / ry) ** 2 + ((z - z0) / rz) ** 2 <= 1.0


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
                  size_mm=DEFAULT_SIZE_MM, generation: int = LATEST_GENERATION
                  ) -> PhantomParts:
    """Generate the phantom's part masks and intensities.

    Parameters
    ----------
    seed : int
        Seed of ``numpy.random.default_rng`` (air cells, bone texture).
    voxel_mm : float
        Isotropic voxel edge [mm].
    size_mm : (3,) float
        Grid extent ``(x, y, z)`` [mm], centred on the frame origin.
    generation : int
        Which shape (:data:`GENERATIONS`; default the latest). Generation 1
        is built by the frozen :mod:`bonesim.io.phantom_v1`.

    Returns
    -------
    PhantomParts
        For generation 1, :class:`bonesim.io.phantom_v1.PhantomParts` (the
        same fields).
    """
    if not voxel_mm > 0:
        raise ValueError(f"voxel_mm must be positive, got {voxel_mm}")
    if generation not in GENERATIONS:
        raise ValueError(f"phantom generation {generation!r} is not one of {GENERATIONS}")
    if generation == _v1.GENERATION:
        return _v1.build_phantom(seed, voxel_mm, size_mm)
    shape = np.maximum(1, np.round(np.asarray(size_mm, float) / voxel_mm)).astype(int)
    cv = Canvas(shape, voxel_mm)
    rng = np.random.default_rng(seed)

    envelope, mid_dura, post_dura = _envelope(cv, generation)

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
    _ear_canal(cv, ear)
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


#: Most bytes of phantom volumes (labels and HU) :func:`phantom_volume`
#: keeps for the process's later calls [bytes]: the default 0.5 mm phantom
#: holds 5.6 MB, a native 0.19 mm one 103 MB (built in about 5 s); a 0.1 mm
#: one (700 MB) is built again each time instead.
CACHED_BYTES_MAX = 160 * 2 ** 20
#: How many such volumes it keeps (the least recently used goes first).
CACHED_VOLUMES = 4


def _volume_bytes(vol: CaseVolume) -> int:
    return vol.labels.nbytes + (0 if vol.hu is None else vol.hu.nbytes)


_volumes = Recent(CACHED_VOLUMES, max_bytes=CACHED_BYTES_MAX, nbytes=_volume_bytes)


def phantom_volume(seed: int = DEFAULT_SEED, voxel_mm: float = DEFAULT_VOXEL_MM,
                   size_mm=DEFAULT_SIZE_MM, structures=PARTS,
                   generation: int = LATEST_GENERATION) -> CaseVolume:
    """The phantom as a :class:`~bonesim.io.volumes.CaseVolume`.

    The phantom is a function of the arguments alone: volumes of up to
    :data:`CACHED_BYTES_MAX` together are built once per process and each call
    returns its own copy of the arrays (a cohort of sessions, a plan and its
    runs load the same phantom many times).

    Parameters
    ----------
    seed, voxel_mm, size_mm, generation
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
    key = (int(seed), float(voxel_mm), tuple(float(v) for v in np.broadcast_to(
        np.asarray(size_mm, float), 3)), tuple(structures), int(generation))
    vol = _volumes.get(key)
    if vol is None:
        vol = _phantom_volume(seed, voxel_mm, size_mm, structures, generation)
        if not _volumes.put(key, vol):
            return vol                              # too large to keep: this one is its own
    return CaseVolume(vol.labels.copy(), vol.spacing_mm, vol.origin_mm.copy(), vol.source,
                      None if vol.hu is None else vol.hu.copy())


def _phantom_volume(seed, voxel_mm, size_mm, structures, generation) -> CaseVolume:
    """:func:`phantom_volume`, built."""
    if generation == _v1.GENERATION:
        return _v1.phantom_volume(seed, voxel_mm, size_mm, structures)
    parts = build_phantom(seed, voxel_mm, size_mm, generation)
    labels = np.zeros(parts.hu.shape, dtype=np.uint8)
    hu = parts.hu
    for s, name in enumerate(structures, start=1):
        labels[parts.masks[name]] = s
    omitted = [p for p in PARTS if p not in structures]
    for name in omitted:
        hu[parts.masks[name]] = HU_AIR
    src = f"procedural left temporal-bone phantom (seed {seed}, generation {generation})"
    return CaseVolume(labels, parts.spacing_mm, parts.origin_mm, src, hu)
