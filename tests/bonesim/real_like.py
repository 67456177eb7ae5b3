"""Exports of the phantom made to look like other people's data.

Real temporal-bone segmentations come as stacks of label slices with their
own axes, colours and names, sinus and dura often in ONE label, no camera and
no display colours, and the volume cropped so that the mastoid touches its
edge. :func:`write_real_like` writes the phantom that way (a ``case.toml``
and its PNG slices), so loaders, landmarks, side checks and plans are tested
on data that is not laid out as bonesim would lay it out.

What a call can vary
--------------------
merged
    sinus, posterior-fossa dura and middle-fossa dura in one label named
    ``"Sigmoid sinus and dura"`` (else three labels of peer-style names).
crop_mm
    keep only the part of the phantom inside a box [mm] (LPS, the phantom's
    frame): e.g. ``y <= 16`` cuts through the sinus so the mastoid touches
    the volume's posterior face.
side
    ``"right"`` mirrors the phantom (a right ear, lateral ``-x``).
stored, declared
    the code the slices are written in and the code the manifest declares
    (``None``: the key is left out, read as LPS). ``stored != declared`` is
    a stack whose manifest lies about its axes.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bonesim.io import phantom as P
from bonesim.io.orientation import from_lps, image_geometry
from bonesim.io.label_stack import write_label_stack

#: Peer-style names and slice colours per phantom part (merged: the three
#: layers over the brain share the first entry's colour and name).
PEER = {
    "bone": ("Bone", (255, 255, 255)),
    "sigmoid_sinus": ("Sigmoid Sinus", (0, 0, 255)),
    "posterior_fossa_dura": ("Posterior Fossa Dura", (255, 0, 255)),
    "middle_fossa_dura": ("Tegmen Dura", (255, 128, 128)),
    "facial_nerve": ("Facial Nerve", (255, 255, 0)),
    "chorda_tympani": ("Chorda Tympani", (255, 160, 0)),
    "labyrinth": ("Inner Ear", (160, 0, 255)),
    "ossicles": ("Ossicles", (0, 255, 255)),
}
MERGED_NAME = "Sigmoid sinus and dura"
MERGED_PARTS = ("sigmoid_sinus", "posterior_fossa_dura", "middle_fossa_dura")
KINDS = {"bone": "bone", "sigmoid_sinus": "soft", "posterior_fossa_dura": "soft",
         "middle_fossa_dura": "soft", "facial_nerve": "critical",
         "chorda_tympani": "critical", "labyrinth": "critical", "ossicles": "critical"}


def real_like_labels(voxel_mm=0.5, merged=True, crop_mm=None, side="left", seed=7):
    """The phantom's labels laid out as a peer's export (in LPS).

    Returns
    -------
    labels : (nx, ny, nz) uint8
    structures : list of (name, kind, rgb)
    origin_mm : (3,) float
        LPS centre of voxel (0, 0, 0) [mm].
    """
    parts = P.build_phantom(seed=seed, voxel_mm=voxel_mm)
    order = [p for p in P.PARTS if not (merged and p in MERGED_PARTS[1:])]
    structures, labels = [], np.zeros(parts.hu.shape, np.uint8)
    for s, part in enumerate(order, start=1):
        name, rgb = PEER[part]
        members = MERGED_PARTS if merged and part == "sigmoid_sinus" else (part,)
        if merged and part == "sigmoid_sinus":
            name = MERGED_NAME
        for m in members:
            labels[parts.masks[m]] = s
        structures.append((name, KINDS[part], rgb))
    origin = parts.origin_mm.copy()
    if side == "right":                          # mirror: lateral becomes -x
        labels = labels[::-1].copy()
        origin[0] = -(origin[0] + voxel_mm * (labels.shape[0] - 1))
    if crop_mm is not None:
        lo = np.asarray(crop_mm[0], float)
        hi = np.asarray(crop_mm[1], float)
        i0 = np.clip(np.ceil((lo - origin) / voxel_mm), 0, labels.shape).astype(int)
        i1 = np.clip(np.floor((hi - origin) / voxel_mm) + 1, 0, labels.shape).astype(int)
        labels = np.ascontiguousarray(labels[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]])
        origin = origin + voxel_mm * i0
    return labels, structures, origin


def write_real_like(folder, *, voxel_mm=0.5, merged=True, crop_mm=None, side="left",
                    stored="PIR", declared="PIR", seed=7, name="peer-export") -> Path:
    """Write a peer-style label-stack case; returns its ``case.toml``.

    ``stored`` is the axis code the slices are written in, ``declared`` what
    the manifest says (None: no ``orientation`` key). ``origin_mm`` is
    written so that a correctly declared stack lands where the phantom lies.
    """
    import shutil

    folder = Path(folder)
    shutil.rmtree(folder / "slices", ignore_errors=True)
    labels, structures, origin = real_like_labels(voxel_mm, merged, crop_mm, side, seed)
    write_label_stack(folder / "slices", labels, [rgb for _, _, rgb in structures],
                      orientation=stored)
    _, first = image_geometry(stored, labels.shape, np.full(3, voxel_mm), origin)
    first = [float(v) for v in first]
    size = [float(n) * voxel_mm for n in from_lps(labels, stored).shape]
    lines = ["[case]", f'name = "{name}"', f'side = "{side}"', "", "[volume]",
             'format = "label-stack"', 'path = "slices"', 'pattern = "*.png"',
             f"size_mm = [{size[0]!r}, {size[1]!r}, {size[2]!r}]",
             f"origin_mm = [{first[0]!r}, {first[1]!r}, {first[2]!r}]",
             f"voxel_mm = {voxel_mm!r}"]
    if declared is not None:
        lines.append(f'orientation = "{declared}"')
    for n, kind, rgb in structures:
        lines += ["", "[[structures]]", f'name = "{n}"', f'kind = "{kind}"',
                  f"color = [{rgb[0]}, {rgb[1]}, {rgb[2]}]"]
    path = folder / "case.toml"
    path.write_text("\n".join(lines) + "\n")
    return path
