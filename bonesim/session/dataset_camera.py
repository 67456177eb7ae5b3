"""Cameras of a dataset: where each frame looks from, and the OpenCV
convention its intrinsics and extrinsics are written in (no VTK here).

Convention (OpenCV, as ``cv2.projectPoints`` uses it)
------------------------------------------------------
* The camera frame has ``+x`` to the image's right, ``+y`` down the image,
  ``+z`` along the optical axis, into the scene; units [mm].
* Extrinsics ``R`` (3, 3), ``t`` (3,) map the case (patient, LPS) frame to
  the camera frame: ``X_cam = R @ X_case + t``. The eye is at
  ``-R.T @ t``; ``cam_to_case`` is the inverse, ``[[R.T, -R.T t], [0, 1]]``.
* Intrinsics ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` [px]: a point
  projects to ``u = fx X/Z + cx``, ``v = fy Y/Z + cy``, where ``(u, v) =
  (0, 0)`` is the *centre* of the top-left pixel, ``u`` runs along a row
  (column index) and ``v`` down (row index): array element ``[v, u]``.
  Square pixels (``fx == fy``), no skew, no distortion; ``cx = (W - 1) / 2``
  and ``cy = (H - 1) / 2``.
* Depth is ``Z`` [mm], the distance along the optical axis (not along the
  ray); ``X_cam = Z * K^-1 @ (u, v, 1)``.
* A stereo pair is parallel and rectified: both cameras have the same ``K``
  and ``R``, the right one ``baseline`` mm along the left one's ``+x``, so
  a point at depth ``Z`` shows at ``u_left - u_right = fx * baseline / Z``.
  The recorded (or fixed, or orbiting) camera is midway between them.

The renderer (:mod:`bonesim.render.dataset`) takes ``R``, ``t`` and ``K``
from the camera VTK actually rendered with (:func:`opencv_extrinsics`,
:func:`opencv_intrinsics`), so they describe the pixels exactly.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["FLIP_YZ", "opencv_extrinsics", "opencv_intrinsics", "look_at", "project",
           "pixel_rays", "depth_from_zbuffer", "points_from_depth", "normals_from_points",
           "cam_to_case", "frame_camera", "orbit_camera", "zoomed", "stereo_cameras"]

#: VTK's camera frame (x right, y up, z toward the viewer) to OpenCV's.
FLIP_YZ = np.diag([1.0, -1.0, -1.0])


def opencv_extrinsics(view_matrix) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` of a VTK camera's view transform (``camera.GetViewTransformMatrix()``
    as a (4, 4) array: case frame -> VTK camera frame)."""
    v = np.asarray(view_matrix, dtype=np.float64).reshape(4, 4)
    return FLIP_YZ @ v[:3, :3], FLIP_YZ @ v[:3, 3]


def opencv_intrinsics(projection, size) -> np.ndarray:
    """``K`` (3, 3) of a VTK perspective projection matrix (``camera.
    GetProjectionTransformMatrix(W / H, -1, 1)`` as a (4, 4) array) for an
    image of ``size = (W, H)`` [px] that the viewport fills."""
    p = np.asarray(projection, dtype=np.float64).reshape(4, 4)
    w, h = (int(v) for v in size)
    if abs(p[0, 2]) > 1e-12 or abs(p[1, 2]) > 1e-12 or p[3, 2] != -1.0:
        raise ValueError("not a centred perspective projection (window centre or "
                         "shear set?)")
    k = np.eye(3)
    k[0, 0] = p[0, 0] * w / 2.0
    k[1, 1] = p[1, 1] * h / 2.0
    k[0, 2] = (w - 1) / 2.0
    k[1, 2] = (h - 1) / 2.0
    return k


def look_at(eye, focal, up) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` of a camera at ``eye`` looking at ``focal`` with ``up`` as
    the image's up (made perpendicular to the view, as VTK's
    ``OrthogonalizeViewUp``); the reference for :func:`opencv_extrinsics`."""
    eye = np.asarray(eye, float)
    z = np.asarray(focal, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)                       # down the image
    r = np.stack([x, y, z])
    return r, -r @ eye


def project(k, r, t, pts) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``(n, 2)`` (``u, v``) and depths ``(n,)`` [mm] of case-frame
    points ``(n, 3)`` [mm]."""
    x = np.asarray(pts, float).reshape(-1, 3) @ np.asarray(r).T + np.asarray(t)
    z = x[:, 2]
    uv = (x[:, :2] / z[:, None]) * np.diag(k)[:2] + np.asarray(k)[:2, 2]
    return uv, z


def pixel_rays(k, size) -> np.ndarray:
    """``K^-1 (u, v, 1)`` of every pixel centre: (H, W, 3) float64 in the camera
    frame, third component 1 (so ``depth * ray`` is the point)."""
    w, h = (int(v) for v in size)
    u = (np.arange(w) - k[0, 2]) / k[0, 0]
    v = (np.arange(h) - k[1, 2]) / k[1, 1]
    out = np.empty((h, w, 3))
    out[..., 0] = u[None, :]
    out[..., 1] = v[:, None]
    out[..., 2] = 1.0
    return out


def depth_from_zbuffer(zb, projection) -> np.ndarray:
    """Metric depth along the optical axis [mm] from a depth buffer.

    Parameters
    ----------
    zb : (H, W) float
        Window depth in [0, 1] (first row at the top); 1 where nothing was drawn.
    projection : (4, 4)
        The projection the frame was drawn with (VTK's, OpenGL convention:
        ``z_ndc = 2 zb - 1``).

    Returns
    -------
    (H, W) float32
        ``Z`` [mm], NaN where nothing was drawn.
    """
    p = np.asarray(projection, dtype=np.float64).reshape(4, 4)
    zb = np.asarray(zb, dtype=np.float64)
    ndc = 2.0 * zb - 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        z = p[2, 3] / (ndc + p[2, 2])
    z[zb >= 1.0] = np.nan
    return z.astype(np.float32)


def points_from_depth(depth, k) -> np.ndarray:
    """Camera-frame points (H, W, 3) float32 [mm] of a depth map (NaN where
    the depth is)."""
    d = np.asarray(depth, np.float64)
    return (pixel_rays(k, (d.shape[1], d.shape[0])) * d[..., None]).astype(np.float32)


def cam_to_case(r, t) -> np.ndarray:
    """The (4, 4) transform camera frame -> case frame of extrinsics ``(R, t)``."""
    m = np.eye(4)
    m[:3, :3] = np.asarray(r).T
    m[:3, 3] = -np.asarray(r).T @ np.asarray(t)
    return m


def normals_from_points(pts) -> np.ndarray:
    """Unit surface normals (H, W, 3) float32 of camera-frame points: the
    cross product of the point differences toward the nearer neighbour
    along each image axis (the one whose depth differs less, so that edges
    take the surface they belong to), turned toward the camera. NaN where a
    pixel or both its neighbours along an axis have no point."""
    p = np.asarray(pts, np.float64)
    h, w, _ = p.shape
    nan = np.full(3, np.nan)

    def diff(axis):
        pad = [(0, 0)] * 3
        pad[axis] = (1, 1)
        q = np.pad(p, pad, constant_values=np.nan)
        sl = [slice(None)] * 3
        sl[axis] = slice(2, None)
        fwd = q[tuple(sl)] - p
        sl[axis] = slice(0, -2)
        bwd = p - q[tuple(sl)]
        zf, zb = np.abs(fwd[..., 2]), np.abs(bwd[..., 2])
        use_f = np.where(np.isnan(zb), True, np.where(np.isnan(zf), False, zf <= zb))
        return np.where(use_f[..., None], fwd, bwd)

    dx, dy = diff(1), diff(0)
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm[..., None]
    flip = np.sum(n * p, axis=2) > 0          # facing away from the eye: turn it
    n[flip] *= -1.0
    bad = ~np.isfinite(n).all(axis=2) | (norm == 0)
    n[bad] = nan
    return n.astype(np.float32)


# ------------------------------------------------------------------ paths
def zoomed(eye, focal, zoom: float) -> np.ndarray:
    """The eye moved ``zoom`` times closer to the focal point."""
    eye, focal = np.asarray(eye, float), np.asarray(focal, float)
    return focal + (eye - focal) / float(zoom)


def orbit_camera(case_camera, t: float, half_angle_deg: float, period_s: float):
    """The case camera's eye circled about its viewing axis: on a cone of
    ``half_angle_deg`` about the focal point, one turn per ``period_s``
    (at ``t = 0`` tilted toward the image's up); ``(eye, focal, up)``."""
    eye = np.asarray(case_camera.eye_mm, float)
    focal = np.asarray(case_camera.focal_mm, float)
    up0 = np.asarray(case_camera.up, float)
    back = eye - focal
    dist = np.linalg.norm(back)
    a = back / dist
    u = up0 - (up0 @ a) * a
    u /= np.linalg.norm(u)
    s = np.cross(a, u)
    phi = 2.0 * math.pi * float(t) / float(period_s)
    th = math.radians(half_angle_deg)
    d = math.cos(th) * a + math.sin(th) * (math.cos(phi) * u + math.sin(phi) * s)
    return focal + dist * d, focal, up0


def frame_camera(mode: str, t: float, recorded, case_camera, zoom: float = 1.0,
                 orbit=(25.0, 12.0)):
    """The camera ``(eye, focal, up)`` of one frame.

    Parameters
    ----------
    mode : {"recorded", "fixed", "orbit"}
    t : float
        Playback time [s].
    recorded : tuple or None
        The recorded camera at ``t`` (``Timeline.camera_at``); None without
        a stream (``recorded`` then shows the case camera).
    case_camera : Camera
        ``eye_mm``, ``focal_mm``, ``up``.
    zoom : float
    orbit : (float, float)
        Half-angle [deg] and period [s] of ``orbit``.
    """
    if mode == "recorded" and recorded is not None:
        eye, focal, up = (np.asarray(v, float) for v in recorded)
    elif mode == "orbit":
        eye, focal, up = orbit_camera(case_camera, t, *orbit)
    else:
        eye, focal, up = (np.asarray(v, float) for v in (case_camera.eye_mm,
                                                          case_camera.focal_mm,
                                                          case_camera.up))
    return zoomed(eye, focal, zoom), focal, up


def stereo_cameras(eye, focal, up, baseline_mm: float | None) -> list:
    """The cameras of one frame: ``[(eye, focal, up)]`` mono, or the left and
    right eyes of a parallel pair ``baseline_mm`` apart, each shifted half the
    baseline along the image's right from the given camera (focal points
    shifted alike, so the optical axes stay parallel)."""
    eye, focal, up = (np.asarray(v, float) for v in (eye, focal, up))
    if baseline_mm is None:
        return [(eye, focal, up)]
    r, _ = look_at(eye, focal, up)
    off = 0.5 * float(baseline_mm) * r[0]
    return [(eye - off, focal - off, up), (eye + off, focal + off, up)]
