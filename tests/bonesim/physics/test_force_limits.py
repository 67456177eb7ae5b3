"""Force limits near a structure: bins, the over-the-limit law, limits files,
and the live watch against a slow reference."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bonesim.engine import events
from bonesim.errors import BonesimError
from bonesim.physics.force_limits import (AT_LIMIT_RTOL, ForceLimits, ForceWatch, bin_edges,
                                          bin_index, force_magnitude, limit_rows,
                                          load_limits, over_limit, save_limits)
from tests.bonesim.fakes import BONE, NERVE, block_model


def _limits(force, speed=None, width=2.0, structure="nerve", closest=math.inf):
    nb = len(force)
    return ForceLimits(width * np.arange(nb + 1), force,
                       np.full(nb, np.nan) if speed is None else speed, np.full(nb, 9),
                       95.0, structure, "applied", width * nb, case="block",
                       source=("a.h5", "b.h5"), closest_mm=closest)


def test_over_limit_is_strictly_above_beyond_rounding_and_nan_flags_nothing():
    lim = np.array([2.0, 2.0, 2.0, np.nan, 0.0])
    v = np.array([2.0 * (1 + AT_LIMIT_RTOL / 2), 2.0 * (1 + 3 * AT_LIMIT_RTOL), 1.0, 99.0,
                  1e-12])
    assert over_limit(v, lim).tolist() == [False, True, False, False, True]
    assert limit_rows([0, -1, 1], [5.0, 6.0]).tolist()[::2] == [5.0, 6.0]
    assert math.isnan(limit_rows([0, -1, 1], [5.0, 6.0])[1])


def test_bins_and_force_kinds():
    e = bin_edges()
    assert bin_index([0.0, 1.99, 2.0, 29.9, 30.0, 30.1, -1, np.nan], e).tolist() == \
        [0, 0, 1, 14, 14, -1, -1, -1]
    s = {"force_n": np.array([[3.0, 4.0, 0.0]]), "vibration_n": np.array([[0.0, 4.0, 0.0]]),
         "mag_n": np.array([7.0])}
    assert force_magnitude(s, "applied").tolist() == [3.0]
    assert force_magnitude(s, "device").tolist() == [5.0]
    assert force_magnitude(s, "normal").tolist() == [7.0]
    with pytest.raises(ValueError, match="force must be one of"):
        force_magnitude(s, "peak")


def test_limits_file_round_trips_with_nan_bins(tmp_path):
    lim = _limits([1.5, np.nan, 2.25], [60000.0, np.nan, 1.0 / 3.0])
    p = save_limits(tmp_path / "lim.toml", lim)
    back = load_limits(p)
    for f in ("edges_mm", "force_n", "speed_rpm", "n"):
        assert np.array_equal(getattr(back, f), getattr(lim, f), equal_nan=True), f
    assert (back.structure, back.force, back.percentile, back.max_distance_mm, back.case,
            back.source) == ("nerve", "applied", 95.0, 6.0, "block", ("a.h5", "b.h5"))
    assert math.isinf(back.closest_mm)                  # no approach checked
    assert not list(tmp_path.glob("*.tmp"))
    # the experts' closest approach travels with the limits to the window
    p = save_limits(tmp_path / "near.toml", _limits([np.nan, 2.0], closest=1.0 / 3.0))
    assert load_limits(p).closest_mm == 1.0 / 3.0
    # a file written before the rule existed: no approach checked
    old = "\n".join(ln for ln in p.read_text().splitlines() if not ln.startswith("closest"))
    (tmp_path / "old.toml").write_text(old)
    assert math.isinf(load_limits(tmp_path / "old.toml").closest_mm)
    (tmp_path / "neg.toml").write_text(old + "\nclosest_mm = -1.0\n")
    with pytest.raises(BonesimError, match="closest_mm must be >= 0"):
        load_limits(tmp_path / "neg.toml")


@pytest.mark.parametrize("text, what", [
    ("format = 'x'", "format must be"),
    ("format = 'bonesim-force-limits-1'\nstructure = 'n'", "field 'force' is missing"),
    ("format = [", "malformed TOML"),
    ("format = 'bonesim-force-limits-1'\nstructure = 'n'\nforce = 'applied'\n"
     "percentile = 95.0\nmax_distance_mm = 4.0\nedges_mm = [0.0, 2.0, 4.0]\n"
     "force_n = [1.0]\nspeed_rpm = [1.0, 2.0]\nn = [1, 1]", "force_n has 1 bins"),
])
def test_a_bad_limits_file_is_refused_naming_it(tmp_path, text, what):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(BonesimError, match=what) as err:
        load_limits(p)
    assert "bad.toml" in str(err.value)
    with pytest.raises(BonesimError, match="cannot read"):
        load_limits(tmp_path / "missing.toml")


def _nerve_block():
    """A bone block with a nerve plane at k == 2 (spacing 0.5 mm)."""
    labels = np.zeros((12, 12, 20), np.uint8)
    labels[:, :, :16] = 1
    labels[:, :, 2] = 2
    model, _ = block_model(labels=labels, structures=[BONE, NERVE])
    return model


def _reference(model, lim, tissue, samples):
    """Per removal, the slow way: its step's sample, its distance to the nerve
    plane (analytic), its bin, over the limit or not; then per step and
    quantity the largest excess (first on ties)."""
    best = {}
    for q in range(len(tissue["t_s"])):
        if tissue["kind"][q] != events.REMOVED:
            continue
        t = tissue["t_s"][q]
        r = int(np.flatnonzero(samples["t_s"] == t)[0])
        k = int(tissue["ijk"][q][2])
        d = 0.5 * abs(k - 2) - 0.25 if k != 2 else 0.0    # to the slab of voxel boxes
        if d > lim.max_distance_mm:
            continue
        b = min(int(d // 2.0), len(lim.force_n) - 1)
        f = float(np.linalg.norm(samples["force_n"][r] - samples["vibration_n"][r]))
        for name, val, table in (("force_n", f, lim.force_n),
                                 ("speed_rpm", float(samples["speed_rpm"][r]), lim.speed_rpm)):
            L = table[b]
            if not math.isnan(L) and val > L * (1 + AT_LIMIT_RTOL):
                key = (t, name)
                if key not in best or val - L > best[key][1] - best[key][2]:
                    best[key] = (name, val, L, d)
        # a bin without a force limit: closer than the closest expert is over
        if math.isnan(lim.force_n[b]) and math.isfinite(lim.closest_mm) and d < lim.closest_mm:
            key = (t, "approach_mm")
            if key not in best or d < best[key][1]:
                best[key] = ("approach_mm", d, lim.closest_mm, d)
    return [(t, *best[(t, name)]) for (t, name) in sorted(best)]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), chunks=st.integers(1, 6),
       closest=st.sampled_from([math.inf, 0.7, 1.6, 3.0]))
def test_watch_equals_a_slow_reference_fed_in_any_chunks(seed, chunks, closest):
    """Force, speed and the closer-than-any-expert rule (a bin without a force
    limit), live in any feeds, against the slow reference."""
    rng = np.random.default_rng(seed)
    model = _nerve_block()
    lim = _limits([np.nan, 1.5, 2.0], [50000.0, np.nan, 70000.0], closest=closest)
    n = 40
    t = np.round(np.cumsum(rng.uniform(0.5e-3, 2e-3, n)), 6)
    samples = {"t_s": t, "force_n": rng.uniform(-2, 2, (n, 3)),
               "vibration_n": rng.uniform(-0.2, 0.2, (n, 3)),
               "mag_n": rng.uniform(0, 3, n), "speed_rpm": rng.uniform(40000, 80000, n)}
    m = 60
    tissue = events.empty_events(m)
    tissue["kind"][:] = np.where(rng.random(m) < 0.85, events.REMOVED, events.CONTACT)
    tissue["t_s"][:] = np.sort(rng.choice(t, m))
    tissue["ijk"][:] = np.column_stack([rng.integers(0, 12, m), rng.integers(0, 12, m),
                                        rng.integers(0, 16, m)])
    watch = ForceWatch(model, lim)
    got = []
    # feeds as the window makes them: tissue drained first, so a removal comes
    # at the latest one feed after the sample of its step (any earlier is fine)
    cut_s = np.r_[0, np.sort(rng.integers(0, n + 1, chunks - 1)), n]
    t_end = 0
    for j in range(chunks):
        a_s, b_s = cut_s[j], cut_s[j + 1]
        due = int(np.searchsorted(tissue["t_s"], t[a_s - 1], side="right")) if a_s else 0
        b_t = int(rng.integers(max(t_end, due), m + 1))
        got += watch.feed({k: v[t_end:b_t] for k, v in tissue.items()},
                          {k: v[a_s:b_s] for k, v in samples.items()})
        t_end = b_t
    got += watch.feed({k: v[t_end:] for k, v in tissue.items()})
    want = _reference(model, lim, tissue, samples)
    assert [(w.t_s, w.quantity) for w in got] == [(w[0], w[1]) for w in want]
    for w, r in zip(got, want):
        assert w.value == pytest.approx(r[2], abs=1e-9)
        assert w.limit == r[3] and w.distance_mm == pytest.approx(r[4], abs=1e-9)
    assert sum(watch.count.values()) == len(want)
    assert watch.last == (got[-1] if got else None)


def test_watch_refuses_a_structure_the_case_lacks():
    with pytest.raises(ValueError, match="'chorda_tympani' is not a structure"):
        ForceWatch(_nerve_block(), _limits([1.0], structure="chorda_tympani"))


# Issue 24, row 6: negative limits were accepted silently; non-UTF-8 and binary
# limits files, and a structure the case lacks, gave tracebacks.
_GOOD = ("format = 'bonesim-force-limits-1'\nstructure = '{s}'\nforce = 'applied'\n"
         "percentile = {p}\nmax_distance_mm = 4.0\nedges_mm = [0.0, 2.0, 4.0]\n"
         "force_n = [{f}, nan]\nspeed_rpm = [1.0, 2.0]\nn = [1, {n}]\n")


@pytest.mark.parametrize("change, needle", [
    ({"f": "-1.0"}, r"\[force_n\]: a limit must be >= 0 \(or nan: no limit\), got -1.0"),
    ({"f": "-inf"}, r"\[force_n\]: a limit must be >= 0"),
    ({"n": "-3"}, r"\[n\]: expert rows per bin cannot be negative"),
    ({"p": "250.0"}, r"percentile must lie in \(0, 100\]"),
])
def test_negative_limits_are_refused_naming_the_field(tmp_path, change, needle):
    p = tmp_path / "lim.toml"
    p.write_text(_GOOD.format(**{"s": "nerve", "f": "1.0", "n": "1", "p": "95.0", **change}))
    with pytest.raises(BonesimError, match=needle) as err:
        load_limits(p)
    assert str(err.value).startswith(str(p)) and "\n" not in str(err.value)
    p.write_text(_GOOD.format(s="nerve", f="1.0", n="1", p="95.0"))
    assert np.isnan(load_limits(p).force_n[1])            # nan: no limit, still fine


@pytest.mark.parametrize("data", [b"# \xe9\nformat = 'x'\n", bytes(range(256)) * 4])
def test_non_utf8_and_binary_limits_files_give_one_line(tmp_path, data):
    p = tmp_path / "lim.toml"
    p.write_bytes(data)
    with pytest.raises(BonesimError, match="not a UTF-8 text") as err:
        load_limits(p)
    assert str(err.value).startswith(str(p))
