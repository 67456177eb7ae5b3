"""Side and orientation checked on every axis (bonesim.io.anatomy_frame),
on peer-style exports of the phantom: every flip and permutation, declared and
not, merged labels or not; and the commands that refuse a contradicted case."""
from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest

from bonesim.errors import BonesimError
from bonesim.io.case import load_case
from tests.bonesim.real_like import write_real_like


def check(tmp_path, **kw):
    c = load_case(write_real_like(tmp_path, **kw))
    return c, c.frame_check


@pytest.mark.parametrize("code", ["LPS", "PIR", "RAS", "ILA", "PLS", "LIP", "SAR"])
@pytest.mark.parametrize("merged", [True, False])
def test_declared_codes_agree(tmp_path, code, merged):
    c, fc = check(tmp_path, stored=code, declared=code, merged=merged)
    assert fc.ok, fc.contradictions
    assert c.orientation_problem() == "" and c.require_orientation() == ""


@pytest.mark.parametrize("stored, flipped", [
    ("RPS", "lateral"), ("LAS", "posterior"), ("LPI", "superior"),     # one flip each
    ("RAI", None), ("PIR", None), ("IRP", None), ("SLA", None)])       # several / permuted
def test_undeclared_flips_are_refused_with_the_fitting_code(tmp_path, stored, flipped):
    c, fc = check(tmp_path, stored=stored, declared=None)
    assert not fc.ok
    assert fc.fitting_code == stored
    assert fc.other_side == (flipped == "lateral")
    if flipped:
        assert len(fc.contradictions) == 1 and flipped in fc.contradictions[0]
    with pytest.raises(BonesimError) as err:
        c.require_orientation()
    msg = str(err.value)
    assert f'orientation = "{stored}"' in msg and "--accept-orientation" in msg
    assert str(c.manifest) in msg and "\n" not in msg
    assert c.require_orientation(accept=True) == c.orientation_problem() != ""


def test_wrongly_declared_upside_down_stack(tmp_path):
    """The issue's PLI stack declared PLS (the S/I letter wrong)."""
    c, fc = check(tmp_path, stored="PLI", declared="PLS")
    assert not fc.ok and fc.fitting_code == "PLI"
    assert "superior" in c.orientation_problem()


def test_mirrored_ear_and_the_wrong_side(tmp_path):
    # a right ear declared left: lateral contradicts, both fixes named
    c, fc = check(tmp_path, side="right", stored="LPS", declared="LPS")
    assert fc.ok                                   # as written: a correct right ear
    wrong = dataclasses.replace(c, side="left")
    fc = wrong.frame_check
    assert not fc.ok and fc.other_side and fc.fitting_code == "RPS"
    assert 'side = "right"' in wrong.orientation_problem()


def test_a_correct_left_ear_with_a_merged_label_is_not_misread(tmp_path):
    """The combined sinus-and-dura label's centre lies in front of the canal;
    split, its channel lies behind: no P/A warning."""
    c, fc = check(tmp_path, stored="PIR", declared="PIR", crop_mm=((-30, -30, -30),
                                                                     (30, 16, 30)))
    assert fc.ok and "posterior" not in fc.unchecked


def test_unchecked_directions_are_said(tmp_path):
    c = load_case(write_real_like(tmp_path, stored="LPS", declared="LPS"))
    keep = [dataclasses.replace(s, name=f"S{i}", anatomy="")
            if s.name in ("Sigmoid sinus and dura", "Facial Nerve") else s
            for i, s in enumerate(c.structures)]
    c2 = dataclasses.replace(c, structures=tuple(keep))
    fc = c2.frame_check
    assert fc.ok and "posterior" in fc.unchecked and "superior" in fc.unchecked


def test_commands_refuse_an_undeclared_flip(tmp_path):
    manifest = write_real_like(tmp_path, stored="LPI", declared=None)
    for cmd in (["demo", "--case", str(manifest), "--out", str(tmp_path / "d")],
                ["trajectory", "--case", str(manifest), "--out", str(tmp_path / "t.csv")],
                ["run", "--offscreen", "--case", str(manifest), "--seconds", "1"]):
        r = subprocess.run([sys.executable, "-m", "bonesim.cli", *cmd],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode != 0, (cmd, r.stdout, r.stderr)
        assert 'orientation = "LPI"' in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = subprocess.run([sys.executable, "-m", "bonesim.cli", "trajectory", "--case",
                        str(manifest), "--out", str(tmp_path / "t.csv"),
                        "--accept-orientation"], capture_output=True, text=True,
                       timeout=300)
    assert "LPI" in r.stderr                          # said, then drilled as declared
