"""Benchmark: model selection in perfros_bag.fitting.regression.fit_curve.

Leave-one-out needs one refit per point per form. The library refits the folds with numpy
(``_lstsq_form``) and keeps scikit-learn's LinearRegression for the reported fit; the
baseline, measured in the same run, refits every fold with scikit-learn too (what a
straightforward implementation does). Same choices, same coefficients; the ratio is the
speed-up. Also times ``perfros-bag fit``'s library call on a synthetic system with many
configurable nodes.

    .venv/bin/python tests/bench/bench_fit.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml
from _timing import median

from perfros_bag.fitting import regression
from perfros_bag.fitting.build import build_model


def _sklearn_folds(form: str, x: np.ndarray, y: np.ndarray) -> tuple[float, ...]:
    return regression.fit_form(form, x, y)


def bench_fit_curve(repeat: int) -> None:
    rng = np.random.default_rng(0)
    print(f"{'points':>6} {'library s':>10} {'sklearn-folds s':>16} {'speed-up':>9}  same choice")
    fast = regression._lstsq_form
    for n in (4, 8, 20, 50):
        x = np.linspace(10, 200, n)
        y = 66.62 * np.log(x / 100) + 56.3 + rng.normal(0, 1.0, n)

        def run(x: np.ndarray = x, y: np.ndarray = y) -> regression.FittedRelation:
            return regression.fit_curve(x.tolist(), y.tolist(), scale=100, monotone="nondecreasing")

        lib = median(run, repeat)
        a = run()
        regression._lstsq_form = _sklearn_folds  # type: ignore[assignment]
        try:
            base = median(run, repeat)
            b = run()
        finally:
            regression._lstsq_form = fast  # type: ignore[assignment]
        same = a.form == b.form and np.allclose(a.coef, b.coef)
        print(f"{n:>6} {lib:>10.4f} {base:>16.4f} {base / lib:>8.1f}x  {same}")


def bench_build_model(nodes: int, repeat: int) -> None:
    rng = np.random.default_rng(1)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        sys_nodes = []
        rows = []
        for i in range(nodes):
            name = f"n{i}"
            values = [10, 20, 30, 40, 50]
            sys_nodes.append({"name": name, "weight": 1.0 / nodes, "parameter": {"name": "p"},
                              "topics": [f"/{name}"],
                              "settings": [{"value": v, "cpu": v, "performance": 20 * k + 20}
                                           for k, v in enumerate(values)]})
            for v in values:
                for r in range(3):
                    rows.append({"recording": f"{name}_{v}_{r}", "node": name, "value": v, "topic": f"/{name}",
                                 "frequency_hz": v / 2 * (1 + rng.normal(0, 0.01)),
                                 "bandwidth_kBps": v / 20 * (1 + rng.normal(0, 0.01)),
                                 "cpu_units_mean": v * (1 + rng.normal(0, 0.02))})
        (d / "system.yaml").write_text(yaml.safe_dump({"computers": [{"name": "s", "kind": "server",
                                                                      "capacity": 10000}],
                                                        "nodes": sys_nodes}))
        with (d / "c.csv").open("w", newline="") as h:
            w = csv.DictWriter(h, fieldnames=["recording", "node", "value", "topic", "frequency_hz",
                                              "bandwidth_kBps", "cpu_units_mean"])
            w.writeheader()
            w.writerows(rows)
        secs = median(lambda: build_model(d / "system.yaml", d / "c.csv"), repeat)
        print(f"build_model: {nodes} configurable nodes x 5 relations, 5 values x 3 recordings: "
              f"{secs:.3f} s ({secs / nodes * 1000:.1f} ms per node)")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    import warnings

    warnings.simplefilter("ignore")
    regression.fit_curve([1, 2, 3], [1, 2, 3.5])  # import scikit-learn outside the timings
    bench_fit_curve(args.repeat)
    for n in (4, 40):
        bench_build_model(n, max(1, args.repeat // 2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
