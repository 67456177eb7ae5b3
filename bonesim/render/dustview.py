"""Bone dust on screen: soft, small, translucent sprites.

The dust must never hide the drilling field. Each dusty cell that
:meth:`bonesim.physics.dust.DustGrid.sprites` lists (the top layer of every pile,
jittered inside its cell) becomes one round sprite facing the camera:

* **flat colour, no rim**: the sprite's colour is the dust's (dry bone
  powder, or the darker paste of wet dust) with no shading; only its opacity
  falls off, smoothly from the centre to 0 at the edge (``(1 - r^2)^2``), so
  overlapping sprites blend into a soft layer instead of a field of rings;
* **small and thin**: radius ``radius_cells * cell * cbrt(min(density, 1))``,
  opacity ``opacity * sqrt(min(density, 1))`` at most (``render.toml``
  ``[dust]``): a full layer of fresh dust lets the cavity floor show through;
* **faded by age**: times ``aged + (1 - aged) * exp(-age / fade_s)``: fresh
  chips flying off the burr are seen, settled dust becomes a veil;
* **wet paste** darker and more translucent (``wet_rgb``, ``wet_opacity``);
* **thinned where the level of detail is on** (:attr:`DustLayer.keep_one_in`
  ``k`` > 1, render.toml ``[lod] dust_keep_one_in``): one sprite in ``k``
  is drawn, chosen by a hash of its position (the same cells every frame:
  no flicker, no pattern), ``sqrt(k)`` times as wide (the area of ``k``
  sprites; at the native voxel a sprite is about two pixels wide, and
  each one costs a triangle however small);
* **depth-tested** against the bone: drawn in VTK's translucent pass after
  the opaque surface, with the depth test on and depth writes off, so dust
  behind a wall is hidden and dust never hides dust behind it entirely
  (blended order-independently, VTK's default, except in a scene drawn
  with the level of detail, which blends in draw order:
  :class:`bonesim.render.scene.Scene`).

:func:`sprite_look` computes radii and colours (numpy only, testable);
:class:`DustLayer` owns the VTK actor.
"""
from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonCore import vtkFloatArray, vtkUnsignedCharArray
from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkRenderingCore import vtkActor, vtkPointGaussianMapper

__all__ = ["sprite_look", "thin_sprites", "DustLayer", "SPLAT_SHADER", "BOUND_SCALE"]

#: Fragment code of a sprite: flat colour, opacity ``(1 - r^2)^2`` to the edge.
SPLAT_SHADER = (
    "//VTK::Color::Impl\n"
    "float dist2 = dot(offsetVCVSOutput.xy, offsetVCVSOutput.xy);\n"
    "if (dist2 > 1.0) { discard; }\n"
    "float fall = 1.0 - dist2;\n"
    "opacity *= fall * fall;\n"
    "diffuseColor = vec3(0.0);\n"
    "ambientColor = vertexColorVSOutput.rgb;\n")


#: Half-width of a sprite's square in sprite radii: just around the disk the
#: shader keeps (offset radius 1).
BOUND_SCALE = 1.0


def sprite_look(density, age_s, wet, cell_mm: float, style):
    """Radius and colour of each dust sprite.

    Parameters
    ----------
    density : (n,) float
        Dust in the cell [cells] (clipped to [0, 1]).
    age_s : (n,) float or None
        Age of the dust [s] (None: fresh).
    wet : (n,) bool-like or None
        Wet paste (None: all dry).
    cell_mm : float
        Dust cell edge [mm].
    style : namespace
        The ``[dust]`` table of :func:`bonesim.render.style.load_style`.

    Returns
    -------
    radius : (n,) float32
        Sprite radius [mm].
    rgba : (n, 4) uint8
        Colour and peak opacity.
    """
    d = np.clip(np.asarray(density, dtype=np.float64).reshape(-1), 0.0, 1.0)
    n = d.shape[0]
    age = np.zeros(n) if age_s is None else \
        np.maximum(np.asarray(age_s, dtype=np.float64).reshape(-1), 0.0)
    w = np.zeros(n, bool) if wet is None else np.asarray(wet).reshape(-1).astype(bool)
    if age.shape[0] != n or w.shape[0] != n:
        raise ValueError(f"{n} dust densities but {age.shape[0]} ages and {w.shape[0]} "
                         "wet flags")
    radius = (style.radius_cells * float(cell_mm) * np.cbrt(d)).astype(np.float32)
    fade = style.aged + (1.0 - style.aged) * np.exp(-age / style.fade_s)
    alpha = style.opacity * np.sqrt(d) * fade * np.where(w, style.wet_opacity, 1.0)
    rgb = np.where(w[:, None], np.asarray(style.wet_rgb), np.asarray(style.dry_rgb))
    rgba = np.empty((n, 4), np.uint8)
    rgba[:, :3] = np.rint(rgb * 255.0)
    rgba[:, 3] = np.rint(np.clip(alpha, 0.0, 1.0) * 255.0)
    return radius, rgba


def thin_sprites(positions, keep_one_in: int) -> np.ndarray:
    """Which sprites to draw when drawing one in ``keep_one_in``.

    Parameters
    ----------
    positions : (n, 3) float32
        Sprite centres [mm] (a cell's is the same every frame).
    keep_one_in : int
        1 keeps every sprite.

    Returns
    -------
    (n,) bool
        Kept: a hash of the position's float32 bits is 0 modulo
        ``keep_one_in``.
    """
    k = int(keep_one_in)
    if k < 1:
        raise ValueError(f"keep_one_in must be at least 1, got {keep_one_in}")
    p = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
    if k == 1:
        return np.ones(len(p), bool)
    u = p.view(np.uint32).astype(np.uint64)
    h = (u[:, 0] * np.uint64(0x9E3779B1) + u[:, 1] * np.uint64(0x85EBCA77)
         + u[:, 2] * np.uint64(0xC2B2AE3D)) & np.uint64(0xFFFFFFFF)
    h ^= h >> np.uint64(15)
    h = (h * np.uint64(0x2C1B3C6D)) & np.uint64(0xFFFFFFFF)
    h ^= h >> np.uint64(12)
    return (h % np.uint64(k)) == 0


class DustLayer:
    """The dust actor of a scene.

    Parameters
    ----------
    renderer : vtkRenderer
    style : namespace
        The ``[dust]`` table of the render style.
    """

    def __init__(self, renderer, style):
        self.style = style
        self.polydata = vtkPolyData()
        self._pts = vtkPoints()
        self._pos = vtkFloatArray()
        self._pos.SetNumberOfComponents(3)
        self._pts.SetData(self._pos)
        self._radius = vtkFloatArray()
        self._radius.SetName("radius")
        self._rgba = vtkUnsignedCharArray()
        self._rgba.SetNumberOfComponents(4)
        self._rgba.SetName("rgba")
        self.polydata.SetPoints(self._pts)
        pd = self.polydata.GetPointData()
        pd.AddArray(self._radius)
        pd.SetScalars(self._rgba)
        m = vtkPointGaussianMapper()
        m.SetInputData(self.polydata)
        m.SetScaleArray("radius")
        m.SetScaleFactor(1.0)
        m.SetEmissive(False)
        m.ScalarVisibilityOn()
        m.SetColorModeToDirectScalars()
        m.SetScalarModeToUsePointData()
        m.SetSplatShaderCode(SPLAT_SHADER)
        # Each sprite is drawn as a square around the disk its shader keeps
        # (offset radius 1, SPLAT_SHADER); VTK's default square reaches three
        # radii (for its Gaussian splats): nine times the area, every
        # fragment of it shaded and then discarded. A square just around the
        # disk draws the same pixels (at most 1/255 apart on a few, from
        # interpolation rounding) with a ninth of the fragments.
        m.SetBoundScale(BOUND_SCALE)
        a = vtkActor()
        a.SetMapper(m)
        p = a.GetProperty()
        p.SetAmbient(1.0)
        p.SetDiffuse(0.0)
        p.SetSpecular(0.0)
        a.ForceTranslucentOn()
        a.SetVisibility(False)
        a.PickableOff()
        renderer.AddActor(a)
        self.actor = a
        self.mapper = m
        self._bufs = None
        self.count = 0
        #: Draw one sprite in this many (module docstring; the scene sets it).
        self.keep_one_in = 1

    def set(self, positions, density, cell_mm: float, age_s=None, wet=None) -> None:
        """Show the sprites (see the module docstring); cells with no dust
        are dropped."""
        p = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
        d = np.asarray(density, dtype=np.float32).reshape(-1)
        if d.shape[0] != p.shape[0]:
            raise ValueError(f"{p.shape[0]} dust positions but {d.shape[0]} densities")
        age = None if age_s is None else np.asarray(age_s, np.float32).reshape(-1)
        w = None if wet is None else np.asarray(wet).reshape(-1)
        for name, arr in (("ages", age), ("wet flags", w)):
            if arr is not None and arr.shape[0] != p.shape[0]:
                raise ValueError(f"{p.shape[0]} dust positions but {arr.shape[0]} {name}")
        keep = d > 0
        if not keep.all():
            p, d = np.ascontiguousarray(p[keep]), d[keep]
            age = None if age is None else age[keep]
            w = None if w is None else w[keep]
        k = int(self.keep_one_in)
        if k > 1:
            keep = thin_sprites(p, k)
            p, d = np.ascontiguousarray(p[keep]), d[keep]
            age = None if age is None else age[keep]
            w = None if w is None else w[keep]
        radius, rgba = sprite_look(d, age, w, cell_mm, self.style)
        if k > 1:           # the area of k sprites
            radius *= np.float32(np.sqrt(k))
        self._bufs = (p, radius, rgba)                 # keep the memory VTK reads alive
        for arr, buf in ((self._pos, p), (self._radius, radius), (self._rgba, rgba)):
            arr.SetVoidArray(buf, int(buf.size), 1)
            arr.Modified()
        self._pts.Modified()
        self.polydata.Modified()
        self.count = int(p.shape[0])
        self.actor.SetVisibility(self.count > 0)
