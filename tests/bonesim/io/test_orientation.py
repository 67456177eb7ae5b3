"""Orientation codes: parsing, reorienting arrays and geometry, exactly."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.io.orientation import (from_lps, image_geometry, lps_geometry,
                                    parse_orientation, to_lps)

ALL_CODES = ["".join(p) for pair in itertools.product("LR", "PA", "SI")
             for p in itertools.permutations(pair)]


def test_there_are_48_codes():
    assert len(set(ALL_CODES)) == 48


@pytest.mark.parametrize("bad, words", [
    ("LP", "three letters"), ("LPSX", "three letters"), ("LPX", "'X' is not one of"),
    ("LLS", "L/R axis more than once"), ("PAS", "P/A axis more than once"),
    (5, "must be a string"), ("", "three letters")])
def test_malformed_codes_name_the_problem(bad, words):
    with pytest.raises(BonesimError, match=words) as e:
        parse_orientation(bad, "case.toml", "volume")
    assert "case.toml" in str(e.value) and "volume" in str(e.value)


def test_lowercase_and_spaces_are_accepted():
    assert parse_orientation(" pls ") == "PLS"


def _naive_to_lps(img, code):
    """Voxel by voxel: image index -> LPS index from the letters."""
    letters = {"L": (0, 1), "R": (0, -1), "P": (1, 1), "A": (1, -1),
               "S": (2, 1), "I": (2, -1)}
    shape = [0, 0, 0]
    for i, ch in enumerate(code):
        shape[letters[ch][0]] = img.shape[i]
    out = np.zeros(shape, img.dtype)
    for idx in np.ndindex(img.shape):
        dst = [0, 0, 0]
        for i, ch in enumerate(code):
            a, s = letters[ch]
            dst[a] = idx[i] if s > 0 else img.shape[i] - 1 - idx[i]
        out[tuple(dst)] = img[idx]
    return out


@pytest.mark.parametrize("code", ALL_CODES)
def test_to_lps_matches_voxelwise_reference_and_inverts(code):
    img = np.arange(2 * 3 * 4, dtype=np.int32).reshape(2, 3, 4)
    lps = to_lps(img, code)
    assert np.array_equal(lps, _naive_to_lps(img, code))
    assert np.array_equal(from_lps(lps, code), img)


@pytest.mark.parametrize("code", ALL_CODES)
def test_geometry_maps_every_voxel_centre(code):
    rng = np.random.default_rng(len(code) + ord(code[0]))
    shape_img = np.array([2, 3, 4])
    sp_img = rng.uniform(0.1, 1.0, 3)
    first = rng.uniform(-5, 5, 3)
    img = np.arange(np.prod(shape_img)).reshape(shape_img)
    lps = to_lps(img, code)
    spacing, origin = lps_geometry(code, shape_img, sp_img, first)
    letters = {"L": (0, 1), "R": (0, -1), "P": (1, 1), "A": (1, -1),
               "S": (2, 1), "I": (2, -1)}
    for idx in np.ndindex(*shape_img):
        # where the image voxel is, walking from the first voxel along the letters
        pos = first.copy()
        for i, ch in enumerate(code):
            a, s = letters[ch]
            pos[a] += s * idx[i] * sp_img[i]
        at = np.argwhere(lps == img[idx])[0]
        assert np.allclose(origin + spacing * at, pos)
    back_sp, back_first = image_geometry(code, lps.shape, spacing, origin)
    assert np.allclose(back_sp, sp_img) and np.allclose(back_first, first)


@pytest.mark.parametrize("code", ["LPS", "PLS", "RAI", "SAL"])
def test_label_stack_round_trip_in_any_orientation(tmp_path, code):
    from bonesim.io.volumes import read_label_stack, write_label_stack

    rng = np.random.default_rng(1)
    labels = rng.integers(0, 3, (5, 6, 7)).astype(np.uint8)
    colors = [(200, 10, 10), (10, 200, 10)]
    write_label_stack(tmp_path, labels, colors, orientation=code)
    spacing_lps = np.array([0.5, 0.25, 0.2])
    sp_img, first = image_geometry(code, labels.shape, spacing_lps, (1.0, 2.0, 3.0))
    n_img = np.array(from_lps(labels, code).shape)
    raw = read_label_stack(tmp_path, "plane*.png", sp_img * n_img, colors,
                           origin_mm=first, orientation=code)
    assert np.array_equal(raw.data, labels)
    assert np.allclose(raw.spacing_mm, spacing_lps)
    assert np.allclose(raw.origin_mm, (1.0, 2.0, 3.0))
