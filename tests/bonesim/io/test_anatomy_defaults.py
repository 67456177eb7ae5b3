"""Defaults a surgeon expects (bonesim.io.anatomy, bonesim.io.neighbours):
clinical names on screen, the nerve monitor's default nerves, and one colour
per structure whatever the resolution a case is loaded at."""
from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bonesim.io import anatomy as A
from bonesim.io import case as C
from bonesim.io import neighbours as N
from bonesim.io import phantom as P
from bonesim.io import volumes as VOL

TABLE = A.load_table()


# ---------------------------------------------------------- clinical names
@pytest.mark.parametrize("name, shown", [
    ("facial_nerve", "Facial nerve"), ("sigmoid_sinus", "Sigmoid sinus"),
    ("chorda_tympani", "Chorda tympani"), ("middle_fossa_dura", "Middle fossa dura"),
    ("posterior_fossa_dura", "Posterior fossa dura"), ("labyrinth", "Labyrinth"),
    ("ossicles", "Ossicles"), ("bone", "Bone"),
    ("Facial Nerve", "Facial nerve"), ("FacialNerve", "Facial nerve"),
    ("Facial nerve", "Facial nerve"),
    # abbreviations the table reads: written out, or the class's name
    ("FN", "Facial nerve"), ("CN7", "Facial nerve"), ("CN VII", "Facial nerve"),
    ("n. VII", "Facial nerve"), ("SS", "Sigmoid sinus"), ("CN VIII", "Vestibulocochlear nerve"),
    ("ICA", "Internal carotid artery"), ("EAC", "External auditory canal"),
    ("LSC", "Lateral semicircular canal"), ("MFD", "Middle fossa dura"),
    ("TM", "Tympanic membrane"), ("CN 5", "Cranial nerve 5"),
    # anything else: tidied, capitals kept
    ("S12", "S12"), ("IAC_contents", "IAC contents"), ("thing_42", "Thing 42"),
    ("  vestibular__nerve ", "Vestibular nerve"), ("V", "Vein"),
])
def test_clinical_names(name, shown):
    assert A.clinical_name(name) == shown


@settings(max_examples=200, deadline=None)
@given(st.one_of(
    st.text(alphabet="abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_ .-",
            max_size=24),
    st.lists(st.sampled_from(sorted(TABLE.aliases) + ["nerve", "vii", "7", "sinus", "left"]),
             min_size=1, max_size=3).map(" ".join)))
def test_clinical_name_is_idempotent(name):
    """Shown names read the same when shown again (the HUD may be handed
    either)."""
    once = A.clinical_name(name)
    assert A.clinical_name(once) == once
    assert "_" not in once


def test_every_class_has_a_title_that_reads_as_itself():
    for cls in TABLE.classes.values():
        assert cls.title and cls.title[0].isupper(), cls.id
        assert A.classify(cls.title).id == cls.id, (cls.id, cls.title)
        assert A.clinical_name(cls.title) == cls.title


def test_structure_display_name():
    case = C.load_case("phantom")
    shown = [s.display_name for s in case.structures]
    assert shown == ["Bone", "Sigmoid sinus", "Posterior fossa dura", "Middle fossa dura",
                     "Facial nerve", "Chorda tympani", "Labyrinth", "Ossicles"]
    assert [s.name for s in case.structures] == list(P.PARTS)      # files keep these


# ------------------------------------------------------------ the monitor
NERVES_SEG = ("Bone", "Facial nerve", "Chorda tympani", "Vestibular nerve",
              "Cochlear nerve", "Sigmoid sinus")


def _nerve_stack(folder, extra=""):
    """A tiny label stack with the facial nerve, the chorda and two nerves of
    the internal auditory canal, none flagged in the manifest."""
    labels = np.zeros((12, 10, 8), np.uint8)
    labels[:] = 1
    for s in range(2, len(NERVES_SEG) + 1):
        labels[2 * s - 3:2 * s - 1, 3:6, 2:5] = s
    colors = [(255, 255, 255), (250, 230, 40), (255, 130, 0), (190, 230, 40),
              (215, 165, 30), (0, 0, 255)]
    VOL.write_label_stack(folder / "slices", labels, colors)
    lines = ['[case]\nname = "nerves"\nside = "left"\n',
             '[volume]\nformat = "label-stack"\npath = "slices"\nsize_mm = [6.0, 5.0, 4.0]\n'
             'orientation = "LPS"\n']
    for name, rgb in zip(NERVES_SEG, colors):
        kind = "bone" if name == "Bone" else "soft" if "sinus" in name else "critical"
        lines.append(f'[[structures]]\nname = "{name}"\nkind = "{kind}"\ncolor = {list(rgb)}\n'
                     + (extra if name == "Cochlear nerve" else ""))
    (folder / "case.toml").write_text("\n".join(lines))
    return folder / "case.toml"


def test_monitor_watches_facial_nerve_and_chorda_and_lists_the_others(tmp_path, capsys):
    from bonesim.io.case_report import print_case_info

    case = C.load_case(_nerve_stack(tmp_path))
    assert [s.name for s in case.structures if s.monitor] == ["Facial nerve",
                                                              "Chorda tympani"]
    assert [s.name for s in case.structures if s.monitor_available and not s.monitor] == \
        ["Vestibular nerve", "Cochlear nerve"]
    info = C.case_info(case)
    assert info["monitored"] == ["Facial nerve", "Chorda tympani"]
    assert info["monitor_available"] == ["Vestibular nerve", "Cochlear nerve"]
    print_case_info(info)
    out = capsys.readouterr().out
    assert ("monitor: Facial nerve, Chorda tympani (also available, off: Vestibular nerve, "
            "Cochlear nerve)") in out


def test_a_manifest_flag_turns_another_nerve_on(tmp_path, capsys):
    from bonesim.io.case_report import print_case_info

    case = C.load_case(_nerve_stack(tmp_path, extra="monitor = true\n"))
    assert [s.name for s in case.structures if s.monitor] == [
        "Facial nerve", "Chorda tympani", "Cochlear nerve"]
    info = C.case_info(case)
    print_case_info(info)
    out = capsys.readouterr().out
    assert ("monitor: Facial nerve, Chorda tympani, Cochlear nerve (also available, off: "
            "Vestibular nerve)") in out


def test_case_info_shows_clinical_names_beside_the_code_names(capsys):
    from bonesim.io.case_report import print_case_info

    info = C.case_info(C.load_case("phantom"))
    assert info["display_names"]["sigmoid_sinus"] == "Sigmoid sinus"
    assert "sigmoid_sinus" in info["counts"]                  # JSON keys: code names
    print_case_info(info)
    out = capsys.readouterr().out
    row = next(ln for ln in out.splitlines() if ln.startswith("sigmoid_sinus "))
    assert "Sigmoid sinus" in row
    assert "monitor: Facial nerve, Chorda tympani\n" in out


# ------------------------------------------------------------- neighbours
def _pooled_reference(labels, n, spacing, origin, cell, within):
    """Cells each structure reaches, and the pairs whose cells lie within reach
    (the definition, by brute force)."""
    from scipy.spatial.distance import cdist

    sp = np.broadcast_to(np.asarray(spacing, float), (3,))
    reach = max(cell, sp.max()) + within
    cells = {}
    for s in range(1, n + 1):
        ijk = np.argwhere(labels == s)
        centre = np.asarray(origin) + ijk * sp
        cells[s] = np.unique(np.floor(np.round(centre / cell, 6)).astype(int), axis=0)
    out = np.zeros((n, n), bool)
    for a, b in itertools.combinations(range(1, n + 1), 2):
        if len(cells[a]) and len(cells[b]):
            near = cdist(cells[a], cells[b]).min() * cell <= reach + 1e-6
            out[a - 1, b - 1] = out[b - 1, a - 1] = near
    return out


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.integers(1, 5), st.sampled_from([0.0, 0.4, 1.5]),
       st.sampled_from([0.19, 0.25, 0.3, (0.19, 0.25, 0.6)]))
def test_pooled_neighbours_match_brute_force(seed, n, within, spacing):
    rng = np.random.default_rng(seed)
    labels = np.zeros((14, 12, 10), np.uint8)
    for s in range(1, n + 1):
        for _ in range(rng.integers(1, 3)):
            lo = rng.integers(0, [13, 11, 9])
            hi = lo + rng.integers(1, 3, size=3)
            labels[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = s
    origin = rng.uniform(-3, 3, 3)
    got = A.neighbours(labels, n, spacing, within, origin, 0.5)
    want = _pooled_reference(labels, n, spacing, origin, 0.5, within)
    np.testing.assert_array_equal(got, want)


def test_many_structures_use_several_words():
    """More than 64 structures: the cell sets take two words."""
    labels = np.zeros((80, 3, 3), np.uint8)
    labels[:, 1, 1] = np.arange(1, 81)            # a row of 80 structures, 0.5 mm apart
    adj = A.neighbours(labels, 80, 0.5, 0.0)
    want = np.zeros((80, 80), bool)
    i = np.arange(79)
    want[i, i + 1] = want[i + 1, i] = True
    np.testing.assert_array_equal(adj, want)
    assert N.pool_presence(labels, 80, 0.5, (0, 0, 0), 0.5)[0].shape[-1] == 2


def test_a_thin_structure_counts_where_it_lies():
    """A structure one 0.19 mm voxel thick is kept by the pooling (it would
    vanish from a 0.5 mm grid resampled by nearest neighbour)."""
    labels = np.ones((60, 60, 20), np.uint8)
    labels[31, :, :] = 2                                       # a 0.19 mm sheet
    labels[40:, :, :] = 3                                      # 1.5 mm beyond it
    bits, first = N.pool_presence(labels, 3, 0.19, (0.0, 0.0, 0.0), 0.5)
    has2 = (bits[..., 0] & np.uint64(2)) != 0
    assert has2.any() and has2.sum() == has2.shape[1] * has2.shape[2]   # one layer of cells
    assert A.neighbours(labels, 3, 0.19, 1.5, (0, 0, 0), 0.5)[1, 2]


def test_neighbours_are_quick_at_256_cubed():
    """A 256^3 label map at 0.19 mm is measured well under a second of CPU
    (once the kernels are compiled; about 0.1 s when written): no
    whole-volume float copy, no distance field."""
    N.warmup()
    rng = np.random.default_rng(3)
    labels = np.ones((256, 256, 256), np.uint8)
    labels[:32] = 0
    for s in range(2, 17):
        c = rng.integers(32, 256, 3)
        r = rng.integers(3, 25, 3)
        labels[tuple(slice(max(a - b, 0), a + b) for a, b in zip(c, r))] = s
    labels[100:200, 50, 60] = 9                               # a thread
    t = time.process_time()                 # CPU: the machine may be shared
    adj = A.neighbours(labels, 16, 0.19, 1.5, (-24.0, -24.0, -24.0), 0.5)
    assert time.process_time() - t < 0.8
    assert adj.any()


# ----------------------------------------------- colours at every voxel_mm
PHANTOM_TWINS = """[case]
name = "phantom-twins"
side = "left"

[volume]
format = "phantom"
seed = 7
voxel_mm = {voxel}
size_mm = [52.0, 52.0, 52.0]

[[structures]]
name = "bone"
kind = "bone"

[[structures]]
name = "sigmoid_sinus"
kind = "soft"

[[structures]]
name = "posterior_fossa_dura"
kind = "soft"
anatomy = "dura"

[[structures]]
name = "middle_fossa_dura"
kind = "soft"
anatomy = "dura"

[[structures]]
name = "facial_nerve"
kind = "critical"

[[structures]]
name = "chorda_tympani"
kind = "critical"
anatomy = "facial_nerve"

[[structures]]
name = "labyrinth"
kind = "critical"

[[structures]]
name = "ossicles"
kind = "critical"
"""


def _colours(case):
    vol = case.load_volume()
    return {s.name: s.display_color for s in case.resolved(vol).structures}, vol


@pytest.mark.slow
def test_phantom_keeps_its_colours_at_every_voxel_size(tmp_path):
    """The phantom generated at 0.5, 0.25 and 0.19 mm (its manifest's
    ``voxel_mm``), with palette colours only and twins that must be told
    apart (both duras read as "dura", the chorda as the facial nerve): the
    same colour per structure at every size."""
    got = []
    for voxel in (0.5, 0.25, 0.19):
        d = tmp_path / str(voxel)
        d.mkdir()
        (d / "case.toml").write_text(PHANTOM_TWINS.format(voxel=voxel))
        colours, vol = _colours(C.load_case(d))
        assert vol.spacing_mm == voxel
        got.append(colours)
    assert got[0] == got[1] == got[2]
    c = got[0]
    # the twins were told apart (they are neighbours), each from the other
    assert c["posterior_fossa_dura"] != c["middle_fossa_dura"]
    assert c["chorda_tympani"] != c["facial_nerve"]
    assert c["facial_nerve"] == A.default_color("facial_nerve", "critical")
    for a, b in (("posterior_fossa_dura", "middle_fossa_dura"),
                 ("chorda_tympani", "facial_nerve")):
        assert A.delta_e(c[a], c[b]) >= TABLE.min_delta_e


STACK_COLOURS = {"bone": (255, 255, 255), "sigmoid_sinus": (0, 0, 255),
                 "posterior_fossa_dura": (200, 150, 160), "middle_fossa_dura": (201, 151, 161),
                 "facial_nerve": (250, 230, 40), "chorda_tympani": (252, 231, 41),
                 "labyrinth": (128, 0, 255), "ossicles": (0, 255, 255)}
STACK_KINDS = {"bone": "bone", "sigmoid_sinus": "soft", "posterior_fossa_dura": "soft",
               "middle_fossa_dura": "soft", "facial_nerve": "critical",
               "chorda_tympani": "critical", "labyrinth": "critical", "ossicles": "critical"}


def _stack_manifest(folder, voxel, size_mm):
    lines = ['[case]\nname = "stack"\nside = "left"\n',
             f'[volume]\nformat = "label-stack"\npath = "slices"\nsize_mm = {list(size_mm)}\n'
             f'orientation = "PIR"\nvoxel_mm = {voxel}\n']
    for name in P.PARTS:
        lines.append(f'[[structures]]\nname = "{name}"\nkind = "{STACK_KINDS[name]}"\n'
                     f'color = {list(STACK_COLOURS[name])}\n')
    path = folder / f"case-{voxel}.toml"
    path.write_text("\n".join(lines))
    return path


@pytest.mark.slow
def test_label_stack_export_keeps_its_colours_at_every_voxel_size(tmp_path):
    """The phantom at 0.25 mm exported as a PIR label stack whose chorda and
    duras come in near-twin colours of the facial nerve's and each other's,
    loaded at 0.5, 0.25 and 0.19 mm: identical colours."""
    vol = P.phantom_volume(7, 0.25, (52.0, 52.0, 52.0), P.PARTS)
    VOL.write_label_stack(tmp_path / "slices", vol.labels,
                          [STACK_COLOURS[n] for n in P.PARTS], orientation="PIR")
    got = [_colours(C.load_case(_stack_manifest(tmp_path, v, (52.0, 52.0, 52.0))))[0]
           for v in (0.5, 0.25, 0.19)]
    assert got[0] == got[1] == got[2]
    c = got[0]
    assert c["facial_nerve"] == STACK_COLOURS["facial_nerve"]
    assert c["chorda_tympani"] != STACK_COLOURS["chorda_tympani"]     # told apart
    assert A.delta_e(c["posterior_fossa_dura"], c["middle_fossa_dura"]) >= TABLE.min_delta_e


def test_a_thin_chorda_keeps_its_colour_where_the_grid_loses_it(tmp_path):
    """A 0.19 mm stack whose chorda is one pixel thick, next to the facial
    nerve in a near-identical yellow: at 0.5 mm the engine's grid does not
    hold the chorda at all, yet it is a neighbour of the nerve at every
    voxel size, so it gets the same distinct colour."""
    n = 80
    labels = np.ones((n, n, 40), np.uint8)
    labels[30:40, 30:40, :] = 2                                 # the facial nerve, 1.9 mm
    kept = set(VOL.nearest_indices(n, 0.19, 0.5, round(n * 0.19 / 0.5)).tolist())
    x = next(i for i in range(42, 50) if i not in kept)         # missed by the 0.5 grid
    labels[x, 30:40, :] = 3                                     # the chorda, 0.19 mm thin
    colours = [(255, 255, 255), (250, 230, 40), (252, 231, 41)]
    VOL.write_label_stack(tmp_path / "slices", labels, colours)
    got = []
    for voxel in (0.19, 0.25, 0.5):
        m = tmp_path / f"case-{voxel}.toml"
        m.write_text(
            '[case]\nname = "thin"\nside = "left"\n\n[volume]\nformat = "label-stack"\n'
            f'path = "slices"\nsize_mm = [{n * 0.19}, {n * 0.19}, {40 * 0.19}]\n'
            f'orientation = "LPS"\nvoxel_mm = {voxel}\n\n'
            '[[structures]]\nname = "Bone"\nkind = "bone"\ncolor = [255, 255, 255]\n\n'
            '[[structures]]\nname = "Facial nerve"\nkind = "critical"\ncolor = [250, 230, 40]\n\n'
            '[[structures]]\nname = "Chorda tympani"\nkind = "critical"\n'
            'color = [252, 231, 41]\n')
        colours_at, vol = _colours(C.load_case(m))
        if voxel == 0.5:
            assert vol.counts(3)[3] == 0                 # the grid lost the chorda
        got.append(colours_at)
    assert got[0] == got[1] == got[2]
    assert got[0]["Chorda tympani"] != (252, 231, 41)
    assert got[0]["Facial nerve"] == (250, 230, 40)
