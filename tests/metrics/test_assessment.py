"""The final-product assessment on scripted products of the phantom: the
planned mastoidectomy scores full marks, and each edit that violates or
leaves undone one item changes exactly the items it was built to change."""
from __future__ import annotations

import math

import numpy as np
import pytest

from tests.metrics import assessment_runs as R


@pytest.fixture(scope="module")
def ph():
    return R.phantom()


@pytest.fixture(scope="module")
def planned():
    return R.planned_present()


@pytest.fixture(scope="module")
def base(ph, planned):
    return ph.assess(planned)


@pytest.fixture(scope="module")
def lumen(ph):
    from metrics.assessment import structure_masks

    return structure_masks(ph.labels, ph.h, ph.origin, ph.structures, ph.lm)["ear_canal"]


def _changed(base, other) -> dict:
    return {it.name: it.outcome for it in other.items
            if it.score != base.item(it.name).score}


def test_planned_mastoidectomy_scores_full_marks(base):
    from metrics.assessment_items import load_scale

    assert [it.name for it in base.items] == [it.name for it in load_scale().items]
    # every item applies to the phantom, and the plan performs every one
    assert all(it.score == 2 and it.outcome == "done" for it in base.items), \
        {it.name: (it.outcome, it.quantities) for it in base.items if it.score != 2}
    assert base.total == base.max_total == 2 * len(base.items)
    q = base.item("sigmoid_sinus").quantities
    assert 0.0 < q["thinnest_mm"] <= 1.0 and q["exposed_mm2"] == 0.0
    assert base.item("antrum").quantities["opening_mm2"] >= 4.0
    assert base.item("saucerization").quantities["hidden_wall_share"] < 0.05


@pytest.mark.parametrize("run, targets", [
    ("expose_sinus", {"sigmoid_sinus": "violated"}),
    ("enter_sinus", {"sigmoid_sinus": "violated", "sinus_intact": "violated"}),
    ("overhang", {"saucerization": "missed"}),
    ("short_of_antrum", {"antrum": "missed"}),
    ("perforate_canal", {"posterior_canal_wall": "violated"}),
    ("thick_tegmen", {"tegmen": "missed"}),
    ("drill_facial_nerve", {"facial_nerve": "violated"}),
    ("drill_chorda", {"chorda_tympani": "violated"}),
    ("open_labyrinth", {"lateral_canal": "violated", "labyrinth": "violated"}),
])
def test_each_violation_changes_exactly_its_items(ph, planned, base, lumen, run, targets):
    present = {
        "expose_sinus": lambda: R.expose_sinus(planned),
        "enter_sinus": lambda: R.expose_sinus(planned, enter=True),
        "overhang": lambda: R.overhang(planned),
        "short_of_antrum": lambda: R.short_of_antrum(planned),
        "perforate_canal": lambda: R.perforate_canal(planned, lumen),
        "thick_tegmen": lambda: R.planned_present("middle_fossa_dura", 2.5),
        "drill_facial_nerve": lambda: R.drill_into(planned, "facial_nerve"),
        "drill_chorda": lambda: R.drill_into(planned, "chorda_tympani"),
        "open_labyrinth": lambda: R.drill_into(planned, "labyrinth"),
    }[run]()
    assert not np.array_equal(present, planned)
    a = ph.assess(present)
    assert _changed(base, a) == targets
    for name in targets:
        it = a.item(name)
        assert it.score == 0
        assert it.advice.endswith(".") and it.advice != base.item(name).advice
        assert len(it.region_mm), f"{name}: no region to mark"


def test_violation_measurements(ph, planned, lumen):
    a = ph.assess(R.expose_sinus(planned))
    assert a.item("sigmoid_sinus").quantities["exposed_mm2"] > 1.0
    assert a.item("sinus_intact").quantities["removed_mm3"] == 0.0
    a = ph.assess(R.overhang(planned))
    q = a.item("saucerization").quantities
    assert q["overhang_mm3"] > 100.0 or q["hidden_wall_share"] > 0.15
    a = ph.assess(R.planned_present("middle_fossa_dura", 2.5))
    assert a.item("tegmen").quantities["thinnest_mm"] > 2.0
    a = ph.assess(R.perforate_canal(planned, lumen))
    assert a.item("posterior_canal_wall").quantities["exposed_mm2"] > 0.5
    a = ph.assess(R.drill_into(planned, "facial_nerve"))
    assert a.item("facial_nerve").quantities["removed_mm3"] > 0.0


def test_nothing_drilled(ph):
    a = ph.assess(ph.tissue0)
    assert a.removed_mm3 == 0.0
    intact = {"facial_nerve", "chorda_tympani", "sinus_intact", "dura_intact", "labyrinth"}
    for it in a.items:
        assert it.outcome == ("done" if it.name in intact else "missed"), it.name
    assert a.total == 10 and a.max_total == 28


def test_checklist_and_json(base, ph, planned):
    import json

    from metrics.assessment import checklist

    lines = checklist(ph.assess(R.expose_sinus(planned)))
    assert lines[0].startswith("final product: 26 of 28")
    assert len(lines) == 1 + len(base.items)
    sinus = next(ln for ln in lines if "Sigmoid sinus thinned" in ln)
    assert "[0/2] violated" in sinus and "exposed" in sinus and "mm^2" in sinus
    d = json.loads(json.dumps(base.as_dict()))
    assert d["total"] == 28 and d["items"][0]["name"] == "saucerization"


def test_assessment_row(base):
    from metrics.assessment import assessment_row

    row = assessment_row(base)
    assert row["assess_total"] == 28 and row["assess_max"] == 28
    assert row["assess_share"] == 1.0
    assert row["assess_antrum"] == 2.0 and len(row) == 3 + len(base.items)


def test_not_applicable_without_structures(ph, planned):
    """A case without a chorda or labyrinth label: those items do not apply
    and leave the total."""
    from metrics.assessment import assess_tissue

    keep = [s for s, st in enumerate(ph.structures, start=1)
            if st.name not in ("chorda_tympani", "labyrinth")]
    lut = np.zeros(256, np.uint8)
    for new, old in enumerate(keep, start=1):
        lut[old] = new
    labels = lut[ph.labels]
    labels[(ph.labels > 0) & (labels == 0)] = 1          # they become bone
    sts = [ph.structures[s - 1] for s in keep]
    a = assess_tissue(labels, planned | ((labels > 0) & (ph.labels == 0)), ph.h, ph.origin,
                      sts, ph.lm, ph.eye)
    na = {it.name for it in a.items if it.score is None}
    assert na == {"chorda_tympani", "labyrinth", "lateral_canal"}
    assert all(it.why for it in a.items if it.score is None)
    assert a.max_total == 2 * (len(a.items) - len(na))


def test_merged_label_export_scores(tmp_path):
    """A peer-style export (sinus and dura in one label, cropped through the
    sinus, PNG slices) loads and scores without error; its sinus and tegmen
    are split from the merged label and assessed."""
    from bonesim.io.case import load_case
    from metrics.assessment import assess_tissue, checklist
    from tests.bonesim.real_like import write_real_like

    path = write_real_like(tmp_path / "peer", merged=True, crop_mm=((-26, -26, -26),
                                                                   (26, 16, 26)))
    case = load_case(path)
    vol = case.load_volume()
    lm = case.landmarks
    c = np.asarray(lm.point("antrum"))
    ijk = np.indices(vol.labels.shape).reshape(3, -1).T
    centres = (vol.origin_mm + vol.spacing_mm * ijk).reshape(vol.labels.shape + (3,))
    # a cavity: a ball under Macewen's triangle down to the antrum
    m = np.asarray(lm.point("macewen"))
    axis = (c - m) / np.linalg.norm(c - m)
    rel = centres - m
    t = rel @ axis
    off = rel - t[..., None] * axis
    cone = (t >= -2) & (t <= np.linalg.norm(c - m)) & \
        (np.sum(off ** 2, axis=3) <= (6.0 - 0.3 * np.clip(t, 0, None)) ** 2)
    kinds = np.array([False] + [s.kind == "bone" for s in case.structures])
    present = (vol.labels > 0) & ~(cone & kinds[vol.labels])
    a = assess_tissue(vol.labels, present, vol.spacing_mm, vol.origin_mm, case.structures,
                      lm, case.camera.eye_mm, case=case.name)
    assert a.removed_mm3 > 100.0
    assert len(checklist(a)) == 1 + len(a.items)
    scored = {it.name for it in a.items if it.score is not None}
    assert {"tegmen", "sigmoid_sinus", "antrum", "saucerization", "facial_nerve",
            "dura_intact", "sinus_intact"} <= scored
    assert a.item("antrum").score >= 1
    for it in a.items:
        assert it.score is None or all(isinstance(v, float) for v in it.quantities.values())


def test_bad_scale_is_one_line(tmp_path):
    from bonesim.errors import BonesimError
    from metrics.assessment_items import load_scale
    from bonesim.resources import data_path

    text = data_path("assessment.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('quantity = "overhang_mm3"', 'quantity = "overhang_m3"'))
    with pytest.raises(BonesimError) as e:
        load_scale(bad)
    msg = str(e.value)
    assert "bad.toml" in msg and "items.saucerization.criteria[0]" in msg and "\n" not in msg
    bad.write_text(text.replace("done = 0.05\npartial = 0.15", "done = 0.15\npartial = 0.05"))
    with pytest.raises(BonesimError, match="worse side"):
        load_scale(bad)


def test_criterion_scoring():
    from metrics.assessment_items import Criterion, Item, Violation

    lo = Criterion("gap_mm", "lower", 1.0, 2.0)
    assert [lo.score(v) for v in (0.5, 1.0, 1.5, 2.5, math.inf, float("nan"))] == \
        [2, 2, 1, 0, 0, 0]
    hi = Criterion("opening_mm2", "higher", 4.0, 1.0)
    assert [hi.score(v) for v in (5.0, 4.0, 2.0, 0.5)] == [2, 2, 1, 0]
    it = Item("x", "X", "antrum", "antrum", (lo, hi), (Violation("gap_mm", 10.0),),
              {"done": "d", "partial": "p", "missed": "m", "violated": "v"})
    assert it.score({"gap_mm": 0.5, "opening_mm2": 2.0}) == (1, "partial")
    assert it.score({"gap_mm": 11.0, "opening_mm2": 9.0}) == (0, "violated")
