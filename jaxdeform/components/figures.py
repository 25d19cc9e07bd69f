"""Figures of deformation components (seed 000, Figs. 2, 5, 8-13) and of their cosine similarity (Fig. 3).

:func:`components_figure` draws a grid of component meshes, one row per autoencoder block (an ``AE0`` row,
then ``AE1`` ... ``AEK``; a linear model's components fill one row, wrapped), each panel the reference deformed
by one component with its deformed region coloured: the per-vertex strength ``||X_diff,i||`` (the summand of
eq. (7)) divided by ``vmax`` (default: the panel's own maximum) gives ``t`` in [0, 1], and a pixel takes
``shade * ((1 - t) grey + t cmap(t))`` -- a neutral grey body that turns into the colormap where the component
deforms the shape. :func:`similarity_figure` draws a K x K heat map with a colour bar.

Rendering goes through :mod:`jaxdeform.mesh.render` (Embree ray casting; by default each panel's camera frames
its own mesh, from one direction around the data set's up axis so that every mesh stands upright and shows its
broad side): per panel one :func:`~jaxdeform.mesh.render.cast_rays` for the interpolated strength and one
:func:`~jaxdeform.mesh.render.render` of a white body for the Lambert shading. Every input is validated before
anything is rendered, and the PNG is written atomically (:func:`~jaxdeform.mesh.render.save_png`), so invalid
input never leaves a file. Both functions return the ``(H, W, 3)`` uint8 image.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from jaxdeform.components.extract import ComponentSet, Removal, deformation_strength, vertex_strength
from jaxdeform.errors import ConnectivityError, DegenerateMeshError, MeshFormatError
from jaxdeform.mesh.render import (
    COLORMAPS,
    VIEWS,
    Camera,
    auto_camera,
    cast_rays,
    colormap,
    guess_up_axis,
    render,
    save_png,
    view_angles,
)

#: The body colour of undeformed regions.
GREY = (0.72, 0.72, 0.72)

_WHITE = (1.0, 1.0, 1.0)
_INK = (30, 30, 30)
_MUTED = (120, 120, 120)


def _font(size: int):
    try:
        return ImageFont.load_default(size=int(size))
    except (TypeError, ValueError, OSError):  # Pillow without FreeType: a fixed bitmap font
        return ImageFont.load_default()


def _text_size(font, text: str) -> tuple[int, int]:
    box = ImageDraw.Draw(Image.new("RGB", (1, 1))).textbbox((0, 0), text, font=font)
    return box[2] - box[0], box[3] - box[1]


def _check_cmap(cmap: str) -> None:
    if cmap not in COLORMAPS:
        raise ValueError(f"unknown colormap {cmap!r}; expected one of {', '.join(COLORMAPS)}.")


# ------------------------------------------------------------------------------------------- one panel


def blend(t, cmap: str = "viridis", body=GREY) -> np.ndarray:
    """Colour of a normalized strength: ``(1 - t) body + t cmap(t)``.

    **Arguments:**

    - ``t``: strength in [0, 1] (clipped), any shape.
    - ``cmap``: the colour map.
    - ``body``: the body's RGB.

    **Returns:**

    Colours of shape ``t.shape + (3,)``.
    """
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    return (1.0 - t)[..., None] * np.asarray(body, dtype=np.float64) + t[..., None] * colormap(t, cmap)


def render_component(
    vertices,
    faces,
    strength,
    camera: Camera,
    width: int,
    height: int,
    *,
    vmax: float | None = None,
    cmap: str = "viridis",
    body=GREY,
    background=_WHITE,
) -> np.ndarray:
    """One component mesh with its deformed region coloured.

    **Arguments:**

    - ``vertices``, ``faces``: the component mesh.
    - ``strength``: ``(V,)`` non-negative per-vertex strength, mapped to t = strength / ``vmax`` and interpolated per
        pixel.
    - ``camera``, ``width``, ``height``: the view and the image size.
    - ``vmax``: the strength of full colour (default None: its maximum; an all-zero strength leaves the body grey).
    - ``cmap``, ``body``, ``background``: the colour map and the body's and background's colours.

    **Returns:**

    An ``(height, width, 3)`` uint8 image.
    """
    s = np.asarray(strength, dtype=np.float64)
    top = float(s.max()) if vmax is None else float(vmax)
    t = s / top if top > 0 else np.zeros_like(s)
    hits = cast_rays(vertices, faces, camera, width, height)
    f = np.asarray(faces, dtype=np.int64)
    hit = hits.hit
    tri = hits.triangle[hit]
    t_pix = np.einsum("nk,nk->n", hits.barycentric[hit], t[f[tri]])
    shade = (
        render(
            vertices,
            faces,
            camera=camera,
            width=width,
            height=height,
            base_color=_WHITE,
            background=_WHITE,
            shading=True,
        ).astype(np.float64)[hit]
        / 255.0
    )
    image = np.empty((height, width, 3))
    image[...] = np.asarray(background, dtype=np.float64)
    image[hit] = shade * blend(t_pix, cmap, body)
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


# -------------------------------------------------------------------------------------------- the grid


def _check_meshes(meshes, faces, strength) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x = np.asarray(meshes, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3 or x.shape[0] == 0 or x.shape[1] == 0:
        raise MeshFormatError(f"component meshes must be a non-empty (K, V, 3) array, got shape {x.shape}.")
    if not np.all(np.isfinite(x)):
        bad = np.argwhere(~np.isfinite(x))[0]
        raise DegenerateMeshError(
            f"component mesh {int(bad[0])} has a NaN or infinite coordinate (vertex {int(bad[1])})."
        )
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0 or not np.issubdtype(f.dtype, np.integer):
        raise MeshFormatError(f"faces must be a non-empty integer (F, 3) array, got {f.dtype} {f.shape}.")
    if f.min() < 0 or f.max() >= x.shape[1]:
        raise ConnectivityError(f"faces index vertex {int(f.max())} but the meshes have {x.shape[1]} vertices.")
    s = np.asarray(strength, dtype=np.float64)
    if s.shape != x.shape[:2]:
        raise ValueError(f"strength must have shape {x.shape[:2]} (one value per component and vertex), got {s.shape}.")
    if not np.all(np.isfinite(s)):
        bad = np.argwhere(~np.isfinite(s))[0]
        raise DegenerateMeshError(f"strength of component {int(bad[0])} is NaN or infinite at vertex {int(bad[1])}.")
    if s.min() < 0:
        raise ValueError("per-vertex strengths are norms and must be non-negative.")
    return x, f.astype(np.int64), s


def _labels(values, k: int, name: str, default) -> list[str]:
    if values is None:
        return [default(i) for i in range(k)]
    out = [str(v) for v in values]
    if len(out) != k:
        raise ValueError(f"{name} must give one entry per component ({k}), got {len(out)}.")
    return out


def _layout_rows(groups: list[str], rows: Sequence[str] | None, max_columns: int) -> list[tuple[str, list[int]]]:
    """(label, component indices) per drawn line: rows in order, each wrapped at ``max_columns``."""
    order = list(dict.fromkeys(groups)) if rows is None else [str(r) for r in rows]
    missing = sorted(set(groups) - set(order))
    if missing:
        raise ValueError(f"components belong to rows not listed in rows: {', '.join(missing)}.")
    lines = []
    for name in order:
        members = [i for i, g in enumerate(groups) if g == name]
        if not members:
            lines.append((name, []))
        for start in range(0, len(members), max_columns):
            lines.append((name if start == 0 else "", members[start : start + max_columns]))
    return lines


def _draw_legend(width: int, height: int, cmap: str, body, text: str, font) -> np.ndarray:
    """A grey -> colormap ramp with a caption, ``height`` pixels high."""
    bar_w, bar_h = min(240, width // 3), max(8, height // 3)
    x0, y0 = 10, (height - bar_h) // 2
    ramp = (blend(np.linspace(0.0, 1.0, bar_w), cmap, body) * 255 + 0.5).astype(np.uint8)
    arr = np.full((height, width, 3), 255, dtype=np.uint8)
    arr[y0 : y0 + bar_h, x0 : x0 + bar_w] = ramp[None]
    strip = Image.fromarray(arr)
    draw = ImageDraw.Draw(strip)
    draw.rectangle([x0 - 1, y0 - 1, x0 + bar_w, y0 + bar_h], outline=_INK)
    draw.text((x0 + bar_w + 10, height // 2), text, font=font, fill=_INK, anchor="lm")
    return np.asarray(strip)


def _framed_points(x: np.ndarray, spread: float = 1.5) -> np.ndarray:
    """The vertices the shared camera frames: every mesh whose bounding-box diagonal is at most ``spread`` times
    the median one (a single wildly deformed component would otherwise shrink every other panel to a dot; it
    is drawn anyway, cropped by its panel)."""
    diag = np.linalg.norm(x.max(axis=1) - x.min(axis=1), axis=-1)
    keep = diag <= spread * np.median(diag)
    return x[keep].reshape(-1, 3)


def _panel_cameras(x: np.ndarray, faces: np.ndarray, view, up_axis, camera, frame: str) -> list[Camera]:
    """One camera per mesh of ``x`` (K, V, 3) for :func:`components_figure` (its arguments of the same names)."""
    if frame not in ("each", "shared"):
        raise ValueError(f"frame must be 'each' or 'shared', got {frame!r}.")
    if camera is not None:
        return [camera] * x.shape[0]
    if up_axis is None:
        up_axis = guess_up_axis(x[0], faces)
    if up_axis not in ("y", "z"):
        raise ValueError(f"up_axis must be 'y', 'z' or None, got {up_axis!r}.")
    az, el = view_angles(view)
    extent = np.ptp(x[0], axis=0)
    depth = 2 if up_axis == "y" else 1  # the horizontal axis that azimuth 0 looks along (x is the other one)
    if extent[depth] > extent[0]:
        az += 90.0  # the broad side faces the other axis
    if frame == "shared":
        return [auto_camera(_framed_points(x), azimuth_deg=az, elevation_deg=el, up_axis=up_axis)] * x.shape[0]
    return [auto_camera(m, azimuth_deg=az, elevation_deg=el, up_axis=up_axis, fit="box") for m in x]


def _check_grid_options(panel, max_columns, vmax) -> tuple[int, int]:
    """``(panel, max_columns)`` of :func:`components_figure` as ints, after checking them and ``vmax``.

    Guarantees ``panel`` >= 16 and ``max_columns`` >= 1; raises ValueError, in this order, for a small panel,
    a non-positive ``max_columns`` or a ``vmax`` that is neither None nor a positive finite number.
    """
    panel, max_columns = int(panel), int(max_columns)
    if panel < 16:
        raise ValueError(f"panel must be at least 16 pixels, got {panel}.")
    if max_columns < 1:
        raise ValueError(f"max_columns must be a positive integer, got {max_columns}.")
    if vmax is not None and not (np.isfinite(vmax) and vmax > 0):
        raise ValueError(f"vmax must be a positive finite number or None, got {vmax}.")
    return panel, max_columns


class _Grid(NamedTuple):
    """Pixel geometry and fonts of a :func:`components_figure` canvas (:func:`_grid_geometry`)."""

    font: object  # captions, legend and "no component kept"
    big: object  # row names and the title
    caption_h: int  # caption band above each panel line
    label_w: int  # row-name column at the left
    gap: int  # between panels and between lines
    width: int
    title_h: int  # 0 without a title
    legend_h: int  # legend strip at the bottom
    line_h: int  # one drawn line: caption band + panel + gap
    height: int


def _grid_geometry(lines: list[tuple[str, list[int]]], panel: int, title: str | None) -> _Grid:
    """The canvas geometry for ``lines`` (from :func:`_layout_rows`) of square ``panel``-pixel panels.

    Font sizes scale with ``panel``; the width fits the longest line (at least one column) after the widest
    row name, the height the title band (when ``title``), every line and the legend strip.
    """
    font = _font(max(10, panel // 18))
    big = _font(max(12, panel // 12))
    caption_h = _text_size(font, "Ag#0.9")[1] + 8
    label_w = max([_text_size(big, name)[0] for name, _ in lines] + [0]) + 24
    columns = max([len(m) for _, m in lines] + [1])
    gap = 4
    width = label_w + columns * (panel + gap)
    title_h = _text_size(big, title)[1] + 16 if title else 0
    legend_h = max(28, panel // 8)
    line_h = panel + caption_h + gap
    height = title_h + len(lines) * line_h + legend_h
    return _Grid(font, big, caption_h, label_w, gap, width, title_h, legend_h, line_h, height)


def _draw_grid_text(
    canvas: np.ndarray, g: _Grid, lines, titles: list[str], title: str | None, panel: int
) -> np.ndarray:
    """``canvas`` (left unchanged) with the title, row names, panel captions and line separators drawn.

    Rows without members get "no component kept". Returns a new ``(g.height, g.width, 3)`` uint8 array.
    """
    pil = Image.fromarray(canvas)
    draw = ImageDraw.Draw(pil)
    if title:
        draw.text((g.width // 2, 8), title, font=g.big, fill=_INK, anchor="mt")
    for r, (name, members) in enumerate(lines):
        top = g.title_h + r * g.line_h
        if name:
            draw.text((12, top + g.caption_h + panel // 2), name, font=g.big, fill=_INK, anchor="lm")
        if not members:
            draw.text(
                (g.label_w + 8, top + g.caption_h + panel // 2),
                "no component kept",
                font=g.font,
                fill=_MUTED,
                anchor="lm",
            )
        for c, i in enumerate(members):
            xo = g.label_w + c * (panel + g.gap)
            draw.text((xo + panel // 2, top + g.caption_h - 4), titles[i], font=g.font, fill=_INK, anchor="mb")
        if r:
            draw.line([(8, top - g.gap // 2), (g.width - 8, top - g.gap // 2)], fill=(225, 225, 225))
    return np.asarray(pil)


def components_figure(
    meshes,
    faces,
    strength,
    path,
    *,
    groups: Sequence[str] | None = None,
    titles: Sequence[str] | None = None,
    rows: Sequence[str] | None = None,
    panel: int = 256,
    max_columns: int = 10,
    view="three_quarter",
    up_axis: str | None = None,
    camera: Camera | None = None,
    frame: str = "each",
    cmap: str = "viridis",
    vmax: float | None = None,
    title: str | None = None,
) -> np.ndarray:
    """A grid of component meshes coloured by per-vertex strength, written to ``path``.

    Every panel looks from one direction: ``view`` turned about ``up_axis`` so that azimuth 0 faces the first
    mesh's broad side (it looks along the shorter of the two horizontal extents), unless ``camera`` is given.
    ``frame="each"`` brings each panel's camera as close as lets its mesh fill the panel; ``"shared"`` uses one
    camera for all, framing the meshes of typical size (:func:`_framed_points`), so that sizes compare.

    **Arguments:**

    - ``meshes``: ``(K, V, 3)``; ``faces``: ``(F, 3)``; ``strength``: ``(K, V)``; ``path``: the PNG to write.
    - ``groups``: ``(K,)`` names each component's row (default: one row, "components").
    - ``rows``: orders the rows and may list rows without components (drawn with "no component kept", e.g. a
        fully pruned AEk).
    - ``titles``: ``(K,)`` caption the panels (default "#i"). ``title``: the figure's title.
    - ``panel``: the side of one square panel in pixels; ``max_columns``: panels per row before it wraps.
    - ``view``: a name of :data:`~jaxdeform.mesh.render.VIEWS` or ``(azimuth, elevation)`` in degrees.
    - ``up_axis``: "y" or "z"; None guesses it from the first mesh (:func:`~jaxdeform.mesh.render.guess_up_axis`).
    - ``camera``: one camera for every panel (``view``, ``up_axis`` and ``frame`` are then unused).
    - ``frame``: "each" or "shared", as above. ``cmap``: the colour map.
    - ``vmax``: None scales each panel to its own maximum strength, a number shares one scale.

    **Returns:**

    The image.
    """
    x, f, s = _check_meshes(meshes, faces, strength)
    k = x.shape[0]
    groups = _labels(groups, k, "groups", lambda i: "components")
    titles = _labels(titles, k, "titles", lambda i: f"#{i}")
    panel, max_columns = _check_grid_options(panel, max_columns, vmax)
    _check_cmap(cmap)
    lines = _layout_rows(groups, rows, max_columns)
    cameras = _panel_cameras(x, f, view, up_axis, camera, frame)

    g = _grid_geometry(lines, panel, title)
    canvas = np.full((g.height, g.width, 3), 255, dtype=np.uint8)
    for r, (_, members) in enumerate(lines):
        y = g.title_h + r * g.line_h + g.caption_h
        for c, i in enumerate(members):
            xo = g.label_w + c * (panel + g.gap)
            canvas[y : y + panel, xo : xo + panel] = render_component(
                x[i], f, s[i], cameras[i], panel, panel, vmax=vmax, cmap=cmap
            )
    scale_text = (
        "per-vertex strength ||X_diff,i||, each panel scaled to its maximum"
        if vmax is None
        else f"per-vertex strength ||X_diff,i|| from 0 to {vmax:.3g}"
    )
    canvas[g.height - g.legend_h :] = _draw_legend(g.width, g.legend_h, cmap, GREY, scale_text, g.font)
    image = _draw_grid_text(canvas, g, lines, titles, title, panel)
    save_png(image, path)
    return image


def component_set_figure(
    cs: ComponentSet, meshes, faces, path, *, removal: Removal | None = None, **kwargs
) -> np.ndarray:
    """:func:`components_figure` of a :class:`~jaxdeform.components.extract.ComponentSet` and its meshes.

    Rows per block (``AE0``, ``AE1`` ...), panels titled with the component index and its strength I (eq. (7)).

    **Arguments:**

    - ``cs``: the components.
    - ``meshes``: their meshes ``(K, V, 3)`` (from :func:`~jaxdeform.components.extract.component_meshes`).
    - ``faces``: triangles ``(F, 3)``.
    - ``path``: the PNG to write.
    - ``removal``: with it only the kept components are drawn and fully pruned blocks keep an empty row.
    - ``kwargs``: passed to :func:`components_figure`.

    **Returns:**

    The image.
    """
    x = np.asarray(meshes)
    if x.ndim != 3 or x.shape[0] != len(cs):
        raise ValueError(f"meshes must be ({len(cs)}, V, 3) (one per component), got shape {x.shape}.")
    total = np.asarray(deformation_strength(cs.values)) if removal is None else removal.strength
    keep = np.ones(len(cs), dtype=bool) if removal is None else np.asarray(removal.keep)
    if keep.shape != (len(cs),):
        raise ValueError(f"the removal describes {keep.shape[0]} components but the set has {len(cs)}.")
    groups = cs.groups()
    rows = list(dict.fromkeys(groups))
    titles = [f"#{int(i)}  I={t:.3g}" for i, t in zip(cs.index, total)]
    if not keep.any():
        raise ValueError("every component was removed, so there is nothing to draw.")
    idx = np.flatnonzero(keep)
    return components_figure(
        x[idx],
        faces,
        np.asarray(vertex_strength(cs.values))[idx],
        path,
        groups=[groups[i] for i in idx],
        titles=[titles[i] for i in idx],
        rows=rows,
        **kwargs,
    )


# ----------------------------------------------------------------------------------- similarity heat map


def _rotated_text(text: str, font, ink) -> Image.Image:
    w, h = _text_size(font, text)
    img = Image.new("RGBA", (w + 4, h + 6), (255, 255, 255, 0))
    ImageDraw.Draw(img).text((2, 1), text, font=font, fill=ink + (255,))
    return img.rotate(90, expand=True)


def _check_similarity(matrix) -> np.ndarray:
    """The similarity ``matrix`` as float64, checked to be a non-empty square of finite values in [-1, 1].

    Raises ValueError for a wrong shape or a value beyond 1 + 1e-6 in magnitude, DegenerateMeshError (naming
    the first bad entry) for a NaN or infinite one.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.ndim != 2 or m.shape[0] != m.shape[1] or m.shape[0] == 0:
        raise ValueError(f"the similarity matrix must be a non-empty square array, got shape {m.shape}.")
    if not np.all(np.isfinite(m)):
        bad = np.argwhere(~np.isfinite(m))[0]
        raise DegenerateMeshError(f"similarity entry ({int(bad[0])}, {int(bad[1])}) is NaN or infinite.")
    if np.abs(m).max() > 1.0 + 1e-6:
        raise ValueError(f"cosine similarities lie in [-1, 1], got a value of {np.abs(m).max():.6g}.")
    return m


def _heat_options(m: np.ndarray, vmin, cmap, cell, annotate) -> tuple[float, str, int, bool]:
    """:func:`similarity_figure`'s defaults resolved for the checked K x K ``m``: ``(lo, cmap, cell, annotate)``.

    ``lo`` = ``vmin`` or 0 / -1 (any negative entry), finite and below 1; ``cmap`` viridis / coolwarm by the sign
    of ``lo`` unless given, and known; ``cell`` in pixels (default ``720 // K`` clamped to 8..48), at least 2;
    ``annotate`` default K <= 16. Raises ValueError, in that order, for a bad ``vmin``, ``cmap`` or ``cell``.
    """
    k = m.shape[0]
    lo = (0.0 if m.min() >= 0 else -1.0) if vmin is None else float(vmin)
    if not (np.isfinite(lo) and lo < 1.0):
        raise ValueError(f"vmin must be a finite number below 1, got {vmin}.")
    cmap = ("viridis" if lo >= 0 else "coolwarm") if cmap is None else cmap
    _check_cmap(cmap)
    cell = max(8, min(48, 720 // k)) if cell is None else int(cell)
    if cell < 2:
        raise ValueError(f"cell must be at least 2 pixels, got {cell}.")
    annotate = k <= 16 if annotate is None else bool(annotate)
    return lo, cmap, cell, annotate


class _Heat(NamedTuple):
    """Pixel geometry and fonts of a :func:`similarity_figure` canvas (:func:`_heat_geometry`)."""

    font: object  # labels and cell values
    tick_font: object
    big: object  # title
    x0: int  # left edge of the K x K cells
    y0: int  # top edge of the cells
    side: int  # K * cell
    bx: int  # left edge of the colour bar
    bar_w: int
    width: int
    height: int


def _heat_geometry(labels: list[str], k: int, cell: int, lo: float, title: str | None) -> _Heat:
    """The canvas geometry for K x K cells of ``cell`` pixels: labels at the left and (rotated) above, the title
    band (when ``title``), and the colour bar with ticks ``lo``, the middle and 1 at the right."""
    font = _font(max(8, min(14, cell - 2)))
    tick_font = _font(12)
    big = _font(16)
    label_w = max(_text_size(font, t)[0] for t in labels) + 10
    label_h = label_w
    title_h = _text_size(big, title)[1] + 16 if title else 6
    pad = 12
    bar_w = 16
    tick_w = max(_text_size(tick_font, f"{v:.2g}")[0] for v in (lo, 1.0, 0.5 * (lo + 1.0))) + 8
    x0, y0 = pad + label_w, title_h + label_h
    side = k * cell
    width = x0 + side + pad + bar_w + 6 + tick_w + pad
    height = y0 + side + pad
    return _Heat(font, tick_font, big, x0, y0, side, x0 + side + pad, bar_w, width, height)


def _draw_heat_frame(draw: ImageDraw.ImageDraw, h: _Heat, lo: float) -> None:
    """Outline the cells and the colour bar and draw the bar's ticks (1, the middle, ``lo``) with ``draw``."""
    x0, y0, side, bx, bar_w = h.x0, h.y0, h.side, h.bx, h.bar_w
    draw.rectangle([x0 - 1, y0 - 1, x0 + side, y0 + side], outline=_INK)
    draw.rectangle([bx - 1, y0 - 1, bx + bar_w, y0 + side], outline=_INK)
    for v in (1.0, 0.5 * (lo + 1.0), lo):
        y = round(y0 + (1.0 - v) / (1.0 - lo) * (side - 1))
        draw.line([(bx + bar_w, y), (bx + bar_w + 4, y)], fill=_INK)
        draw.text((bx + bar_w + 6, y), f"{v:.2g}", font=h.tick_font, fill=_INK, anchor="lm")


def _annotate_cells(draw: ImageDraw.ImageDraw, h: _Heat, m: np.ndarray, lo: float, cmap: str, cell: int) -> None:
    """Write each value of ``m`` (two decimals) centred in its cell, dark on light colours and light on dark."""
    k = m.shape[0]
    for i in range(k):
        for j in range(k):
            t = (m[i, j] - lo) / (1.0 - lo)
            luminance = float(np.dot(colormap(t, cmap), [0.299, 0.587, 0.114]))
            draw.text(
                (h.x0 + j * cell + cell // 2, h.y0 + i * cell + cell // 2),
                f"{m[i, j]:.2f}",
                font=h.font,
                fill=(20, 20, 20) if luminance > 0.5 else (240, 240, 240),
                anchor="mm",
            )


def similarity_figure(
    matrix,
    path,
    *,
    labels: Sequence[str] | None = None,
    title: str | None = "cosine similarity",
    cell: int | None = None,
    annotate: bool | None = None,
    cmap: str | None = None,
    vmin: float | None = None,
) -> np.ndarray:
    """A heat map of a K x K similarity matrix with a colour bar, written to ``path`` (Fig. 3).

    **Arguments:**

    - ``matrix``: ``(K, K)``.
    - ``path``: the PNG to write.
    - ``labels``: ``(K,)`` name rows and columns (default 0 ... K-1).
    - ``title``: the figure's title.
    - ``cell``: the side of one cell in pixels, at least 2 (default None: ``720 // K`` clamped to 8..48).
    - ``annotate``: write each value in its cell (default: K <= 16).
    - ``cmap``: defaults to viridis on [0, 1] and the diverging coolwarm on [-1, 1].
    - ``vmin``: the colour range is [``vmin``, 1], ``vmin`` by default 0 when every entry is non-negative (as in
        Fig. 3) and -1 otherwise.

    **Returns:**

    The image.

    **Raises:**

    ``ValueError`` for a bad ``vmin``, ``cmap`` or ``cell``.
    """
    m = _check_similarity(matrix)
    k = m.shape[0]
    labels = _labels(labels, k, "labels", str)
    lo, cmap, cell, annotate = _heat_options(m, vmin, cmap, cell, annotate)
    h = _heat_geometry(labels, k, cell, lo, title)

    canvas = np.full((h.height, h.width, 3), 255, dtype=np.uint8)
    rgb = (colormap((m - lo) / (1.0 - lo), cmap) * 255 + 0.5).astype(np.uint8)
    canvas[h.y0 : h.y0 + h.side, h.x0 : h.x0 + h.side] = np.repeat(np.repeat(rgb, cell, axis=0), cell, axis=1)
    rows = np.arange(h.side)
    ramp = (colormap(1.0 - rows / max(h.side - 1, 1), cmap) * 255 + 0.5).astype(np.uint8)
    canvas[h.y0 : h.y0 + h.side, h.bx : h.bx + h.bar_w] = ramp[:, None]

    pil = Image.fromarray(canvas)
    draw = ImageDraw.Draw(pil)
    if title:
        draw.text((h.x0 + h.side // 2, 8), title, font=h.big, fill=_INK, anchor="mt")
    for i, text in enumerate(labels):
        draw.text((h.x0 - 6, h.y0 + i * cell + cell // 2), text, font=h.font, fill=_INK, anchor="rm")
        rot = _rotated_text(text, h.font, _INK)
        pil.paste(rot, (h.x0 + i * cell + (cell - rot.width) // 2, h.y0 - 4 - rot.height), rot)
    draw = ImageDraw.Draw(pil)
    _draw_heat_frame(draw, h, lo)
    if annotate:
        _annotate_cells(draw, h, m, lo, cmap, cell)
    image = np.asarray(pil)
    save_png(image, path)
    return image


__all__ = [
    "VIEWS",
    "GREY",
    "blend",
    "render_component",
    "components_figure",
    "component_set_figure",
    "similarity_figure",
]
