"""Which way the anatomy faces: side and orientation checked on every axis.

A label stack carries no orientation of its own, and a manifest can declare
the wrong one (or none: the stack is read as LPS). This module reads the
three anatomical directions of an ear from the structures themselves, in the
frame the volume was loaded in, and compares them with what the declared side
and orientation expect.

Directions from the anatomy
---------------------------
Each direction is the weighted sum of unit vectors between the centroids of
two landmark groups (:mod:`bonesim.io.landmarks`; merged sinus-and-dura
labels split first), one per *cue* whose two groups are both present:

lateral (``+x`` for a left ear, ``-x`` for a right one)
    labyrinth to middle ear (1), labyrinth to ear canal (1), internal
    auditory canal to labyrinth (0.7), labyrinth to sigmoid sinus (0.4);
posterior (``+y``)
    middle ear to sinus (1), ear canal to sinus (1), labyrinth to sinus
    (0.7), carotid to jugular bulb (0.5);
superior (``+z``)
    middle ear (else labyrinth) to the dura nearest it, the tegmen (1;
    the posterior fossa's dura lies further away), jugular bulb to labyrinth
    (0.7), carotid to middle ear (0.5), the facial nerve's end farthest from
    the labyrinth (the stylomastoid foramen) to its nearest end (0.7), the
    sinus's end nearest the labyrinth (the jugular bulb) to its farthest
    (0.4).

The axes of the loaded frame are then matched to the three directions by the
signed permutation that agrees best with them. Where it differs from the
declared frame on an axis whose direction is clear (its unit sum within
about 50 degrees of the fitted axis and at least one full cue behind it), the
case contradicts its declaration: :func:`check_frame` names the contradiction
and the orientation code (and, for a lateral flip, the side) that fits.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from bonesim.io.orientation import LETTERS, axis_map

__all__ = ["CUES", "FrameCheck", "anatomy_directions", "check_frame"]

#: (direction, from group, to group, weight); "tegmen_near" is the dura
#: nearest the middle ear, "facial_ends" / "sinus_ends" the ends of a
#: structure nearest and farthest from the labyrinth.
CUES = (
    ("lateral", "labyrinth", "middle_ear", 1.0),
    ("lateral", "labyrinth", "ear_canal", 1.0),
    ("lateral", "iac", "labyrinth", 0.7),
    ("lateral", "labyrinth", "sinus", 0.4),
    ("posterior", "middle_ear", "sinus", 1.0),
    ("posterior", "ear_canal", "sinus", 1.0),
    ("posterior", "labyrinth", "sinus", 0.7),
    ("posterior", "carotid", "jugular", 0.5),
    ("superior", "ref", "tegmen_near", 1.0),
    ("superior", "jugular", "labyrinth", 0.7),
    ("superior", "carotid", "middle_ear", 0.5),
    ("superior", "facial_far", "facial_near", 0.7),
    ("superior", "sinus_near", "sinus_far", 0.4),
)
#: Least agreement (cosine) of a direction with its fitted axis, and least
#: summed weight, for the direction to count as clear.
CLEAR_COS = 0.64
CLEAR_WEIGHT = 0.95
_OPPOSITE = {"L": "R", "R": "L", "P": "A", "A": "P", "S": "I", "I": "S"}
_DIRS = ("lateral", "posterior", "superior")
#: How a cue's end reads in a message.
_READ = {"labyrinth": "labyrinth", "middle_ear": "middle ear", "ear_canal": "ear canal",
         "iac": "internal auditory canal", "sinus": "sigmoid sinus",
         "carotid": "carotid", "jugular": "jugular bulb", "ref": "middle ear",
         "tegmen_near": "tegmen", "facial_far": "facial nerve's lower end",
         "facial_near": "facial nerve's upper end", "sinus_near": "sinus's lower end",
         "sinus_far": "sinus's upper end"}


@dataclass(frozen=True)
class FrameCheck:
    """How the anatomy's directions agree with the declared frame.

    Attributes
    ----------
    ok : bool
        No clear contradiction.
    directions : dict of str -> (3,) float
        Summed cue vectors per anatomical direction, loaded frame (absent
        where no cue applies).
    fitted : dict of str -> (int, int)
        Per anatomical direction, the loaded axis (0 x, 1 y, 2 z) and sign
        that fit it best.
    contradictions : tuple of str
        One phrase per clear disagreement.
    fitting_code : str or None
        For a label stack: the orientation code that puts the anatomy where
        the declared side expects it (None when nothing contradicts or the
        format holds its own orientation).
    other_side : bool
        Only the lateral direction disagrees: the data fit the other ear as
        well (a mirrored stack or the wrong ``side``).
    unchecked : tuple of str
        Directions no cue could measure.
    """

    ok: bool
    directions: dict = field(default_factory=dict)
    fitted: dict = field(default_factory=dict)
    contradictions: tuple = ()
    fitting_code: str | None = None
    other_side: bool = False
    unchecked: tuple = ()

    def message(self, declared: str | None, source: str, side: str) -> str:
        """One line naming the contradiction and what fits (empty when ok)."""
        if self.ok:
            return ""
        what = "; ".join(self.contradictions)
        code = f'orientation "{declared}" ({source})' if declared else \
            "the orientation in the file's header"
        line = f"the anatomy contradicts the declared side \"{side}\" and {code}: {what}"
        if self.fitting_code:
            line += f'; the stack fits orientation = "{self.fitting_code}"'
        elif declared is None:
            line += "; check the file's header orientation"
        if self.other_side:
            other = "right" if side == "left" else "left"
            line += f' (or side = "{other}" with the orientation as it is)'
        return line


def _centroid(m):
    return np.argwhere(m).mean(axis=0)


def anatomy_directions(masks: dict, spacing_mm: float, origin_mm) -> tuple[dict, dict]:
    """Summed cue vectors per anatomical direction in the loaded frame.

    Parameters
    ----------
    masks : dict of str -> (nx, ny, nz) bool
        Landmark-group masks (:func:`bonesim.io.landmarks.group_masks`).
    spacing_mm : float
        Cell edge [mm].
    origin_mm : (3,) float
        Centre of cell (0, 0, 0) [mm].

    Returns
    -------
    directions : dict of str -> (3,) float
        ``sum(w * unit(B - A))`` per direction over the cues that apply.
    weights : dict of str -> float
        Summed weights of those cues.
    cues : dict of str -> list of (float, (3,) float, str, str)
        Per direction, each applied cue: weight, unit vector, from, to.
    """
    h = float(spacing_mm)
    origin = np.asarray(origin_mm, float)
    pts = {g: origin + h * np.argwhere(m) for g, m in masks.items() if m.any()}
    cen = {g: p.mean(axis=0) for g, p in pts.items()}
    ref = "middle_ear" if "middle_ear" in cen else ("labyrinth" if "labyrinth" in cen
                                                   else None)
    if ref is not None:
        cen["ref"] = cen[ref]
        dura = [pts[g] for g in ("tegmen", "dura") if g in pts]
        if dura:
            d = np.concatenate(dura)
            dist = np.linalg.norm(d - cen[ref], axis=1)
            cen["tegmen_near"] = d[dist <= dist.min() + 6.0].mean(axis=0)
    if "labyrinth" in cen:
        for g in ("facial_nerve", "sinus"):
            if g in pts and len(pts[g]) >= 10:
                dist = np.linalg.norm(pts[g] - cen["labyrinth"], axis=1)
                lo, hi = np.percentile(dist, [5, 95])
                key = "facial" if g == "facial_nerve" else "sinus"
                cen[key + "_near"] = pts[g][dist <= lo].mean(axis=0)
                cen[key + "_far"] = pts[g][dist >= hi].mean(axis=0)
    dirs, weights, used = {}, {}, {}
    for d, a, b, w in CUES:
        if a in cen and b in cen:
            v = cen[b] - cen[a]
            n = float(np.linalg.norm(v))
            if n > 2.0 * h:
                dirs[d] = dirs.get(d, np.zeros(3)) + w * v / n
                weights[d] = weights.get(d, 0.0) + w
                used.setdefault(d, []).append((w, v / n, a, b))
    return dirs, weights, used


def check_frame(masks: dict, spacing_mm: float, origin_mm, side: str,
                declared_code: str | None) -> FrameCheck:
    """Compare the anatomy's directions with the declared side and frame.

    Parameters
    ----------
    masks, spacing_mm, origin_mm
        As :func:`anatomy_directions`.
    side : {"left", "right"}
        The declared ear.
    declared_code : str or None
        The code the stack was read with (a label stack's declared or
        assumed orientation); None when the file's header gave it.

    Returns
    -------
    FrameCheck
    """
    dirs, weights, used = anatomy_directions(masks, spacing_mm, origin_mm)
    lat = 1 if side == "left" else -1
    expected = {"lateral": (0, lat), "posterior": (1, 1), "superior": (2, 1)}
    known = [d for d in _DIRS if d in dirs]
    unchecked = tuple(d for d in _DIRS if d not in dirs)
    if not known:
        return FrameCheck(True, unchecked=unchecked)
    best, best_score = None, -np.inf
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            fit = {d: (perm[i], signs[i]) for i, d in enumerate(_DIRS)}
            score = sum(fit[d][1] * dirs[d][fit[d][0]] for d in known)
            # ties (an unmeasured direction) keep the declared frame
            score += 1e-6 * sum(fit[d] == expected[d] for d in _DIRS)
            if score > best_score:
                best, best_score = fit, score
    contradictions = []
    clear_wrong = []
    for d in known:
        v = dirs[d] / max(np.linalg.norm(dirs[d]), 1e-12)
        ax, sg = best[d]
        if best[d] == expected[d]:
            continue
        cos_fit = sg * v[ax]
        cos_exp = expected[d][1] * v[expected[d][0]]
        if cos_fit >= CLEAR_COS and weights[d] >= CLEAR_WEIGHT and cos_exp < 0.3:
            clear_wrong.append(d)
            axis = "xyz"[ax]
            sign = "+" if sg > 0 else "-"
            want = "xyz"[expected[d][0]]
            wsign = "+" if expected[d][1] > 0 else "-"
            # the cue that speaks loudest for the fitted axis
            w, u, a, b = max(used[d], key=lambda c: c[0] * sg * c[1][ax])
            contradictions.append(f"{d} (from the {_READ[a]} to the {_READ[b]}) points "
                                  f"along {sign}{axis}, not {wsign}{want}")
    if not clear_wrong:
        return FrameCheck(True, dirs, best, (), None, False, unchecked)
    code = None
    if declared_code is not None:
        # the loaded axis a runs toward the anatomical letter `toward[a]`
        letter = {"lateral": "L" if side == "left" else "R", "posterior": "P",
                  "superior": "S"}
        toward = {}
        for d in _DIRS:
            ax, sg = best[d]
            toward[ax] = letter[d] if sg > 0 else _OPPOSITE[letter[d]]
        source, sign = axis_map(declared_code)
        img = [""] * 3
        for a in range(3):
            t = toward[a]
            img[source[a]] = t if sign[a] > 0 else _OPPOSITE[t]
        code = "".join(img)
        assert all(ch in LETTERS for ch in code)
    other_side = clear_wrong == ["lateral"] and best["lateral"][0] == 0
    return FrameCheck(False, dirs, best, tuple(contradictions), code, other_side,
                      unchecked)
