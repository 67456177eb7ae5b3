"""The frozen first phantom (generation 1, ``phantom@1``) builds what the code
at commit 15854c3 built.

The hashes below were taken by running the old code itself, in a detached
worktree of that commit with today's virtual environment:

* labels and HU: at 15854c3, ``bonesim.case.load_case("phantom").load_volume()``
  and ``hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()`` of its
  ``labels`` (uint8) and ``hu`` (float32), 104 x 104 x 104 voxels;
* the model: 15854c3 had no session recorder, so the model hash is the one
  the recorder wrote into the header of a session recorded at e59789d, the
  last commit before the phantom changed (``bonesim/phantom.py`` there is
  byte for byte the one of 15854c3): ``model_sha256`` of the phantom with the
  cutting-5mm burr, oversampling 2, on the scripted device
  (``tests/bonesim/data/sessions/phantom1_schema1.h5``; see the README there).
"""
from __future__ import annotations

import hashlib

import numpy as np
import pytest

from bonesim.io import phantom as P
from bonesim.io import phantom_v1 as V1

LABELS_SHA256 = "22212dd3117cb39fd2bc2f00cb99bfad85b41127dc6817ccbc973666f8377d91"
HU_SHA256 = "756247144d82f5276f8ba03fcd25d9ab4b7543e90cdcdf9d53536be817620e4a"
MODEL_SHA256 = "3905c8250f0bc8d06fc85640ff9b7619fc713167c646a9548bd9df885d0a9f60"
#: voxels per label of that volume (0 = empty, then the manifest's order)
COUNTS = [874650, 211805, 14950, 10164, 11111, 724, 88, 1150, 222]


def _sha(a) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


@pytest.fixture(scope="module")
def case():
    from bonesim.io.case import load_case

    return load_case("phantom@1")


def test_phantom_at_1_is_the_phantom_of_15854c3(case):
    from bonesim.io.case import case_versions

    assert case_versions("phantom") == ["phantom@2", "phantom@1"]
    assert case.name == "phantom" and case.volume.generation == 1
    vol = case.load_volume()
    assert vol.shape == (104, 104, 104) and vol.spacing_mm == 0.5
    np.testing.assert_allclose(vol.origin_mm, [-25.75] * 3)
    assert np.bincount(vol.labels.ravel(), minlength=9).tolist() == COUNTS
    assert _sha(vol.labels) == LABELS_SHA256
    assert vol.hu.dtype == np.float32 and _sha(vol.hu) == HU_SHA256
    # the manifest of that time: the camera was declared, not derived
    cam = case.resolved(vol).camera
    assert cam.eye_mm == (120.0, 3.0, -2.0) and cam.focal_mm == (14.0, 3.0, -2.0)


def test_phantom_at_1_builds_the_recorded_model():
    from bonesim.engine.device_caps import DeviceCaps
    from bonesim.io.burrs import load_burr
    from bonesim.io.loading import load_model
    from bonesim.session.header import model_sha256

    inf = float("inf")
    caps = DeviceCaps("scripted", inf, (inf, inf, inf), inf, 1000.0)
    m = load_model("phantom@1", load_burr("cutting-5mm"), device=caps, oversample=2)
    assert model_sha256(m) == MODEL_SHA256
    # and the latest phantom does not (so the hash tells the versions apart)
    assert model_sha256(load_model("phantom", load_burr("cutting-5mm"), device=caps,
                                   oversample=2)) != MODEL_SHA256


def test_generation_1_goes_to_the_frozen_generator():
    """The current generator hands generation 1 to phantom_v1, with any seed,
    grid and structure list; the first phantom is not the latest one."""
    a = P.phantom_volume(3, 1.0, (40.0, 40.0, 40.0), ("bone", "facial_nerve"), generation=1)
    b = V1.phantom_volume(3, 1.0, (40.0, 40.0, 40.0), ("bone", "facial_nerve"))
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.hu, b.hu)
    assert set(np.unique(a.labels)) == {0, 1, 2}
    parts = P.build_phantom(3, 1.0, (40.0, 40.0, 40.0), generation=1)
    np.testing.assert_array_equal(parts.masks["bone"], V1.build_phantom(3, 1.0, (40.0,) * 3)
                                  .masks["bone"])
    latest = P.build_phantom(3, 1.0, (40.0, 40.0, 40.0))
    assert not np.array_equal(parts.masks["bone"], latest.masks["bone"])
