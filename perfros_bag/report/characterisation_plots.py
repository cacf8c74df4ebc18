"""A PNG of the characterisation: per configurable node, CPU and message frequency against
the parameter value (the measured Table I), with the p95 CPU as an error bar."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

from perfros_bag.characterisation.table import Row


def plot_characterisation(rows: Sequence[Row], path: str | Path) -> int:
    """Write the plot atomically; returns the number of node panels (0: nothing to plot,
    then no file is written). A panel per node that has at least two numeric settings."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from perfros_bag.fileio import atomic_open

    # node -> value -> (cpu means, cpu p95s, freqs) over recordings
    data: dict[str, dict[float, tuple[list[float], list[float], list[float]]]] = defaultdict(dict)
    params: dict[str, str] = {}
    seen: set[tuple[str, str, float]] = set()
    for r in rows:
        if not r.node or isinstance(r.value, bool) or not isinstance(r.value, int | float):
            continue
        params[r.node] = r.parameter or "value"
        value = float(r.value)
        cpu, p95, freq = data[r.node].setdefault(value, ([], [], []))
        key = (r.recording, r.node, value)
        if key not in seen and r.cpu_units_mean is not None:
            seen.add(key)
            cpu.append(r.cpu_units_mean)
            p95.append(r.cpu_units_p95 if r.cpu_units_p95 is not None else r.cpu_units_mean)
        if r.topic and r.frequency_hz is not None:
            freq.append(r.frequency_hz)
    nodes = [n for n, by_value in data.items() if len(by_value) >= 2]
    if not nodes:
        return 0
    cols = min(2, len(nodes))
    nrows = (len(nodes) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(5.5 * cols, 3.6 * nrows), squeeze=False)
    for ax, node in zip(axes.flat, nodes, strict=False):
        values = sorted(data[node])
        cpu_m = [_mean(data[node][v][0]) for v in values]
        p95_m = [_mean(data[node][v][1]) for v in values]
        freq_m = [_mean(data[node][v][2]) for v in values]
        xs = range(len(values))
        if any(c is not None for c in cpu_m):
            heights = [c or 0.0 for c in cpu_m]
            err = [max(0.0, (p or 0.0) - (c or 0.0)) for c, p in zip(cpu_m, p95_m, strict=True)]
            ax.bar(xs, heights, color="#4c72b0", alpha=0.8, label="CPU (mean, bar to p95)",
                   yerr=[[0.0] * len(err), err], capsize=3)
        ax.set_ylabel("CPU units")
        ax.set_xticks(list(xs), [f"{v:g}" for v in values])
        ax.set_xlabel(params[node])
        ax.set_title(node)
        if any(f is not None for f in freq_m):
            ax2 = ax.twinx()
            ax2.plot(list(xs), [f if f is not None else float("nan") for f in freq_m], "o-", color="#dd8452",
                     label="frequency")
            ax2.set_ylabel("Hz", color="#dd8452")
            ax2.set_ylim(bottom=0)
    for ax in list(axes.flat)[len(nodes):]:
        ax.axis("off")
    fig.suptitle("Characterisation: CPU and frequency per setting")
    fig.tight_layout()
    with atomic_open(path, "wb", encoding=None) as fh:
        fig.savefig(fh, format="png", dpi=100)
    plt.close(fig)
    return len(nodes)


def _mean(xs: list[float]) -> float | None:
    return sum(xs) / len(xs) if xs else None
