"""OR-Tools CP-SAT on a plan model written by bench_fleet_plan.py (its own process: ortools
and highspy cannot share one, docs/solvers.md). Reads the model JSON on stdin, writes the
answer JSON on stdout. Needs only ortools.

Model: x[n,k,c] booleans (node n at kept choice k on computer c), one per node; a
coresidence group's members on one computer; CPU per computer; objective Σ round(w·P·SCALE).
The bench only sends instances whose network can never overflow, so there are no network
rows (the plan is checked against the network afterwards all the same)."""

from __future__ import annotations

import json
import sys
import time

from ortools.sat.python import cp_model

SCALE = 1_000_000  # performance is scaled and rounded: CP-SAT needs integer coefficients
CPU_SCALE = 1_000


def main() -> int:
    model_doc = json.load(sys.stdin)
    t0 = time.perf_counter()
    m = cp_model.CpModel()
    x: dict[tuple[str, int, str], cp_model.IntVar] = {}
    load: dict[str, list[tuple[int, cp_model.IntVar]]] = {c: [] for c in model_doc["capacity"]}
    objective = []
    for g in model_doc["groups"]:
        members, allowed = g["members"], g["allowed"]
        on = {c: m.NewBoolVar("") for c in allowed} if len(members) > 1 else None
        if on is not None:
            m.AddExactlyOne(on.values())
        for n in members:
            opts = model_doc["choices"][n]  # [cpu, w*P]
            lits = []
            for c in allowed:
                here = []
                for k, (cpu, value) in enumerate(opts):
                    v = m.NewBoolVar("")
                    x[(n, k, c)] = v
                    here.append(v)
                    load[c].append((int(round(cpu * CPU_SCALE)), v))
                    objective.append((int(round(value * SCALE)), v))
                if on is not None:
                    m.Add(sum(here) == on[c])
                lits += here
            m.AddExactlyOne(lits)
    for c, terms in load.items():
        if terms:
            m.Add(sum(a * v for a, v in terms) <= int(round(model_doc["capacity"][c] * CPU_SCALE + 1e-6)))
    m.Maximize(sum(a * v for a, v in objective))
    solver = cp_model.CpSolver()
    solver.parameters.max_time_in_seconds = max(model_doc["time_limit"] - (time.perf_counter() - t0), 0.1)
    solver.parameters.num_workers = model_doc.get("workers", 2)
    status = solver.Solve(m)
    out: dict[str, object] = {"status": solver.StatusName(status), "build_s": t0, "wall_s": time.perf_counter() - t0}
    if status in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        out["placement"] = {n: c for (n, k, c), v in x.items() if solver.Value(v)}
        out["level"] = {n: k for (n, k, c), v in x.items() if solver.Value(v)}
        out["objective_scaled"] = solver.ObjectiveValue() / SCALE
        out["bound_scaled"] = solver.BestObjectiveBound() / SCALE
    json.dump(out, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
