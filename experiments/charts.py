"""Line charts of the experiments, drawn with matplotlib's Agg renderer and written as PNG.

A :class:`matplotlib.figure.Figure` on its own Agg canvas: no pyplot, so importing this module selects no
backend and leaves matplotlib's global state alone. :func:`figure` makes one of ``size`` pixels at
:data:`DPI`; :func:`save` writes it atomically (a PNG of exactly that size). Mesh pictures are not charts: they
stay with the project's ray-caster (:mod:`jaxdeform.mesh.render`).
"""

from __future__ import annotations

import textwrap
from pathlib import Path

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from jaxdeform.mesh.io import atomic_path

DPI = 150
SIZE = (1200, 750)  # pixels: 8 x 5 inches at DPI


def figure(size: tuple[int, int] = SIZE) -> tuple[Figure, Axes]:
    """(figure, axes) of ``size`` (width, height) pixels at :data:`DPI`, laid out so that titles, tick labels and
    a legend outside the axes (``fig.legend(loc="outside right upper")``) fit."""
    width, height = size
    if width < 1 or height < 1:
        raise ValueError(f"size must be positive pixels, got {size}.")
    fig = Figure(figsize=(width / DPI, height / DPI), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.grid(True, which="major", color="0.9", linewidth=0.8)
    ax.set_axisbelow(True)
    return fig, ax


def title(ax: Axes, text: str) -> None:
    """``text`` over the axes, wrapped to about their width (three fifths of the figure's: the legend's column
    takes the rest)."""
    chars = max(20, int(0.6 * ax.figure.get_figwidth() * DPI / 13))  # about 13 pixels a character (12 pt, 150 dpi)
    ax.set_title(textwrap.fill(text, chars))


def thousands(ax_axis) -> None:
    """Tick labels of ``ax_axis`` (``ax.xaxis`` or ``ax.yaxis``) as integers with thousands separators."""
    ax_axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:,.0f}"))


def save(fig: Figure, path: Path) -> Path:
    """Write ``fig`` as a PNG at ``path`` (atomically; the folder is made): exactly the figure's pixel size."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return path
