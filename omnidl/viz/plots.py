"""Matplotlib plots (Agg backend, files written atomically)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from omnidl.utils.io import atomic_write


def plot_curves(path: str | Path, x: Sequence[float], curves: Mapping[str, Sequence[float]], xlabel: str = "",
                ylabel: str = "", title: str = "") -> Path:
    """Line plot of ``curves[name]`` against ``x`` into ``path`` (PNG/PDF/SVG by suffix)."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    try:
        for name, ys in curves.items():
            ax.plot(list(x), list(ys), marker="o", label=name)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        if title:
            ax.set_title(title)
        ax.grid(True, alpha=0.3)
        if curves:
            ax.legend()
        fig.tight_layout()
        path = Path(path)
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format=path.suffix.lstrip(".") or "png"))
    finally:
        plt.close(fig)


def plot_curve_panels(path: str | Path, x: Sequence[float], groups: Mapping[str, Mapping[str, Sequence[float]]],
                      xlabel: str = "", title: str = "") -> Path:
    """One panel per unit: ``groups[unit][name]`` are the curves of that unit (e.g. ``{"metres": {"rmse": ...},
    "fraction": {"delta1": ...}}``), so metres and fractions never share an axis. Panels sit side by side and
    each legend is drawn below its axes, off the data. Written atomically (PNG/PDF/SVG by suffix)."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    groups = {u: c for u, c in groups.items() if c}
    if not groups:
        raise ValueError("plot_curve_panels: no curves to plot")
    n = len(groups)
    fig, axes = plt.subplots(1, n, figsize=(4.8 * n, 4.2), dpi=100, squeeze=False)
    try:
        for ax, (unit, curves) in zip(axes[0], groups.items()):
            for name, ys in curves.items():
                ax.plot(list(x), list(ys), marker="o", label=name)
            ax.set_xlabel(xlabel)
            ax.set_ylabel(unit)
            ax.grid(True, alpha=0.3)
            ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=min(3, len(curves)), frameon=False)
        if title:
            fig.suptitle(title)
        fig.tight_layout()
        path = Path(path)
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format=path.suffix.lstrip(".") or "png",
                                                          bbox_inches="tight"))
    finally:
        plt.close(fig)
