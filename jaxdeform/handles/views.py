"""Multi-view renders of a mesh for barycentric feature distillation (seed 004, Sec. 3.2 and App. J).

Cameras. ``n`` view directions come from the Fibonacci sphere (App. J: "100 views using Fibonacci sampling"):

    y_i = 1 - (2 i + 1) / n,   r_i = sqrt(1 - y_i^2),   phi_i = i * pi (3 - sqrt 5),
    d_i = (r_i cos phi_i, y_i, r_i sin phi_i),           i = 0 .. n - 1,

i.e. equal-area latitude bands walked with the golden angle; the spiral's axis is the world's up (+y by
default), so no view direction is parallel to the cameras' up vector. Every camera looks at the bounding-box
centre ``c`` from ``c + D d_i`` with ``D = margin * R / sin(fov / 2)`` (``R``: the bounding sphere about ``c``,
so the whole sphere fits the field of view from every direction). With ``tight=True`` (default) each camera's
field of view is then narrowed to the mesh's own silhouette: the largest tangent ``|x_c / z_c|``,
``|y_c / z_c|`` of a vertex in camera coordinates, times ``margin`` — the mesh fills the image, which gives
the 2D backbone the most pixels of it, and every vertex still projects inside the image.

Simplification. Meshes above ``target_faces`` (50k, Sec. 4) are decimated with quadric error metrics
(Garland and Heckbert, through ``fast_simplification``) before rendering; smaller meshes are used as they are.

Rendering. One ray per pixel centre through :class:`jaxdeform.mesh.render.RayCaster` (one Embree scene for all
views). For every covered pixel (i, j) (its centre hits a triangle, the set Omega of eq. 3) we keep the
triangle id, the barycentric coordinates B(i, j) and the surface point P_ij = B(i, j) T(i, j) (eq. 2: T holds
the triangle's vertex positions, computed in float64 and stored as float32), plus the shaded colour the 2D
backbone sees: two-sided Lambert with a headlight (``render.py``'s shading) times the base colour or the
barycentric interpolation of per-vertex colours, on a white background. Pixel (i, j) has its centre at
image coordinates (y, x) = (i + 0.5, j + 0.5), row 0 at the top, the convention of the patch grid in
``backbone.py``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import fast_simplification
import numpy as np
from jaxtyping import Float, Int

from jaxdeform.errors import DegenerateMeshError
from jaxdeform.mesh.render import AMBIENT, Camera, RayCaster, _check_mesh, _check_vertices, _rgb

#: pi (3 - sqrt 5): the golden angle in radians.
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))

#: Colour of the mesh in the renders when no per-vertex colours are given (RGB in [0, 1]).
BASE_COLOR = (0.75, 0.78, 0.85)


# ---------------------------------------------------------------------------------------------- cameras


def fibonacci_directions(n: int) -> Float[np.ndarray, "n 3"]:
    """``n`` unit vectors spread evenly over the sphere (Fibonacci spiral about +y), float64."""
    n = int(n)
    if n < 1:
        raise ValueError(f"the number of directions must be at least 1, got {n}.")
    i = np.arange(n, dtype=np.float64)
    y = 1.0 - (2.0 * i + 1.0) / n
    r = np.sqrt(np.maximum(1.0 - y * y, 0.0))
    phi = i * GOLDEN_ANGLE
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)


def _orient(directions: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Rotate directions made about +y so that +y goes to ``up`` (unit)."""
    y = np.array([0.0, 1.0, 0.0])
    c = float(np.dot(y, up))
    if c > 1.0 - 1e-12:
        return directions
    if c < -1.0 + 1e-12:
        return directions * np.array([1.0, -1.0, -1.0])  # half turn about x
    axis = np.cross(y, up)
    s = float(np.linalg.norm(axis))
    k = axis / s
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    rot = np.eye(3) + s * kx + (1.0 - c) * (kx @ kx)  # Rodrigues
    return directions @ rot.T


def fibonacci_cameras(
    vertices,
    n: int = 100,
    *,
    fov_deg: float = 40.0,
    margin: float = 1.05,
    up=(0.0, 1.0, 0.0),
    tight: bool = True,
    aspect: float = 1.0,
) -> list[Camera]:
    """``n`` cameras on the Fibonacci sphere around the mesh, all looking at its bounding-box centre.

    **Arguments:**

    - ``vertices``: the mesh's vertices ``(V, 3)``.
    - ``n``: the number of cameras.
    - ``fov_deg``: sets the distance (the bounding sphere times ``margin`` fills it); in (0, 180).
    - ``margin``: at least 1.
    - ``up``: the world's vertical, which every camera keeps upright.
    - ``tight``: narrow each camera's field of view to the mesh's projection times ``margin``.
    - ``aspect``: the image's width / height (``Camera.fov_deg`` spans the shorter side).

    **Returns:**

    The ``n`` cameras.

    **Raises:**

    ``ValueError`` for invalid vertices, ``fov_deg`` or ``margin``.
    """
    v = _check_vertices(vertices)
    if not 0.0 < float(fov_deg) < 180.0:
        raise ValueError(f"fov_deg must lie strictly between 0 and 180, got {fov_deg}.")
    if not float(margin) >= 1.0:
        raise ValueError(f"margin must be at least 1, got {margin}.")
    if not float(aspect) > 0.0:
        raise ValueError(f"aspect must be positive, got {aspect}.")
    up_v = np.asarray(up, dtype=np.float64).reshape(-1)
    if up_v.shape != (3,) or not np.linalg.norm(up_v) > 0.0:
        raise ValueError(f"up must be a non-zero 3-vector, got {up!r}.")
    up_v = up_v / np.linalg.norm(up_v)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    radius = float(np.sqrt(np.max(np.sum((v - centre) ** 2, axis=1))))
    if radius == 0.0:
        raise DegenerateMeshError("all vertices coincide, so there is nothing to frame.")
    distance = float(margin) * radius / math.sin(math.radians(fov_deg) / 2.0)
    cameras = []
    for d in _orient(fibonacci_directions(n), up_v):
        cam = Camera(eye=tuple(centre + distance * d), target=tuple(centre), up=tuple(up_v), fov_deg=fov_deg)
        if tight:
            fwd, right, cup = cam.basis()
            rel = v - np.asarray(cam.eye)
            z = rel @ fwd  # > 0: every vertex lies inside the bounding sphere, in front of the camera
            tx = float(np.max(np.abs(rel @ right) / z))
            ty = float(np.max(np.abs(rel @ cup) / z))
            # tangent of the half field of view across the shorter side that holds both extents
            t = max(tx / aspect, ty) if aspect >= 1.0 else max(tx, ty * aspect)
            fov = 2.0 * math.degrees(math.atan(float(margin) * t))
            fov = min(max(fov, 1e-3), float(fov_deg))  # a mesh seen exactly edge-on has no extent: keep fov > 0
            cam = Camera(eye=cam.eye, target=cam.target, up=cam.up, fov_deg=fov)
        cameras.append(cam)
    return cameras


# ----------------------------------------------------------------------------------------- simplification


def simplify(vertices, faces, target_faces: int = 50_000) -> tuple[Float[np.ndarray, "v 3"], Int[np.ndarray, "f 3"]]:
    """QEM-decimate a mesh to about ``target_faces`` faces when it has more; otherwise return it unchanged.

    **Arguments:**

    - ``vertices``, ``faces``: the mesh, ``(V, 3)`` and ``(F, 3)``.
    - ``target_faces``: at least 4.

    **Returns:**

    Float64 vertices and int64 faces (the decimated mesh's own, compact vertex list).

    **Raises:**

    ``ValueError`` if ``target_faces < 4``, and the mesh checks' errors.
    """
    v, f = _check_mesh(vertices, faces)
    target = int(target_faces)
    if target < 4:
        raise ValueError(f"target_faces must be at least 4, got {target_faces}.")
    if f.shape[0] <= target:
        return v, f
    pts, tris = fast_simplification.simplify(v, f, target_count=target)
    pts, tris = np.asarray(pts, dtype=np.float64), np.asarray(tris, dtype=np.int64)
    if tris.shape[0] == 0:
        raise DegenerateMeshError(f"QEM simplification of {f.shape[0]} faces to {target} left no faces.")
    return pts, tris


# -------------------------------------------------------------------------------------------- rendering


class CoveredPixels(NamedTuple):
    """The covered pixels of all views as flat arrays (the set Omega of eq. 3), P = their number."""

    view: Int[np.ndarray, " p"]  # int32 view index
    pixel_yx: Float[np.ndarray, "p 2"]  # float32 pixel-centre image coordinates (i + 0.5, j + 0.5)
    points: Float[np.ndarray, "p 3"]  # float32 surface points P_ij = B(i, j) T(i, j)


class RenderedViews(NamedTuple):
    """Ray-cast renders of N views of H x W pixels (background: ``tri`` -1, ``bary`` 0, ``points`` NaN)."""

    tri: Int[np.ndarray, "n h w"]  # int32 triangle covering the pixel centre, -1 for background
    bary: Float[np.ndarray, "n h w 3"]  # float32 barycentric coordinates B(i, j) of the pixel centre's hit
    points: Float[np.ndarray, "n h w 3"]  # float32 P_ij = B(i, j) T(i, j) (eq. 2)
    rgb: np.ndarray  # (n, h, w, 3) uint8 shaded colours, the backbone's input

    @property
    def image_hw(self) -> tuple[int, int]:
        return int(self.tri.shape[1]), int(self.tri.shape[2])

    def covered(self) -> CoveredPixels:
        """View index, pixel centre (y, x) and surface point of every covered pixel, in row-major order."""
        n, h, w = self.tri.shape
        flat = np.flatnonzero(self.tri.reshape(-1) >= 0)
        view, rest = np.divmod(flat, h * w)
        i, j = np.divmod(rest, w)
        yx = np.stack([i, j], axis=1).astype(np.float32) + np.float32(0.5)
        return CoveredPixels(view.astype(np.int32), yx, self.points.reshape(-1, 3)[flat])


def _vertex_colors(colors, n_vertices: int) -> np.ndarray:
    c = np.asarray(colors)
    if c.shape != (n_vertices, 3):
        raise ValueError(f"colors must have shape ({n_vertices}, 3) (one RGB per vertex), got {c.shape}.")
    c = c.astype(np.float64) / 255.0 if np.issubdtype(c.dtype, np.integer) else c.astype(np.float64)
    if not np.all(np.isfinite(c)) or c.min() < 0.0 or c.max() > 1.0:
        raise ValueError("colors must be finite RGB floats in [0, 1] (or uint8 0-255).")
    return c


def render_views(
    vertices,
    faces,
    cameras: list[Camera],
    resolution: int | tuple[int, int] = 512,
    colors=None,
    progress: bool = True,
    *,
    base_color=BASE_COLOR,
    background=(1.0, 1.0, 1.0),
) -> RenderedViews:
    """Ray-cast every camera; see the module docstring.

    Memory: N H W (4 + 12 + 12 + 3) bytes (about 800 MB for 100 views at 512).

    **Arguments:**

    - ``vertices``, ``faces``: the mesh.
    - ``cameras``: the N cameras.
    - ``resolution``: square side, or (height, width).
    - ``colors``: optional per-vertex RGB (``(V, 3)``, floats in [0, 1] or uint8), interpolated with the
        barycentrics and shaded; otherwise ``base_color``.
    - ``progress``: show a progress bar.
    - ``base_color``, ``background``: the mesh's and the background's colour.

    **Returns:**

    The :class:`RenderedViews` (triangle id, barycentrics, surface point and shaded RGB per pixel).

    **Raises:**

    ``ValueError`` for a resolution below 1 x 1.
    """
    caster = RayCaster(vertices, faces)
    v, f = caster.vertices, caster.faces
    h, w = (int(resolution), int(resolution)) if np.ndim(resolution) == 0 else (int(resolution[0]), int(resolution[1]))
    if h < 1 or w < 1:
        raise ValueError(f"resolution must be at least 1 x 1 pixels, got {resolution!r}.")
    cameras = list(cameras)
    if not cameras:
        raise ValueError("render_views needs at least one camera.")
    vc = None if colors is None else _vertex_colors(colors, v.shape[0])
    base = _rgb(base_color, "base_color")
    bg = np.round(_rgb(background, "background") * 255.0).astype(np.uint8)
    n = len(cameras)
    tri = np.full((n, h, w), -1, dtype=np.int32)
    bary = np.zeros((n, h, w, 3), dtype=np.float32)
    points = np.full((n, h, w, 3), np.nan, dtype=np.float32)
    rgb = np.empty((n, h, w, 3), dtype=np.uint8)
    rgb[...] = bg
    from tqdm.auto import tqdm

    for k, cam in enumerate(tqdm(cameras, desc="render views", unit="view", disable=not progress)):
        tr = caster.trace(cam, w, h)
        corners = f[tr.triangle]  # (m, 3) vertex ids of the hit triangles
        tri[k].reshape(-1)[tr.pixel] = tr.triangle
        bary[k].reshape(-1, 3)[tr.pixel] = tr.barycentric
        points[k].reshape(-1, 3)[tr.pixel] = np.einsum("mk,mkc->mc", tr.barycentric, v[corners])
        colour = base if vc is None else np.einsum("mk,mkc->mc", tr.barycentric, vc[corners])
        colour = colour * caster.shade(tr, AMBIENT)[:, None]
        rgb[k].reshape(-1, 3)[tr.pixel] = (np.clip(colour, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return RenderedViews(tri, bary, points, rgb)
