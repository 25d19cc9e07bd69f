"""The handle-editing page's view: :class:`Viewport` (camera, ray casts, frames) and pure display-pixel helpers.

Display pixels: x to the right, y down; pixel (i, j) covers [j, j+1) x [i, i+1) of a ``width`` x ``height`` image.
The argument checks raise ``ValueError`` with one sentence that names the offending argument.
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Callable

import numpy as np
from jaxtyping import Float
from PIL import Image

from jaxdeform.mesh.render import Camera, RayHits, auto_camera, cast_rays, pixel_scale, project, render

#: A pick within this many display pixels of a handle's marker selects that handle.
MARKER_RADIUS = 8.0
#: Degrees of orbit per pixel dragged.
ORBIT_DEG_PER_PIXEL = 0.4
#: Colouring by the selected handle's weights: coolwarm over [-1, 1], so weight 0 is the map's light grey centre
#: and weight 1 its dark red end.
WEIGHT_COLORMAP = "coolwarm"
WEIGHT_RANGE = (-1.0, 1.0)
#: JPEG quality of the drag frames.
JPEG_QUALITY = 90
#: Allowed downscale factors of preview images.
PREVIEW_SCALES = (1, 2, 4)
IMAGE_FORMATS = ("png", "jpeg")


def compose(a: Float[np.ndarray, "3 4"], b: Float[np.ndarray, "3 4"]) -> np.ndarray:
    """The affine map ``a o b`` (apply ``b`` first) of two (3, 4) matrices, as a float64 (3, 4) array."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return np.concatenate([a[:, :3] @ b[:, :3], (a[:, :3] @ b[:, 3] + a[:, 3])[:, None]], axis=1)


def translation_step(camera: Camera, width: int, height: int, point, start, end) -> np.ndarray:
    """World translation (3,) in the view plane that moves ``point``'s projection from pixel ``start`` to ``end``.

    **Arguments:**

    - ``camera``, ``width``, ``height``: the view the pixels belong to.
    - ``point``: (3,) world position of the dragged point.
    - ``start``, ``end``: (x, y) display pixels.

    **Returns:**

    ``s (dx r - dy u)`` with (r, u) the camera's right and up vectors and ``s`` the world size of a pixel at
    the point's depth; it has no component along the view direction.

    **Raises:**

    ``ValueError`` when the point is not in front of the camera.
    """
    fwd, right, up = camera.basis()
    depth = float((np.asarray(point, dtype=np.float64) - np.asarray(camera.eye)) @ fwd)
    if not depth > 0.0:
        raise ValueError("the handle is behind the camera, so it cannot be dragged in this view.")
    s = depth * pixel_scale(camera, width, height)
    dx, dy = float(end[0]) - float(start[0]), float(end[1]) - float(start[1])
    return s * (dx * right - dy * up)


def swept_angle(centre, start, end, min_radius: float = 2.0) -> float:
    """Counter-clockwise (on screen, y down) angle in degrees in (-180, 180] swept by the cursor around ``centre``.

    Zero when either point lies within ``min_radius`` pixels of the centre (the angle is unstable there).
    """
    a = np.asarray(start, dtype=np.float64) - np.asarray(centre, dtype=np.float64)
    b = np.asarray(end, dtype=np.float64) - np.asarray(centre, dtype=np.float64)
    if np.hypot(*a) < min_radius or np.hypot(*b) < min_radius:
        return 0.0
    turn = math.atan2(-b[1], b[0]) - math.atan2(-a[1], a[0])
    turn = (turn + math.pi) % (2.0 * math.pi) - math.pi
    return math.degrees(turn)


def interior_pixel(hit: np.ndarray, margin: int = 3) -> tuple[float, float] | None:
    """A covered pixel away from the silhouette, for a first click.

    **Arguments:**

    - ``hit``: (H, W) bool coverage mask.
    - ``margin``: half-size of the block that must be covered.

    **Returns:**

    Centre (x, y) of the covered pixel nearest the image centre whose (2 margin + 1)^2 block is all covered;
    failing that, of any covered pixel nearest the centre; None when nothing is covered.
    """
    h, w = hit.shape
    for m in (margin, 0):
        k = 2 * m + 1
        if h < k or w < k:
            continue
        c = np.pad(np.cumsum(np.cumsum(hit.astype(np.int64), 0), 1), ((1, 0), (1, 0)))
        full = (c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]) == k * k  # block starting at (i, j)
        ii, jj = np.nonzero(full)
        if ii.size:
            ii, jj = ii + m, jj + m
            best = int(np.argmin((ii + 0.5 - h / 2.0) ** 2 + (jj + 0.5 - w / 2.0) ** 2))
            return float(jj[best] + 0.5), float(ii[best] + 0.5)
    return None


# ------------------------------------------------------------------------------------------- argument checks


def check_number(x, name: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    """``x`` as a float; ``ValueError`` unless it is a finite real number (not a bool) in [lo, hi]."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise ValueError(f"'{name}' must be a finite number.")
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"'{name}' must be a finite number.")
    if not lo <= x <= hi:
        raise ValueError(f"'{name}' must lie in [{lo:g}, {hi:g}], got {x:g}.")
    return x


def check_index(x, n: int, what: str) -> int:
    """``x`` as an int; ``ValueError`` unless it is an integer (not a bool) in [0, n)."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)):
        raise ValueError(f"'{what}' must be an integer {what} index.")
    if not 0 <= x < n:
        raise ValueError(f"{what} {x} does not exist (there are {n}).")
    return int(x)


def check_choice(x, name: str, choices: tuple[str, ...]) -> str:
    """``x`` unchanged; ``ValueError`` unless it is one of ``choices``."""
    if not isinstance(x, str) or x not in choices:
        raise ValueError(f"'{name}' must be one of {', '.join(choices)}.")
    return x


def check_image_size(width: int, height: int) -> tuple[int, int]:
    """(width, height) as ints; ``ValueError`` unless both are at least 16 pixels."""
    if int(width) < 16 or int(height) < 16:
        raise ValueError(f"the page's image must be at least 16 x 16 pixels, got {width} x {height}.")
    return int(width), int(height)


def check_array(x, shape: tuple[int, ...], message: str) -> np.ndarray:
    """``x`` as a float64 array of ``shape``; ``ValueError(message)`` unless it is one with finite entries."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(message) from None
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ValueError(message)
    return a


# ------------------------------------------------------------------------------------------------- viewport


class Viewport:
    """The page's camera, orbiting the rest mesh's bounding-box centre, and what is seen through it.

    Ray casts and frames are cached under a version number given by the caller, which must change whenever the
    mesh, the camera or the colouring changes.

    **Arguments:**

    - ``rest``: (V, 3) rest vertices (they fix the orbit centre and the framing).
    - ``width``, ``height``: the displayed image in pixels, at least 16 each.
    - ``up_axis``: "x", "y" or "z".
    """

    def __init__(self, rest: np.ndarray, width: int, height: int, up_axis: str = "y"):
        self.width, self.height = check_image_size(width, height)
        auto_camera(rest, up_axis=up_axis)  # validates up_axis and the vertices
        self.rest, self.up_axis = rest, up_axis
        self._hits: tuple[int, RayHits] | None = None
        self._pixels: dict[int, tuple[int, np.ndarray]] = {}
        self._images: dict[tuple[int, str], tuple[int, bytes]] = {}
        self.reset()

    def reset(self) -> None:
        """The initial camera: azimuth 30, elevation 20 degrees, zoom 1."""
        self.azimuth, self.elevation, self.zoom = 30.0, 20.0, 1.0
        self._update()

    def _update(self) -> None:
        base = auto_camera(self.rest, azimuth_deg=self.azimuth, elevation_deg=self.elevation, up_axis=self.up_axis)
        eye = np.asarray(base.target) + self.zoom * (np.asarray(base.eye) - np.asarray(base.target))
        self.camera = Camera(eye=tuple(eye), target=base.target, up=base.up, fov_deg=base.fov_deg)

    def orbit(self, start, end) -> None:
        """Turn the camera by ``ORBIT_DEG_PER_PIXEL`` per pixel of the drag from ``start`` (x, y) to ``end``;
        the elevation stays within [-89, 89] degrees, the azimuth within [-180, 180)."""
        self.azimuth = (self.azimuth - ORBIT_DEG_PER_PIXEL * (end[0] - start[0]) + 180.0) % 360.0 - 180.0
        self.elevation = float(np.clip(self.elevation + ORBIT_DEG_PER_PIXEL * (end[1] - start[1]), -89, 89))
        self._update()

    def set(
        self,
        *,
        zoom: float | None = None,
        azimuth: float | None = None,
        elevation: float | None = None,
        reset: bool = False,
    ) -> None:
        """Reset first if ``reset``; ``zoom`` in [0.01, 100] multiplies the camera distance (kept within 0.1 to
        10 times the initial one); ``azimuth`` in [-180, 180], ``elevation`` in [-89, 89] degrees. All arguments
        are checked before anything changes."""
        zoom = None if zoom is None else check_number(zoom, "zoom", 0.01, 100.0)
        azimuth = None if azimuth is None else check_number(azimuth, "azimuth", -180.0, 180.0)
        elevation = None if elevation is None else check_number(elevation, "elevation", -89.0, 89.0)
        if reset:
            self.reset()
        if zoom is not None:
            self.zoom = float(np.clip(self.zoom * zoom, 0.1, 10.0))
        if azimuth is not None:
            self.azimuth = azimuth
        if elevation is not None:
            self.elevation = elevation
        self._update()

    def as_json(self) -> dict:
        """The camera (eye, target, up, fov_deg) and its orbit parameters (azimuth, elevation, zoom)."""
        cam = self.camera
        return {
            "eye": list(cam.eye),
            "target": list(cam.target),
            "up": list(cam.up),
            "fov_deg": cam.fov_deg,
            "azimuth": self.azimuth,
            "elevation": self.elevation,
            "zoom": self.zoom,
        }

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Display coordinates (P, 2) and depths (P,) of world points (P, 3)."""
        return project(self.camera, self.width, self.height, np.asarray(points, dtype=np.float64))

    def markers(self, vertices: np.ndarray, handles: list[int], anchors: list[int]) -> list[dict]:
        """``{"kind": "handle" | "anchor", "index", "vertex", "x", "y"}`` of every handle and anchor vertex that
        lies in front of the camera, ``index`` its position in ``handles`` or ``anchors``."""
        out = []
        for kind, ids in (("handle", handles), ("anchor", anchors)):
            if not ids:
                continue
            xy, depth = self.project(vertices[ids])
            for k, (vid, p, d) in enumerate(zip(ids, xy, depth)):
                if d > 0 and np.all(np.isfinite(p)):
                    out.append({"kind": kind, "index": k, "vertex": int(vid), "x": float(p[0]), "y": float(p[1])})
        return out

    @staticmethod
    def marker_at(markers: list[dict], x: float, y: float) -> int | None:
        """The index of the handle whose marker is nearest (x, y) within ``MARKER_RADIUS`` pixels, or None."""
        best, marker = MARKER_RADIUS, None
        for m in markers:
            d = math.hypot(m["x"] - x, m["y"] - y)
            if m["kind"] == "handle" and d <= best:
                best, marker = d, m["index"]
        return marker

    def pick(self, version: int, vertices: np.ndarray, faces: np.ndarray, x: float, y: float):
        """(triangle, vertex, point) seen at display coordinates (x, y): the hit triangle (-1 on the background),
        its corner nearest the hit point and the world hit point (both None on the background)."""
        i, j = min(int(y), self.height - 1), min(int(x), self.width - 1)
        hits = self.ray_hits(version, vertices, faces)
        tri = int(hits.triangle[i, j])
        if tri < 0:
            return tri, None, None
        corners, point = faces[tri], hits.points[i, j]
        dist = np.linalg.norm(vertices[corners] - point, axis=1)
        return tri, int(corners[int(np.argmin(dist))]), point

    def ray_hits(self, version: int, vertices: np.ndarray, faces: np.ndarray) -> RayHits:
        """Every display pixel's ray cast against the mesh (cached per version)."""
        if self._hits is None or self._hits[0] != version:
            self._hits = (version, cast_rays(vertices, faces, self.camera, self.width, self.height))
        return self._hits[1]

    def frame(
        self,
        version: int,
        vertices: np.ndarray,
        faces: np.ndarray,
        scalar: Callable[[], np.ndarray | None],
        scale: int,
        fmt: str,
        timings: dict,
    ) -> bytes:
        """The mesh rendered and encoded (cached per version, scale and format).

        **Arguments:**

        - ``version``: the caller's version of what the image shows.
        - ``vertices``, ``faces``: the mesh to render.
        - ``scalar``: called on a cache miss; a per-vertex value coloured through ``WEIGHT_COLORMAP`` over
            ``WEIGHT_RANGE``, or None for plain shading.
        - ``scale``: one of ``PREVIEW_SCALES``; the image has (width / scale, height / scale) pixels with the same
            camera, so preview pixel (i, j) covers display block [scale j, scale (j + 1)) x [scale i, ...).
        - ``fmt``: "png" (lossless) or "jpeg" (quality ``JPEG_QUALITY``).
        - ``timings``: receives ``render[_1/scale]_ms`` and ``{fmt}[_1/scale]_ms`` of the work done.
        """
        if isinstance(scale, bool) or scale not in PREVIEW_SCALES:
            raise ValueError(f"'scale' must be one of {', '.join(map(str, PREVIEW_SCALES))}.")
        check_choice(fmt, "fmt", IMAGE_FORMATS)
        suffix = "" if scale == 1 else f"_1/{scale}"
        cached = self._images.get((scale, fmt))
        if cached is not None and cached[0] == version:
            return cached[1]
        pixels = self._pixels.get(scale)
        if pixels is None or pixels[0] != version:
            t0 = time.perf_counter()
            img = render(
                vertices,
                faces,
                camera=self.camera,
                width=max(1, round(self.width / scale)),
                height=max(1, round(self.height / scale)),
                scalar=scalar(),
                cmap=WEIGHT_COLORMAP,
                vmin=WEIGHT_RANGE[0],
                vmax=WEIGHT_RANGE[1],
                colorbar=False,
            )
            pixels = self._pixels[scale] = (version, img)
            timings[f"render{suffix}_ms"] = 1e3 * (time.perf_counter() - t0)
        t1 = time.perf_counter()
        buf = io.BytesIO()
        if fmt == "png":
            Image.fromarray(pixels[1]).save(buf, format="PNG", compress_level=1)
        else:
            Image.fromarray(pixels[1]).save(buf, format="JPEG", quality=JPEG_QUALITY)
        timings[f"{fmt}{suffix}_ms"] = 1e3 * (time.perf_counter() - t1)
        self._images[(scale, fmt)] = (version, buf.getvalue())
        return buf.getvalue()
