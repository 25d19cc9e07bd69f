"""The handle-editing page's state without any transport: :class:`EditSession`.

A session holds one mesh with its per-vertex features, the handles with their (3, 4) affine transforms, the anchors
(eq. 7), the options (locality eq. 8, symmetry eq. 9, partition of unity eq. 10, weight colouring) and the view
(:class:`~jaxdeform.handles.viewport.Viewport`). After every change the displayed mesh equals
``Deformer.deform(**session.deform_args())``, or the rest mesh itself while there are no handles. Screen positions
are display pixels: x to the right, y down, pixel (i, j) covers [j, j+1) x [i, i+1) of a width x height image.

Every public method holds :attr:`EditSession.lock` (re-entrant: hold it to make several calls atomic), and
:attr:`EditSession.version` increases with every change of what the image shows. Bad arguments raise
``ValueError`` (or a :class:`jaxdeform.errors.JaxDeformError` from the library) with one sentence, and change
nothing.
"""

from __future__ import annotations

import functools
import io
import threading
import time
from dataclasses import dataclass

import numpy as np
from PIL import Image

from jaxdeform.handles.viewport import (
    MARKER_RADIUS,
    Viewport,
    check_array,
    check_choice,
    check_image_size,
    check_index,
    check_number,
    compose,
    interior_pixel,
    swept_angle,
    translation_step,
)
from jaxdeform.handles.weights import Deformer, make_transform

PICK_ACTIONS = ("query", "handle", "rotate", "anchor")
DRAG_MODES = ("translate", "rotate", "orbit")
RESET_TARGETS = ("transforms", "all", "view")
#: a handle's transform is refused when its linear part has an entry above this, or when it takes the handle more
#: than this many mesh sizes (bounding-box diagonals) from the mesh's centre
TRANSFORM_LIMIT = 1e3


@dataclass
class Options:
    """Deformation and display options; ``lam`` is the locality exponent, used only while ``locality``."""

    locality: bool = False
    lam: float = 2.0
    symmetric: bool = False
    pou: bool = False
    show_weights: bool = True

    def as_json(self) -> dict:
        """The options as the page names them (``lambda`` for ``lam``)."""
        return {
            "locality": self.locality,
            "lambda": self.lam,
            "symmetric": self.symmetric,
            "pou": self.pou,
            "show_weights": self.show_weights,
        }


def _locked(method):
    """``method`` run while holding ``self.lock``."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with self.lock:
            return method(self, *args, **kwargs)

    return run


class EditSession:
    """Handles, transforms, anchors, options and view of one mesh, with its deformed mesh and rendered frames.

    **Arguments:**

    - ``vertices``: ``(V, 3)`` finite rest positions.
    - ``faces``: ``(F, 3)`` vertex indices.
    - ``Z``: ``(V, C)`` per-vertex features (unit rows after normalisation by :class:`Deformer`).
    - ``field_fn``: points ``(P, 3)`` -> features ``(P, C)``; enables symmetry detection (``symmetry_available``).
    - ``width``, ``height``: the displayed image in pixels, at least 16 each.
    - ``up_axis``: the camera's up axis.
    """

    def __init__(self, vertices, faces, Z, *, field_fn=None, width: int = 512, height: int = 512, up_axis: str = "y"):
        self.width, self.height = check_image_size(width, height)
        self.rest = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.n_features = int(np.shape(Z)[1]) if np.ndim(Z) == 2 else None
        self.deformer = Deformer(self.rest, self.faces, Z, field_fn=field_fn)
        self.field_given = field_fn is not None
        self.plane = self.deformer.symmetry_plane() if self.field_given else None
        self.view = Viewport(self.rest, width, height, up_axis)
        lo, hi = self.rest.min(axis=0), self.rest.max(axis=0)
        self._size, self._centre = float(np.linalg.norm(hi - lo)) or 1.0, 0.5 * (lo + hi)
        self.lock = threading.RLock()
        self.version = 0
        self._reset_all()

    # ----------------------------------------------------------------------------------------------- internals

    def _reset_all(self) -> None:
        self.handles: list[int] = []
        self.transforms: list[np.ndarray] = []
        self.anchors: list[int] = []
        self.selected: int | None = None
        self.options = Options()
        self.deformed = self.rest.copy()
        self.timings: dict[str, float] = {}

    def _locality(self) -> float:
        return float(self.options.lam) if self.options.locality else 0.0

    def _anchor_array(self):
        return np.asarray(self.anchors, dtype=np.int64) if self.anchors else ()

    def _changed(self, *, geometry: bool = True) -> None:
        """Recompute the deformed mesh if ``geometry``, then bump the version."""
        if geometry:
            t0 = time.perf_counter()
            if not self.handles:
                self.deformed = self.rest.copy()
            else:
                self.deformed = np.asarray(
                    self.deformer.deform(
                        np.asarray(self.handles, dtype=np.int64),
                        np.stack(self.transforms),
                        anchors=self._anchor_array(),
                        locality=self._locality(),
                        symmetric=self.options.symmetric and self.plane is not None,
                        pou=self.options.pou,
                    )
                )
            self.timings["deform_ms"] = 1e3 * (time.perf_counter() - t0)
        self.version += 1

    def _deformed64(self) -> np.ndarray:
        return np.asarray(self.deformed, dtype=np.float64)

    def _markers(self) -> list[dict]:
        return self.view.markers(self._deformed64(), self.handles, self.anchors)

    def _handle(self, handle: int | None) -> int:
        """The handle index ``handle`` (checked), or the selected one when None."""
        if handle is not None:
            return check_index(handle, len(self.handles), "handle")
        if self.selected is None:
            raise ValueError("no handle is selected; click the mesh to add one first.")
        return self.selected

    def _vertex(self, vertex: int) -> int:
        return check_index(vertex, self.rest.shape[0], "vertex")

    def _select(self, k: int | None) -> None:
        if k != self.selected:
            self.selected = k
            self._changed(geometry=False)

    def _apply(self, k: int, step: np.ndarray) -> None:
        """Compose ``step`` on the left of handle ``k``'s transform and select the handle."""
        previous, self.selected = self.selected, k
        try:
            self._set_transform(k, compose(step, self.transforms[k]))
        except ValueError:
            self.selected = previous
            raise

    def _set_transform(self, k: int, transform: np.ndarray) -> None:
        """Give handle ``k`` the ``(3, 4)`` ``transform`` and recompute the mesh, or raise ``ValueError`` and keep
        the session as it was when the transform or the mesh it gives is not finite or beyond
        :data:`TRANSFORM_LIMIT`."""
        t = np.asarray(transform, np.float64)
        size, centre = self._size, self._centre
        with np.errstate(over="ignore", invalid="ignore"):
            image = t[:, :3] @ np.asarray(self.rest[self.handles[k]], np.float64) + t[:, 3]
            absurd = (
                not np.all(np.isfinite(t))
                or np.abs(t[:, :3]).max() > TRANSFORM_LIMIT
                or not np.abs(image - centre).max() <= TRANSFORM_LIMIT * size
            )
        if absurd:
            raise ValueError(
                f"the transform of handle {k} is not finite or moves it beyond {TRANSFORM_LIMIT:g} mesh sizes; "
                "it was not applied."
            )
        old = self.transforms[k]
        self.transforms[k] = t
        self._changed()
        if not np.all(np.isfinite(self.deformed)):
            self.transforms[k] = old
            self._changed()
            raise ValueError(f"the transform of handle {k} gives a mesh that is not finite; it was not applied.")

    # ------------------------------------------------------------------------------------------------- queries

    def deform_args(self) -> dict:
        """Keyword arguments of ``Deformer.deform`` (JSON values) that reproduce the displayed mesh."""
        with self.lock:
            return {
                "handles": list(self.handles),
                "transforms": [t.tolist() for t in self.transforms],
                "anchors": list(self.anchors),
                "locality": self._locality(),
                "symmetric": bool(self.options.symmetric),
                "pou": bool(self.options.pou),
            }

    @_locked
    def mesh_info(self) -> dict:
        """Sizes of the mesh, image and features, bounding box, ``symmetry_available``, ``field_given``,
        ``covered_pixel`` ((x, y) inside the displayed silhouette, or None) and ``marker_radius``."""
        hint = interior_pixel(self.view.ray_hits(self.version, self._deformed64(), self.faces).hit)
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

    @_locked
    def state(self) -> dict:
        """The whole editable state as JSON values: version, handles, transforms, anchors, selected, options,
        deform_args, symmetry_plane, camera, width, height, markers (projected handles / anchors) and timings."""
        plane = None
        if self.plane is not None:
            plane = {
                "normal": np.asarray(self.plane.normal, dtype=np.float64).tolist(),
                "offset": float(self.plane.offset),
                "score": float(self.plane.score),
            }
        return {
            "version": self.version,
            "handles": list(self.handles),
            "transforms": [t.tolist() for t in self.transforms],
            "anchors": list(self.anchors),
            "selected": self.selected,
            "options": self.options.as_json(),
            "deform_args": self.deform_args(),
            "symmetry_plane": plane,
            "camera": self.view.as_json(),
            "width": self.width,
            "height": self.height,
            "markers": self._markers(),
            "timings": dict(self.timings),
        }

    @_locked
    def deformed_vertices(self, dtype=None) -> np.ndarray:
        """A copy of the displayed mesh.

        **Arguments:**

        - ``dtype``: the copy's dtype (None: as computed, float32 once deformed).

        **Returns:**

        ``(V, 3)``.
        """
        return np.array(self.deformed, dtype=dtype)

    @_locked
    def weights(self) -> np.ndarray:
        """DFD weights of the handles under the current anchors and locality.

        **Returns:**

        ``(V, K)``; ``(V, 0)`` without handles.
        """
        if not self.handles:
            return np.zeros((self.rest.shape[0], 0))
        return np.asarray(
            self.deformer.weights(
                np.asarray(self.handles, dtype=np.int64), anchors=self._anchor_array(), locality=self._locality()
            )
        )

    @_locked
    def selected_weights(self) -> np.ndarray | None:
        """The selected handle's weight column.

        **Returns:**

        ``(V,)`` float64, or None when no handle is selected.
        """
        return None if self.selected is None else np.asarray(self.weights()[:, self.selected], dtype=np.float64)

    @_locked
    def image_bytes(self, scale: int = 1, fmt: str = "png") -> tuple[int, bytes]:
        """The current view, encoded; rendered once per version and scale.

        **Arguments:**

        - ``scale``: one of ``PREVIEW_SCALES``; > 1 renders (W / scale, H / scale) pixels with the same camera, so
            preview pixel (i, j) covers display block [scale j, scale (j + 1)) x [scale i, scale (i + 1)).
        - ``fmt``: "png" (lossless) or "jpeg" (quality ``JPEG_QUALITY``, cheaper to encode: drag frames).

        **Returns:**

        (version, image bytes). With ``show_weights`` and a selected handle the mesh is coloured by that
        handle's weights through ``WEIGHT_COLORMAP`` over ``WEIGHT_RANGE``.
        """
        scalar = lambda: self.selected_weights() if self.options.show_weights else None  # noqa: E731
        data = self.view.frame(self.version, self._deformed64(), self.faces, scalar, scale, fmt, self.timings)
        return self.version, data

    def image(self, scale: int = 1) -> np.ndarray:
        """The current view as an array (decoded from the PNG of :meth:`image_bytes`).

        **Arguments:**

        - ``scale``: as :meth:`image_bytes`.

        **Returns:**

        ``(H, W, 3)`` uint8.
        """
        return np.asarray(Image.open(io.BytesIO(self.image_bytes(scale, "png")[1])).convert("RGB"))

    # ------------------------------------------------------------------------------------------------- handles

    @_locked
    def add_handle(self, vertex: int) -> int:
        """Make ``vertex`` a handle with the identity transform and select it.

        A vertex that already is a handle is only selected.

        **Arguments:**

        - ``vertex``: a vertex index.

        **Returns:**

        Its handle index.

        **Raises:**

        ``ValueError`` for an anchor or an invalid vertex.
        """
        vertex = self._vertex(vertex)
        if vertex in self.anchors:
            raise ValueError(f"vertex {vertex} is an anchor; remove the anchor before making it a handle.")
        if vertex in self.handles:
            self._select(self.handles.index(vertex))
            return self.selected
        self.handles.append(vertex)
        self.transforms.append(np.eye(3, 4))
        self.selected = len(self.handles) - 1
        self._changed()
        return self.selected

    @_locked
    def select_handle(self, handle: int | None = None) -> int:
        """Select a handle.

        **Arguments:**

        - ``handle``: an index into ``handles`` (None: keep the selected one).

        **Returns:**

        Its index.

        **Raises:**

        ``ValueError`` for an invalid index, or None with no handle selected.
        """
        self._select(self._handle(handle))
        return self.selected

    @_locked
    def deselect(self) -> None:
        """Select no handle (the image then shows no weights)."""
        self._select(None)

    @_locked
    def remove_handle(self, handle: int | None = None) -> None:
        """Remove a handle; the selection moves to the next remaining handle.

        **Arguments:**

        - ``handle``: an index into ``handles`` (default None: the selected one).

        **Returns:**

        Nothing.

        **Raises:**

        ``ValueError`` for an invalid index, or None with no handle selected.
        """
        k = self._handle(handle)
        del self.handles[k], self.transforms[k]
        self.selected = None if not self.handles else min(k, len(self.handles) - 1)
        self._changed()

    @_locked
    def set_transform(self, handle: int | None, transform) -> None:
        """Set a handle's affine map; the identity resets it.

        **Arguments:**

        - ``handle``: an index into ``handles`` (default None: the selected one).
        - ``transform``: the ``(3, 4)`` affine map.

        **Returns:**

        Nothing.

        **Raises:**

        ``ValueError`` for an invalid handle, a transform that is not a finite ``(3, 4)`` array, or one beyond
        :data:`TRANSFORM_LIMIT` (the session is left as it was).
        """
        k = self._handle(handle)
        self._set_transform(
            k, check_array(transform, (3, 4), "'transform' must be 3 rows of 4 finite numbers (an affine map).")
        )

    def reset_handle(self, handle: int | None = None) -> None:
        """Give a handle the identity transform.

        **Arguments:**

        - ``handle``: an index into ``handles`` (default None: the selected one).

        **Returns:**

        Nothing.
        """
        self.set_transform(handle, np.eye(3, 4))

    @_locked
    def translate_handle(self, translation, handle: int | None = None) -> None:
        """Translate a handle by a world vector, composed on the left of its transform.

        Without symmetry or partition of unity every vertex i moves by ``W_ik t``: the handle vertex by ``t`` when its
        own weight is 1 (always, unless an anchor with similar features lowers it).

        **Arguments:**

        - ``translation``: the world vector t ``(3,)``.
        - ``handle``: an index into ``handles`` (default None: the selected one).

        **Returns:**

        Nothing.
        """
        k = self._handle(handle)
        t = check_array(translation, (3,), "'translation' must be 3 finite numbers.")
        self._apply(k, make_transform(self._deformed64()[self.handles[k]], translate=t))

    @_locked
    def rotate_handle(self, axis, degrees: float, handle: int | None = None) -> None:
        """Rotate a handle about an axis through the handle's current position, composed on the left of its transform.

        **Arguments:**

        - ``axis``: the rotation axis ``(3,)``, non-zero.
        - ``degrees``: the angle.
        - ``handle``: an index into ``handles`` (default None: the selected one).

        **Returns:**

        Nothing.

        **Raises:**

        ``ValueError`` for a zero axis or an invalid handle.
        """
        k = self._handle(handle)
        a = check_array(axis, (3,), "'axis' must be 3 finite numbers.")
        if not np.linalg.norm(a) > 0.0:
            raise ValueError("'axis' must be a non-zero vector.")
        degrees = check_number(degrees, "degrees")
        self._apply(k, make_transform(self._deformed64()[self.handles[k]], axis=a, degrees=degrees))

    # ------------------------------------------------------------------------------------------------- anchors

    @_locked
    def toggle_anchor(self, vertex: int) -> bool:
        """Pin ``vertex`` as an anchor or unpin it.

        **Arguments:**

        - ``vertex``: a vertex index.

        **Returns:**

        Whether it is an anchor now.

        **Raises:**

        ``ValueError`` for a handle or an invalid vertex.
        """
        vertex = self._vertex(vertex)
        if vertex in self.handles:
            raise ValueError(f"vertex {vertex} is a handle; a handle cannot also be an anchor.")
        if vertex in self.anchors:
            self.anchors.remove(vertex)
        else:
            self.anchors.append(vertex)
        self._changed()
        return vertex in self.anchors

    @_locked
    def clear_anchors(self) -> None:
        """Remove every anchor."""
        self.anchors = []
        self._changed()

    # ---------------------------------------------------------------------------------------- screen actions

    @_locked
    def pick(self, x: float, y: float, action: str = "query") -> dict:
        """Pick the displayed mesh at display pixel (x, y).

        **Arguments:**

        - ``x``, ``y``: display coordinates in [0, width] x [0, height].
        - ``action``: ``query`` (report only), ``handle`` (select the handle whose marker is under the cursor, else
            add a handle at the picked vertex), ``rotate`` (the marker's handle, else keep the selection, else
            add a handle) or ``anchor`` (toggle an anchor at the picked vertex).

        **Returns:**

        ``{"hit", "triangle", "vertex", "point", "handle"}``: the hit triangle and its corner nearest the hit
        point (None on the background), the world hit point, and the handle the action selected (or None).
        """
        x = check_number(x, "x", 0.0, self.width)
        y = check_number(y, "y", 0.0, self.height)
        action = check_choice(action, "action", PICK_ACTIONS)
        tri, vertex, point = self.view.pick(self.version, self._deformed64(), self.faces, x, y)
        handle = None
        if action in ("handle", "rotate"):
            handle = self.view.marker_at(self._markers(), x, y)
            if handle is None and action == "rotate":
                handle = self.selected
            if handle is None and vertex is not None:
                handle = self.add_handle(vertex)
            if handle is not None:
                self._select(handle)
        elif action == "anchor" and vertex is not None:
            self.toggle_anchor(vertex)
        return {
            "hit": tri >= 0,
            "triangle": tri if tri >= 0 else None,
            "vertex": vertex,
            "point": None if point is None else point.tolist(),
            "handle": handle,
        }

    @_locked
    def drag(self, mode: str, start, end, handle: int | None = None) -> None:
        """One step of a drag from display pixel ``start`` (x, y) to ``end``.

        **Arguments:**

        - ``mode``: ``translate``: the handle moves by ``s (dx r - dy u)`` (camera right / up vectors, ``s`` the world
            size of a pixel at the handle's depth), so its projection follows the cursor exactly; ``rotate``:
            about the view axis through the handle's current position p by the angle the cursor sweeps around
            p's projection (counter-clockwise on screen is positive); ``orbit``: the camera turns about the
            mesh's bounding-box centre, ``ORBIT_DEG_PER_PIXEL`` per pixel. Handle steps are composed on the
            left of the handle's transform (``D <- M D``) and select the handle.
        - ``start``, ``end``: (x, y) display coordinates.
        - ``handle``: the handle index, or None for the selected one (ignored by ``orbit``).
        """
        mode = check_choice(mode, "mode", DRAG_MODES)
        start = check_array(start, (2,), "'from' must be a pair [x, y] of display pixel coordinates.")
        end = check_array(end, (2,), "'to' must be a pair [x, y] of display pixel coordinates.")
        if mode == "orbit":
            self.view.orbit(start, end)
            self._changed(geometry=False)
            return
        k = self._handle(handle)
        p = self._deformed64()[self.handles[k]]
        if mode == "translate":
            move = translation_step(self.view.camera, self.width, self.height, p, start, end)
            self._apply(k, make_transform(p, translate=move))
        else:
            angle = swept_angle(self.view.project(p[None])[0][0], start, end)
            self._apply(k, make_transform(p, axis=-self.view.camera.basis()[0], degrees=angle))

    # ----------------------------------------------------------------------------------------- options, view

    @_locked
    def set_options(
        self,
        *,
        locality: bool | None = None,
        lam: float | None = None,
        symmetric: bool | None = None,
        pou: bool | None = None,
        show_weights: bool | None = None,
    ) -> dict:
        """Change the given options (None keeps one).

        The mesh is deformed again only when an option of the deformation changed.

        **Arguments:**

        - ``locality``: use the locality weighting (eq. 8).
        - ``lam``: the locality exponent, in [0, 100].
        - ``symmetric``: symmetry-preserving blending; needs a detected plane.
        - ``pou``: the partition-of-unity extension (eq. 10).
        - ``show_weights``: colour the mesh by the selected handle's weights.

        **Returns:**

        The options as :meth:`Options.as_json`.

        **Raises:**

        ``ValueError`` for ``lam`` outside [0, 100] or ``symmetric`` without a detected plane.
        """
        new = Options(**vars(self.options))
        if locality is not None:
            new.locality = bool(locality)
        if lam is not None:
            new.lam = check_number(lam, "lambda", 0.0, 100.0)
        if symmetric is not None:
            new.symmetric = bool(symmetric)
            if new.symmetric and self.plane is None:
                why = "no feature field was given" if not self.field_given else "the field showed no symmetry plane"
                raise ValueError(f"symmetric deformation is unavailable because {why}.")
        if pou is not None:
            new.pou = bool(pou)
        if show_weights is not None:
            new.show_weights = bool(show_weights)
        old, self.options = self.options, new
        self._changed(
            geometry=(new.locality, new.lam, new.symmetric, new.pou) != (old.locality, old.lam, old.symmetric, old.pou)
        )
        return new.as_json()

    @_locked
    def set_view(
        self,
        *,
        zoom: float | None = None,
        azimuth: float | None = None,
        elevation: float | None = None,
        reset: bool = False,
    ) -> None:
        """Change the camera; see :meth:`Viewport.set`.

        **Arguments:**

        - ``zoom``: in [0.01, 100], multiplies the camera's distance (kept within 0.1 to 10 times the initial one).
        - ``azimuth``, ``elevation``: the camera's angles, in [-180, 180] and [-89, 89] degrees.
        - ``reset``: back to the initial camera first.

        **Returns:**

        Nothing.

        **Raises:**

        ``ValueError`` for an argument out of range (all are checked before anything changes).
        """
        self.view.set(zoom=zoom, azimuth=azimuth, elevation=elevation, reset=reset)
        self._changed(geometry=False)

    @_locked
    def reset(self, what: str = "all") -> None:
        """Reset part of the session.

        **Arguments:**

        - ``what``: ``transforms``: every handle back to the identity; ``all``: no handles, anchors, selection, default
            options (the rest mesh is displayed); ``view``: the initial camera.

        **Returns:**

        Nothing.

        **Raises:**

        ``ValueError`` for another ``what``.
        """
        what = check_choice(what, "what", RESET_TARGETS)
        if what == "view":
            self.view.reset()
            self._changed(geometry=False)
            return
        if what == "transforms":
            self.transforms = [np.eye(3, 4) for _ in self.handles]
        else:
            self._reset_all()
        self._changed()
