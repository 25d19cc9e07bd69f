"""A small CPU ray-cast renderer (Embree through ``embreex``) for quick looks and figures.

One primary ray per pixel (or ``supersample``\\ :sup:`2` per pixel), no shadows: smooth per-vertex normals
interpolated with the hit's barycentric coordinates, two-sided Lambert shading with a headlight at the
camera plus ambient light. A per-vertex ``scalar`` is interpolated per pixel and mapped through a colormap
implemented here in NumPy (``viridis`` and the diverging ``coolwarm``, append ``_r`` to reverse), with an
optional colour bar drawn by PIL in a strip at the right of the image (the mesh viewport is narrowed so the
bar never covers the mesh).

Conventions: images are ``(H, W, 3)`` uint8; colours given as arguments are RGB floats in [0, 1];
``Camera.fov_deg`` is the angle spanned by the *shorter* side of the viewport, so a camera frames a mesh the
same way at any aspect ratio. Everything is vectorized over pixels (Embree traces the rays in one call).
A :class:`RayCaster` builds the Embree scene once and traces it from many cameras (multi-view rendering).
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh
from jaxtyping import ArrayLike, Float
from PIL import Image, ImageDraw, ImageFont

from jaxdeform.errors import ConnectivityError, DegenerateMeshError, MeshFormatError
from jaxdeform.mesh.io import default_mode
from jaxdeform.typing import Real

#: Fraction of light that is ambient; the rest is the (two-sided) Lambert headlight.
AMBIENT = 0.25

# Anchor colours (RGB 0-255), evenly spaced over [0, 1] and interpolated linearly.
_CMAP_ANCHORS: dict[str, np.ndarray] = {
    # Perceptually uniform dark blue -> green -> yellow (samples of matplotlib's viridis).
    "viridis": np.array(
        [
            [68, 1, 84],
            [72, 40, 120],
            [62, 73, 137],
            [49, 104, 142],
            [38, 130, 142],
            [31, 158, 137],
            [53, 183, 121],
            [110, 206, 88],
            [181, 222, 43],
            [253, 231, 37],
        ],
        dtype=np.float64,
    ),
    # Diverging blue -> light grey/white -> red (close to Moreland's "cool to warm").
    "coolwarm": np.array(
        [
            [59, 76, 192],
            [98, 130, 234],
            [141, 176, 254],
            [184, 208, 249],
            [221, 221, 221],
            [245, 196, 173],
            [244, 154, 123],
            [222, 96, 77],
            [180, 4, 38],
        ],
        dtype=np.float64,
    ),
}

COLORMAPS = tuple(sorted(_CMAP_ANCHORS)) + tuple(sorted(name + "_r" for name in _CMAP_ANCHORS))


def _cmap_anchors(name: str) -> np.ndarray:
    base, reverse = (name[:-2], True) if name.endswith("_r") else (name, False)
    if base not in _CMAP_ANCHORS:
        raise ValueError(f"unknown colormap {name!r}; expected one of {', '.join(COLORMAPS)}.")
    anchors = _CMAP_ANCHORS[base] / 255.0
    return anchors[::-1] if reverse else anchors


def colormap(t, cmap: str = "viridis") -> np.ndarray:
    """Map values to colours.

    **Arguments:**

    - `t`: values in [0, 1] (clipped), any shape.
    - `cmap`: a colormap name (optionally with a `_r` suffix for reversed).

    **Returns:**

    RGB floats in [0, 1], shape `t.shape + (3,)`.

    **Raises:**

    `ValueError` for an unknown colormap.
    """
    anchors = _cmap_anchors(cmap)
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    x = t * (anchors.shape[0] - 1)
    i = np.minimum(np.floor(x).astype(np.int64), anchors.shape[0] - 2)
    w = (x - i)[..., None]
    return anchors[i] * (1.0 - w) + anchors[i + 1] * w


_GOLDEN = 0.6180339887498949


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectorized HSV -> RGB, all inputs in [0, 1]; returns ``h.shape + (3,)``."""
    h6 = (np.asarray(h) % 1.0) * 6.0
    i = np.floor(h6).astype(np.int64) % 6
    fr = h6 - np.floor(h6)
    p, q, t = v * (1.0 - s), v * (1.0 - s * fr), v * (1.0 - s * (1.0 - fr))
    table = np.stack(
        [np.stack(c, axis=-1) for c in ((v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q))],
        axis=0,
    )  # (6, n, 3)
    return table[i, np.arange(i.size)]


def categorical_colors(n: int) -> np.ndarray:
    """Visually distinct RGB colours, deterministic.

    Hues step by the golden ratio (so any prefix is spread over the colour wheel and colour ``i`` is the same
    for every ``n``), with value and saturation alternating over a short cycle so that neighbouring hues
    that come close on the wheel still differ in brightness.

    **Arguments:**

    - `n`: the number of colours, non-negative.

    **Returns:**

    Colours in [0, 1], shape `(n, 3)`.

    **Raises:**

    `ValueError` for a negative `n`.
    """
    n = int(n)
    if n < 0:
        raise ValueError(f"the number of colours must be non-negative, got {n}.")
    if n == 0:
        return np.zeros((0, 3))
    i = np.arange(n)
    hue = (0.08 + i * _GOLDEN) % 1.0
    sat = np.array([0.75, 0.55, 0.90])[i % 3]
    val = np.array([0.92, 0.72, 0.82, 0.62])[i % 4]
    return np.clip(_hsv_to_rgb(hue, sat, val), 0.0, 1.0)


# ----------------------------------------------------------------------------------------------- camera


def _vec3(x, name: str) -> tuple[float, float, float]:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(
            f"camera {name} must be 3 finite numbers, got {[float(t) for t in a] if a.size <= 3 else x!r}."
        )
    return (float(a[0]), float(a[1]), float(a[2]))


#: A 3-vector as :class:`Camera` takes it: any 3 numbers, a sequence or an array (it stores a tuple of 3 floats).
Vector3 = Sequence[float | int] | Real[ArrayLike, "3"]


@dataclass(frozen=True)
class Camera:
    """A pinhole camera at `eye` looking at `target`.

    Vectors are stored as tuples of floats (the dataclass is hashable).

    **Arguments:**

    - `eye`: the camera position, 3 finite numbers.
    - `target`: the point looked at, 3 finite numbers, not `eye`.
    - `up`: a non-zero vertical hint; it need not be orthogonal to the view.
    - `fov_deg`: the field of view across the shorter side of the viewport, strictly between 0 and 180.

    **Raises:**

    `ValueError` for any argument outside these rules.
    """

    eye: Vector3
    target: Vector3
    up: Vector3 = (0.0, 1.0, 0.0)
    fov_deg: float | int = 35.0

    def __post_init__(self):
        for name in ("eye", "target", "up"):
            object.__setattr__(self, name, _vec3(getattr(self, name), name))
        fov = float(self.fov_deg)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"camera fov_deg must lie strictly between 0 and 180, got {self.fov_deg}.")
        object.__setattr__(self, "fov_deg", fov)
        if np.linalg.norm(np.subtract(self.target, self.eye)) == 0.0:
            raise ValueError("camera eye and target must differ.")
        if np.linalg.norm(self.up) == 0.0:
            raise ValueError("camera up must be a non-zero vector.")

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The camera's orthonormal frame.

        **Returns:**

        `(forward, right, up)` unit vectors `(3,)`; up is re-chosen if it is parallel to the view.
        """
        fwd = np.subtract(self.target, self.eye)
        fwd = fwd / np.linalg.norm(fwd)
        up = np.asarray(self.up) / np.linalg.norm(self.up)
        right = np.cross(fwd, up)
        if np.linalg.norm(right) < 1e-9:
            alt = np.eye(3)[int(np.argmin(np.abs(fwd)))]
            right = np.cross(fwd, alt)
        right = right / np.linalg.norm(right)
        return fwd, right, np.cross(right, fwd)


def auto_camera(
    vertices,
    *,
    azimuth_deg: float | int = 30.0,
    elevation_deg: float | int = 20.0,
    fov_deg: float | int = 35.0,
    up_axis: str = "y",
    margin: float | int = 1.08,
    fit: str = "sphere",
) -> Camera:
    """A camera looking at the mesh from the given direction, framing it.

    **Arguments:**

    - `vertices`: positions `(V, 3)`.
    - `azimuth_deg`: turns around the vertical (0 looks from +z for y-up, from -y for z-up).
    - `elevation_deg`: lifts the eye above the horizontal plane.
    - `fov_deg`: the field of view.
    - `up_axis`: the world's vertical, "y" (the graphics convention of most mesh data sets) or "z".
    - `margin`: > 1 leaves a little room around the mesh.
    - `fit`: "sphere": the camera looks at the bounding-box centre from where the bounding sphere fits the view
        (the same distance from every direction); "box": it looks along the same direction at the centre of the
        mesh's extent across the view and comes as close as lets every vertex project inside the view of a
        square image (the mesh fills the view along its longer projected side).

    **Returns:**

    The :class:`Camera`.

    **Raises:**

    `ValueError` for a non-finite angle, an unknown `up_axis` or `fit`; `MeshFormatError` for bad vertices.
    """
    v = _check_vertices(vertices)
    for name, value in (("azimuth", azimuth_deg), ("elevation", elevation_deg), ("field of view", fov_deg)):
        if not math.isfinite(value):
            raise ValueError(f"the camera's {name} must be a finite number of degrees, got {float(value)}.")
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    radius = float(np.sqrt(np.max(np.sum((v - centre) ** 2, axis=1))))
    if radius == 0.0:
        radius = 1.0
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    horizontal, vertical = math.cos(el), math.sin(el)
    if up_axis == "y":
        direction = np.array([horizontal * math.sin(az), vertical, horizontal * math.cos(az)])
        up = (0.0, 1.0, 0.0)
    elif up_axis == "z":
        direction = np.array([horizontal * math.sin(az), -horizontal * math.cos(az), vertical])
        up = (0.0, 0.0, 1.0)
    else:
        raise ValueError(f"up_axis must be 'y' or 'z', got {up_axis!r}.")
    if fit == "sphere":
        distance = margin * radius / math.sin(math.radians(fov_deg) / 2.0)
        return Camera(eye=tuple(centre + distance * direction), target=tuple(centre), up=up, fov_deg=fov_deg)
    if fit != "box":
        raise ValueError(f"fit must be 'sphere' or 'box', got {fit!r}.")
    _, right, upward = Camera(eye=tuple(centre + direction), target=tuple(centre), up=up).basis()
    # a vertex at offset (a, b) across the view and t toward the eye projects inside the view when
    # max(|a|, |b|) <= tan(fov / 2) (distance - t) / margin; the camera then slides across the view until the
    # projected extent is centred (a few fixed-point rounds: the projection depends on the distance)
    slope = math.tan(math.radians(fov_deg) / 2.0) / margin

    def fitted(target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        rel = v - target
        spread = np.maximum(np.abs(rel @ right), np.abs(rel @ upward))
        toward = rel @ direction
        distance = max(float(np.max(toward + spread / slope)), float(np.max(toward)) + 1e-6 * radius)
        depth = distance - toward
        return distance, (rel @ right) / depth, (rel @ upward) / depth

    for _ in range(12):
        distance, across, along = fitted(centre)
        shift = 0.5 * (across.max() + across.min()) * right + 0.5 * (along.max() + along.min()) * upward
        centre = centre + distance * shift
    distance = fitted(centre)[0]
    return Camera(eye=tuple(centre + distance * direction), target=tuple(centre), up=up, fov_deg=fov_deg)


def _part_count(faces: np.ndarray, inside: np.ndarray) -> int:
    """Connected pieces of the faces whose three vertices are all ``inside`` (edge-connected)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    sub = faces[inside[faces].all(axis=1)]
    if sub.shape[0] == 0:
        return 0
    n = inside.shape[0]
    edges = np.concatenate([sub[:, [0, 1]], sub[:, [1, 2]]])
    graph = coo_matrix((np.ones(edges.shape[0]), (edges[:, 0], edges[:, 1])), shape=(n, n))
    labels = connected_components(graph, directed=False)[1]
    return int(np.unique(labels[np.unique(sub)]).size)


def guess_up_axis(vertices, faces, slab: float = 0.15) -> str:
    """A guess of a standing shape's vertical, "y" or "z", for framing figures of data that does not say.

    Feet, legs and arms make a standing shape come apart into several pieces near its lowest or highest end,
    while its front and back ends are one piece each (a head, a tail). For each candidate axis the faces within
    ``slab`` of the extent from either end are split into connected pieces; the axis with the most pieces at
    one of its ends wins, a tie goes to the longer extent. Right for the data sets of ``../shared/data`` that
    stand (horse-gallop and horse-poses y, samba y, cactus z); wrong for some figurines (armadillo,
    cheburashka): take it as a default that a user overrides.

    **Arguments:**

    - `vertices`: `(V, 3)`; `faces`: `(F, 3)` vertex indices.
    - `slab`: the fraction of the extent at each end, in (0, 0.5].

    **Returns:**

    "y" or "z".

    **Raises:**

    `ValueError` for a `slab` outside (0, 0.5]; `MeshFormatError` for bad vertices.
    """
    v, f = _check_mesh(vertices, faces)
    f = f.astype(np.int64)
    if not 0.0 < slab <= 0.5:
        raise ValueError(f"slab must lie in (0, 0.5], got {slab}.")
    score = {}
    for name, axis in (("y", 1), ("z", 2)):
        h = v[:, axis]
        lo, hi = float(h.min()), float(h.max())
        cut = slab * (hi - lo)
        pieces = max(_part_count(f, h <= lo + cut), _part_count(f, h >= hi - cut))
        score[name] = (pieces, hi - lo)
    return "y" if score["y"] >= score["z"] else "z"


# ----------------------------------------------------------------------------------------- ray casting


@dataclass(frozen=True, eq=False)
class RayHits:
    """Per-pixel result of :func:`cast_rays` (row 0 is the top of the image).

    ``triangle`` (H, W) int64 face index, -1 for background; ``barycentric`` (H, W, 3) weights of the face's
    three vertices (sum 1; zeros on background); ``points`` (H, W, 3) hit positions (NaN on background);
    ``depth`` (H, W) distance from the eye along the ray (inf on background); ``directions`` (H, W, 3) unit
    ray directions.
    """

    triangle: np.ndarray
    barycentric: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    directions: np.ndarray = field(repr=False)

    @property
    def hit(self) -> np.ndarray:
        """Whether each pixel hit the mesh, `(H, W)` bool."""
        return self.triangle >= 0


def _check_vertices(vertices) -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise MeshFormatError(f"vertices must be a non-empty (V, 3) array, got shape {v.shape}.")
    if not np.all(np.isfinite(v)):
        bad = int(np.argwhere(~np.isfinite(v))[0, 0])
        raise MeshFormatError(f"vertex {bad} has a NaN or infinite coordinate; cannot render it.")
    return v


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = _check_vertices(vertices)
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshFormatError(f"faces must be an (F, 3) array, got shape {f.shape}.")
    if f.shape[0] == 0:
        raise DegenerateMeshError("the mesh has no faces, so there is nothing to render.")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshFormatError(f"faces must hold integer vertex indices, got dtype {f.dtype}.")
    if f.min() < 0 or f.max() >= v.shape[0]:
        bad = int(f.max()) if f.max() >= v.shape[0] else int(f.min())
        raise ConnectivityError(f"faces index vertex {bad} but the mesh has {v.shape[0]} vertices.")
    return v, f.astype(np.int64)


def _ray_directions(camera: Camera, width: int, height: int) -> np.ndarray:
    """Unit ray directions, (height * width, 3) float32, row-major from the top-left pixel."""
    fwd, right, up = camera.basis()
    half = math.tan(math.radians(camera.fov_deg) / 2.0) / (min(width, height) / 2.0)
    xs = ((np.arange(width) + 0.5 - width / 2.0) * half).astype(np.float32)
    ys = ((height / 2.0 - (np.arange(height) + 0.5)) * half).astype(np.float32)
    d = fwd.astype(np.float32) + xs[None, :, None] * right.astype(np.float32)
    d = d + ys[:, None, None] * up.astype(np.float32)
    d = d.reshape(-1, 3)
    d /= np.sqrt(np.einsum("nc,nc->n", d, d))[:, None]
    return d


@dataclass(frozen=True, eq=False)
class Trace:
    """Compact ray-cast result of one view: only the hit pixels (flat row-major indices into the image)."""

    width: int
    height: int
    directions: np.ndarray  # (H * W, 3) float32 unit ray directions
    pixel: np.ndarray  # (m,) flat indices of the hit pixels
    triangle: np.ndarray  # (m,) int64
    barycentric: np.ndarray  # (m, 3) float64, non-negative, summing to 1


class RayCaster:
    """An Embree scene of one mesh, built once and traced from any number of cameras.

    Embree works in float32, so the scene is shifted to put ``origin`` (default: the bounding-box centre) at
    the origin; cameras should look at points near it (hit positions are recomputed in float64 from the
    barycentrics, so only the ray-triangle test itself is float32). Vertex normals for :meth:`shade` are
    computed once, on first use.
    """

    def __init__(self, vertices, faces, origin=None):
        v, f = _check_mesh(vertices, faces)
        self.vertices, self.faces = v, f
        if origin is None:
            origin = 0.5 * (v.min(axis=0) + v.max(axis=0))
        self.origin = np.asarray(_vec3(origin, "origin"))
        self._scene = rtcs.EmbreeScene()
        shifted = np.ascontiguousarray(v - self.origin, dtype=np.float32)
        self._mesh = TriangleMesh(self._scene, shifted, np.ascontiguousarray(f, dtype=np.int32))
        self._normals: np.ndarray | None = None

    @property
    def vertex_normals(self) -> np.ndarray:
        """Area-weighted (unnormalised) vertex normals, `(V, 3)` float64, computed once."""
        if self._normals is None:
            self._normals = _vertex_normals(self.vertices, self.faces)
        return self._normals

    def trace(self, camera: Camera, width: int, height: int) -> Trace:
        """Trace one ray through the centre of every pixel of an image.

        **Arguments:**

        - `camera`: the :class:`Camera`.
        - `width`, `height`: the image size in pixels, at least 1.

        **Returns:**

        The :class:`Trace` of the hit pixels.

        **Raises:**

        `ValueError` for an image smaller than 1 x 1.
        """
        if int(width) < 1 or int(height) < 1:
            raise ValueError(f"image size must be at least 1 x 1 pixels, got {width} x {height}.")
        width, height = int(width), int(height)
        dirs = _ray_directions(camera, width, height)
        eye = (np.asarray(camera.eye) - self.origin).astype(np.float32)
        origins = np.ascontiguousarray(np.broadcast_to(eye, dirs.shape))
        res = self._scene.run(origins, dirs, output=1)
        prim = np.asarray(res["primID"])
        pixel = np.flatnonzero(prim >= 0)
        # Embree's (u, v) weight the face's 2nd and 3rd vertex: p = (1 - u - v) p0 + u p1 + v p2.
        u = np.asarray(res["u"])[pixel].astype(np.float64)
        w = np.asarray(res["v"])[pixel].astype(np.float64)
        bary = np.clip(np.stack([1.0 - u - w, u, w], axis=-1), 0.0, None)
        bary /= np.maximum(bary.sum(axis=-1, keepdims=True), 1e-30)
        return Trace(width, height, dirs, pixel, prim[pixel].astype(np.int64), bary)

    def shade(self, trace: Trace, ambient: float = AMBIENT) -> np.ndarray:
        """Two-sided Lambert shading with a headlight.

        **Arguments:**

        - `trace`: a :class:`Trace` of this caster.
        - `ambient`: the darkest value.

        **Returns:**

        One value per hit pixel of `trace`, `(m,)`, in [ambient, 1].
        """
        return _shade(self.vertices, self.faces, trace, ambient, self.vertex_normals)


def _trace(v: np.ndarray, f: np.ndarray, camera: Camera, width: int, height: int) -> Trace:
    return RayCaster(v, f, origin=camera.target).trace(camera, width, height)


def pixel_scale(camera: Camera, width: int, height: int) -> float:
    """The view-plane size of one pixel at unit depth (as the renderer's rays).

    **Arguments:**

    - `camera`: the :class:`Camera`.
    - `width`, `height`: the image size.

    **Returns:**

    tan(fov / 2) / (min(W, H) / 2).
    """
    return math.tan(math.radians(camera.fov_deg) / 2.0) / (min(width, height) / 2.0)


def project(
    camera: Camera, width: int, height: int, points: Float[ArrayLike, "p 3"]
) -> tuple[Float[np.ndarray, "p 2"], Float[np.ndarray, " p"]]:
    """Display coordinates of points and their depth along the view direction.

    The inverse of the renderer's rays: the ray through pixel (i, j)'s centre (j + 0.5, i + 0.5) has direction
    `forward + (j + 0.5 - W/2) s right + (H/2 - i - 0.5) s up` with `s` = :func:`pixel_scale`.

    **Arguments:**

    - `camera`: the :class:`Camera`.
    - `width`, `height`: the image size.
    - `points`: positions `(P, 3)`.

    **Returns:**

    `(xy, depth)`: display coordinates `(P, 2)` and depths `(P,)` (non-finite coordinates at zero depth).
    """
    fwd, right, up = camera.basis()
    q = np.asarray(points, dtype=np.float64).reshape(-1, 3) - np.asarray(camera.eye)
    depth = q @ fwd
    s = pixel_scale(camera, width, height)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (q @ right) / depth / s + width / 2.0
        y = height / 2.0 - (q @ up) / depth / s
    return np.stack([x, y], axis=-1), depth


def cast_rays(vertices, faces, camera: Camera, width: int, height: int) -> RayHits:
    """Trace one ray through the centre of every pixel of an image.

    **Arguments:**

    - `vertices`: positions `(V, 3)`.
    - `faces`: triangles `(F, 3)`.
    - `camera`: the :class:`Camera`.
    - `width`, `height`: the image size.

    **Returns:**

    The per-pixel :class:`RayHits`.

    **Raises:**

    `MeshFormatError` for bad vertices or faces; `DegenerateMeshError` for a mesh without faces;
    `ConnectivityError` for a face index out of range.
    """
    v, f = _check_mesh(vertices, faces)
    tr = _trace(v, f, camera, width, height)
    n = tr.width * tr.height
    tri = np.full(n, -1, dtype=np.int64)
    tri[tr.pixel] = tr.triangle
    bary = np.zeros((n, 3))
    bary[tr.pixel] = tr.barycentric
    pts = np.einsum("nk,nkc->nc", tr.barycentric, v[f[tr.triangle]])
    points = np.full((n, 3), np.nan)
    points[tr.pixel] = pts
    depth = np.full(n, np.inf)
    depth[tr.pixel] = np.linalg.norm(pts - np.asarray(camera.eye), axis=-1)
    shape = (tr.height, tr.width)
    return RayHits(
        triangle=tri.reshape(shape),
        barycentric=bary.reshape(shape + (3,)),
        points=points.reshape(shape + (3,)),
        depth=depth.reshape(shape),
        directions=tr.directions.astype(np.float64).reshape(shape + (3,)),
    )


# ------------------------------------------------------------------------------------------- rendering


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # area-weighted face normals
    n = np.zeros_like(v)
    for c in range(3):
        for k in range(3):
            n[:, c] += np.bincount(f[:, k], weights=cross[:, c], minlength=v.shape[0])
    return n


def _shade(v, f, tr: Trace, ambient: float, vn: np.ndarray | None = None) -> np.ndarray:
    """Two-sided Lambert with a headlight, per hit pixel: values in [ambient, 1] (``vn``: vertex normals)."""
    tri = tr.triangle
    if vn is None:
        vn = _vertex_normals(v, f)
    n = np.einsum("nk,nkc->nc", tr.barycentric, vn[f[tri]])
    norm = np.linalg.norm(n, axis=-1)
    bad = norm < 1e-12
    if np.any(bad):  # vertex normals cancel out (e.g. a fold): use the face normal instead
        fv = v[f[tri[bad]]]
        n[bad] = np.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0])
        norm = np.linalg.norm(n, axis=-1)
    n = n / np.maximum(norm, 1e-30)[:, None]
    lambert = np.abs(np.einsum("nc,nc->n", n, tr.directions[tr.pixel]))
    return ambient + (1.0 - ambient) * lambert


def _rgb(color, name: str) -> np.ndarray:
    c = np.asarray(color, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)) or c.min() < 0.0 or c.max() > 1.0:
        raise ValueError(f"{name} must be 3 RGB floats in [0, 1], got {color!r}.")
    return c


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, ValueError, OSError):  # Pillow without FreeType: fixed-size bitmap font
        return ImageFont.load_default()


def _fmt(x: float) -> str:
    s = f"{x:.3g}"
    return "0" if s in ("-0", "0") else s


def _text_size(draw: ImageDraw.ImageDraw, text: str, font) -> tuple[int, int]:
    box = draw.textbbox((0, 0), text, font=font)
    return box[2] - box[0], box[3] - box[1]


def _colorbar_layout(width: int, height: int, vmin: float, vmax: float, label: str | None):
    font = _font(max(10, round(height / 42)))
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    ticks = [vmax, 0.5 * (vmin + vmax), vmin] if vmax > vmin else [vmax]
    texts = [_fmt(t) for t in ticks]
    text_w = max(_text_size(probe, t, font)[0] for t in texts)
    bar_w = max(12, round(height / 30))
    pad = max(6, round(height / 60))
    strip = pad + bar_w + pad // 2 + 4 + text_w + pad
    if label:
        strip = max(strip, _text_size(probe, label, font)[0] + 2 * pad)
    if strip > width // 2 or height < 60:
        return None  # too small an image to hold a readable colour bar
    return font, ticks, texts, bar_w, pad, strip


def _draw_colorbar(image: np.ndarray, strip: int, layout, vmin, vmax, cmap, label, background) -> np.ndarray:
    font, ticks, texts, bar_w, pad, _ = layout
    height, width = image.shape[:2]
    pil = Image.fromarray(image)
    draw = ImageDraw.Draw(pil)
    ink = (20, 20, 20) if float(np.dot(background, [0.299, 0.587, 0.114])) > 0.5 else (235, 235, 235)
    text_h = _text_size(draw, "0.9e+09", font)[1]
    top = round(0.12 * height) + (text_h + pad if label else 0)
    bottom = height - round(0.12 * height)
    if bottom - top < 8:
        top, bottom = pad, height - pad
    x0 = width - strip + pad
    x1 = x0 + bar_w
    rows = np.arange(top, bottom)
    t = 1.0 - (rows - top) / max(bottom - top - 1, 1)  # vmax at the top
    colours = (np.clip(colormap(t, cmap), 0, 1) * 255 + 0.5).astype(np.uint8)
    bar = np.repeat(colours[:, None, :], x1 - x0, axis=1)
    out = np.asarray(pil).copy()
    out[top:bottom, x0:x1] = bar
    pil = Image.fromarray(out)
    draw = ImageDraw.Draw(pil)
    draw.rectangle([x0 - 1, top - 1, x1, bottom], outline=ink, width=1)
    for value, text in zip(ticks, texts):
        frac = 0.5 if vmax <= vmin else (vmax - value) / (vmax - vmin)
        y = round(top + frac * (bottom - top - 1))
        draw.line([(x1, y), (x1 + 4, y)], fill=ink, width=1)
        draw.text((x1 + 4 + pad // 2, y), text, font=font, fill=ink, anchor="lm")
    if label:
        draw.text((width - strip / 2, top - pad), label, font=font, fill=ink, anchor="mb")
    return np.asarray(pil)


def _check_vertex_colors(vertex_colors, scalar, n_vertices: int) -> np.ndarray | None:
    """Validate :func:`render`'s ``vertex_colors`` against ``scalar`` and the vertex count.

    Takes the raw ``vertex_colors`` (or None), the raw ``scalar`` (only tested for None) and ``n_vertices``.
    Returns None when ``vertex_colors`` is None, else a float64 ``(n_vertices, 3)`` array with every entry finite
    and in [0, 1]. Raises ValueError (nothing else is checked first) if both ``scalar`` and ``vertex_colors``
    are given, if the shape is not ``(n_vertices, 3)``, or if a colour is not finite or leaves [0, 1].
    """
    if vertex_colors is not None and scalar is not None:
        raise ValueError("give either scalar or vertex_colors, not both.")
    vc = None
    if vertex_colors is not None:
        vc = np.asarray(vertex_colors, dtype=np.float64)
        if vc.shape != (n_vertices, 3):
            raise ValueError(f"vertex_colors must have shape ({n_vertices}, 3) (one RGB per vertex), got {vc.shape}.")
        if not np.all(np.isfinite(vc)) or vc.min() < 0.0 or vc.max() > 1.0:
            raise ValueError("vertex_colors must be finite RGB floats in [0, 1].")
    return vc


def _check_image_size(width, height, supersample) -> tuple[int, int, int]:
    """``(width, height, k)`` as ints, ``k`` the supersampling factor.

    Guarantees ``width``, ``height`` >= 1 and ``k`` >= 1; raises ValueError otherwise (size first).
    """
    width, height, k = int(width), int(height), int(supersample)
    if width < 1 or height < 1:
        raise ValueError(f"image size must be at least 1 x 1 pixels, got {width} x {height}.")
    if k < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample}.")
    return width, height, k


def _check_scalar(scalar, n_vertices: int, vmin, vmax) -> tuple[np.ndarray | None, float | None, float | None]:
    """Validate a per-vertex ``scalar`` and resolve its colour range.

    Returns ``(None, None, None)`` when ``scalar`` is None; else ``(s, lo, hi)`` with ``s`` the float64 scalar
    flattened to ``(n_vertices,)`` (all finite), ``lo`` = ``vmin`` (default ``s.min()``) and ``hi`` = ``vmax``
    (default ``s.max()``) as floats, both finite with ``lo <= hi``. Raises MeshFormatError for a wrong length
    or a NaN / infinite value (naming the first such vertex), ValueError for a bad range.
    """
    if scalar is None:
        return None, None, None
    s = np.asarray(scalar, dtype=np.float64).reshape(-1)
    if s.shape[0] != n_vertices:
        raise MeshFormatError(f"scalar has {s.shape[0]} values but the mesh has {n_vertices} vertices.")
    if not np.all(np.isfinite(s)):
        bad = int(np.argwhere(~np.isfinite(s))[0, 0])
        raise MeshFormatError(f"scalar value of vertex {bad} is NaN or infinite; cannot colour by it.")
    lo = float(s.min()) if vmin is None else float(vmin)
    hi = float(s.max()) if vmax is None else float(vmax)
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
        raise ValueError(f"vmin and vmax must be finite with vmin <= vmax, got {lo} and {hi}.")
    return s, lo, hi


def _hit_colours(v, f, tr: Trace, s, lo, hi, cmap: str, vc, base: np.ndarray, shading: bool) -> np.ndarray:
    """Linear RGB of every hit pixel of ``tr``: an ``(len(tr.pixel), 3)`` float array.

    With a scalar ``s`` (and its range ``lo``..``hi``; ``hi == lo`` maps to the middle of ``cmap``) the colour is
    ``cmap`` at the scalar interpolated at the hit point; else with vertex colours ``vc`` the colour of the hit
    triangle's vertex of largest barycentric weight; else ``base``. ``shading`` multiplies by the two-sided
    Lambert factor of :func:`_shade` (in [AMBIENT, 1]). Values stay in [0, 1] when the inputs do.
    """
    if s is not None:
        value = np.einsum("nk,nk->n", tr.barycentric, s[f[tr.triangle]])
        t = np.full_like(value, 0.5) if hi == lo else (value - lo) / (hi - lo)
        colour = colormap(t, cmap)
    elif vc is not None:
        corner = np.argmax(tr.barycentric, axis=-1)  # the hit triangle's nearest vertex
        colour = vc[f[tr.triangle, corner]]
    else:
        colour = np.broadcast_to(base, (tr.pixel.size, 3))
    if shading:
        colour = colour * _shade(v, f, tr, AMBIENT)[:, None]
    return colour


def _compose_image(
    tr: Trace, colour: np.ndarray, bg: np.ndarray, width: int, height: int, view_w: int, k: int
) -> np.ndarray:
    """The ``(height, width, 3)`` uint8 image: the traced view in the left ``view_w`` columns, background elsewhere.

    ``tr`` was traced at ``(view_w * k) x (height * k)`` pixels and ``colour`` holds its hit pixels' colours; the
    ``k x k`` samples of each pixel are averaged, then values are clipped to [0, 1] and rounded to 0..255. The
    columns right of ``view_w`` (the colour bar's strip) are left at ``bg``.
    """
    image = np.empty((height * k * view_w * k, 3))
    image[...] = bg
    image[tr.pixel] = colour
    image = image.reshape(height * k, view_w * k, 3)
    if k > 1:
        image = image.reshape(height, k, view_w, k, 3).mean(axis=(1, 3))
    full = np.empty((height, width, 3))
    full[...] = bg
    full[:, :view_w] = image
    return (np.clip(full, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def render(
    vertices,
    faces,
    *,
    scalar=None,
    camera: Camera | None = None,
    width: int = 800,
    height: int = 600,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    colorbar: bool = True,
    label: str | None = None,
    base_color=(0.75, 0.78, 0.85),
    background=(1.0, 1.0, 1.0),
    shading: bool = True,
    supersample: int = 1,
    vertex_colors=None,
) -> np.ndarray:
    """Render a mesh to an image.

    Without `scalar` the mesh is drawn in `base_color`; with a per-vertex `scalar` each pixel gets the scalar
    interpolated at its hit point, mapped through `cmap` over [vmin, vmax] (values outside are clipped), and a
    colour bar is drawn at the right unless `colorbar=False` (or the image is too small to hold one: under 60
    pixels high, or the bar and its labels would take more than half the width).

    `vertex_colors` colours each hit pixel with the colour of the hit triangle's vertex of largest
    barycentric weight: flat per-region colours, never blended across part boundaries (except by the pixel
    averaging of `supersample` > 1 on boundary pixels), and no colour bar.

    **Arguments:**

    - `vertices`: positions `(V, 3)`.
    - `faces`: triangles `(F, 3)`.
    - `scalar`: per-vertex values `(V,)`, or None.
    - `camera`: the :class:`Camera`; None: :func:`auto_camera`.
    - `width`, `height`: the image size in pixels.
    - `cmap`: the colormap name.
    - `vmin`, `vmax`: the colour range; None: the scalar's range.
    - `colorbar`: draw a colour bar (with a scalar).
    - `label`: the colour bar's label.
    - `base_color`, `background`: RGB colours in [0, 1] of the mesh (without a scalar) and of the background.
    - `shading`: False draws flat colours (no lighting).
    - `supersample`: k traces k x k rays per pixel and averages them (anti-aliasing).
    - `vertex_colors`: `(V, 3)` RGB floats in [0, 1] (e.g. :func:`categorical_colors` indexed by part labels);
      it cannot be combined with `scalar`.

    **Returns:**

    A `(height, width, 3)` uint8 image.

    **Raises:**

    `ValueError` for bad options (colormap, colours, sizes, scalar, vertex colours); `MeshFormatError` for bad
    vertices or faces; `DegenerateMeshError` for no faces; `ConnectivityError` for a face index out of range.
    """
    v, f = _check_mesh(vertices, faces)
    vc = _check_vertex_colors(vertex_colors, scalar, v.shape[0])
    if cmap not in COLORMAPS:
        _cmap_anchors(cmap)  # raises with the list of names
    base = _rgb(base_color, "base_color")
    bg = _rgb(background, "background")
    width, height, k = _check_image_size(width, height, supersample)
    s, lo, hi = _check_scalar(scalar, v.shape[0], vmin, vmax)
    if camera is None:
        camera = auto_camera(v)

    strip, layout = 0, None
    if s is not None and colorbar:
        layout = _colorbar_layout(width, height, lo, hi, label)
        strip = 0 if layout is None else layout[-1]
    view_w = width - strip

    tr = _trace(v, f, camera, view_w * k, height * k)
    colour = _hit_colours(v, f, tr, s, lo, hi, cmap, vc, base, shading)
    out = _compose_image(tr, colour, bg, width, height, view_w, k)
    if layout is not None:
        out = _draw_colorbar(out, strip, layout, lo, hi, cmap, label, bg)
    return out


def caption(image: np.ndarray, text: str) -> np.ndarray:
    """Write text small at the top-left of a panel (dark ink on the white background).

    **Arguments:**

    - `image`: a uint8 image `(H, W, 3)`.
    - `text`: the caption.

    **Returns:**

    A new image of the same shape.
    """
    pil = Image.fromarray(image)
    draw = ImageDraw.Draw(pil)
    draw.text((6, 4), text, fill=(40, 40, 40))
    return np.asarray(pil)


def hstack(panels: list[np.ndarray], gap: int = 4) -> np.ndarray:
    """Panels of one height side by side.

    **Arguments:**

    - `panels`: uint8 images `(H, W_i, 3)`, non-empty list.
    - `gap`: white columns between panels.

    **Returns:**

    A uint8 image `(H, sum W_i + gaps, 3)`.
    """
    h = panels[0].shape[0]
    sep = np.full((h, gap, 3), 255, dtype=np.uint8)
    parts: list[np.ndarray] = []
    for i, p in enumerate(panels):
        if i:
            parts.append(sep)
        parts.append(p)
    return np.concatenate(parts, axis=1)


def save_png(image, path) -> Path:
    """Write an image as PNG atomically (temporary file + rename).

    **Arguments:**

    - `image`: a uint8 array `(H, W)`, `(H, W, 3)` or `(H, W, 4)`.
    - `path`: the file; its folder is created if missing.

    **Returns:**

    The path written.

    **Raises:**

    `ValueError` for an image of another dtype or shape.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (3, 4))):
        raise ValueError(f"image must be a uint8 (H, W), (H, W, 3) or (H, W, 4) array, got {img.dtype} {img.shape}.")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        default_mode(tmp)
        with os.fdopen(fd, "wb") as fh:
            Image.fromarray(img).save(fh, format="PNG")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def render_png(path, vertices, faces, **kwargs) -> np.ndarray:
    """:func:`render` a mesh and :func:`save_png` it.

    **Arguments:**

    - `path`: the PNG file.
    - `vertices`, `faces`: the mesh.
    - `kwargs`: the options of :func:`render`.

    **Returns:**

    The image, as :func:`render` returns it.

    **Raises:**

    The errors of :func:`render` and :func:`save_png`.
    """
    image = render(vertices, faces, **kwargs)
    save_png(image, path)
    return image


#: Named view directions for :func:`auto_camera`: (azimuth, elevation) in degrees.
VIEWS: dict[str, tuple[float, float]] = {
    "front": (0.0, 10.0),
    "back": (180.0, 10.0),
    "side": (90.0, 10.0),
    "left": (-90.0, 10.0),
    "right": (90.0, 10.0),
    "top": (0.0, 89.0),
    "bottom": (0.0, -89.0),
    "three_quarter": (30.0, 20.0),
}


def view_angles(view) -> tuple[float, float]:
    """The angles of a view.

    **Arguments:**

    - `view`: a name of :data:`VIEWS` or an (azimuth, elevation) pair in degrees.

    **Returns:**

    `(azimuth, elevation)` in degrees, floats.

    **Raises:**

    `ValueError` for an unknown name or a malformed pair.
    """
    if isinstance(view, str):
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}; expected one of {', '.join(VIEWS)} or (azimuth, elevation).")
        return VIEWS[view]
    try:
        az, el = (float(x) for x in view)
    except (TypeError, ValueError):
        raise ValueError(f"a view is a name or an (azimuth_deg, elevation_deg) pair, got {view!r}.") from None
    return az, el
