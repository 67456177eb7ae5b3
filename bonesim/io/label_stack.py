"""Label stacks: a folder of RGB(A) slice images, one colour per structure.

A stack carries no orientation or spacing of its own; the case manifest gives
its extent (``size_mm``) and its axis code (``orientation``, see
:mod:`bonesim.io.orientation`). Reading puts it in the LPS patient frame.

Big stacks (hundreds of 512 x 512 slices) are read in one pass: the slice
headers first (sizes checked before any pixel is decoded), then the slices
decoded in parallel threads (Pillow's decoder and the mapping kernel release
the GIL), each mapped straight from colour to structure index in one pass
(:func:`bonesim.io.label_slices.map_slice`) and written into its place in
the one LPS-ordered ``uint8`` array the reader returns. No RGB volume and
no second copy of the labels is ever held.
"""
from __future__ import annotations

import os
import re
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from bonesim.errors import BonesimError
from bonesim.io.orientation import PATIENT_FRAME, from_lps, lps_geometry, parse_orientation, to_lps
from bonesim.io.raw_volume import MAX_LISTED, MAX_STRUCTURES, RawVolume

__all__ = ["UNKNOWN_COLOR_MODES", "MAX_DECODE_THREADS", "natural_key",
           "read_label_stack", "write_label_stack"]

UNKNOWN_COLOR_MODES = ("error", "nearest", "background")
"""What to do with label-stack colours that match no structure."""

MAX_DECODE_THREADS = 8
"""Most threads decoding slices at once (at most one per CPU)."""

_UNKNOWN = np.uint16(0xFFFF)         # colour-table entry of a colour no structure has
                                     # (bonesim.io.label_slices.UNKNOWN)


def natural_key(name: str) -> tuple:
    """Sort key that orders embedded numbers numerically (plane2 < plane10)."""
    parts = re.split(r"(\d+)", name)
    key = tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts)
    return key, name


def _pack_rgb(rgb) -> np.ndarray:
    rgb = np.asarray(rgb, dtype=np.uint32)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


def _unpack_rgb(code: int) -> tuple[int, int, int]:
    code = int(code)
    return (code >> 16) & 255, (code >> 8) & 255, code & 255


def _color_table(colors) -> np.ndarray:
    """(2**24,) uint16: packed RGB -> structure index; black -> 0; others unknown."""
    table = np.full(1 << 24, _UNKNOWN, dtype=np.uint16)
    table[0] = 0
    for s, rgb in enumerate(colors, start=1):
        if rgb is not None:
            table[int(_pack_rgb(rgb))] = s
    return table


def _nearest_structures(codes: np.ndarray, colors) -> np.ndarray:
    """Structure index of the closest structure colour (RGB distance) per code."""
    ref = [(s, rgb) for s, rgb in enumerate(colors, start=1) if rgb is not None]
    if not ref:
        return np.zeros(len(codes), dtype=np.uint8)
    idx = np.array([s for s, _ in ref], dtype=np.uint8)
    rgb_ref = np.array([rgb for _, rgb in ref], dtype=float)
    got = np.array([_unpack_rgb(c) for c in codes], dtype=float).reshape(-1, 3)
    d2 = ((got[:, None, :] - rgb_ref[None]) ** 2).sum(-1)
    return idx[np.argmin(d2, axis=1)]


def _slice_pixels(path: Path) -> np.ndarray:
    """One decoded slice, (rows, cols, 3 or 4) uint8 (RGB or RGBA)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if im.mode not in ("RGB", "RGBA"):
                im = im.convert("RGBA")
            return np.asarray(im)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise BonesimError(f"unreadable slice image: {exc}", path) from None


def _slice_codes(px: np.ndarray) -> np.ndarray:
    """Packed RGB of one decoded slice, (rows, cols) uint32; transparent
    pixels 0."""
    code = px[..., 0].astype(np.uint32) << 16
    code |= px[..., 1].astype(np.uint32) << 8
    code |= px[..., 2]
    if px.shape[-1] == 4:
        code[px[..., 3] == 0] = 0
    return code


def _slice_sizes(files: list[Path]) -> dict[tuple[int, int], list[Path]]:
    """Image size (width, height) -> files, from the headers alone."""
    from PIL import Image, UnidentifiedImageError

    sizes: dict[tuple[int, int], list[Path]] = {}
    for f in files:
        try:
            with Image.open(f) as im:
                size = im.size
        except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
            raise BonesimError(f"unreadable slice image: {exc}", f) from None
        sizes.setdefault(size, []).append(f)
    return sizes


def read_label_stack(folder: str | Path, pattern: str, size_mm, colors,
                     unknown_colors: str = "error", origin_mm=None,
                     orientation: str = PATIENT_FRAME, progress=None,
                     threads: int | None = None) -> RawVolume:
    """Read a folder of RGB(A) slices where each colour marks one structure.

    Parameters
    ----------
    folder : str or Path
        Folder of images.
    pattern : str
        Glob selecting the slices (e.g. ``"*.png"``); matches are sorted
        naturally (``plane2`` before ``plane10``). Slice ``k`` is ``z`` index k.
    size_mm : (3,) float
        Physical extent of the stack along image columns, image rows (top row
        first) and slices, in that order [mm].
    colors : sequence of (3,) int or None
        RGB of structure ``s`` at position ``s - 1``; ``None`` for a structure
        not drawn in the stack.
    unknown_colors : {"error", "nearest", "background"}
        Colours matching no structure: raise (naming each colour and its voxel
        count), map to the nearest structure colour (RGB distance), or drop.
        Black and fully transparent pixels are always background.
    origin_mm : (3,) float, optional
        Case-frame (LPS) centre of the first slice's top-left pixel [mm];
        default centres the stack on 0.
    orientation : str
        The stack's axis code (:mod:`bonesim.io.orientation`): the directions
        in which image columns, rows and slices increase. ``"LPS"`` (the
        default) reads columns as ``+x``, rows as ``+y``, slices as ``+z``.
    progress : callable, optional
        ``progress(done, total, what)`` after each decoded slice.
    threads : int, optional
        Decoding threads (default: one per CPU, at most
        :data:`MAX_DECODE_THREADS`).

    Returns
    -------
    RawVolume
        ``data`` uint8 structure indices, axes along +x, +y, +z (LPS).
    """
    folder = Path(folder)
    if not folder.exists():
        raise BonesimError("label-stack folder not found", folder)
    if not folder.is_dir():
        raise BonesimError("expected a folder of label images, got a file", folder)
    if unknown_colors not in UNKNOWN_COLOR_MODES:
        raise ValueError(f"unknown_colors must be one of {UNKNOWN_COLOR_MODES}")
    size = np.asarray(size_mm, dtype=float).reshape(3)
    if np.any(~np.isfinite(size)) or np.any(size <= 0):
        raise BonesimError(f"missing spacing: size_mm must be three positive "
                           f"numbers, got {size.tolist()}", folder)
    code = parse_orientation(orientation, folder, "orientation")
    files = sorted((p for p in folder.glob(pattern) if p.is_file()),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise BonesimError(f"no images match pattern {pattern!r}", folder)
    sizes = _slice_sizes(files)
    if len(sizes) > 1:
        parts = [f"{w}x{h} px ({len(fs)} file(s), e.g. {fs[0].name})"
                 for (w, h), fs in sorted(sizes.items(), key=lambda kv: -len(kv[1]))]
        raise BonesimError("mixed slice sizes (width x height): " + ", ".join(parts),
                           folder)
    (width, height), = sizes
    shape_img = (width, height, len(files))            # columns, rows, slices
    labels = np.empty(to_lps(np.broadcast_to(np.uint8(0), shape_img), code).shape,
                      dtype=np.uint8)
    image_view = from_lps(labels, code)                # (cols, rows, slices) view
    from bonesim.io.label_slices import map_slice     # numba: only when a stack is read

    table = _color_table(colors)
    strays: dict[int, int] = {}
    lock = threading.Lock()
    done = [0]

    def decode(k: int) -> None:
        px = _slice_pixels(files[k])                   # (rows, cols, 3|4) uint8
        if map_slice(px, table, image_view[:, :, k]):  # unknown colours: name them
            codes = _slice_codes(px)                   # (rows, cols) uint32
            idx = table[codes]                         # (rows, cols) uint16
            unknown = idx == _UNKNOWN
            values, inverse, counts = np.unique(codes[unknown],
                                                return_inverse=True, return_counts=True)
            if unknown_colors == "nearest":
                idx[unknown] = _nearest_structures(values, colors)[inverse]
            else:
                idx[unknown] = 0
            with lock:
                for v, c in zip(values.tolist(), counts.tolist()):
                    strays[v] = strays.get(v, 0) + c
            image_view[:, :, k] = idx.T
        if progress is not None:
            with lock:
                done[0] += 1
                progress(done[0], len(files), "decoding slices")

    n_threads = threads or min(MAX_DECODE_THREADS, os.cpu_count() or 1)
    if n_threads <= 1 or len(files) == 1:
        for k in range(len(files)):
            decode(k)
    else:
        with ThreadPoolExecutor(n_threads, thread_name_prefix="bonesim-slices") as pool:
            for _ in pool.map(decode, range(len(files))):
                pass
    if strays and unknown_colors == "error":
        values = np.array(list(strays), dtype=np.int64)
        counts = np.array([strays[v] for v in values.tolist()], dtype=np.int64)
        order = np.lexsort((values, -counts))
        listed = ", ".join(f"RGB{_unpack_rgb(values[i])} x {counts[i]} voxels"
                           for i in order[:MAX_LISTED])
        more = (f" and {len(values) - MAX_LISTED} more"
                if len(values) > MAX_LISTED else "")
        raise BonesimError(
            f"{len(values)} colour(s) match no structure ({int(counts.sum())} "
            f"voxels): {listed}{more}; add them to [[structures]] or set "
            "unknown_colors = \"nearest\" or \"background\"", folder)
    shape = np.array(shape_img, dtype=float)
    spacing, origin = lps_geometry(code, shape, size / shape,
                                   np.zeros(3) if origin_mm is None else origin_mm)
    if origin_mm is None:                   # centred on the frame's origin
        origin = -(np.array(labels.shape) - 1) * spacing / 2
    src = f"{folder} (label stack '{pattern}', {len(files)} slices, {code})"
    return RawVolume(labels, spacing, origin, src)


def write_label_stack(folder: str | Path, labels: np.ndarray, colors,
                      stem: str = "plane", orientation: str = PATIENT_FRAME) -> list[Path]:
    """Write structure indices as RGB PNG slices ``plane1.png, plane2.png, ...``.

    Parameters
    ----------
    folder : str or Path
        Created if needed.
    labels : (nx, ny, nz) uint8
        Structure index per voxel, axis order ``(x, y, z)`` of the LPS frame.
    colors : sequence of (3,) int
        RGB of structure ``s`` at position ``s - 1``; must be unique and not
        black (black is background).
    stem : str
        File-name stem.
    orientation : str
        Axis code of the written stack (:mod:`bonesim.io.orientation`): with
        ``"LPS"`` slice ``k`` is ``labels[:, :, k]``, columns along x and
        rows along y. Reading the files back with the same code gives
        ``labels`` exactly.
    """
    from PIL import Image

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    code = parse_orientation(orientation)
    lut = np.zeros((MAX_STRUCTURES + 1, 3), dtype=np.uint8)
    for s, rgb in enumerate(colors, start=1):
        lut[s] = rgb
    image = from_lps(np.asarray(labels), code)           # (cols, rows, slices) view
    paths = []
    for k in range(image.shape[2]):
        path = folder / f"{stem}{k + 1}.png"
        rgb = lut[np.ascontiguousarray(image[:, :, k].T)]
        Image.fromarray(rgb, mode="RGB").save(path, compress_level=1)
        paths.append(path)
    return paths
