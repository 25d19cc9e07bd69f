"""The interactive DFD page: ``jaxdeform handles serve MESH`` (a local web server on 127.0.0.1).

The page shows the mesh rendered on the server by the embreex ray caster (:mod:`jaxdeform.mesh.render`), as a
PNG that is replaced after every interaction, so it needs neither WebGL nor a GPU (it works in headless
Chromium with ``--disable-gpu``). Everything it loads is served from ``static/`` beside this module.

Interaction (all in display pixels: x to the right, y down, pixel (i, j) covers [j, j+1) x [i, i+1)):

- click the mesh: the pixel's ray is cast with the *same* camera and image size the displayed image was
  rendered with (:func:`~jaxdeform.mesh.render.cast_rays` of the displayed, deformed mesh), and the hit
  triangle's vertex nearest to the hit point becomes a handle (a click within ``MARKER_RADIUS`` pixels of a
  handle's marker selects that handle instead);
- drag: translates the selected handle in the view plane through its current position. A pixel step
  (dx, dy) moves it by ``s (dx r - dy u)`` with (r, u) the camera's right and up vectors and
  ``s = d tan(fov / 2) / (min(W, H) / 2)`` the world size of a pixel at the handle's depth d, so the handle's
  projection follows the cursor exactly (the step has no component along the view direction);
- shift + drag: rotates the selected handle about the view axis through its current position p by the angle
  the cursor sweeps around p's projection (counter-clockwise on screen = positive about -forward, i.e. about
  the axis pointing at the viewer); the increment is composed on the left of the handle's transform,
  ``D <- M D`` with ``M = make_transform(p, axis=-forward, degrees=angle)``, so p stays where it is;
- ctrl + click (or anchor mode): toggles an anchor vertex (eq. 7); drag on the background (or right / alt
  drag anywhere) orbits the camera about the mesh's bounding-box centre, the wheel zooms;
- options: locality (eq. 8, with lambda), symmetry (eq. 9, only when a plane was detected from the field),
  partition of unity (eq. 10), colouring by the selected handle's weight column (grey 0 to red 1).

Deformation goes through :class:`jaxdeform.handles.weights.Deformer`: the displayed mesh is exactly
``Deformer.deform(**state["deform_args"])`` (the Deformer keeps the weights of the last handles / anchors /
locality, so a drag step only blends), and the colouring is the selected column of ``Deformer.weights``.

JSON endpoints (POST bodies are JSON objects; a bad request answers 400 with ``{"error": one sentence}``):
``GET /api/mesh-info``, ``GET /api/state[?vertices=1]`` (deformed vertices as base64 little-endian floats),
``GET /api/image.png[?scale=2]`` (or ``.jpg``), ``POST /api/pick {x, y, action}``,
``POST /api/drag {mode, from, to[, handle]}``, ``POST /api/options``, ``POST /api/view``, ``POST /api/handle``,
``POST /api/anchor``, ``POST /api/reset``.
The server binds only a loopback address and answers only requests whose Host header names it (no DNS
rebinding), and refuses cross-origin POSTs.
"""

from __future__ import annotations

import base64
import io
import ipaddress
import json
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np
from jaxtyping import Float
from PIL import Image

from jaxdeform.errors import JaxDeformError
from jaxdeform.handles.weights import Deformer, make_transform
from jaxdeform.mesh.render import Camera, RayHits, auto_camera, cast_rays, pixel_scale, project, render

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
#: A click within this many display pixels of a handle's marker selects that handle.
MARKER_RADIUS = 8.0
#: Degrees of orbit per pixel dragged.
ORBIT_DEG_PER_PIXEL = 0.4
#: Colouring by the selected handle's weights: coolwarm over [-1, 1], so weight 0 is the map's light grey
#: centre and weight 1 its dark red end.
WEIGHT_COLORMAP = "coolwarm"
WEIGHT_RANGE = (-1.0, 1.0)
#: JPEG quality of the drag frames.
JPEG_QUALITY = 90
#: Allowed downscale factors of preview images.
PREVIEW_SCALES = (1, 2, 4)
#: Largest request body accepted (bytes).
MAX_BODY = 1 << 20
_STATIC_NAME = re.compile(r"^[A-Za-z0-9_-]+\.(html|js|css)$")
_CONTENT_TYPES = {"html": "text/html; charset=utf-8", "js": "text/javascript; charset=utf-8", "css": "text/css"}


class BadRequest(ValueError):
    """A request the page cannot serve; its message (one sentence) goes back with status 400."""


# ------------------------------------------------------------------------------------------ geometry helpers


def compose(a: Float[np.ndarray, "3 4"], b: Float[np.ndarray, "3 4"]) -> np.ndarray:
    """The affine map ``a o b`` (apply b first) of two (3, 4) matrices."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return np.concatenate([a[:, :3] @ b[:, :3], (a[:, :3] @ b[:, 3] + a[:, 3])[:, None]], axis=1)


def translation_step(camera: Camera, width: int, height: int, point, start, end) -> np.ndarray:
    """World translation (3,) that moves ``point``'s projection from display pixel ``start`` to ``end``."""
    fwd, right, up = camera.basis()
    depth = float((np.asarray(point, dtype=np.float64) - np.asarray(camera.eye)) @ fwd)
    if not depth > 0.0:
        raise BadRequest("the handle is behind the camera, so it cannot be dragged in this view.")
    s = depth * pixel_scale(camera, width, height)
    dx, dy = float(end[0]) - float(start[0]), float(end[1]) - float(start[1])
    return s * (dx * right - dy * up)


def swept_angle(centre, start, end, min_radius: float = 2.0) -> float:
    """Counter-clockwise (on screen, y down) angle in degrees swept by the cursor around ``centre``.

    Zero when either point is within ``min_radius`` pixels of the centre (the angle is unstable there).
    """
    a = np.asarray(start, dtype=np.float64) - np.asarray(centre, dtype=np.float64)
    b = np.asarray(end, dtype=np.float64) - np.asarray(centre, dtype=np.float64)
    if np.hypot(*a) < min_radius or np.hypot(*b) < min_radius:
        return 0.0
    turn = math.atan2(-b[1], b[0]) - math.atan2(-a[1], a[0])
    turn = (turn + math.pi) % (2.0 * math.pi) - math.pi
    return math.degrees(turn)


def interior_pixel(hit: np.ndarray, margin: int = 3) -> tuple[float, float] | None:
    """Centre (x, y) of the covered pixel nearest the image centre whose (2 margin + 1)^2 block is all covered."""
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


def encode_vertices(v: np.ndarray) -> dict:
    """(V, 3) floats as ``{"dtype", "shape", "data"}`` with base64 little-endian bytes."""
    a = np.asarray(v)
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
    return {"dtype": str(a.dtype.name), "shape": list(a.shape), "data": base64.b64encode(a.tobytes()).decode("ascii")}


def decode_vertices(payload: dict) -> np.ndarray:
    """Inverse of :func:`encode_vertices`."""
    dtype = np.dtype(payload["dtype"]).newbyteorder("<")
    return np.frombuffer(base64.b64decode(payload["data"]), dtype=dtype).reshape(payload["shape"])


# ------------------------------------------------------------------------------------------ request parsing


def _number(body: dict, key: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    x = body.get(key)
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise BadRequest(f"'{key}' must be a finite number.")
    if not lo <= x <= hi:
        raise BadRequest(f"'{key}' must lie in [{lo:g}, {hi:g}], got {x:g}.")
    return float(x)


def _point(body: dict, key: str) -> tuple[float, float]:
    p = body.get(key)
    if not isinstance(p, (list, tuple)) or len(p) != 2:
        raise BadRequest(f"'{key}' must be a pair [x, y] of display pixel coordinates.")
    return _number({"x": p[0]}, "x"), _number({"y": p[1]}, "y")


def _flag(body: dict, key: str) -> bool:
    x = body.get(key)
    if not isinstance(x, bool):
        raise BadRequest(f"'{key}' must be true or false.")
    return x


def _index(body: dict, key: str, n: int, what: str) -> int:
    x = body.get(key)
    if isinstance(x, bool) or not isinstance(x, int):
        raise BadRequest(f"'{key}' must be an integer {what} index.")
    if not 0 <= x < n:
        raise BadRequest(f"{what} {x} does not exist (there are {n}).")
    return int(x)


def _choice(body: dict, key: str, choices: tuple[str, ...], default: str | None = None) -> str:
    x = body.get(key, default)
    if x not in choices:
        raise BadRequest(f"'{key}' must be one of {', '.join(choices)}.")
    return x


# ------------------------------------------------------------------------------------------------- session


@dataclass
class Options:
    locality: bool = False
    lam: float = 2.0
    symmetric: bool = False
    pou: bool = False
    show_weights: bool = True

    def as_json(self) -> dict:
        return {"locality": self.locality, "lambda": self.lam, "symmetric": self.symmetric, "pou": self.pou,
                "show_weights": self.show_weights}


class Session:
    """The page's state (handles, transforms, anchors, options, view) and its deformed mesh; thread-safe.

    Every public method takes the lock; ``version`` increases with every change of what the image shows.
    """

    def __init__(self, vertices, faces, Z, *, field_fn=None, width: int = 512, height: int = 512,
                 up_axis: str = "y"):
        if int(width) < 16 or int(height) < 16:
            raise ValueError(f"the page's image must be at least 16 x 16 pixels, got {width} x {height}.")
        self.rest = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.width, self.height, self.up_axis = int(width), int(height), up_axis
        self.n_features = int(np.shape(Z)[1]) if np.ndim(Z) == 2 else None
        self.deformer = Deformer(self.rest, self.faces, Z, field_fn=field_fn)
        self.field_given = field_fn is not None
        self.plane = self.deformer.symmetry_plane() if self.field_given else None
        auto_camera(self.rest, up_axis=up_axis)  # validates up_axis and the vertices
        self._lock = threading.RLock()
        self.version = 0
        self._reset_all()
        self._reset_view()
        self._images: dict[tuple[int, str], tuple[int, bytes]] = {}
        self._pixels: dict[int, tuple[int, np.ndarray]] = {}
        self._hits: tuple[int, RayHits] | None = None

    # ----------------------------------------------------------------------------------------- internals

    def _reset_all(self) -> None:
        self.handles: list[int] = []
        self.transforms: list[np.ndarray] = []
        self.anchors: list[int] = []
        self.selected: int | None = None
        self.options = Options()
        self.deformed = self.rest.copy()
        self.timings: dict[str, float] = {}

    def _reset_view(self) -> None:
        self.azimuth, self.elevation, self.zoom = 30.0, 20.0, 1.0
        self._update_camera()

    def _update_camera(self) -> None:
        base = auto_camera(self.rest, azimuth_deg=self.azimuth, elevation_deg=self.elevation, up_axis=self.up_axis)
        eye = np.asarray(base.target) + self.zoom * (np.asarray(base.eye) - np.asarray(base.target))
        self.camera = Camera(eye=tuple(eye), target=base.target, up=base.up, fov_deg=base.fov_deg)

    def _locality(self) -> float:
        return float(self.options.lam) if self.options.locality else 0.0

    def deform_args(self) -> dict:
        """Keyword arguments of ``Deformer.deform`` that reproduce the displayed mesh."""
        return {
            "handles": list(self.handles),
            "transforms": [t.tolist() for t in self.transforms],
            "anchors": list(self.anchors),
            "locality": self._locality(),
            "symmetric": bool(self.options.symmetric),
            "pou": bool(self.options.pou),
        }

    def _changed(self, *, geometry: bool = True) -> None:
        """Recompute the deformed mesh if ``geometry`` (``Deformer.deform`` of the state), bump the version."""
        if geometry:
            t0 = time.perf_counter()
            if not self.handles:
                self.deformed = self.rest.copy()
            else:
                self.deformed = np.asarray(self.deformer.deform(
                    np.asarray(self.handles, dtype=np.int64), np.stack(self.transforms), anchors=self._anchor_array(),
                    locality=self._locality(), symmetric=self.options.symmetric and self.plane is not None,
                    pou=self.options.pou))
            self.timings["deform_ms"] = 1e3 * (time.perf_counter() - t0)
        self.version += 1

    def _anchor_array(self):
        return np.asarray(self.anchors, dtype=np.int64) if self.anchors else ()

    def _selected_weights(self) -> np.ndarray | None:
        """The selected handle's weight column (V,) under the current anchors and locality, or None."""
        if self.selected is None or not self.handles:
            return None
        W = self.deformer.weights(np.asarray(self.handles, dtype=np.int64), anchors=self._anchor_array(),
                                  locality=self._locality())
        return np.asarray(W[:, self.selected], dtype=np.float64)

    def _deformed64(self) -> np.ndarray:
        return np.asarray(self.deformed, dtype=np.float64)

    def _ray_hits(self) -> RayHits:
        if self._hits is None or self._hits[0] != self.version:
            self._hits = (self.version, cast_rays(self._deformed64(), self.faces, self.camera, self.width, self.height))
        return self._hits[1]

    def _markers(self) -> list[dict]:
        pts = self._deformed64()
        out = []
        for kind, ids in (("handle", self.handles), ("anchor", self.anchors)):
            if not ids:
                continue
            xy, depth = project(self.camera, self.width, self.height, pts[ids])
            for k, (vid, p, d) in enumerate(zip(ids, xy, depth)):
                if d > 0 and np.all(np.isfinite(p)):
                    out.append({"kind": kind, "index": k, "vertex": int(vid), "x": float(p[0]), "y": float(p[1])})
        return out

    def _handle_index(self, body: dict) -> int:
        if "handle" in body and body["handle"] is not None:
            return _index(body, "handle", len(self.handles), "handle")
        if self.selected is None:
            raise BadRequest("no handle is selected; click the mesh to add one first.")
        return self.selected

    def _toggle_anchor(self, vertex: int) -> None:
        """Pin ``vertex`` as an anchor, or unpin it if it is one (a handle cannot be an anchor)."""
        if vertex in self.handles:
            raise BadRequest(f"vertex {vertex} is a handle; a handle cannot also be an anchor.")
        if vertex in self.anchors:
            self.anchors.remove(vertex)
        else:
            self.anchors.append(vertex)

    def _add_handle(self, vertex: int) -> int:
        if vertex in self.anchors:
            raise BadRequest(f"vertex {vertex} is an anchor; remove the anchor before making it a handle.")
        if vertex in self.handles:
            if self.selected != self.handles.index(vertex):
                self.selected = self.handles.index(vertex)
                self._changed(geometry=False)
            return self.selected
        self.handles.append(int(vertex))
        self.transforms.append(np.eye(3, 4))
        self.selected = len(self.handles) - 1
        self._changed()
        return self.selected

    # ---------------------------------------------------------------------------------------- public API

    def mesh_info(self) -> dict:
        with self._lock:
            hint = interior_pixel(self._ray_hits().hit)
            return {
                "n_vertices": int(self.rest.shape[0]),
                "n_faces": int(self.faces.shape[0]),
                "n_features": self.n_features,
                "width": self.width,
                "height": self.height,
                "bbox_min": self.rest.min(axis=0).tolist(),
                "bbox_max": self.rest.max(axis=0).tolist(),
                "symmetry_available": self.plane is not None,
                "field_given": self.field_given,
                "covered_pixel": None if hint is None else list(hint),
                "marker_radius": MARKER_RADIUS,
            }

    def state(self, *, vertices: bool = False, dtype: str | None = None) -> dict:
        with self._lock:
            plane = None
            if self.plane is not None:
                plane = {"normal": np.asarray(self.plane.normal, dtype=np.float64).tolist(),
                         "offset": float(self.plane.offset), "score": float(self.plane.score)}
            cam = self.camera
            out = {
                "version": self.version,
                "handles": list(self.handles),
                "transforms": [t.tolist() for t in self.transforms],
                "anchors": list(self.anchors),
                "selected": self.selected,
                "options": self.options.as_json(),
                "deform_args": self.deform_args(),
                "symmetry_plane": plane,
                "camera": {"eye": list(cam.eye), "target": list(cam.target), "up": list(cam.up),
                           "fov_deg": cam.fov_deg, "azimuth": self.azimuth, "elevation": self.elevation,
                           "zoom": self.zoom},
                "width": self.width,
                "height": self.height,
                "markers": self._markers(),
                "timings": dict(self.timings),
            }
            if vertices:
                v = self.deformed if dtype is None else np.asarray(self.deformed, dtype=dtype)
                out["vertices"] = encode_vertices(v)
            return out

    def image_bytes(self, scale: int = 1, fmt: str = "png") -> tuple[int, bytes]:
        """(version, encoded image) of the current view, rendered once per version and scale.

        ``fmt`` "png" (lossless) or "jpeg" (quality ``JPEG_QUALITY``, ~20x faster to encode: the page's drag
        frames). ``scale`` > 1 renders a preview of (W / scale, H / scale) pixels with the same camera (the field
        of view spans the shorter side, so the framing is the same and preview pixel (i, j) covers display block
        [scale j, scale (j + 1)) x [scale i, scale (i + 1))); the page uses it while dragging when full frames are
        slow.
        """
        if scale not in PREVIEW_SCALES:
            raise BadRequest(f"'scale' must be one of {', '.join(map(str, PREVIEW_SCALES))}.")
        with self._lock:
            key = (scale, fmt)
            cached = self._images.get(key)
            if cached is None or cached[0] != self.version:
                pixels = self._pixels.get(scale)
                suffix = "" if scale == 1 else f"_1/{scale}"
                if pixels is None or pixels[0] != self.version:
                    t0 = time.perf_counter()
                    scalar = self._selected_weights() if self.options.show_weights else None
                    img = render(self._deformed64(), self.faces, camera=self.camera,
                                 width=max(1, round(self.width / scale)), height=max(1, round(self.height / scale)),
                                 scalar=scalar, cmap=WEIGHT_COLORMAP, vmin=WEIGHT_RANGE[0], vmax=WEIGHT_RANGE[1],
                                 colorbar=False)
                    pixels = self._pixels[scale] = (self.version, img)
                    self.timings[f"render{suffix}_ms"] = 1e3 * (time.perf_counter() - t0)
                t1 = time.perf_counter()
                buf = io.BytesIO()
                if fmt == "png":
                    Image.fromarray(pixels[1]).save(buf, format="PNG", compress_level=1)
                else:
                    Image.fromarray(pixels[1]).save(buf, format="JPEG", quality=JPEG_QUALITY)
                self.timings[f"{fmt}{suffix}_ms"] = 1e3 * (time.perf_counter() - t1)
                cached = self._images[key] = (self.version, buf.getvalue())
            return cached

    def image_png(self, scale: int = 1) -> tuple[int, bytes]:
        """(version, PNG bytes) of the current view; see :meth:`image_bytes`."""
        return self.image_bytes(scale, "png")

    def image(self) -> np.ndarray:
        """The current view as an (H, W, 3) uint8 array (decoded from the served PNG)."""
        return np.asarray(Image.open(io.BytesIO(self.image_png()[1])).convert("RGB"))

    def pick(self, body: dict) -> dict:
        """``{x, y, action}``: action ``query`` (report only), ``handle`` (select the marker under the cursor,
        else add a handle at the picked vertex), ``rotate`` (select the marker under the cursor, else keep the
        selection, else add a handle) or ``anchor`` (toggle an anchor at the picked vertex)."""
        x = _number(body, "x", 0.0, self.width)
        y = _number(body, "y", 0.0, self.height)
        action = _choice(body, "action", ("query", "handle", "rotate", "anchor"), "query")
        with self._lock:
            i, j = min(int(y), self.height - 1), min(int(x), self.width - 1)
            hits = self._ray_hits()
            tri = int(hits.triangle[i, j])
            vertex = None
            point = None
            if tri >= 0:
                corners = self.faces[tri]
                point = hits.points[i, j]
                dist = np.linalg.norm(self._deformed64()[corners] - point, axis=1)
                vertex = int(corners[int(np.argmin(dist))])
            marker = None
            if action in ("handle", "rotate"):
                best = MARKER_RADIUS
                for m in self._markers():
                    d = math.hypot(m["x"] - x, m["y"] - y)
                    if m["kind"] == "handle" and d <= best:
                        best, marker = d, m["index"]
            handle = None
            if action in ("handle", "rotate"):
                if marker is not None:
                    handle = marker
                elif action == "rotate" and self.selected is not None:
                    handle = self.selected
                elif vertex is not None:
                    handle = self._add_handle(vertex)
                if handle is not None and handle != self.selected:
                    self.selected = handle
                    self._changed(geometry=False)
            elif action == "anchor" and vertex is not None:
                self._toggle_anchor(vertex)
                self._changed()
            return {
                "hit": tri >= 0,
                "triangle": tri if tri >= 0 else None,
                "vertex": vertex,
                "point": None if point is None else point.tolist(),
                "handle": handle,
                "state": self.state(),
            }

    def drag(self, body: dict) -> dict:
        """``{mode: translate | rotate | orbit, from: [x, y], to: [x, y], handle?}``: one step of a drag."""
        mode = _choice(body, "mode", ("translate", "rotate", "orbit"))
        start, end = _point(body, "from"), _point(body, "to")
        with self._lock:
            if mode == "orbit":
                self.azimuth = (self.azimuth - ORBIT_DEG_PER_PIXEL * (end[0] - start[0]) + 180.0) % 360.0 - 180.0
                self.elevation = float(np.clip(self.elevation + ORBIT_DEG_PER_PIXEL * (end[1] - start[1]), -89, 89))
                self._update_camera()
                self._changed(geometry=False)
                return self.state()
            k = self._handle_index(body)
            self.selected = k
            p = self._deformed64()[self.handles[k]]
            if mode == "translate":
                move = translation_step(self.camera, self.width, self.height, p, start, end)
                step = make_transform(p, translate=move)
            else:
                centre = project(self.camera, self.width, self.height, p[None])[0][0]
                fwd = self.camera.basis()[0]
                step = make_transform(p, axis=-fwd, degrees=swept_angle(centre, start, end))
            self.transforms[k] = compose(np.asarray(step, dtype=np.float64), self.transforms[k])
            self._changed()
            return self.state()

    def set_options(self, body: dict) -> dict:
        known = {"locality", "lambda", "symmetric", "pou", "show_weights"}
        unknown = sorted(set(body) - known)
        if unknown:
            raise BadRequest(f"unknown option '{unknown[0]}'; the options are {', '.join(sorted(known))}.")
        with self._lock:
            new = Options(**vars(self.options))
            if "locality" in body:
                new.locality = _flag(body, "locality")
            if "lambda" in body:
                new.lam = _number(body, "lambda", 0.0, 100.0)
            if "symmetric" in body:
                new.symmetric = _flag(body, "symmetric")
                if new.symmetric and self.plane is None:
                    why = "no feature field was given" if not self.field_given else "the field showed no symmetry plane"
                    raise BadRequest(f"symmetric deformation is unavailable because {why}.")
            if "pou" in body:
                new.pou = _flag(body, "pou")
            if "show_weights" in body:
                new.show_weights = _flag(body, "show_weights")
            geometry = (new.locality, new.lam, new.symmetric, new.pou) != (
                self.options.locality, self.options.lam, self.options.symmetric, self.options.pou)
            self.options = new
            self._changed(geometry=geometry)
            return self.state()

    def set_view(self, body: dict) -> dict:
        """``{zoom?: factor (multiplies the distance), azimuth?, elevation?, reset?: true}``."""
        with self._lock:
            if body.get("reset"):
                self._reset_view()
            if "zoom" in body:
                self.zoom = float(np.clip(self.zoom * _number(body, "zoom", 0.01, 100.0), 0.1, 10.0))
            if "azimuth" in body:
                self.azimuth = _number(body, "azimuth", -180.0, 180.0)
            if "elevation" in body:
                self.elevation = _number(body, "elevation", -89.0, 89.0)
            self._update_camera()
            self._changed(geometry=False)
            return self.state()

    def edit_handle(self, body: dict) -> dict:
        """``{action: add, vertex}``, ``{action: select | remove | reset, handle}``, ``{action: deselect}`` or
        ``{action: transform, handle, transform: 3 x 4 rows}`` (sets the handle's affine map)."""
        action = _choice(body, "action", ("add", "select", "deselect", "remove", "reset", "transform"))
        with self._lock:
            if action == "deselect":
                self.selected = None
                self._changed(geometry=False)
                return self.state()
            if action == "add":
                self._add_handle(_index(body, "vertex", self.rest.shape[0], "vertex"))
                return self.state()
            k = self._handle_index(body)
            if action == "select":
                self.selected = k
                self._changed(geometry=False)
            elif action == "remove":
                del self.handles[k], self.transforms[k]
                self.selected = None if not self.handles else min(k, len(self.handles) - 1)
                self._changed()
            elif action == "reset":
                self.transforms[k] = np.eye(3, 4)
                self._changed()
            else:
                try:
                    t = np.asarray(body.get("transform"), dtype=np.float64)
                except (TypeError, ValueError):
                    t = np.zeros(0)
                if t.shape != (3, 4) or not np.all(np.isfinite(t)):
                    raise BadRequest("'transform' must be 3 rows of 4 finite numbers (an affine map).")
                self.transforms[k] = t
                self._changed()
            return self.state()

    def edit_anchor(self, body: dict) -> dict:
        """``{action: toggle, vertex}`` or ``{action: clear}``."""
        action = _choice(body, "action", ("toggle", "clear"))
        with self._lock:
            if action == "clear":
                self.anchors = []
            else:
                self._toggle_anchor(_index(body, "vertex", self.rest.shape[0], "vertex"))
            self._changed()
            return self.state()

    def reset(self, body: dict) -> dict:
        """``{what: transforms | all | view}``."""
        what = _choice(body, "what", ("transforms", "all", "view"))
        with self._lock:
            if what == "view":
                self._reset_view()
                self._changed(geometry=False)
            elif what == "transforms":
                self.transforms = [np.eye(3, 4) for _ in self.handles]
                self._changed()
            else:
                self._reset_all()
                self._changed()
            return self.state()


# --------------------------------------------------------------------------------------------- HTTP layer


class _Handler(BaseHTTPRequestHandler):
    server_version = "jaxdeform-handles"
    protocol_version = "HTTP/1.1"

    @property
    def session(self) -> Session:
        return self.server.session  # type: ignore[attr-defined]

    def log_message(self, fmt, *args):  # quiet: the terminal belongs to the CLI
        log.debug("%s - %s", self.address_string(), fmt % args)

    def _send(self, status: int, body: bytes, content_type: str, extra: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, status: int, obj) -> None:
        self._send(status, json.dumps(obj).encode("utf-8"), "application/json")

    def _error(self, status: int, message: str) -> None:
        self.close_connection = True  # a refused request's body may be unread: never reuse the connection
        self._json(status, {"error": message})

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").strip().lower()
        port = self.server.server_address[1]
        names = {"127.0.0.1", "localhost", self.server.server_address[0]}
        return host in names | {f"{n}:{port}" for n in names}

    def _route(self, method: str) -> None:
        if not self._host_ok():
            self._error(HTTPStatus.FORBIDDEN, "this page answers only requests addressed to 127.0.0.1 or localhost.")
            return
        url = urlsplit(self.path)
        path, query = url.path, parse_qs(url.query)
        try:
            if method == "GET":
                self._get(path, query)
            else:
                self._post(path)
        except BadRequest as exc:
            self._error(HTTPStatus.BAD_REQUEST, str(exc))
        except (ValueError, TypeError, JaxDeformError) as exc:  # e.g. from the Deformer: still the request's fault
            text = str(exc).strip()
            self._error(HTTPStatus.BAD_REQUEST, text.splitlines()[0] if text else "the request was refused.")
        except Exception as exc:  # noqa: BLE001 - answer instead of dropping the connection
            log.exception("request %s %s failed", method, path)
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"the server failed: {type(exc).__name__}: {exc}")

    def _get(self, path: str, query: dict) -> None:
        if path in ("/", "/index.html"):
            self._static("index.html")
        elif path.startswith("/static/"):
            self._static(path[len("/static/"):])
        elif path == "/favicon.ico":
            self._send(HTTPStatus.NO_CONTENT, b"", "image/x-icon")
        elif path == "/api/mesh-info":
            self._json(HTTPStatus.OK, self.session.mesh_info())
        elif path == "/api/state":
            want = query.get("vertices", ["0"])[-1] in ("1", "true", "yes")
            dtype = query.get("dtype", [None])[-1]
            if dtype not in (None, "float32", "float64"):
                raise BadRequest("'dtype' must be float32 or float64.")
            self._json(HTTPStatus.OK, self.session.state(vertices=want, dtype=dtype))
        elif path in ("/api/image.png", "/api/image.jpg"):
            try:
                scale = int(query.get("scale", ["1"])[-1])
            except ValueError:
                raise BadRequest("'scale' must be an integer.") from None
            fmt = "png" if path.endswith(".png") else "jpeg"
            version, data = self.session.image_bytes(scale, fmt)
            self._send(HTTPStatus.OK, data, f"image/{fmt}", {"X-Version": str(version)})
        else:
            self._error(HTTPStatus.NOT_FOUND, f"there is no page or endpoint at {path}.")

    def _static(self, name: str) -> None:
        path = STATIC_DIR / name
        if not _STATIC_NAME.match(name) or not path.is_file():
            self._error(HTTPStatus.NOT_FOUND, f"there is no static file named {name!r}.")
            return
        self._send(HTTPStatus.OK, path.read_bytes(), _CONTENT_TYPES[name.rsplit(".", 1)[1]])

    def _body(self) -> dict:
        try:
            n = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            raise BadRequest("the Content-Length header is not a number.") from None
        if n < 0 or n > MAX_BODY:
            raise BadRequest(f"the request body must hold at most {MAX_BODY} bytes.")
        raw = self.rfile.read(n)
        try:
            body = json.loads(raw.decode("utf-8")) if raw else None
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise BadRequest("the request body is not valid JSON.") from None
        if not isinstance(body, dict):
            raise BadRequest("the request body must be a JSON object.")
        return body

    def _post(self, path: str) -> None:
        origin = self.headers.get("Origin")
        if origin is not None and urlsplit(origin).netloc.lower() not in {
            f"{n}:{self.server.server_address[1]}" for n in ("127.0.0.1", "localhost")
        }:
            self._error(HTTPStatus.FORBIDDEN, "cross-origin requests are refused.")
            return
        routes: dict[str, Callable[[dict], dict]] = {
            "/api/pick": self.session.pick,
            "/api/drag": self.session.drag,
            "/api/options": self.session.set_options,
            "/api/view": self.session.set_view,
            "/api/handle": self.session.edit_handle,
            "/api/anchor": self.session.edit_anchor,
            "/api/reset": self.session.reset,
        }
        if path not in routes:
            self._error(HTTPStatus.NOT_FOUND, f"there is no endpoint at {path}.")
            return
        self._json(HTTPStatus.OK, routes[path](self._body()))

    def do_GET(self):  # noqa: N802 - http.server's naming
        self._route("GET")

    def do_HEAD(self):  # noqa: N802
        self._route("GET")

    def do_POST(self):  # noqa: N802
        self._route("POST")


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address, session: Session):
        self.session = session
        super().__init__(address, _Handler)


def loopback_host(host: str) -> str:
    """The IPv4 loopback address to bind for ``host`` (``localhost`` -> 127.0.0.1); anything else is refused."""
    name = "127.0.0.1" if host == "localhost" else host
    try:
        addr = ipaddress.ip_address(name)
    except ValueError:
        addr = None
    if addr is None or addr.version != 4 or not addr.is_loopback:
        raise ValueError(f"the page binds only to an IPv4 loopback address such as 127.0.0.1, got {host!r}.")
    return name


class PageServer:
    """A running page: ``url``, ``port``, ``session``; ``shutdown()`` stops it, ``wait()`` blocks until then."""

    def __init__(self, session: Session, host: str, port: int):
        self.session = session
        self._httpd = _Server((loopback_host(host), int(port)), session)
        self.host, self.port = self._httpd.server_address[:2]
        self.url = f"http://{self.host}:{self.port}/"
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._run, name="jaxdeform-handles-page", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self._httpd.serve_forever(poll_interval=0.2)
        finally:
            self._stopped.set()

    @property
    def server_address(self) -> tuple[str, int]:
        return self._httpd.server_address[:2]

    def shutdown(self) -> None:
        """Stop serving and close the socket (idempotent)."""
        if self._thread.is_alive():
            self._httpd.shutdown()
            self._thread.join()
        self._httpd.server_close()

    def wait(self) -> None:
        """Block until the server stops; Ctrl-C shuts it down."""
        try:
            while not self._stopped.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            self.shutdown()

    def __enter__(self) -> PageServer:
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()


def serve(
    vertices,
    faces,
    Z,
    *,
    field_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    host: str = "127.0.0.1",
    port: int = 0,
    block: bool = True,
    width: int = 512,
    height: int = 512,
    up_axis: str = "y",
    announce: Callable[[str], None] | None = None,
) -> PageServer:
    """Serve the interactive page for a mesh with per-vertex features ``Z`` (V, C), unit-norm rows.

    ``field_fn`` (points (P, 3) -> unit features (P, C)) enables symmetry detection (eq. 9). ``port=0`` takes
    a free port. ``announce(url)`` is called once the socket is bound. With ``block`` the call serves until
    Ctrl-C (then shuts down); otherwise it returns the running :class:`PageServer` at once.
    """
    session = Session(vertices, faces, Z, field_fn=field_fn, width=width, height=height, up_axis=up_axis)
    server = PageServer(session, host, port)
    if announce is not None:
        announce(server.url)
    if block:
        server.wait()
    return server
