"""The demo mastoidectomy (bonesim.io.mastoid_plan via bonesim.io.toolpath):
a cavity a surgeon would drill, on the phantom and on peer-style exports of it
(merged sinus-and-dura label, cropped at the sinus and the tip, a right ear,
each flip declared), with its margins at the source resolution, the volume's
edge left alone, and rinses between passes.

What the plan cuts is checked geometrically: every bone voxel whose centre a
drilling burr's sphere reaches (:func:`swept`, the plan's intent, independent
of the engine's density model); the phantom's main job, through the engine,
removes that bone (``tests/bonesim/render/test_mastoidectomy_images.py``).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from bonesim.errors import BonesimError
from bonesim.io.burrs import load_burr
from bonesim.io.case import load_case
from bonesim.io.mastoid_plan import danger_groups
from bonesim.io.toolpath import (DemoPlan, default_plan_path, demo_trajectory,
                                 load_demo_plan, plan_mastoidectomy)
from tests.bonesim.real_like import write_real_like

PLAN = load_demo_plan()
CROP = ((-30.0, -30.0, -17.0), (30.0, 20.0, 30.0))   # behind the sinus, the tip


# ----------------------------------------------------------------- helpers
def box_clearance(points, labels, spacing, origin, group, reach):
    """Reference, independent of bonesim.physics.clearance: the distance [mm] from
    each point to the nearest box of a voxel in ``group`` (every voxel of the
    map, each the box of its spacing), exact up to ``reach`` (beyond: inf)."""
    spacing = np.broadcast_to(np.asarray(spacing, float), (3,))
    centres = np.asarray(origin) + spacing * np.argwhere(np.isin(labels, group))
    if not len(centres):
        return np.full(len(points), np.inf)
    tree = cKDTree(centres)
    half_diag = np.linalg.norm(spacing) / 2
    out = np.full(len(points), np.inf)
    near = np.isfinite(tree.query(points, distance_upper_bound=reach + half_diag)[0])
    for q in np.flatnonzero(near):
        c = centres[tree.query_ball_point(points[q], reach + half_diag)]
        gap = np.maximum(np.abs(points[q] - c) - spacing / 2, 0.0)
        out[q] = min(np.sqrt((gap ** 2).sum(-1)).min(), out[q])
    return out


def swept(shape, spacing, origin, traj, radii):
    """Voxels whose centre lies in the sphere of a drilling burr at some
    sample of ``traj`` (radius ``radii[burr]``) [bool, the grid's shape]:
    a centre is cut when the nearest drilling sample of that burr lies within
    the radius (a k-d tree of the samples, queried at every centre of the box
    the spheres span)."""
    cut = np.zeros(shape, bool)
    on = np.flatnonzero(traj.drill)
    origin = np.asarray(origin, float)
    for b, r in enumerate(radii):
        pts = traj.pos_mm[on[traj.burr[on] == b]]
        if not len(pts):
            continue
        lo = np.maximum(np.floor((pts.min(0) - r - origin) / spacing).astype(int), 0)
        hi = np.minimum(np.ceil((pts.max(0) + r - origin) / spacing).astype(int) + 1,
                        shape)
        if np.any(hi <= lo):
            continue
        ijk = np.stack(np.meshgrid(*[np.arange(a, z) for a, z in zip(lo, hi)],
                                   indexing="ij"), -1).reshape(-1, 3)
        # the nearest sample, when it lies within r (the bound is exclusive)
        d, _ = cKDTree(pts).query(origin + spacing * ijk,
                                  distance_upper_bound=np.nextafter(r, np.inf))
        sel = ijk[np.isfinite(d)]
        cut[sel[:, 0], sel[:, 1], sel[:, 2]] = True
    return cut


def planned(case):
    pr = plan_mastoidectomy(case, "cutting-5mm")
    radii = [load_burr(b).radius_mm for b in pr.burrs]
    return pr, radii


def cavity_report(case, pr, radii):
    """What the plan cuts, as a surgeon would check it."""
    vol = case.load_volume()
    lm = case.landmarks
    h, o = vol.spacing_mm, vol.origin_mm
    kinds = np.array(["none"] + [s.kind for s in case.structures])
    bone = (kinds == "bone")[vol.labels]
    cut = swept(vol.labels.shape, h, o, pr.trajectory, radii) & bone
    grid = np.stack(np.meshgrid(*[o[a] + h * np.arange(n) for a, n in
                                  enumerate(vol.shape)], indexing="ij"), -1)
    # the volume's faces are h/2 beyond the outermost centres
    edge = np.min(np.stack([np.minimum(grid[..., a] - (o[a] - h / 2),
                                       o[a] + h * (n - 0.5) - grid[..., a])
                            for a, n in enumerate(vol.shape)]), axis=0)
    masks = lm.masks                                        # on the analysis grid

    def near(group, within):
        m = masks.get(group)
        if m is None:
            return 0
        assert m.shape == vol.labels.shape                  # 0.5 mm: the same grid
        d = ndimage.distance_transform_edt(~m, sampling=h)
        return int((cut & (d <= within)).sum())

    mac = lm.point("macewen")
    at_mac = bone & (np.linalg.norm(grid - mac, axis=-1) <= 1.5)
    ant = lm.point("antrum")
    r_ant = lm.get("antrum").detail["radius_mm"]
    into_antrum = cut & (np.linalg.norm(grid - ant, axis=-1) <= r_ant + 1.5)
    return {"removed": int(cut.sum()),
            "macewen_removed": float(cut[at_mac].mean()) if at_mac.any() else 0.0,
            "antrum_wall_removed": int(into_antrum.sum()),
            "thin_over_sinus": near("sinus", 1.5),
            "thin_over_tegmen": near("tegmen", 1.5) + near("dura", 1.5),
            "edge_mm": float(edge[cut].min()) if cut.any() else np.inf,
            "cut": cut}


def assert_a_mastoidectomy(case, pr, radii):
    """The Done-when of the plan: in Macewen's triangle, into the antrum, bone
    thinned over the sinus and the tegmen, 1 mm from every critical structure
    at the source resolution, 2 mm from the volume's edge."""
    rep = cavity_report(case, pr, radii)
    assert rep["removed"] > 15000, rep["removed"]
    assert rep["macewen_removed"] > 0.9, rep["macewen_removed"]
    assert rep["antrum_wall_removed"] > 50, rep["antrum_wall_removed"]
    assert rep["thin_over_sinus"] > 100, rep["thin_over_sinus"]
    assert rep["thin_over_tegmen"] > 100, rep["thin_over_tegmen"]
    assert rep["edge_mm"] >= PLAN.edge_mm, rep["edge_mm"]
    # margins at the source resolution, per burr, every drilling sample
    tr = pr.trajectory
    nat = case.load_volume().native_labels
    crit, thin, canal = danger_groups(case.structures)
    on = tr.drill.astype(bool)
    r = np.asarray(radii)[tr.burr[on]]
    d = box_clearance(tr.pos_mm[on], nat.labels, nat.spacing_mm, nat.origin_mm, crit,
                      4.0)
    assert (d - r).min() >= PLAN.margin_mm - 1e-6
    assert (d - r).min() < PLAN.margin_mm + 0.5              # and it does come close
    d = box_clearance(tr.pos_mm[on], nat.labels, nat.spacing_mm, nat.origin_mm, thin, 4.0)
    assert (d - r).min() >= PLAN.thin_margin_mm - 1e-6
    return rep


# -------------------------------------------------------------- the phantom
@pytest.fixture(scope="module")
def phantom():
    case = load_case("phantom")
    pr, radii = planned(case)
    return case, pr, radii


def test_phantom_plan_is_a_mastoidectomy(phantom):
    case, pr, radii = phantom
    assert pr.burrs == ("cutting-5mm", PLAN.finish_burr)
    rep = assert_a_mastoidectomy(case, pr, radii)
    tr = pr.trajectory
    assert np.all(np.diff(tr.t_s) > 0)
    np.testing.assert_allclose(np.linalg.norm(tr.axis, axis=1), 1.0)
    # the cutting burr first, then the diamond; the change with the drill off
    change = np.flatnonzero(np.diff(tr.burr) != 0)
    assert len(change) == 1 and tr.burr[0] == 0 and tr.burr[-1] == 1
    assert not tr.drill[change[0] + 1]
    assert np.all(tr.speed_rpm[tr.burr == 1] == load_burr(PLAN.finish_burr)
                  .default_speed_rpm)
    # the cavity lies behind the canal's wall (above the canal, Macewen's
    # triangle, from over its axis) and below the tegmen
    lm = case.landmarks
    vol = case.load_volume()
    p = vol.origin_mm + vol.spacing_mm * np.argwhere(rep["cut"])
    canal = lm.get("ear_canal")
    y_c, z_c, r_c = canal.point_mm[1], canal.point_mm[2], canal.detail["radius_mm"]
    beside = p[:, 2] < z_c + r_c
    assert p[beside, 1].min() >= canal.detail["posterior_wall_y_mm"] - 0.5
    assert p[~beside, 1].min() >= y_c - 2.6            # a cutting burr's radius
    assert p[:, 2].max() <= lm.point("tegmen")[2]


def test_saucerized_not_undercut(phantom):
    """Seen from the eye the cut is a height field over the outline: along
    each ray of the view, no bone is left above a cut voxel (no overhang)."""
    case, pr, radii = phantom
    rep = cavity_report(case, pr, radii)
    vol = case.load_volume()
    kinds = np.array(["none"] + [s.kind for s in case.structures])
    bone = (kinds == "bone")[vol.labels] & ~rep["cut"]
    # the view is lateral here (+x for this left ear): rays run along -x
    assert np.allclose(pr.trajectory.axis[0], [-1.0, 0.0, 0.0], atol=1e-9)
    cut = rep["cut"]
    lateral_bone = np.flip(np.logical_or.accumulate(np.flip(bone, 0), axis=0), 0)
    # a cut voxel with bone still lateral to it, within 3 voxels: the sphere's
    # own curvature; anything more is an overhang
    over = cut & np.roll(lateral_bone, -4, axis=0)
    assert over.sum() < 0.02 * cut.sum(), over.sum()


def test_a_plan_made_until_a_time_is_the_whole_plans_start(phantom):
    """``until_s``: the samples up to that time, to the bit, whether the
    planner stops in the cutting burr's passes, at a rinse or in the
    finishing burr's."""
    case, pr, _ = phantom
    tr = pr.trajectory
    change = float(tr.t_s[np.flatnonzero(tr.burr == 1)[0]])
    rinse = float(tr.t_s[np.flatnonzero(tr.irrigation)[0]])
    for until in (0.0, 3.0, rinse + 0.5, change + 2.0):
        part = plan_mastoidectomy(case, "cutting-5mm", until_s=until)
        k = int(np.searchsorted(tr.t_s, until, side="right"))
        assert len(part.trajectory.t_s) == k
        for f in ("t_s", "pos_mm", "axis", "drill", "speed_rpm", "suction", "irrigation",
                  "burr"):
            np.testing.assert_array_equal(getattr(part.trajectory, f), getattr(tr, f)[:k],
                                          err_msg=f"{f} until {until}")
        assert part.summary["until_s"] == until
    with pytest.raises(ValueError, match="until_s"):
        plan_mastoidectomy(case, "cutting-5mm", until_s=-1.0)


def test_demo_trajectory_is_deterministic_and_one_burr(phantom):
    case, pr, _ = phantom
    again = plan_mastoidectomy(case, "cutting-5mm")
    np.testing.assert_array_equal(again.trajectory.pos_mm, pr.trajectory.pos_mm)
    one = demo_trajectory(case, "cutting-5mm")
    assert (one.burr == 0).all() and np.all(one.speed_rpm == 60000.0)


def test_rinses_irrigate_then_suction_between_passes(phantom):
    _, pr, _ = phantom
    traj = pr.trajectory
    assert not np.any(traj.drill & (traj.suction | traj.irrigation))
    rinse = traj.suction | traj.irrigation
    dt = np.diff(traj.t_s, append=traj.t_s[-1])
    drilled = np.cumsum(dt * traj.drill)
    starts = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], (rinse | ~traj.drill), [0]])
                                   .astype(int)))
    for a, b in zip(edges[::2], edges[1::2]):
        if not rinse[a:b].any():
            continue
        starts.append(a)
        first_irr = np.flatnonzero(traj.irrigation[a:b])
        first_suc = np.flatnonzero(traj.suction[a:b])
        assert first_irr.size and first_suc.size and first_irr[-1] < first_suc[0]
    gaps = np.diff(drilled[np.array(starts)], prepend=0.0)
    assert len(starts) >= 2 and np.all(gaps[:-1] >= PLAN.rinse_every_s - 1e-6)
    assert gaps[-1] > 0.0 and not traj.drill[starts[-1]:].any()
    depth = traj.pos_mm @ traj.axis[0]
    assert np.any(depth[traj.suction] > depth[traj.drill].min() + 5.0)   # in the cavity
    assert dt[rinse].sum() < 0.4 * dt[traj.drill].sum()


# ----------------------------------------------------------- peer exports
@pytest.mark.parametrize("kw", [dict(), dict(crop_mm=CROP), dict(side="right",
                                                                  stored="RAS",
                                                                  declared="RAS")],
                         ids=["merged", "cropped", "right"])
def test_peer_export_plans_are_mastoidectomies(tmp_path, kw):
    case = load_case(write_real_like(tmp_path, **kw))
    assert case.require_orientation() == ""
    pr, radii = planned(case)
    assert_a_mastoidectomy(case, pr, radii)


@pytest.fixture(scope="module")
def lps_plan(tmp_path_factory):
    """The plan of the export stored and declared in LPS (the flips' reference)."""
    ref = load_case(write_real_like(tmp_path_factory.mktemp("lps"), stored="LPS",
                                    declared="LPS"))
    return plan_mastoidectomy(ref, "cutting-5mm").trajectory


@pytest.mark.parametrize("code", ["RPS", "LAS", "LPI", "ILA"])
def test_each_declared_flip_plans_the_same_cavity(tmp_path, lps_plan, code):
    """A stack stored flipped (or permuted) and declared so loads
    voxel-identical in LPS, so its plan is the same path to the bit."""
    flipped = load_case(write_real_like(tmp_path / code, stored=code, declared=code))
    assert flipped.require_orientation() == ""
    a = lps_plan
    b = plan_mastoidectomy(flipped, "cutting-5mm").trajectory
    np.testing.assert_array_equal(a.pos_mm, b.pos_mm)
    np.testing.assert_array_equal(a.burr, b.burr)


def test_margin_holds_at_a_finer_anisotropic_source(tmp_path):
    """Slices of 0.25 mm pixels, 0.5 mm apart, read onto the 0.5 mm grid: the
    margins hold on the source voxels, where the grid alone would not."""
    from bonesim.io.phantom import phantom_volume
    from bonesim.io.volumes import write_label_stack

    case = load_case("phantom")
    fine = phantom_volume(7, 0.25, (52.0, 52.0, 52.0))
    labels = np.ascontiguousarray(fine.labels[:, :, ::2])
    write_label_stack(tmp_path / "s", labels, [s.display_color for s in case.structures],
                      orientation="LPS")
    lines = ['[case]', 'name = "fine"', 'side = "left"', '', '[volume]',
             'format = "label-stack"', 'path = "s"', 'voxel_mm = 0.5',
             'size_mm = [52.0, 52.0, 52.0]', 'orientation = "LPS"']
    for s in case.structures:
        lines += ['', '[[structures]]', f'name = "{s.name}"', f'kind = "{s.kind}"',
                  f'color = {list(s.display_color)}']
    (tmp_path / "case.toml").write_text("\n".join(lines) + "\n")
    fc = load_case(tmp_path / "case.toml")
    pr, radii = planned(fc)
    nat = fc.load_volume().native_labels
    np.testing.assert_allclose(nat.spacing_mm, [0.25, 0.25, 0.5])
    tr = pr.trajectory
    on = tr.drill.astype(bool)
    crit, _, _ = danger_groups(fc.structures)
    d = box_clearance(tr.pos_mm[on], nat.labels, nat.spacing_mm, nat.origin_mm, crit, 4.0)
    assert (d - np.asarray(radii)[tr.burr[on]]).min() >= PLAN.margin_mm - 1e-6


# ------------------------------------------------------------ plan file, errors
def test_shipped_plan_is_the_documented_defaults():
    assert PLAN == DemoPlan()


BAD_PLANS = [
    ("\nmargin_mm = 1.0", "\n", "missing required key(s) 'margin_mm'", "plan"),
    ("\nmargin_mm = 1.0", "\nmargin_mm = 1.0\nburr_radius_mm = 2.0",
     "unknown key(s) 'burr_radius_mm'", "plan"),
    ("layer_mm = 1.5", "layer_mm = 0.0", "'layer_mm' must be a finite number > 0", "plan"),
    ("n_layers = 24", "n_layers = 2.5", "'n_layers' must be an integer", "plan"),
    ("irrigation_every = 2", "irrigation_every = 0", "'irrigation_every' must be >= 1",
     "plan"),
    ("line_overlap = 0.5", "line_overlap = 1.5", "'line_overlap' must be <= 0.99", "plan"),
    ("rinse_gap_mm = 0.5", 'rinse_gap_mm = "small"', "'rinse_gap_mm' must be a number",
     "plan"),
    ("wall_slope = 1.2", "wall_slope = inf", "'wall_slope' must be a finite number > 0",
     "cavity"),
    ('finish_burr = "diamond-3mm"', "finish_burr = 3", "'finish_burr' must be", "finish"),
]


@pytest.mark.parametrize("old,new,fragment,table", BAD_PLANS)
def test_bad_plan_files_name_file_and_key(tmp_path, old, new, fragment, table):
    text = default_plan_path().read_text()
    assert old in text
    path = tmp_path / "demo_plan.toml"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(BonesimError) as e:
        load_demo_plan(path)
    assert fragment in str(e.value) and str(path) in str(e.value)
    assert e.value.field == table


def test_a_case_without_the_landmarks_gets_one_line(tmp_path):
    """No canal label, the opening filled, no middle ear: the plan says which
    landmark is missing, naming the manifest."""
    from bonesim.io import phantom as P

    case = load_case("phantom")
    vol = case.load_volume()
    parts = P.build_phantom(case.volume.seed, vol.spacing_mm, case.volume.size_mm)
    labels = vol.labels.copy()
    labels[parts.envelope & (labels == 0)] = 1            # no canal, no air at all
    labels[labels == case.index("ossicles")] = 1
    from bonesim.io.volumes import write_label_stack

    write_label_stack(tmp_path / "s", labels, [s.display_color for s in case.structures])
    lines = ['[case]', 'name = "solid"', 'side = "left"', '', '[volume]',
             'format = "label-stack"', 'path = "s"', 'orientation = "LPS"',
             'size_mm = [52.0, 52.0, 52.0]']
    for s in case.structures:
        lines += ['', '[[structures]]', f'name = "{s.name}"', f'kind = "{s.kind}"',
                  f'color = {list(s.display_color)}']
    (tmp_path / "case.toml").write_text("\n".join(lines) + "\n")
    solid = load_case(tmp_path / "case.toml")
    with pytest.raises(BonesimError) as e:
        plan_mastoidectomy(solid)
    msg = str(e.value)
    assert "ear canal" in msg and str(tmp_path / "case.toml") in msg and "\n" not in msg


def test_one_burr_plan_matches_its_first_stage(phantom):
    case, pr, _ = phantom
    one = plan_mastoidectomy(case, "cutting-5mm", finish_burr=None)
    assert one.burrs == ("cutting-5mm",)
    assert one.summary["stages"][0] == pr.summary["stages"][0]
    assert dataclasses.replace(PLAN, finish_burr="diamond-2mm") != PLAN
