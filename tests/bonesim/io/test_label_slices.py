"""Mapping one label slice to structure indices (bonesim.io.label_slices)
against a slow reference."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.io import label_slices as LS

COLORS = [(255, 255, 255), (0, 0, 255), (200, 200, 0)]


def table_of(colors):
    table = np.full(LS.TABLE_SIZE, LS.UNKNOWN, dtype=np.uint16)
    table[0] = 0
    for s, (r, g, b) in enumerate(colors, start=1):
        table[(r << 16) | (g << 8) | b] = s
    return table


def reference(px, colors):
    """Pixel by pixel: index of the colour, 0 for black, transparent or unknown."""
    rows, cols, depth = px.shape
    out = np.zeros((cols, rows), np.uint8)
    unknown = 0
    for r in range(rows):
        for c in range(cols):
            rgb = tuple(int(v) for v in px[r, c, :3])
            if (depth == 4 and px[r, c, 3] == 0) or rgb == (0, 0, 0):
                continue
            if rgb in colors:
                out[c, r] = colors.index(rgb) + 1
            else:
                unknown += 1
    return out, unknown


def random_slice(rng, rows, cols, depth, stray=True):
    palette = np.array([(0, 0, 0)] + COLORS + ([(1, 2, 3)] if stray else []), np.uint8)
    px = palette[rng.integers(0, len(palette), size=(rows, cols))]
    if depth == 4:
        alpha = np.where(rng.random((rows, cols)) < 0.2, 0, 255).astype(np.uint8)
        px = np.concatenate([px, alpha[..., None]], axis=2)
    return px


@pytest.mark.parametrize("depth", [3, 4])
@pytest.mark.parametrize("plane", ["c", "transposed", "reversed"])
def test_map_slice_matches_the_reference(depth, plane):
    rng = np.random.default_rng(depth)
    px = random_slice(rng, 7, 5, depth)
    vol = np.full((3, 7, 5), 99, np.uint8)
    out = {"c": np.full((5, 7), 99, np.uint8),
           "transposed": np.full((7, 5), 99, np.uint8).T,
           "reversed": vol[1, ::-1, ::-1].T}[plane]       # a plane of a volume, flipped
    want, unknown = reference(px, COLORS)
    px.flags.writeable = False                            # as Pillow hands it over
    assert LS.map_slice(px, table_of(COLORS), out) == unknown > 0
    np.testing.assert_array_equal(out, want)
    if plane == "reversed":
        assert (vol[0] == 99).all() and (vol[2] == 99).all()   # only its own plane


def test_map_slice_checks_its_arrays():
    table = table_of(COLORS)
    px = np.zeros((4, 3, 3), np.uint8)
    with pytest.raises(ValueError, match="px"):
        LS.map_slice(np.zeros((4, 3, 2), np.uint8), table, np.zeros((3, 4), np.uint8))
    with pytest.raises(ValueError, match="table"):
        LS.map_slice(px, table[:10], np.zeros((3, 4), np.uint8))
    with pytest.raises(ValueError, match=r"out must be \(3, 4\)"):
        LS.map_slice(px, table, np.zeros((4, 3), np.uint8))
    ro = np.zeros((3, 4), np.uint8)
    ro.flags.writeable = False
    with pytest.raises(ValueError, match="writeable"):
        LS.map_slice(px, table, ro)
    LS.warmup()
