"""Figures in the paper's forms: every axis names its quantity and unit (µs, ±); the title names the
run, the rig and the date; legends beside the axes, never over the data; each saved as PNG and SVG."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from usmswitch.client.plots import MICRO, legend_beside, legends_over_data

__all__ = ["MICRO", "legend_beside"]  # the experiments' figures take them from here

DIRECTION_NAMES = ("on", "off")
DIRECTION_COLOURS = ("tab:blue", "tab:orange")


def new_figure(rows: int = 1, cols: int = 1, *, width: float = 7.5, height: float = 4.2) -> tuple[Any, Any]:
    """A figure and its axes (matplotlib without a display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        rows, cols, figsize=(width, height * rows), squeeze=False, constrained_layout=True
    )
    return fig, axes


def save(fig: Any, figures_dir: Path, name: str, stamp: str = "") -> list[str]:
    """`name`.png and `name`.svg in `figures_dir`, titled `stamp` (the run, the rig, the date:
    Context.save gives it); returns their paths relative to the run's folder."""
    import matplotlib.pyplot as plt

    figures_dir.mkdir(parents=True, exist_ok=True)
    if stamp:
        fig.suptitle(stamp, fontsize=9)
    clipped = clipped_text(fig)
    if clipped:  # a title or label cut at the figure's edge reads wrong: a bug of the figure's layout
        plt.close(fig)
        raise ValueError(f"figure {name}: text outside the figure: {clipped}")
    covering = legends_over_data(fig)
    if covering:  # as much a bug of the layout: the reader loses the points under it
        plt.close(fig)
        raise ValueError(f"figure {name}: a legend over the data: {covering}")
    out = []
    for suffix in ("png", "svg"):
        path = figures_dir / f"{name}.{suffix}"
        fig.savefig(path, dpi=130)
        out.append(f"{figures_dir.name}/{path.name}")
    plt.close(fig)
    return out


def clipped_text(fig: Any) -> list[str]:
    """The titles and axis labels that do not lie wholly inside the figure (laid out as saved)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    box = fig.bbox
    texts = [fig._suptitle] if fig._suptitle is not None else []  # matplotlib has no public getter of it
    for ax in fig.axes:
        texts += [ax.title, ax.xaxis.label, ax.yaxis.label]
    out = []
    for text in texts:
        if not text.get_text():
            continue
        ext = text.get_window_extent(renderer)
        if ext.x0 < box.x0 - 0.5 or ext.x1 > box.x1 + 0.5 or ext.y0 < box.y0 - 0.5 or ext.y1 > box.y1 + 0.5:
            out.append(text.get_text())
    return out


def thin(x: np.ndarray, y: np.ndarray, most: int = 5000) -> tuple[np.ndarray, np.ndarray]:
    """At most `most` points, evenly taken: a 100,000-stroke series plots as its shape."""
    if len(x) <= most:
        return x, y
    idx = np.linspace(0, len(x) - 1, most).astype(np.int64)
    return x[idx], y[idx]


def histogram_with_normal(ax: Any, values_us: np.ndarray, label: str, colour: str) -> None:
    """A density histogram of `values_us` with the normal curve of the same mean and std (Fig. 14)."""
    v = values_us[~np.isnan(values_us)]
    if len(v) < 2:
        return
    mu, sd = float(np.mean(v)), float(np.std(v, ddof=1))
    ax.hist(
        v,
        bins=40,
        density=True,
        alpha=0.45,
        color=colour,
        label=f"{label}: mean {mu:.1f} {MICRO}, std {sd:.1f} {MICRO}",
    )
    xs = np.linspace(v.min(), v.max(), 200)
    if sd > 0:
        ax.plot(xs, np.exp(-0.5 * ((xs - mu) / sd) ** 2) / (sd * np.sqrt(2 * np.pi)), color=colour, lw=1.5)
