"""Figures for part decompositions: segmentations in categorical colours, error heat maps, frame strips.

All three functions render with :mod:`jaxdeform.mesh.render` (CPU ray casting) and write one PNG atomically
(:func:`jaxdeform.mesh.render.save_png`: temporary file + rename), returning the ``(H, W, 3)`` uint8 image.

Views are named directions for :func:`~jaxdeform.mesh.render.auto_camera` (``VIEWS``: azimuth and
elevation in degrees around the world's vertical ``up_axis``), or explicit ``(azimuth_deg, elevation_deg)``
pairs. With a y-up mesh, "front" looks from +z, "side" from +x and "top" from above.

Part labels are coloured by label *value* (``categorical_colors(max_label + 1)[label]``), so the same label
has the same colour in every figure; negative labels (unassigned vertices) are drawn grey.
"""

from __future__ import annotations

import numpy as np

from jaxdeform.errors import MeshFormatError
from jaxdeform.mesh.render import VIEWS, auto_camera, caption, categorical_colors, hstack, render, save_png, view_angles

#: Colour of vertices with a negative (unassigned) label.
UNASSIGNED = (0.6, 0.6, 0.6)

_BACKGROUND = (1.0, 1.0, 1.0)


def _view_name(view) -> str:
    if isinstance(view, str):
        return view
    az, el = view_angles(view)
    return f"az {az:g}, el {el:g}"


def _vertices(vertices, name: str = "vertices") -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise MeshFormatError(f"{name} must be a non-empty (V, 3) array, got shape {v.shape}.")
    return v


def label_colors(labels, n_vertices: int) -> np.ndarray:
    """Per-vertex colours for integer part labels.

    **Arguments:**

    - ``labels``: ``(V,)`` part per vertex (negative = unassigned, grey).
    - ``n_vertices``: V.

    **Returns:**

    RGB ``(V, 3)``.
    """
    lab = np.asarray(labels)
    if lab.ndim != 1 or lab.shape[0] != n_vertices:
        raise ValueError(f"labels must have shape ({n_vertices},) (one per vertex), got {lab.shape}.")
    if lab.size and not np.issubdtype(lab.dtype, np.integer):
        if not np.all(np.isfinite(lab)) or not np.all(lab == np.round(lab)):
            raise ValueError(f"labels must be integers, got dtype {lab.dtype} with non-integer values.")
    lab = lab.astype(np.int64)
    n = int(lab.max()) + 1 if lab.size else 0
    palette = categorical_colors(max(n, 0))
    out = np.empty((n_vertices, 3))
    out[:] = UNASSIGNED
    ok = lab >= 0
    out[ok] = palette[lab[ok]]
    return out


def segmentation_figure(
    vertices,
    faces,
    labels,
    path,
    views=("front", "side", "top"),
    width: int = 480,
    height: int = 360,
    *,
    up_axis: str = "y",
    captions: bool = True,
    shading: bool = True,
) -> np.ndarray:
    """One PNG with the mesh seen from each of ``views`` side by side, parts in categorical colours.

    Each pixel takes the colour of the hit triangle's vertex of largest barycentric weight (no blending across
    parts).

    **Arguments:**

    - ``vertices``, ``faces``: the mesh.
    - ``labels``: ``(V,)`` integer part per vertex.
    - ``path``: the PNG to write.
    - ``views``: the named views.
    - ``width``, ``height``: the size of *one* view.
    - ``up_axis``: the world's up axis.
    - ``captions``: caption each view with its name.
    - ``shading``: shade the colours.

    **Returns:**

    The image, ``len(views) * width`` (plus 4-pixel gaps) wide.
    """
    v = _vertices(vertices)
    colours = label_colors(labels, v.shape[0])
    views = (views,) if isinstance(views, str) else tuple(views)
    if not views:
        raise ValueError("views must name at least one view.")
    panels = []
    for view in views:
        az, el = view_angles(view)
        cam = auto_camera(v, azimuth_deg=az, elevation_deg=el, up_axis=up_axis)
        img = render(
            v,
            faces,
            vertex_colors=colours,
            camera=cam,
            width=width,
            height=height,
            shading=shading,
            background=_BACKGROUND,
        )
        panels.append(caption(img, _view_name(view)) if captions else img)
    image = hstack(panels)
    save_png(image, path)
    return image


def error_figure(
    vertices,
    faces,
    error,
    path,
    label: str = "reconstruction error",
    *,
    view="three_quarter",
    width: int = 800,
    height: int = 600,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    up_axis: str = "y",
) -> np.ndarray:
    """A heat map of a per-vertex error with a colour bar, written to ``path``.

    **Arguments:**

    - ``vertices``, ``faces``: the mesh.
    - ``error``: ``(V,)`` per-vertex error.
    - ``path``: the PNG to write.
    - ``label``: the colour bar's title.
    - ``view``: the named view.
    - ``width``, ``height``: the image size.
    - ``cmap``: the colour map.
    - ``vmin``, ``vmax``: the colour range; by default [0, max error] for non-negative errors (the data's own range
        otherwise); pass the same ``vmax`` to several figures to compare them.
    - ``up_axis``: the world's up axis.

    **Returns:**

    The image.
    """
    v = _vertices(vertices)
    e = np.asarray(error, dtype=np.float64)
    if e.shape != (v.shape[0],):
        raise ValueError(f"error must have shape ({v.shape[0]},) (one value per vertex), got {e.shape}.")
    if vmin is None and np.all(np.isfinite(e)) and e.min() >= 0.0 and (vmax is None or vmax >= 0.0):
        vmin = 0.0  # errors are distances: anchor the colour bar at zero
    az, el = view_angles(view)
    cam = auto_camera(v, azimuth_deg=az, elevation_deg=el, up_axis=up_axis)
    image = render(
        v,
        faces,
        scalar=e,
        camera=cam,
        width=width,
        height=height,
        cmap=cmap,
        vmin=vmin,
        vmax=vmax,
        colorbar=True,
        label=label,
        background=_BACKGROUND,
    )
    save_png(image, path)
    return image


def strip_figure(
    frames,
    faces,
    path,
    labels=None,
    *,
    view="side",
    width: int = 320,
    height: int = 240,
    step: int = 1,
    up_axis: str = "y",
    captions: bool = True,
) -> np.ndarray:
    """Frames side by side in one PNG, all seen by one camera fitted to every frame.

    **Arguments:**

    - ``frames``: ``(T, V, 3)``.
    - ``faces``: triangles ``(F, 3)``.
    - ``path``: the PNG to write.
    - ``labels``: ``(V,)`` parts; the vertices are then coloured by part (the same colours in every frame),
        otherwise the mesh is drawn plain.
    - ``view``: the named view.
    - ``width``, ``height``: one frame's panel.
    - ``step``: > 1 keeps every step-th frame.
    - ``up_axis``: the world's up axis.
    - ``captions``: caption each panel with its frame index.

    **Returns:**

    The image.
    """
    x = np.asarray(frames, dtype=np.float64)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[2] != 3 or x.shape[0] == 0 or x.shape[1] == 0:
        raise MeshFormatError(f"frames must be a non-empty (T, V, 3) array, got shape {x.shape}.")
    step = int(step)
    if step < 1:
        raise ValueError(f"step must be a positive integer, got {step}.")
    colours = None if labels is None else label_colors(labels, x.shape[1])
    az, el = view_angles(view)
    cam = auto_camera(x.reshape(-1, 3), azimuth_deg=az, elevation_deg=el, up_axis=up_axis)
    panels = []
    for t in range(0, x.shape[0], step):
        img = render(x[t], faces, vertex_colors=colours, camera=cam, width=width, height=height, background=_BACKGROUND)
        panels.append(caption(img, str(t)) if captions else img)
    image = hstack(panels, gap=2)
    save_png(image, path)
    return image


__all__ = ["VIEWS", "UNASSIGNED", "label_colors", "segmentation_figure", "error_figure", "strip_figure"]
