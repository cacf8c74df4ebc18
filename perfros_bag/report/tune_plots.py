"""The tuning loop's rounds (``tune``, tune.json) as a picture: predicted vs measured."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from perfros_bag.report.figures import label, png_bytes, subplots


def plot_tune(rounds: Sequence[Mapping[str, Any]]) -> bytes:
    """Per round: each node's planned CPU, measured CPU and the refitted model's CPU at the
    deployed value (left); expected and measured Σ w·P (eq 10) (right). PNG."""
    xs = [int(r["round"]) for r in rounds]
    names = sorted({n for r in rounds for n in r["nodes"]})
    with subplots(1, 2, figsize=(11, 4.0)) as (fig, (left, right)):
        for i, name in enumerate(names):
            color = f"C{i % 10}"
            pts = [(r["round"], r["nodes"][name]) for r in rounds if name in r["nodes"]]

            def line(key: str, pts: list[tuple[int, Mapping[str, Any]]] = pts) -> tuple[list[int], list[float]]:
                sel = [(x, n[key]) for x, n in pts if n.get(key) is not None]
                return [x for x, _ in sel], [float(y) for _, y in sel]

            left.plot(*line("cpu_planned"), "o--", color=color, label=f"{label(name)} planned")
            left.plot(*line("cpu_measured"), "s-", color=color, label=f"{label(name)} measured")
            left.plot(*line("model_cpu_after"), "x:", color=color, label=f"{label(name)} refit")
        left.set_xlabel("round")
        left.set_ylabel("CPU units")
        left.set_title("per node: planned vs measured CPU, and the refit", fontsize=10)
        left.set_xticks(xs)
        left.grid(alpha=0.3)
        left.legend(fontsize=7, ncol=1 if len(names) < 4 else 2)
        right.plot(xs, [float(r["expected"]) for r in rounds], "o--", label="expected Σ w·P")
        right.plot(xs, [float(r["measured"]) for r in rounds], "s-", label="measured Σ w·P")
        right.set_xlabel("round")
        right.set_xticks(xs)
        right.set_title("eq 10: expected vs measured", fontsize=10)
        right.grid(alpha=0.3)
        right.legend(fontsize=8)
        fig.tight_layout()
        return png_bytes(fig)
