"""The one matplotlib set-up of every plot: the Agg backend (no display needed), PNGs at
100 dpi, figures closed once written. matplotlib is imported only when a plot is drawn."""

from __future__ import annotations

import io
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


def png_bytes(fig: Any) -> bytes:
    """The figure as PNG bytes (trimmed to its content); the figure is closed."""
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    finally:
        pyplot().close(fig)
    return buf.getvalue()


def save_png(fig: Any, path: str | Path) -> Path:
    """Write the figure to ``path`` atomically (its folder is made); the figure is closed."""
    try:
        with atomic_open(path, "wb", encoding=None) as fh:
            fig.savefig(fh, format="png", dpi=DPI)
    finally:
        pyplot().close(fig)
    return Path(path)


def label(text: str, limit: int = 40) -> str:
    """User text for matplotlib: shortened, with ``$`` escaped (no mathtext from data)."""
    return text[:limit].replace("$", r"\$")
