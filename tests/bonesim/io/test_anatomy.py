"""Names, palette and neighbours (bonesim.io.anatomy); the automatic surgical view
(bonesim.io.surgical_view) and the cortex it is read on (bonesim.io.landmarks)."""
from __future__ import annotations

import colorsys
import dataclasses
import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import cdist

from bonesim.io import anatomy as A
from bonesim.io import phantom as P
from bonesim.io import surgical_view as V
from bonesim.io.landmarks import find_canal_pits, find_landmarks, lateral_height_map
from bonesim.io.case import load_case
from bonesim.errors import BonesimError
from tests.bonesim.fakes import BONE

TABLE = A.load_table()


# ------------------------------------------------------------------ names
@pytest.mark.parametrize("name, cls", [
    ("facial_nerve", "facial_nerve"), ("Facial Nerve", "facial_nerve"),
    ("FacialNerve", "facial_nerve"), ("facial", "facial_nerve"),
    ("n. VII", "facial_nerve"), ("CN VII", "facial_nerve"), ("cn7", "facial_nerve"),
    ("N_VII", "facial_nerve"), ("Nervus facialis", "facial_nerve"),
    ("chorda_tympani", "chorda_tympani"), ("Chorda", "chorda_tympani"),
    ("sup. vestibular n.", "vestibular_nerve"), ("Cochlear_Nerve", "cochlear_nerve"),
    ("CN VIII", "vestibulocochlear_nerve"), ("greater petrosal nerve", "nerve"),
    ("Cochlea", "cochlea"), ("LSC", "labyrinth"), ("semicircular canals", "labyrinth"),
    ("Sigmoid Sinus", "sigmoid_sinus"), ("sinus", "sigmoid_sinus"),
    ("sinus tympani", "middle_ear"), ("facial recess", "middle_ear"),
    ("superior petrosal sinus", "vein"), ("Jugular bulb", "jugular_bulb"),
    ("ICA", "carotid_artery"), ("Carotid", "carotid_artery"), ("a. carotis", "artery"),
    ("Stapes", "stapes"), ("malleus", "malleus"), ("Incus", "incus"),
    ("ossicles", "ossicles"), ("EAC", "ear_canal"), ("external acoustic meatus",
                                                      "ear_canal"),
    ("IAC", "internal_auditory_canal"), ("Tegmen", "middle_fossa_dura"),
    ("MFD", "middle_fossa_dura"), ("posterior fossa dura", "posterior_fossa_dura"),
    ("Dura", "dura"), ("mastoid air cells", "middle_ear"), ("Mastoid", "bone"),
    ("temporal_bone", "bone"), ("TM", "tympanic_membrane"), ("Otic capsule",
                                                             "otic_capsule"),
])
def test_classify_names(name, cls):
    got = A.classify(name)
    assert got is not None and got.id == cls, (name, got)


def test_unknown_names_and_normalisation():
    assert A.classify("thing 42") is None and A.classify("") is None
    assert A.normalize_name("Facial_Nerve") == ("facial", "nerve")
    assert A.normalize_name("n. VII") == ("nerve", "7")
    assert A.normalize_name("CN7") == ("cranial", "nerve", "7")
    assert A.normalize_name("7th nerve") == ("7", "nerve")
    assert A.default_kind("thing 42") == "critical"        # unknown: kept safe
    assert A.default_kind("Sigmoid sinus") == "soft" and A.default_kind("Bone") == "bone"


@pytest.mark.parametrize("name, kind, watched, available", [
    ("facial_nerve", "critical", True, True), ("Chorda tympani", "critical", True, True),
    ("n. VII", "critical", True, True), ("FN", "critical", True, True),
    # nerves of the internal auditory canal and others: listed, off
    ("vestibular nerve", "critical", False, True), ("cochlear nerve", "critical", False, True),
    ("CN VIII", "critical", False, True), ("optic nerve", "soft", False, True),
    ("cochlea", "critical", False, False), ("sigmoid_sinus", "soft", False, False),
    ("ICA", "critical", False, False), ("nerve canal", "bone", False, False),
])
def test_monitor_defaults(name, kind, watched, available):
    """A mastoidectomy's monitor watches the facial nerve and the chorda
    tympani; the other nerves can be watched but are off by default."""
    assert A.default_monitor(name, kind) is watched
    assert A.monitor_available(name, kind) is available


def _hue_deg(rgb):
    return 360.0 * colorsys.rgb_to_hsv(*(np.asarray(rgb) / 255.0))[0]


def test_palette_is_anatomical_and_fixes_the_reported_case():
    """The names of the user's case that drew the facial nerve white, the
    carotid yellow, the chorda in bone colour and the stapes in sinus blue."""
    c = {n: A.default_color(n, A.default_kind(n)) for n in
         ("Bone", "Facial Nerve", "Carotid", "Chorda tympani", "Stapes", "Sigmoid sinus",
          "Middle fossa dura", "Labyrinth", "Jugular bulb")}
    assert 40 <= _hue_deg(c["Facial Nerve"]) <= 65                  # yellow
    assert _hue_deg(c["Carotid"]) <= 15 or _hue_deg(c["Carotid"]) >= 345   # red
    assert 200 <= _hue_deg(c["Sigmoid sinus"]) <= 250               # blue
    assert 200 <= _hue_deg(c["Jugular bulb"]) <= 250
    assert 260 <= _hue_deg(c["Labyrinth"]) <= 300                   # purple
    h, s, v = colorsys.rgb_to_hsv(*(np.asarray(c["Middle fossa dura"]) / 255.0))
    assert (h * 360 <= 20 or h * 360 >= 330) and 0.1 <= s <= 0.4    # pink-grey
    assert c["Bone"] == (235, 225, 200)                             # ivory
    for a, b in [("Chorda tympani", "Bone"), ("Stapes", "Sigmoid sinus"),
                 ("Facial Nerve", "Bone"), ("Carotid", "Facial Nerve"),
                 ("Facial Nerve", "Chorda tympani"), ("Stapes", "Bone")]:
        assert A.delta_e(c[a], c[b]) >= TABLE.min_delta_e, (a, b)


def test_table_errors_name_file_and_field(tmp_path):
    text = A.default_table_path().read_text()
    bad = tmp_path / "anatomy.toml"
    bad.write_text(text.replace('role = "sinus"', 'role = "lake"'))
    with pytest.raises(BonesimError, match="'role' must be one of") as e:
        A.load_table(bad)
    assert e.value.field == "classes.sigmoid_sinus" and str(bad) in str(e.value)
    bad.write_text(text.replace("min_delta_e = 15.0", "min_delta_e = -1"))
    with pytest.raises(BonesimError, match="'min_delta_e' must be >="):
        A.load_table(bad)


# ------------------------------------------------------------- neighbours
def _neighbours_reference(labels, n, spacing, within):
    pts = {s: np.argwhere(labels == s) * spacing for s in range(1, n + 1)}
    out = np.zeros((n, n), bool)
    for a, b in itertools.combinations(range(1, n + 1), 2):
        if len(pts[a]) and len(pts[b]):
            near = cdist(pts[a], pts[b]).min() <= spacing + within + 1e-9
            out[a - 1, b - 1] = out[b - 1, a - 1] = near
    return out


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.integers(1, 5), st.sampled_from([0.0, 0.5, 1.5]))
def test_neighbours_match_brute_force(seed, n, within):
    rng = np.random.default_rng(seed)
    labels = np.zeros((9, 8, 7), np.uint8)
    for s in range(1, n + 1):                 # a few random boxes per structure
        for _ in range(rng.integers(1, 3)):
            lo = rng.integers(0, [8, 7, 6])
            hi = lo + rng.integers(1, 3, size=3)
            labels[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = s
    got = A.neighbours(labels, n, 0.5, within)
    np.testing.assert_array_equal(got, _neighbours_reference(labels, n, 0.5, within))
    assert not got.diagonal().any() and (got == got.T).all()


def test_neighbours_analytic_gap():
    labels = np.zeros((20, 3, 3), np.uint8)
    labels[2, 1, 1] = 1
    labels[6, 1, 1] = 2          # centres 2 mm apart: a 1.5 mm gap at 0.5 mm voxels
    assert A.neighbours(labels, 2, 0.5, 1.5)[0, 1]
    assert not A.neighbours(labels, 2, 0.5, 1.4)[0, 1]
    labels[6, 1, 1] = 0
    labels[3, 1, 1] = 2          # touching faces
    assert A.neighbours(labels, 2, 0.5, 0.0)[0, 1]


# ---------------------------------------------------------------- colours
_START = [(235, 225, 200), (236, 226, 201), (40, 90, 230), (45, 92, 228),
          (255, 215, 0), (250, 210, 5)]


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 6).flatmap(lambda n: st.tuples(
    st.just(n),
    st.lists(st.sampled_from(A.COLOR_SOURCES), min_size=n, max_size=n),
    st.lists(st.sampled_from(_START), min_size=n, max_size=n),
    st.lists(st.booleans(), min_size=n * n, max_size=n * n))))
def test_resolve_colors_invariants(case):
    n, sources, colors, bits = case
    adj = np.array(bits, bool).reshape(n, n)
    adj = (adj | adj.T) & ~np.eye(n, dtype=bool)
    cands = [list(TABLE.fallback)] * n
    out = A.resolve_colors(colors, sources, cands, adj, TABLE.min_delta_e)
    order = sorted(range(n), key=lambda s: (A.COLOR_SOURCES.index(sources[s]), s))
    for s in range(n):
        if sources[s] == "manifest":
            assert out[s] == colors[s]                     # never changed
        else:
            assert out[s] == colors[s] or out[s] in cands[s]
    for a, b in itertools.combinations(range(n), 2):
        if not adj[a, b] or A.delta_e(out[a], out[b]) >= TABLE.min_delta_e:
            continue
        later = a if order.index(a) > order.index(b) else b
        assert sources[later] == "manifest" or not any(
            all(A.delta_e(c, out[t]) >= TABLE.min_delta_e
                for t in order[:order.index(later)] if adj[later, t])
            for c in [colors[later]] + cands[later]), "an avoidable clash was left"
    # colours that clash with no neighbour are kept
    lone = [s for s in range(n) if not adj[s].any()]
    assert all(out[s] == colors[s] for s in lone)


def test_resolve_colors_changes_the_weaker_source():
    adj = np.array([[0, 1], [1, 0]], bool)
    same = [(40, 90, 230), (40, 90, 230)]
    out = A.resolve_colors(same, ["palette", "label"], [[(255, 0, 0)], [(0, 255, 0)]],
                           adj, 15.0)
    assert out == [(255, 0, 0), (40, 90, 230)]        # the label colour wins
    out = A.resolve_colors(same, ["manifest", "manifest"], [[], []], adj, 15.0)
    assert out == same                                  # the user's choice stands
    with pytest.raises(ValueError, match="colour source"):
        A.resolve_colors(same, ["palette", "guess"], [[], []], adj, 15.0)


# ------------------------------------------------------------ height map
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.sampled_from(["left", "right"]))
def test_lateral_height_map_matches_loop(seed, side):
    rng = np.random.default_rng(seed)
    mask = rng.random((6, 5, 4)) < 0.3
    origin = rng.normal(size=3) * 10
    got = lateral_height_map(mask, 0.5, origin, side)
    lat = 1.0 if side == "left" else -1.0
    for j in range(5):
        for k in range(4):
            xs = [origin[0] + 0.5 * i for i in range(6) if mask[i, j, k]]
            if xs:
                assert got[j, k] == pytest.approx(max(lat * x for x in xs))
            else:
                assert math.isnan(got[j, k])


def test_canal_pit_of_a_drilled_slab():
    h = np.full((80, 80), 10.0)                 # a flat cortex, 0.5 mm columns
    j, k = np.mgrid[:80, :80]
    hole = (j - 30.0) ** 2 + (k - 50.0) ** 2 <= 8.0 ** 2     # r = 4 mm
    h[hole] = -5.0
    pits = find_canal_pits(h, 0.5, 9.0, 4.0, 8.0, 400.0)
    assert len(pits) == 1
    p = pits[0]
    assert p["j"] == pytest.approx(30, abs=0.01) and p["k"] == pytest.approx(50, abs=0.01)
    assert p["area_mm2"] == pytest.approx(math.pi * 16, rel=0.05)
    assert p["depth_mm"] == pytest.approx(15.0)
    assert find_canal_pits(h, 0.5, 9.0, 20.0, 8.0, 400.0) == []   # not that deep


# ------------------------------------------------------------ the view
@pytest.fixture(scope="module")
def phantom():
    c = load_case("phantom")
    vol = c.load_volume()
    return c, vol


def _mirror(labels, origin):
    """The phantom mirrored left-right: a right ear in LPS."""
    o = np.array(origin, float)
    o[0] = -(o[0] + (labels.shape[0] - 1) * 0.5)
    return np.ascontiguousarray(labels[::-1]), o


def _unnamed(structures, drop):
    """The structures, those of the anatomical classes ``drop`` renamed so
    that their names read as nothing."""
    return [dataclasses.replace(s, name=f"structure {i}", anatomy="")
            if s.anatomy in drop else s for i, s in enumerate(structures, start=1)]


def _view(c, labels, origin, side, structures=None, **params):
    structures = c.structures if structures is None else structures
    return V.surgical_view(labels, 0.5, origin, structures, side, params=params or None)


def _marks(c, labels, origin, side, structures=None):
    return find_landmarks(labels, 0.5, origin, c.structures if structures is None
                          else structures, side)


def assert_looks_at_mastoid(view, labels, origin, side):
    """The view of a mastoidectomy on the phantom (landmarks of bonesim.io.phantom,
    mirrored for a right ear): from lateral, onto the cortex behind and above
    the canal, in front of the sinus, below the tegmen, superior up."""
    lat = 1.0 if side == "left" else -1.0
    eye, focal, up = (np.array(v) for v in (view.eye_mm, view.focal_mm, view.up))
    d = (focal - eye) / np.linalg.norm(focal - eye)
    assert -d[0] * lat >= math.cos(math.radians(30.5))          # looks medially
    assert up[2] > 0.85 and abs(up @ d) < 1e-9                  # superior up
    bone = np.argwhere(labels == 1) * 0.5 + origin
    assert lat * eye[0] > (lat * bone[:, 0]).max() + 50         # well outside the bone
    canal_y, canal_z = P.EAC_AXIS_MM[0][1], P.EAC_AXIS_MM[0][2]
    assert focal[1] > canal_y + P.EAC_RADIUS_MM                 # behind the canal
    assert canal_z < focal[2] < P.TEGMEN_Z_MM                   # above it, below tegmen
    sinus_front = min(p[1] for p in P.SINUS_PATH_MM[1:4]) - P.SINUS_RADIUS_MM
    assert focal[1] < sinus_front                               # in front of the sinus
    # on the cortex: bone just medial of the focal point, none lateral
    ijk = np.round((focal - origin) / 0.5).astype(int)
    col = labels[:, ijk[1], ijk[2]] == 1
    xs = origin[0] + 0.5 * np.flatnonzero(col)
    assert abs((lat * xs).max() - lat * focal[0]) <= 1.0
    # over the antrum (Macewen's triangle): within the demo's 9 mm disc
    antrum = np.array(P.ANTRUM_CENTER_MM)
    assert math.hypot(focal[1] - antrum[1], focal[2] - antrum[2]) < 9.0


@pytest.mark.parametrize("side", ["left", "right"])
def test_view_looks_at_the_mastoid_for_both_sides(phantom, side):
    c, vol = phantom
    labels, origin = (vol.labels, vol.origin_mm) if side == "left" else \
        _mirror(vol.labels, vol.origin_mm)
    view = _view(c, labels, origin, side)
    assert_looks_at_mastoid(view, labels, origin, side)
    assert "air channel" in _marks(c, labels, origin, side).get("ear_canal").source
    np.testing.assert_allclose(view.landmarks["canal"], P.EAC_AXIS_MM[0][1:], atol=0.5)
    assert view.landmarks["tegmen"][1] == pytest.approx(P.TEGMEN_Z_MM, abs=0.5)
    if side == "right":                      # the mirror image of the left view
        left = _view(c, vol.labels, vol.origin_mm, "left")
        np.testing.assert_allclose(view.focal_mm, np.array(left.focal_mm) * [-1, 1, 1],
                                   atol=1e-9)


def test_view_fallbacks(phantom):
    c, vol = phantom
    # a labelled canal: the phantom's canal air painted as a structure
    labels = vol.labels.copy()
    a, b = np.array(P.EAC_AXIS_MM)
    pts = np.stack(np.meshgrid(*[vol.origin_mm[i] + 0.5 * np.arange(n)
                                 for i, n in enumerate(vol.shape)], indexing="ij"), -1)
    t = np.clip(((pts - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
    r = np.linalg.norm(pts - (a + t[..., None] * (b - a)), axis=-1)
    canal = (r <= P.EAC_RADIUS_MM) & (labels == 0) & (pts[..., 0] > 9)
    labels[canal] = 8                                   # reuse index 8 as "EAC"
    eac = list(c.structures[:7]) + [dataclasses.replace(c.structures[7], name="EAC",
                                                        kind="soft", anatomy="ear_canal")]
    view = _view(c, labels, vol.origin_mm, "left", eac)
    assert _marks(c, labels, vol.origin_mm, "left", eac).get("ear_canal").confidence \
        == "labelled"
    assert_looks_at_mastoid(view, vol.labels, vol.origin_mm, "left")
    # no sinus, no dura: fixed offsets from the canal
    bare = _unnamed(c.structures, ("sigmoid_sinus", "middle_fossa_dura",
                                   "posterior_fossa_dura"))
    view = _view(c, vol.labels, vol.origin_mm, "left", bare)
    assert any("no sinus" in n for n in view.notes)
    assert _marks(c, vol.labels, vol.origin_mm, "left", bare).get("tegmen").confidence \
        == "estimated"
    assert_looks_at_mastoid(view, vol.labels, vol.origin_mm, "left")
    # no canal opening (filled with bone), no ossicles: the middle ear is gone,
    # the view falls back to the bone's lateral face, still lateral and on bone
    filled = vol.labels.copy()
    envelope = P.build_phantom(c.volume.seed, 0.5, c.volume.size_mm).envelope
    filled[canal & envelope] = 1
    none = _unnamed(c.structures, ("ossicles",))
    view = _view(c, filled, vol.origin_mm, "left", none)
    assert any("no ear canal found" in n for n in view.notes)
    eye, focal = np.array(view.eye_mm), np.array(view.focal_mm)
    assert (eye - focal)[0] > 0 and focal[2] < P.TEGMEN_Z_MM
    # no canal opening but ossicles: the canal lies lateral to the middle ear
    view = _view(c, filled, vol.origin_mm, "left")
    assert "lateral to the middle ear" in _marks(c, filled, vol.origin_mm, "left") \
        .get("ear_canal").source
    assert_looks_at_mastoid(view, filled, vol.origin_mm, "left")


def test_view_input_errors(phantom):
    c, vol = phantom
    with pytest.raises(ValueError, match="no bone"):
        _view(c, np.zeros((4, 4, 4), np.uint8), (0, 0, 0), "left")
    with pytest.raises(ValueError, match="side"):
        _view(c, vol.labels, vol.origin_mm, "middle")


@pytest.mark.parametrize("face_deg, view_deg", [(5.0, 0.0), (20.0, 20.0), (50.0, 30.0)])
def test_view_follows_a_turned_cortex_within_limits(face_deg, view_deg):
    """A block whose lateral face is turned posteriorly by ``face_deg``: the view
    follows its normal, straight lateral under snap_tilt_deg (10), at most
    max_tilt_deg (30) from lateral."""
    n = np.array([math.cos(math.radians(face_deg)), math.sin(math.radians(face_deg)), 0])
    g = (np.arange(64) - 31.5) * 0.5
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    bone = (x * n[0] + y * n[1] <= 4.0) & (np.abs(y) < 12) & (np.abs(z) < 12) & (x > -14)
    labels = bone.astype(np.uint8)
    view = V.surgical_view(labels, 0.5, (g[0],) * 3, [BONE], "left")
    d = np.subtract(view.focal_mm, view.eye_mm)
    d /= np.linalg.norm(d)
    assert math.degrees(math.acos(-d[0])) == pytest.approx(view_deg, abs=1.0)
    assert d[1] <= 1e-12 and abs(d[2]) < 1e-9          # turned toward posterior only
    assert np.linalg.norm(np.subtract(view.eye_mm, view.focal_mm)) == pytest.approx(100)
    focal = np.array(view.focal_mm)
    assert focal @ n == pytest.approx(4.0, abs=0.5)     # on the face
