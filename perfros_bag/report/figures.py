"""The one matplotlib set-up of every plot: the Agg backend (no display needed), PNGs at
100 dpi, every figure closed when its ``with subplots(...)`` block ends (also on an error).
matplotlib is imported only when a plot is drawn."""

from __future__ import annotations

import io
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from perfros_bag.fileio import atomic_open

DPI = 100


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


@contextmanager
def subplots(*args: Any, **kwargs: Any) -> Iterator[tuple[Any, Any]]:
    """``pyplot.subplots(...)`` as ``(figure, axes)``; the figure is closed at the end."""
    plt = pyplot()
    fig, axes = plt.subplots(*args, **kwargs)
    try:
        yield fig, axes
    finally:
        plt.close(fig)


def png_bytes(fig: Any) -> bytes:
    """The figure as PNG bytes (trimmed to its content)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    return buf.getvalue()


def save_png(fig: Any, path: str | Path) -> Path:
    """Write the figure to ``path`` atomically (its folder is made)."""
    with atomic_open(path, "wb", encoding=None) as fh:
        fig.savefig(fh, format="png", dpi=DPI)
    return Path(path)


def label(text: str, limit: int = 40) -> str:
    """User text for matplotlib: shortened, with ``$`` escaped (no mathtext from data)."""
    return text[:limit].replace("$", r"\$")
