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
