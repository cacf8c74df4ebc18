"""A watch's windows as a timeline: expected and measured Σ w·P, alarms and re-plans."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from perfros_bag.report.figures import png_bytes, subplots


def plot_watch(windows: Sequence[Mapping[str, Any]], replans: Sequence[Mapping[str, Any]]) -> bytes:
    """Per window (seconds since the first window's end): expected and measured Σ w·P, a red
    mark where a new alarm was raised, a dashed line at each re-plan. PNG."""
    t0 = float(windows[0]["t"])
    xs = [float(w["t"]) - t0 for w in windows]
    with subplots(1, 1, figsize=(10, 3.6)) as (fig, ax):
        ax.plot(xs, [float(w["overall"]["expected"]) for w in windows], "--", label="expected Σ w·P")
        ax.plot(xs, [float(w["overall"]["measured"]) for w in windows], "o-", ms=3, label="measured Σ w·P")
        alarmed = [(x, float(w["overall"]["measured"])) for x, w in zip(xs, windows, strict=True)
                   if any(a.get("new") for a in w["alarms"])]
        if alarmed:
            ax.plot([x for x, _ in alarmed], [y for _, y in alarmed], "x", color="red", ms=9, mew=2, label="new alarm")
        for i, r in enumerate(replans):
            ax.axvline(float(r["t"]) - t0, color="grey", ls=":", label="re-plan" if i == 0 else None)
        ax.set_xlabel("seconds since the first window")
        ax.set_ylabel("Σ w·P")
        ax.set_title("watch: eq 10 per window", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        return png_bytes(fig)
