"""The bone of a recording exported as a case (bonesim.session.bone_export):
it reloads with exactly the recording's remaining voxels, and a run started
from it continues where the recording stopped."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bonesim.errors import BonesimError
from bonesim.session.bone_export import EXPORT_JSON, export_bone
from bonesim.session.playback import Player
from bonesim.session.reader import read_session
from tests.bonesim.dataset_runs import demo_part, record

FIRST_S, MORE_S = 3.0, 3.0


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The demo's first 3 s recorded (A), and A followed by the next 3 s (A+B)."""
    d = tmp_path_factory.mktemp("export")
    a = record(d / "a.h5", demo_part(0.0, FIRST_S))
    ab = record(d / "ab.h5", demo_part(0.0, FIRST_S + MORE_S))
    return d, a, ab


def _initial_minus_removals(session):
    """Reference without the replica: the case's initial occupancy and labels
    with every recorded removal (one epoch) cleared, voxel by voxel."""
    model = session.load_model()
    dens, lab = model.grid.to_dense()
    occ = dens > 0
    rem = session.removals
    assert (rem["epoch"] == 0).all()
    for i, j, k in rem["ijk"]:
        occ[i, j, k] = False
    return np.where(occ, lab, 0), model


def _occupancy(model):
    d, lab = model.grid.to_dense()
    return np.where(d > 0, lab, 0)


@pytest.mark.parametrize("fmt", ["seg-nrrd", "nrrd"])
def test_last_moment_reloads_with_exactly_the_remaining_voxels(runs, tmp_path, fmt):
    from bonesim.io.loading import load_model

    _, a, _ = runs
    s = read_session(a)
    out = tmp_path / fmt
    res = export_bone(s, None, fmt, out)
    want, model = _initial_minus_removals(s)
    assert res["removed_voxels"] == len(s.removals["t_s"]) > 50
    assert res["remaining_voxels"] == int((want > 0).sum())
    back = load_model(out / "case.toml", "cutting-5mm")
    assert back.grid.shape == model.grid.shape and back.spacing_mm == model.spacing_mm
    np.testing.assert_array_equal(back.grid.origin_mm, model.grid.origin_mm)
    np.testing.assert_array_equal(_occupancy(back), want)
    # the structures keep their names, kinds and colours
    assert [(x.name, x.kind, x.display_color) for x in back.structures] == \
        [(x.name, x.kind, x.display_color) for x in model.structures]
    info = json.loads((out / EXPORT_JSON).read_text())
    assert info["run_sha256"] and info["at_s"] == pytest.approx(s.duration_s)
    np.testing.assert_allclose(info["tool"]["pos_mm"], s.samples["pos_mm"][-1])


def test_an_earlier_moment_and_the_slicer_file(runs, tmp_path):
    import nrrd

    _, a, _ = runs
    s = read_session(a)
    out = tmp_path / "mid"
    res = export_bone(s, 1.5, "seg-nrrd", out)
    p = Player(s, surface=False)
    p.seek(1.5)
    d, lab = p.grid.to_dense()
    data, hdr = nrrd.read(str(out / "segmentation.seg.nrrd"))
    np.testing.assert_array_equal(data, np.where(d > 0, lab, 0))
    assert hdr["Segment0_Name"] == "bone" and hdr["space"] == "left-posterior-superior"
    assert res["removed_voxels"] < len(s.removals["t_s"])
    with pytest.raises(BonesimError, match="outside the recording"):
        export_bone(s, 99.0, "seg-nrrd", tmp_path / "late")
    with pytest.raises(BonesimError, match="already exists"):
        export_bone(s, 1.5, "seg-nrrd", out)


def test_a_run_started_from_the_export_continues_where_the_recording_stopped(runs):
    """A+B drilled in one go, against A recorded, exported at its end, and B
    drilled on the exported case: the same tissue in the end, but for the
    voxels B grazed that A had already partly drilled (the recording has no
    partial densities: they start whole in the export)."""
    d, a, ab = runs
    s = read_session(a)
    out = d / "from_a"
    export_bone(s, None, "seg-nrrd", out)
    # B starts at A's last point of the path (10 ms apart) and drills on
    b = record(d / "b.h5", demo_part(FIRST_S - 0.01, MORE_S + 0.01), case=out / "case.toml")
    sb, sab = read_session(b), read_session(ab)
    # the continued run starts with the tool where A stopped, and its samples
    # are the one-go run's from there on
    np.testing.assert_allclose(sb.samples["pos_mm"][0], s.samples["pos_mm"][-1], atol=1e-9)
    q = len(s.samples["t_s"]) - 1
    n = min(len(sb.samples["t_s"]), len(sab.samples["t_s"]) - q)
    np.testing.assert_allclose(sb.samples["pos_mm"][:n], sab.samples["pos_mm"][q:q + n],
                               atol=1e-9)
    assert len(sb.removals["t_s"]) > 50                # it goes on drilling
    pb = Player(sb, surface=False)
    pb.seek(pb.timeline.duration)
    pab = Player(sab, surface=False)
    pab.seek(pab.timeline.duration)
    cont, full = _occupancy_of(pb), _occupancy_of(pab)
    assert cont.shape == full.shape
    removed_b = (_initial_minus_removals(s)[0] > 0) & (cont == 0)
    differ = (cont > 0) != (full > 0)
    assert removed_b.sum() == len(sb.removals["t_s"])
    assert differ.sum() <= 0.05 * removed_b.sum(), (differ.sum(), removed_b.sum())
    # labels agree wherever both hold tissue
    both = (cont > 0) & (full > 0)
    np.testing.assert_array_equal(cont[both], full[both])


def _occupancy_of(player):
    d, lab = player.grid.to_dense()
    return np.where(d > 0, lab, 0)


def test_a_moved_fragment_is_written_where_it_lay():
    """A piece split off as body 1 and moved 8 mm along +x: the export holds its
    voxels 16 voxels further along x, and none where it was cut from."""
    from types import SimpleNamespace

    from bonesim.engine.bodies import publish_pose, publish_split_box
    from bonesim.engine.model import make_state
    from bonesim.engine.replica import TissueReplica
    from bonesim.io.loading import load_model
    from bonesim.session.bone_export import bone_at

    model = load_model("phantom", "cutting-5mm")
    state = make_state(model)
    rep = TissueReplica(model, state)
    lo, hi = (78, 44, 40), (94, 63, 59)
    b, n = publish_split_box(state, 0, lo, hi, 0.0)
    publish_pose(state, b, (8.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0), 0.0)
    rep.drain()
    player = SimpleNamespace(grid=rep.grid, replica=rep, t=0.0, seek=lambda t: None,
                             timeline=SimpleNamespace(epoch_at=lambda t: 0))
    labels, info = bone_at(player, 0.0)
    dens, lab = model.grid.to_dense()
    before = np.where(dens > 0, lab, 0)
    piece = np.zeros(before.shape, bool)
    piece[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1] = True
    piece &= before > 0
    assert info["moved_bodies"] == [b] and piece.sum() == n > 100
    moved = np.zeros_like(piece)
    moved[16:] = piece[:-16]                            # 8 mm = 16 voxels along x
    # the piece's voxels are where it lies now, with their labels ...
    np.testing.assert_array_equal(labels[moved & (before == 0)],
                                  np.roll(before, 16, axis=0)[moved & (before == 0)])
    # ... the place it was cut from is empty but where it now lies again
    assert not labels[piece & ~moved].any()
    assert info["remaining_voxels"] == int((before > 0).sum())
    # voxels landing on tissue that stayed are counted, not written twice
    assert info["overlapping"] == int((moved & (before > 0) & ~piece).sum()) + int(
        (piece.sum() - moved.sum()))
