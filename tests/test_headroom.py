"""``solve --headroom H``: every computer keeps H of its capacity free. Checked against the
same instance written with its capacities cut by hand, and by the independent checker."""

from __future__ import annotations

import copy
import subprocess
import sys
from typing import Any

import pytest
import yaml

from perfros_bag.errors import InputError
from perfros_bag.solver import solve
from perfros_bag.solver.check import check_plan
from perfros_bag.system.planfile import load_plan
from perfros_bag.system.systemfile import parse_system
from tests.test_flow import EXAMPLE

pytestmark = pytest.mark.filterwarnings("ignore:.*weights sum to")


def cut(data: dict[str, Any], keep: float) -> dict[str, Any]:
    out = copy.deepcopy(data)
    for c in out["computers"]:
        for key in ("capacity", "max_capacity"):
            if key in c:
                c[key] = c[key] * keep
    return out


@pytest.mark.parametrize("method", ["exact", "greedy+", "bruteforce"])
@pytest.mark.parametrize("headroom", [0.1, 0.35])
def test_problem_1_equals_the_instance_with_capacities_cut_by_hand(method: str, headroom: float) -> None:
    system = parse_system(copy.deepcopy(EXAMPLE), "flow.yaml")
    plan = solve(system, 1, method, headroom=headroom)
    by_hand = solve(parse_system(cut(EXAMPLE, 1 - headroom), "cut.yaml"), 1, method)
    assert plan.status == by_hand.status
    assert plan.objective == pytest.approx(by_hand.objective)
    assert check_plan(system, plan) == []
    for c in EXAMPLE["computers"]:
        pc = plan.computers[c["name"]]
        assert pc.capacity == c["capacity"]
        assert pc.margin == pytest.approx(headroom * c["capacity"])
        assert pc.cpu <= (1 - headroom) * c["capacity"] + 1e-9


def test_problem_2_sizes_servers_with_the_margin() -> None:
    data = copy.deepcopy(EXAMPLE)
    system = parse_system(data, "flow.yaml")
    plain = solve(system, 2, "exact")
    kept = solve(system, 2, "exact", headroom=0.25)
    assert check_plan(system, kept) == []
    server = kept.computers["server"]
    assert server.capacity == pytest.approx(server.cpu / 0.75)
    assert server.margin == pytest.approx(0.25 * server.capacity)
    assert kept.objective == pytest.approx(server.capacity)
    assert kept.objective >= plain.objective - 1e-9


def test_checker_refuses_a_plan_that_eats_its_margin() -> None:
    system = parse_system(copy.deepcopy(EXAMPLE), "flow.yaml")
    plan = solve(system, 1, "exact")
    busiest = max(plan.computers.values(), key=lambda pc: pc.cpu / (pc.capacity or 1))
    busiest.margin = (busiest.capacity or 0) - busiest.cpu + 1.0
    assert any("margin" in why for why in check_plan(system, plan))


@pytest.mark.parametrize("bad", [-0.1, 1.0, 2.0, float("nan")])
def test_headroom_outside_0_1_is_refused(bad: float) -> None:
    system = parse_system(copy.deepcopy(EXAMPLE), "flow.yaml")
    with pytest.raises(InputError, match="headroom must be in"):
        solve(system, 1, "exact", headroom=bad)


def test_cli_headroom(tmp_path: Any) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(EXAMPLE))
    bad = subprocess.run([sys.executable, "-m", "perfros_bag", "solve", str(path), "--headroom", "1"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert [line for line in bad.stderr.splitlines() if line.strip()] \
        == ["error: --headroom must be in [0, 1), got 1.0"]
    good = subprocess.run([sys.executable, "-m", "perfros_bag", "solve", str(path), "--method", "exact",
                           "--headroom", "0.2", "--out", str(tmp_path / "plan.json")], capture_output=True, text=True)
    assert good.returncode == 0, good.stderr
    plan = load_plan(tmp_path / "plan.json")
    assert plan.extra["headroom"] == 0.2
    assert {n: pc.margin for n, pc in plan.computers.items()} == pytest.approx({"robot": 6.0, "server": 10.0})


# ---- measured headroom: fit's cpu_error and `solve --headroom auto` ----------------------
# Every expected number below is computed here from the rows written or the system stated
# (the rule of docs/solvers.md, "Headroom"), never taken from a solver run.

FAIR = 0.25  # docs/solvers.md: FAIR_SHARE


def test_fair_share_is_the_one_constant() -> None:
    from perfros_bag.fitting import cpu_error
    from perfros_bag.system.cpuerror import FAIR_SHARE

    assert FAIR_SHARE == FAIR and cpu_error.FAIR_SHARE is FAIR_SHARE


def _row(rec: str, node: str, param: str | None, value: float | None, mean: float, p95: float,
         input_hz: float | None = None) -> Any:
    from perfros_bag.characterisation.csvfile import Row

    topic = f"/{node}/out"
    return Row(rec, node, param or "", value, topic, "std_msgs/String", 100, 20.0, 5.0, 1.0, mean, p95, 40,
               input_hz=input_hz)


# det: value -> runs of (cpu_units_mean, cpu_units_p95); value 15 is a setting never measured
DET_RUNS = {10.0: [(20.0, 25.0), (22.0, 26.0)], 20.0: [(40.0, 44.0)], 30.0: [(60.0, 70.0), (64.0, 71.0)]}
DET_SETTINGS = {10.0: (21.0, 40.0), 15.0: (30.0, 55.0), 20.0: (40.0, 70.0), 30.0: (62.0, 100.0)}  # value -> (cpu, perf)


def _fit_small(tmp_path: Any) -> dict[str, Any]:
    import json

    from perfros_bag.characterisation.csvfile import write_characterisation
    from perfros_bag.fitting.build import build_model
    from perfros_bag.fitting.modelfile import write_model

    system = {
        "computers": [{"name": "robot", "kind": "robot", "capacity": 100}],
        "nodes": [
            {"name": "det", "weight": 0.5, "parameter": {"name": "rate"}, "topics": ["/det/out"],
             "settings": [{"value": v, "cpu": c, "performance": p} for v, (c, p) in DET_SETTINGS.items()]},
            {"name": "quiet", "weight": 0.5, "topics": ["/quiet/out"], "settings": [{"cpu": 5.0, "performance": 100}]},
        ],
    }
    rows = [_row(f"det_{v:g}_{i}.bag", "det", "rate", v, m, p) for v, runs in DET_RUNS.items()
            for i, (m, p) in enumerate(runs)]
    rows.append(_row("quiet.bag", "quiet", None, None, 8.0, 8.0))
    (tmp_path / "system.yaml").write_text(yaml.safe_dump(system))
    write_characterisation(tmp_path / "char.csv", rows)
    with pytest.warns():
        result = build_model(tmp_path / "system.yaml", tmp_path / "char.csv")
    write_model(tmp_path / "model.json", result.document)
    return dict(json.loads((tmp_path / "model.json").read_text()))


def _runs_part(runs: list[tuple[float, float]]) -> float:
    """burst (mean p95 - mean) + the runs' sample standard deviation, by hand."""
    import statistics

    means = [m for m, _ in runs]
    burst = max(0.0, sum(p - m for m, p in runs) / len(runs))
    return burst + (statistics.stdev(means) if len(means) > 1 else 0.0)


def test_fit_writes_each_settings_error_by_the_rule(tmp_path: Any) -> None:
    from perfros_bag.system.types import Curve

    model = _fit_small(tmp_path)
    nodes = {n["name"]: n for n in model["system"]["nodes"]}
    det = nodes["det"]
    assert "curve" in det  # fitted: the measured values' CPU comes from parameter->cpu
    p2c = det["relations"]["parameter->cpu"]
    curve = Curve(p2c["form"], tuple(p2c["coef"]), tuple(p2c["domain"]), p2c["scale"])
    loo = model["fits"]["det"]["parameter->cpu"]["loo_rmse"]
    assert loo is not None and loo > 0
    errors = {s["value"]: s["cpu_error"] for s in det["settings"]}
    cpu = {s["value"]: s["cpu"] for s in det["settings"]}
    for v, runs in DET_RUNS.items():  # measured: burst + spread + |fit - mean|, at least the floor
        mean = sum(m for m, _ in runs) / len(runs)
        assert cpu[v] == pytest.approx(mean)
        want = max(_runs_part(runs) + abs(curve(v) - mean), FAIR * mean)
        assert errors[v] == pytest.approx(want, rel=1e-7)
    # 15 was never measured: its neighbours' spread, interpolated, plus the fit's LOO RMSE
    between = (_runs_part(DET_RUNS[10.0]) + _runs_part(DET_RUNS[20.0])) / 2
    assert errors[15.0] == pytest.approx(max(between + loo, FAIR * 30.0), rel=1e-5)  # model.json: LOO to 6 digits
    assert errors[15.0] > between  # an unmeasured value carries more than its neighbours' spread
    assert det["cpu_error_between"] == pytest.approx(loo, rel=1e-5)
    # one steady run (p95 = mean): the floor, FAIR_SHARE x its CPU
    assert nodes["quiet"]["settings"][0]["cpu_error"] == pytest.approx(FAIR * 8.0)
    load = parse_system(model["system"], "model.json")  # the model loads with its new keys
    assert load.node["det"].cpu_error_between == pytest.approx(loo, rel=1e-5)


def test_fit_driven_node_states_its_error_as_a_share(tmp_path: Any) -> None:
    import json

    import numpy as np

    from perfros_bag.characterisation.csvfile import Row
    from perfros_bag.fitting.build import build_model
    from perfros_bag.fitting.modelfile import write_model
    from tests.test_fit_driven import CAMERA, DETECTOR, lstsq, system_yaml, write_inputs

    rng = np.random.default_rng(7)
    table: list[Row] = []
    runs: dict[float, list[tuple[float, float, float]]] = {}  # value -> (F_in, mean, p95)
    for rate, f_in in CAMERA.items():
        for value, (base, k, ratio, size) in DETECTOR.items():
            rec = f"rec_r{rate:g}_s{value:g}.bag"
            mean = base + k * f_in + float(rng.normal(0, 0.8))
            p95 = mean * (1.2 + 0.1 * float(rng.random()))
            runs.setdefault(value, []).append((f_in, mean, p95))
            f_out = ratio * f_in
            table.append(Row(rec, "camera", "rate", rate, "/camera/image", "sensor_msgs/Image", 100, 20.0,
                             f_in, 100.0 * f_in, 1.0 + 0.4 * f_in, 1.1 + 0.4 * f_in, 40))
            table.append(Row(rec, "detector", "scale", value, "/det/out", "std_msgs/String", 100, 20.0,
                             f_out, size * f_out / 1000.0, mean, p95, 40, input_hz=f_in))
    sys_path, csv_path = write_inputs(tmp_path, system_yaml(), table)
    with pytest.warns():
        result = build_model(sys_path, csv_path)
    write_model(tmp_path / "model.json", result.document)
    model = json.loads((tmp_path / "model.json").read_text())
    det = next(n for n in model["system"]["nodes"] if n["name"] == "detector")
    share = {s["value"]: s["cpu_error_share"] for s in det["settings"]}
    source = {d["value"]: d["source"] for d in model["driven"]["detector"]}
    run_share: dict[float, float] = {}
    for value, pts in runs.items():
        assert source[value] == "measured"
        base, k = lstsq([(f, m) for f, m, _ in pts])
        assert base > 0 and k > 0  # the plain least-squares line (nothing clipped)
        f_bar = sum(f for f, _, _ in pts) / len(pts)
        level = base + k * f_bar
        burst = sum(p - m for _, m, p in pts) / len(pts)
        resid = [m - (base + k * f) for f, m, _ in pts]
        spread = (sum(r * r for r in resid) / (len(resid) - 1)) ** 0.5
        gap = abs(level - sum(m for _, m, _ in pts) / len(pts))
        run_share[value] = (burst + spread) / level
        assert share[value] == pytest.approx(max((burst + spread + gap) / level, FAIR), rel=1e-6)
    fits = model["fits"]["detector"]
    loo_base, loo_k = fits["parameter->cpu_base"]["loo_rmse"], fits["parameter->cpu_per_hz"]["loo_rmse"]
    f_ref = sum(f for pts in runs.values() for f, _, _ in pts) / sum(len(pts) for pts in runs.values())
    grid = [s for s in det["settings"] if source[s["value"]] == "grid"]
    assert grid
    values = sorted(run_share)
    for s in grid:
        v = s["value"]
        lo = max(x for x in values if x < v)
        hi = min(x for x in values if x > v)
        between = run_share[lo] + (run_share[hi] - run_share[lo]) * (v - lo) / (hi - lo)
        fit_part = (loo_base + loo_k * f_ref) / (s["cpu"] + s["cpu_per_hz"] * f_ref)
        assert share[v] == pytest.approx(max(between + fit_part, FAIR), rel=1e-5)
        assert share[v] >= between
    # the model solves under auto, its plan checked independently
    system = parse_system(model["system"], "model.json")
    plan = solve(system, 1, "exact", headroom="auto")
    assert check_plan(system, plan) == []
    pn = plan.nodes["detector"]
    own = next(s for s in det["settings"] if abs(s["value"] - pn.value) < 1e-9)
    camera = _independent_error(model["system"], "camera", plan.nodes["camera"].cpu)
    assert plan.computers["robot"].margin == pytest.approx(max(own["cpu_error_share"], FAIR) * pn.cpu + camera,
                                                           rel=1e-9)


# A small instance: a robot and a server, discrete nodes stating cpu_error (b's second
# setting below the floor, c none at all) and a curve node.
SMALL: dict[str, Any] = {
    "computers": [{"name": "robot", "kind": "robot", "capacity": 14},
                  {"name": "server", "kind": "server", "capacity": 16}],
    "nodes": [
        {"name": "a", "weight": 0.3, "parameter": {"name": "p"}, "residence": ["robot"],
         "settings": [{"value": 1, "cpu": 2, "performance": 30, "cpu_error": 0.5},
                      {"value": 2, "cpu": 4, "performance": 60, "cpu_error": 1.5},
                      {"value": 3, "cpu": 6, "performance": 100, "cpu_error": 0.2}]},
        {"name": "b", "weight": 0.3, "parameter": {"name": "p"},
         "settings": [{"value": 1, "cpu": 3, "performance": 20, "cpu_error": 1.0},
                      {"value": 2, "cpu": 5, "performance": 70, "cpu_error": 0.3},
                      {"value": 3, "cpu": 8, "performance": 100, "cpu_error": 2.0}]},
        {"name": "c", "weight": 0.2, "settings": [{"cpu": 4, "performance": 100}]},
        {"name": "d", "weight": 0.2, "parameter": {"name": "q"},
         "settings": [{"value": 1, "cpu": 2, "performance": 40, "cpu_error": 0.8},
                      {"value": 2, "cpu": 6, "performance": 100, "cpu_error": 1.6}],
         "curve": {"form": "linear", "coef": [1500, 10], "cpu": [2, 6]}, "cpu_error_between": 0.5},
    ],
}


def _independent_error(data: dict[str, Any], node: str, cpu: float) -> float:
    """The rule, written again: a setting's stated error; a curve level between settings the
    line between theirs plus cpu_error_between; at least FAIR x cpu."""
    n = next(x for x in data["nodes"] if x["name"] == node)
    pts = sorted((s["cpu"], s.get("cpu_error", 0.0)) for s in n["settings"])
    stated = next((e for c, e in pts if abs(c - cpu) < 1e-9), None)
    if stated is None and "curve" in n:
        (c0, e0), (c1, e1) = next(((p, q) for p, q in zip(pts, pts[1:], strict=False) if p[0] <= cpu <= q[0]))
        stated = e0 + (e1 - e0) * (cpu - c0) / (c1 - c0) + n.get("cpu_error_between", 0.0)
    return max(stated or 0.0, FAIR * cpu)


def _inflated_by_hand(data: dict[str, Any], resolution: float = 1.0) -> dict[str, Any]:
    """The instance with every choice's CPU raised by its error: discrete settings only (a
    curve node as one setting per CPU level), no cpu_error keys."""
    out = copy.deepcopy(data)
    for n in out["nodes"]:
        if "curve" in n:
            lo, hi = n["curve"]["cpu"]
            a, b = n["curve"]["coef"]
            levels = [lo + k * resolution for k in range(int((hi - lo) / resolution) + 1)]
            n["settings"] = [{"value": float(i), "cpu": c + _independent_error(data, n["name"], c),
                              "performance": a * c / 100 + b} for i, c in enumerate(levels)]
            n.pop("curve")
            n.pop("cpu_error_between", None)
        else:
            for s in n["settings"]:
                s["cpu"] = s["cpu"] + _independent_error(data, n["name"], s["cpu"])
                s.pop("cpu_error", None)
    return out


@pytest.mark.parametrize("method", ["exact", "greedy", "greedy+", "bruteforce"])
@pytest.mark.parametrize("problem", [1, 2])
def test_auto_keeps_each_computers_margin_free(method: str, problem: int) -> None:
    system = parse_system(copy.deepcopy(SMALL), "small.yaml")
    plan = solve(system, problem, method, headroom="auto")
    assert plan.status != "infeasible" and plan.extra["headroom"] == "auto"
    assert check_plan(system, plan) == []
    for name, pc in plan.computers.items():
        on = [n for n, pn in plan.nodes.items() if pn.computer == name]
        want = sum(_independent_error(SMALL, n, plan.nodes[n].cpu) for n in on)
        assert pc.margin == pytest.approx(want, abs=1e-9)
        assert pc.cpu == pytest.approx(sum(plan.nodes[n].cpu for n in on), abs=1e-9)
        assert pc.capacity is not None and pc.cpu <= pc.capacity - pc.margin + 1e-9
        if problem == 2 and name == "server":
            assert pc.capacity == pytest.approx(pc.cpu + pc.margin)
    # each node's planned CPU is the model's own: one of its settings' or a level of its curve
    for name, pn in plan.nodes.items():
        node = system.node[name]
        assert any(abs(c.cpu - pn.cpu) < 1e-9 for c in node.choices())


@pytest.mark.parametrize("problem", [1, 2])
def test_auto_equals_brute_force_on_the_cpus_inflated_by_hand(problem: int) -> None:
    system = parse_system(copy.deepcopy(SMALL), "small.yaml")
    auto = solve(system, problem, "exact", headroom="auto")
    by_hand = solve(parse_system(_inflated_by_hand(SMALL), "inflated.yaml"), problem, "bruteforce")
    assert auto.status == by_hand.status == "optimal"
    assert auto.objective == pytest.approx(by_hand.objective, rel=1e-9)
    plain = solve(system, problem, "exact")  # the margins cost: never better than without them
    assert (auto.objective <= plain.objective + 1e-9) if problem == 1 else (auto.objective >= plain.objective - 1e-9)


def test_auto_without_any_error_keeps_the_floor_and_says_so() -> None:
    data = _inflated_by_hand(SMALL)  # no cpu_error anywhere
    system = parse_system(data, "plain.yaml")
    plan = solve(system, 1, "exact", headroom="auto")
    assert check_plan(system, plan) == []
    assert plan.reason is not None and "no cpu_error" in plan.reason and "25 %" in plan.reason
    for pc in plan.computers.values():
        assert pc.margin == pytest.approx(FAIR * pc.cpu)


def test_auto_driven_node_error_follows_its_input_rate() -> None:
    data = copy.deepcopy(EXAMPLE)
    data["nodes"][1]["settings"][0]["cpu_error_share"] = 0.3
    data["nodes"][1]["settings"][1]["cpu_error_share"] = 0.05  # below the floor
    system = parse_system(data, "flow.yaml")
    for problem in (1, 2):
        plan = solve(system, problem, "exact", headroom="auto")
        assert check_plan(system, plan) == []
        share = {1.05: 0.3, 1.4: FAIR}
        want = {c: 0.0 for c in plan.computers}
        for name, pn in plan.nodes.items():
            s = share.get(pn.value or 0.0, FAIR) if name == "people" else FAIR
            want[pn.computer] += s * pn.cpu
        for name, pc in plan.computers.items():
            assert pc.margin == pytest.approx(want[name], abs=1e-9)
            assert pc.cpu <= (pc.capacity or 0.0) - pc.margin + 1e-9


def test_default_and_numeric_headroom_ignore_the_errors() -> None:
    system = parse_system(copy.deepcopy(SMALL), "small.yaml")
    plain = parse_system(copy.deepcopy(SMALL) | {"nodes": [
        {k: v for k, v in n.items() if k != "cpu_error_between"} | {"settings": [
            {k: v for k, v in s.items() if k != "cpu_error"} for s in n["settings"]]} for n in SMALL["nodes"]]},
        "plain.yaml")
    for headroom in (0.0, 0.2):
        assert solve(system, 1, "exact", headroom=headroom).objective == pytest.approx(
            solve(plain, 1, "exact", headroom=headroom).objective)


@pytest.mark.parametrize(("where", "change", "message"), [
    ("a", {"cpu_error": -1}, "node 'a': settings[0].cpu_error: must be >= 0, got -1"),
    ("a", {"cpu_error": float("nan")}, "node 'a': settings[0].cpu_error: must be a finite number"),
    ("a", {"cpu_error": "lots"}, "node 'a': settings[0].cpu_error: must be a finite number"),
    ("a", {"cpu_error_share": 0.2}, "node 'a': settings[0]: cpu_error_share: only a driven node"),
    ("people", {"cpu_error": 1.0}, "node 'people': settings[0].cpu_error: a driven node (input:) states its error "
                                   "relative to its CPU: cpu_error_share"),
    ("people", {"cpu_error_share": -0.5}, "node 'people': settings[0].cpu_error_share: must be >= 0, got -0.5"),
])
def test_bad_errors_are_one_clear_line(where: str, change: dict[str, Any], message: str) -> None:
    data = copy.deepcopy(EXAMPLE)
    data["nodes"].append(copy.deepcopy(SMALL["nodes"][0]) | {"residence": None})
    node = next(n for n in data["nodes"] if n["name"] == where)
    node["settings"][0].update(change)
    with pytest.raises(InputError) as exc:
        parse_system(data, "bad.yaml")
    assert str(exc.value).startswith(f"bad.yaml: {message}")
    assert "\n" not in str(exc.value)


def test_cpu_error_between_needs_a_curve() -> None:
    data = copy.deepcopy(SMALL)
    data["nodes"][0]["cpu_error_between"] = 1.0
    with pytest.raises(InputError, match=r"small.yaml: node 'a': cpu_error_between: only a node with a curve"):
        parse_system(data, "small.yaml")
    data["nodes"][0]["cpu_error_between"] = -1.0
    with pytest.raises(InputError, match=r"node 'a': cpu_error_between: must be >= 0"):
        parse_system(data, "small.yaml")


@pytest.mark.parametrize("bad", ["Auto ", "AUTO", "automatic", 1.0, -0.1, True, None])
def test_solve_headroom_bad_values(bad: Any) -> None:
    system = parse_system(copy.deepcopy(SMALL), "small.yaml")
    if isinstance(bad, str) and bad.strip().lower() == "auto":
        bad = bad + "x"
    with pytest.raises(InputError, match="headroom must be in"):
        solve(system, 1, "exact", headroom=bad)


def test_cli_headroom_auto(tmp_path: Any) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(SMALL))
    for bad, line in (("x", "error: --headroom must be 'auto' or a number in [0, 1), got 'x'"),
                      ("nan", "error: --headroom must be in [0, 1), got nan"),
                      ("-0.1", "error: --headroom must be in [0, 1), got -0.1")):
        done = subprocess.run([sys.executable, "-m", "perfros_bag", "solve", str(path), "--headroom", bad],
                              capture_output=True, text=True)
        assert done.returncode == 2 and [x for x in done.stderr.splitlines() if x.strip()] == [line], done.stderr
    out = tmp_path / "plan.json"
    good = subprocess.run([sys.executable, "-m", "perfros_bag", "solve", str(path), "--method", "exact",
                           "--headroom", "auto", "--out", str(out)], capture_output=True, text=True)
    assert good.returncode == 0, good.stderr
    plan = load_plan(out)
    assert plan.extra["headroom"] == "auto"
    system = parse_system(copy.deepcopy(SMALL), "small.yaml")
    assert check_plan(system, plan) == []
    assert all(pc.margin and pc.margin > 0 for pc in plan.computers.values())


def test_tune_takes_auto() -> None:
    from perfros_bag.tune.loop import _check_args

    _check_args(3, 5.0, "auto", "exact", 100.0)
    with pytest.raises(InputError, match=r"headroom must be in \[0, 1\), got 'automatic'"):
        _check_args(3, 5.0, "automatic", "exact", 100.0)


def test_tune_cli_headroom(tmp_path: Any) -> None:
    from tests.conftest import FIXTURES

    out = tmp_path / "out"
    base = [sys.executable, "-m", "perfros_bag", "tune", str(FIXTURES / "app" / "app.launch"), "--space",
            str(FIXTURES / "app" / "space.yaml"), "--system", str(FIXTURES / "recordings" / "system.yaml"),
            "--out", str(out)]
    for bad, line in (("automatic", "error: --headroom must be 'auto' or a number in [0, 1), got 'automatic'"),
                      ("1", "error: headroom must be in [0, 1), got 1.0")):
        done = subprocess.run([*base, "--headroom", bad], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and done.stderr.strip().splitlines()[0].startswith(line), done.stderr
        assert len(done.stderr.strip().splitlines()) == 1 and not out.exists()


def test_fit_p95_has_no_burst(tmp_path: Any) -> None:
    import json
    import statistics

    from perfros_bag.fitting.build import build_model
    from perfros_bag.fitting.modelfile import write_model
    from perfros_bag.system.types import Curve

    _fit_small(tmp_path)  # writes system.yaml and char.csv
    with pytest.warns():
        result = build_model(tmp_path / "system.yaml", tmp_path / "char.csv", cpu="p95")
    write_model(tmp_path / "p95.json", result.document)
    det = next(n for n in json.loads((tmp_path / "p95.json").read_text())["system"]["nodes"] if n["name"] == "det")
    p2c = det["relations"]["parameter->cpu"]
    curve = Curve(p2c["form"], tuple(p2c["coef"]), tuple(p2c["domain"]), p2c["scale"])
    for s in det["settings"]:
        runs = DET_RUNS.get(s["value"])
        if runs is None:
            continue
        p95s = [p for _, p in runs]
        mean = sum(p95s) / len(p95s)
        spread = statistics.stdev(p95s) if len(p95s) > 1 else 0.0
        assert s["cpu"] == pytest.approx(mean)
        assert s["cpu_error"] == pytest.approx(max(spread + abs(curve(s["value"]) - mean), FAIR * mean), rel=1e-7)


def test_tune_solves_each_round_with_auto(tmp_path: Any) -> None:
    from perfros_bag.tune.loop import _solve

    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(SMALL))
    plan = _solve(path, "exact", "auto")
    assert plan.extra["headroom"] == "auto"
    assert check_plan(parse_system(copy.deepcopy(SMALL), "small.yaml"), plan) == []
    assert plan.objective == pytest.approx(solve(parse_system(copy.deepcopy(SMALL), "s.yaml"), 1, "exact",
                                                 headroom="auto").objective)
