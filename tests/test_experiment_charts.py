"""The experiments' line charts (matplotlib, Agg) write a PNG of the size asked, with something drawn on it."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image


def _check_png(path, size) -> None:
    img = Image.open(path)
    assert img.format == "PNG" and img.size == size
    rgb = np.asarray(img.convert("RGB")).astype(int)
    assert (rgb.min(axis=-1) < 200).mean() > 0.01  # axes, text, lines: not a blank page
    coloured = (rgb.max(axis=-1) - rgb.min(axis=-1)) > 80  # the lines' colours (grey and black are not)
    assert coloured.mean() > 0.001
    assert not [p for p in path.parent.iterdir() if p.name.startswith(".")]  # the atomic write's temporary is gone


def test_fig6_chart(tmp_path):
    from experiments.components import editing

    rows = {
        "tube/multiscale": {"3": {"mean_error": 0.04}, "6": {"mean_error": 0.02}, "12": {"mean_error": 0.012}},
        "tube/multiscale (one stage)": {
            "3": {"mean_error": 0.05},
            "6": {"mean_error": 0.03},
            "12": {"mean_error": 0.02},
        },
        "tube/pca": {"3": {"mean_error": 0.06}, "6": {"mean_error": 0.05}, "12": {"mean_error": 0.03}},
    }
    path = editing.plot(rows, (3, 6, 12), tmp_path / "fig6" / "fig6.png", size=(600, 400))
    assert path == tmp_path / "fig6" / "fig6.png"
    _check_png(path, (600, 400))


def test_learning_curves_chart(tmp_path):
    from experiments import charts
    from experiments.components import curves

    rows = {
        label: {
            "levels": levels,
            "paper_max_relative_squared_error": curves.PAPER[levels],
            "curve": [{"epoch": e, "max_rse": 0.5 * np.exp(-e / 300) + 1e-3 * levels} for e in range(100, 1001, 100)],
        }
        for label, levels in (("two", 2), ("three", 3))
    }
    rows["two"]["curve"][0]["max_rse"] = 0.0  # not drawable on the log axis: left out, not an error
    _check_png(curves.plot(rows, tmp_path / "curves.png", size=(480, 360)), (480, 360))
    _check_png(curves.plot(rows, tmp_path / "default" / "curves.png"), charts.SIZE)  # 1200 x 750 at 150 dpi
    with pytest.raises(ValueError, match="size"):
        charts.figure((0, 100))
