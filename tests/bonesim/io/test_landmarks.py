"""Landmarks of a mastoidectomy in any labelling (bonesim.io.landmarks): the
pooled analysis grid, merged labels split by thickness, and every landmark
on the phantom and on peer-style exports of it (merged, cropped, mirrored,
finer, stored in other axis codes)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bonesim.io import landmarks as L
from bonesim.io import phantom as P
from bonesim.io.case import load_case
from tests.bonesim.fakes import FakeStructure
from tests.bonesim.real_like import write_real_like

CROP_BACK = ((-30.0, -30.0, -30.0), (30.0, 16.0, 30.0))    # the sinus cut by the edge


# ------------------------------------------------------------ analysis grid
def _pool_reference(labels, kinds, f):
    """Per f^3 block: the structure of the highest kind rank, then index."""
    rank = {"critical": 3, "soft": 2, "bone": 1}
    m = [-(-n // f) for n in labels.shape]
    out = np.zeros(m, np.uint8)
    for i in range(m[0]):
        for j in range(m[1]):
            for k in range(m[2]):
                block = labels[i * f:(i + 1) * f, j * f:(j + 1) * f, k * f:(k + 1) * f]
                best = 0
                for s in np.unique(block):
                    if s and (best == 0 or (rank[kinds[s - 1]], s)
                              > (rank[kinds[best - 1]], best)):
                        best = int(s)
                out[i, j, k] = best
    return out


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10 ** 6), st.sampled_from([1, 2, 3]),
       st.tuples(*[st.integers(1, 9)] * 3))
def test_analysis_grid_pools_like_the_reference(seed, f, shape):
    rng = np.random.default_rng(seed)
    kinds = ["bone", "soft", "critical", "bone"]
    labels = rng.integers(0, 5, shape).astype(np.uint8)
    got, h, origin = L.analysis_grid(labels, 0.2, (1.0, 2.0, 3.0), kinds, 0.2 * f)
    np.testing.assert_array_equal(got, _pool_reference(labels, kinds, f))
    assert h == pytest.approx(0.2 * f)
    np.testing.assert_allclose(origin, np.array([1.0, 2.0, 3.0]) + 0.1 * (f - 1))


def test_thin_nerves_survive_pooling():
    labels = np.ones((30, 30, 30), np.uint8)
    labels[:, 14, 14] = 2                                  # a one-voxel nerve
    got, _, _ = L.analysis_grid(labels, 0.1, (0, 0, 0), ["bone", "critical"], 0.5)
    assert got.shape == (6, 6, 6) and (got[:, 2, 2] == 2).all() and (got == 2).sum() == 6


# ------------------------------------------------------------ groups, split
@pytest.mark.parametrize("name, groups", [
    ("Sigmoid sinus and dura", {"sinus", "dura"}), ("Sinus & Dura", {"sinus", "dura"}),
    ("sigmoid_sinus", {"sinus"}), ("Tegmen Dura", {"tegmen", "dura"}),
    ("posterior_fossa_dura", {"dura"}), ("Inner Ear", {"labyrinth"}),
    ("sinus tympani", {"middle_ear"}), ("Facial Nerve", {"facial_nerve"}),
    ("Ossicles", {"middle_ear"}), ("EAC", {"ear_canal"}), ("ICA", {"carotid"}),
    ("chorda tympani", set()), ("S12", set())])
def test_groups_read_from_names(name, groups):
    got, = L.structure_groups([FakeStructure(name, "soft")])
    assert got == groups


def test_bone_is_in_no_group():
    got, = L.structure_groups([FakeStructure("mastoid", "bone")])
    assert got == set()


def test_split_channel_finds_the_tube_not_the_sheet():
    h = 0.5
    g = np.arange(80) * h
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    tube = (x - 20) ** 2 + (y - 20) ** 2 <= 3.5 ** 2                 # radius 3.5 mm
    sheet = (np.abs(z - 30) <= 0.75) & (x < 30)                       # 1.5 mm thick
    mask = tube | sheet
    ch = L.split_channel(mask, h, 1.6, 2.0, 40.0)
    assert (ch & tube).sum() >= 0.97 * tube.sum()                     # the tube back
    far = sheet & ((x - 20) ** 2 + (y - 20) ** 2 > 6.0 ** 2)          # sheet away from it
    assert not (ch & far).any()
    assert not L.split_channel(sheet, h, 1.6, 2.0, 40.0).any()        # a sheet alone
    small = (x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2 <= 2.0 ** 2  # 33 mm^3 ball
    assert not L.split_channel(small, h, 1.6, 2.0, 40.0).any()


# ---------------------------------------------------------------- landmarks
def _landmarks(case_or_path):
    c = case_or_path if not isinstance(case_or_path, (str, type(None))) and \
        hasattr(case_or_path, "structures") else load_case(case_or_path)
    v = c.load_volume()
    return L.find_landmarks(v.labels, v.spacing_mm, v.origin_mm, c.structures, c.side), c


def _mirrored(point, side):
    p = np.asarray(point, float)
    return p * [-1, 1, 1] if side == "right" else p


def assert_phantom_landmarks(lm, side="left", cropped=False):
    """The phantom's landmarks where its generator put them (mirrored for a
    right ear), each with a source and confidence."""
    m = lambda p: _mirrored(p, side)                                     # noqa: E731
    pt = lm.point
    np.testing.assert_allclose(pt("ear_canal")[1:], P.EAC_AXIS_MM[0][1:], atol=0.6)
    assert lm.get("ear_canal").detail["radius_mm"] == pytest.approx(P.EAC_RADIUS_MM,
                                                                    abs=0.6)
    # the antrum: the air space, not an air cell nor the middle ear
    assert np.linalg.norm(pt("antrum") - m(P.ANTRUM_CENTER_MM)) < 1.0
    assert lm.get("antrum").confidence == "found"
    assert 10.0 <= lm.get("antrum").detail["depth_mm"] <= 14.0
    # the lateral canal: the bulge of the lateral semicircular canal
    c, _ = P.SCC_MM["lateral"]
    top = m((c[0] + P.SCC_MAJOR_MM + P.SCC_MINOR_MM, c[1], c[2]))
    assert np.linalg.norm(pt("lateral_canal") - top) < 1.5
    assert pt("tegmen")[2] == pytest.approx(P.TEGMEN_Z_MM, abs=0.6)
    front = pt("sigmoid_sinus")[1]
    band = [q for q in P.SINUS_PATH_MM if abs(q[2] - P.EAC_AXIS_MM[0][2]) <= 8.0]
    assert front < min(q[1] for q in band)                 # in front of the channel's axis
    assert front > P.EAC_AXIS_MM[0][1] + P.EAC_RADIUS_MM + 10.0
    mac = pt("macewen")
    assert P.EAC_AXIS_MM[0][1] < mac[1] < P.EAC_AXIS_MM[0][1] + P.EAC_RADIUS_MM + 0.5
    assert P.EAC_AXIS_MM[0][2] < mac[2] < P.TEGMEN_Z_MM
    assert np.linalg.norm(pt("facial_nerve") - m(P.FACIAL_PATH_MM[1])) < 2.5   # 2nd genu
    for name, lmk in lm.items.items():
        assert lmk.source and lmk.confidence in L.CONFIDENCES, name


def test_phantom_landmarks():
    lm, _ = _landmarks("phantom")
    assert_phantom_landmarks(lm)
    assert lm.get("sigmoid_sinus").confidence == "labelled"
    assert lm.get("tegmen").confidence == "labelled"
    assert not lm.missing


@pytest.mark.parametrize("kw", [
    dict(),                                                          # merged, PIR
    dict(crop_mm=CROP_BACK),                                          # sinus at the edge
    dict(side="right", stored="RAS", declared="RAS"),                # a right ear
    dict(stored="ILA", declared="ILA"),                              # other axes
    dict(voxel_mm=0.25),                                             # finer
    dict(merged=False, stored="LPS", declared=None)])
def test_landmarks_of_peer_exports(tmp_path, kw):
    lm, c = _landmarks(write_real_like(tmp_path, **kw))
    assert_phantom_landmarks(lm, kw.get("side", "left"))
    merged = kw.get("merged", True)
    assert lm.get("sigmoid_sinus").confidence == ("split" if merged else "labelled")
    assert lm.get("tegmen").confidence == ("split" if merged else "labelled")
    if merged:
        assert any("split by thickness" in n for n in lm.notes)


def test_antrum_estimated_when_filled(tmp_path):
    c = load_case("phantom")
    v = c.load_volume()
    labels = v.labels.copy()
    parts = P.build_phantom(c.volume.seed, v.spacing_mm, c.volume.size_mm)
    y = v.origin_mm[1] + v.spacing_mm * np.arange(v.shape[1])
    mastoid = parts.envelope & (y[None, :, None] > -7.0)     # behind the middle ear
    labels[mastoid & (labels == 0)] = 1          # sclerotic: no antrum, no air cells
    lm = L.find_landmarks(labels, v.spacing_mm, v.origin_mm, c.structures, c.side)
    a = lm.get("antrum")
    assert a.confidence == "estimated" and "estimated" in a.source
    # where it must be: deep to Macewen's triangle, lateral to the lateral canal
    assert lm.point("lateral_canal")[0] + 3.5 < a.point_mm[0] < lm.point("macewen")[0] - 8


def test_missing_landmarks_are_said(tmp_path):
    c = load_case("phantom")
    v = c.load_volume()
    anon = [dataclasses.replace(s, name=f"S{i}", anatomy="") if s.kind != "bone" else s
            for i, s in enumerate(c.structures)]
    lm = L.find_landmarks(v.labels, v.spacing_mm, v.origin_mm, anon, c.side)
    text = " ".join(lm.missing)
    assert "sigmoid sinus" in text and "facial nerve" in text and "labyrinth" in text
    assert lm.get("tegmen").confidence == "estimated"
    assert lm.get("ear_canal").confidence == "found"        # the opening in the cortex


def _inside_hull_slow(solid, reach):
    """Cell by cell: along each of the six axis directions, a solid cell at a
    distance of at most ``reach`` cells (the cell itself included)."""
    out = np.zeros(solid.shape, bool)
    for i, j, k in np.ndindex(solid.shape):
        ok = True
        for axis in range(3):
            for sign in (-1, 1):
                seen = False
                for d in range(reach + 1):
                    p = [i, j, k]
                    p[axis] += sign * d
                    if 0 <= p[axis] < solid.shape[axis] and solid[tuple(p)]:
                        seen = True
                        break
                ok &= seen
        out[i, j, k] = ok
    return out


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10 ** 6), st.floats(0.05, 0.6), st.integers(0, 6))
def test_inside_hull_matches_a_cell_by_cell_search(seed, density, reach):
    solid = np.random.default_rng(seed).random((9, 8, 7)) < density
    assert np.array_equal(L.inside_hull(solid, reach), _inside_hull_slow(solid, reach))
