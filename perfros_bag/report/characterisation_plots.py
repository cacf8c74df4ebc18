"""A PNG of the characterisation: per configurable node, CPU and message frequency against
the parameter value (the measured Table I), with the p95 CPU as an error bar."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

from perfros_bag.characterisation.csvfile import Row
from perfros_bag.characterisation.settings import by_setting, mean
from perfros_bag.report.figures import save_png, subplots


def plot_characterisation(rows: Sequence[Row], path: str | Path) -> int:
    """Write the plot atomically; returns the number of node panels (0: nothing to plot,
    then no file is written). A panel per node that has at least two numeric settings."""
    # node -> value -> (cpu, p95, frequency) means over its recordings
    data: dict[str, dict[float, tuple[float | None, float | None, float | None]]] = defaultdict(dict)
    params: dict[str, str] = {}
    for setting in by_setting(rows):
        if isinstance(setting.value, bool) or not isinstance(setting.value, int | float):
            continue
        params[setting.node] = setting.parameter or "value"
        p95s = [m.cpu_p95 if m.cpu_p95 is not None else m.cpu for m in setting.recordings if m.cpu is not None]
        data[setting.node][float(setting.value)] = (mean(setting.cpus()), mean([p for p in p95s if p is not None]),
                                                    mean(setting.frequencies()))
    nodes = [n for n, by_value in data.items() if len(by_value) >= 2]
    if not nodes:
        return 0
    cols = min(2, len(nodes))
    nrows = (len(nodes) + cols - 1) // cols
    with subplots(nrows, cols, figsize=(5.5 * cols, 3.6 * nrows), squeeze=False) as (fig, axes):
        for ax, node in zip(axes.flat, nodes, strict=False):
            values = sorted(data[node])
            cpu_m = [data[node][v][0] for v in values]
            p95_m = [data[node][v][1] for v in values]
            freq_m = [data[node][v][2] for v in values]
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
        save_png(fig, path)
    return len(nodes)

