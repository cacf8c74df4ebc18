"""``membership: choose``: a plan may run a container's hosted nodes standalone, paying the
copy of its input (issue 34). Checked against the independent checker's own copy of the
copy rule, a price computed by hand, and the best over every subset of freed nodes that
brute force finds on its own."""

from __future__ import annotations

import copy
import itertools
import random
from pathlib import Path
from typing import Any

import pytest

from perfros_bag.errors import InputError
from perfros_bag.solver import solve
from perfros_bag.solver.check import check_plan
from perfros_bag.system.plan import Status
from perfros_bag.system.planfile import check_against_system, load_plan, save_plan
from perfros_bag.system.systemfile import parse_system

pytestmark = pytest.mark.filterwarnings("ignore:.*weights sum to")

FRAME = 230_400  # bytes per camera frame
PRICE = 2.0  # CPU units per MB/s of copies


def _doc(robot: float = 20.0, server: float = 45.0, **extra: Any) -> dict[str, Any]:
    """A camera on its robot and a nodelet manager hosting two driven nodelets on its frames:
    the nodelet fixture's shape (fixtures/nodelet)."""
    cam_topic = "/camera/image_raw"
    doc: dict[str, Any] = {
        "computers": [{"name": "robot", "kind": "robot", "capacity": robot},
                      {"name": "server", "kind": "server", "capacity": server}],
        "links": [{"between": ["robot", "server"], "bandwidth_kBps": 20000}],
        "membership": "choose",
        "nodes": [
            {"name": "camera", "weight": 0.2, "residence": ["robot"], "topics": [cam_topic],
             "parameter": {"name": "publish_rate", "unit": "Hz"},
             "settings": [{"value": 5, "cpu": 1.0, "performance": 50, "frequency_hz": 5,
                           "bandwidth_kBps": 5 * FRAME / 1000},
                          {"value": 10, "cpu": 2.0, "performance": 100, "frequency_hz": 10,
                           "bandwidth_kBps": 10 * FRAME / 1000}]},
            {"name": "manager", "weight": 0.1, "settings": [{"cpu": 0.5, "performance": 100}],
             "copy_cpu_per_MBps": PRICE},
            {"name": "people", "weight": 0.4, "container": "manager", "input": cam_topic,
             "parameter": {"name": "scale0"}, "topics": ["/people/found"],
             "settings": [{"value": 1.1, "cpu": 0.2, "cpu_per_hz": 4.0, "performance": 100, "bytes_per_msg": 300},
                          {"value": 1.4, "cpu": 0.2, "cpu_per_hz": 1.5, "performance": 40, "bytes_per_msg": 300}]},
            {"name": "smooth", "weight": 0.3, "container": "manager", "input": cam_topic,
             "parameter": {"name": "kernel_size"}, "topics": ["/smooth/image"],
             "settings": [{"value": 13, "cpu": 0.2, "cpu_per_hz": 1.2, "performance": 100,
                           "bytes_per_msg": FRAME},
                          {"value": 7, "cpu": 0.2, "cpu_per_hz": 0.4, "performance": 60, "bytes_per_msg": FRAME}]},
        ],
        "edges": [{"from": "camera", "to": "people"}, {"from": "camera", "to": "smooth"}],
    }
    doc.update(extra)
    return doc


def _not_driven(doc: dict[str, Any]) -> dict[str, Any]:
    """The nodelets as `init` drafts them when the camera's rate is not swept (the nodelet
    fixture): settings of fixed CPU at the camera's highest rate, no ``input``."""
    doc = copy.deepcopy(doc)
    for n in doc["nodes"][2:]:
        n.pop("input")
        for s in n["settings"]:
            s["cpu"] = round(s["cpu"] + s.pop("cpu_per_hz") * 10, 6)
            s["frequency_hz"] = 10
            s["bandwidth_kBps"] = s.pop("bytes_per_msg") * 10 / 1000
    return doc


def test_the_copy_price_by_hand() -> None:
    system = parse_system(_doc(), "s.yaml")
    # a driven node: one more copy of a 230.4 kB frame per input message, at 2 units per MB/s
    assert system.copy_charge("people") == pytest.approx((PRICE * FRAME / 1e6, 0.0))
    assert system.copy_charge("camera") is None and system.copy_charge("manager") is None
    # not driven: the MB/s of its edge in, at the camera's fastest setting (10 Hz)
    assert parse_system(_not_driven(_doc()), "s.yaml").copy_charge("smooth") == pytest.approx(
        (0.0, PRICE * 10 * FRAME / 1e6))
    freed = system.freed(["people"])
    assert freed.membership == "keep" and freed.node["people"].container is None
    assert [s.cpu_per_hz for s in freed.node["people"].settings] == pytest.approx(
        [4.0 + PRICE * FRAME / 1e6, 1.5 + PRICE * FRAME / 1e6])
    assert sorted(sorted(g) for g in freed.coresidence_groups) == [["camera"], ["manager", "smooth"], ["people"]]
    no_price = copy.deepcopy(_doc())
    del no_price["nodes"][1]["copy_cpu_per_MBps"]
    assert parse_system(no_price, "s.yaml").copy_charge("people") is None
    still = parse_system(_not_driven(_doc()), "s.yaml").freed(["smooth"])
    assert still.node["smooth"].copy_cpu == pytest.approx(PRICE * 10 * FRAME / 1e6)
    assert still.node["smooth"].settings == parse_system(_not_driven(_doc()), "s.yaml").node["smooth"].settings


def test_a_freed_system_carries_the_charges_it_put_on_its_nodes_and_restate_takes_them_back() -> None:
    """``freed`` says what it charged each node it freed (the hand-computed copy price), and
    ``restate`` takes exactly that off a freed node the plan leaves on its container's computer."""
    from perfros_bag.solver.membership import restate
    from perfros_bag.system.plan import Plan, PlannedComputer, PlannedNode

    system = parse_system(_doc(), "s.yaml")
    assert system.charged == {}
    freed = system.freed(["people"])
    assert freed.charged == {"people": pytest.approx((PRICE * FRAME / 1e6, 0.0))}
    fixed = parse_system(_not_driven(_doc()), "s.yaml")
    assert fixed.freed(["smooth"]).charged == {"smooth": pytest.approx((0.0, PRICE * 10 * FRAME / 1e6))}
    with pytest.raises(ValueError, match=r"\['camera'\] cannot run standalone"):
        system.freed(["people", "camera"])

    def plan() -> Plan:  # people at 10 Hz of input with the manager on the robot
        return Plan(1, "exact", "optimal", computers={"robot": PlannedComputer("robot", 100.0, 50.0)},
                    nodes={"manager": PlannedNode("robot", 5.0, 50.0, 0.0), "people": PlannedNode(
                        "robot", 20.0, 50.0, 1.0, input_hz=10.0)})

    back = restate(system, freed, plan())
    taken = PRICE * FRAME / 1e6 * 10.0
    assert back.nodes["people"].cpu == pytest.approx(20.0 - taken) and not back.nodes["people"].standalone
    assert back.computers["robot"].cpu == pytest.approx(50.0 - taken)
    assert restate(system, system.freed([]), plan()).nodes["people"].cpu == 20.0


def test_a_split_plan_beats_the_kept_membership_and_passes_the_checker(tmp_path: Path) -> None:
    """Neither computer holds the camera, the manager and both nodelets at their best; run
    apart they do: the detector standalone on the server (or the smoother), paying the copy."""
    choose = parse_system(_doc(), "s.yaml")
    keep = parse_system(_doc(membership="keep"), "s.yaml")
    kept, split = solve(keep, 1, "exact"), solve(choose, 1, "exact")
    assert check_plan(keep, kept) == [] and check_plan(choose, split) == []
    assert split.status == Status.OPTIMAL and split.objective is not None and kept.objective is not None
    assert split.objective > kept.objective + 1e-6
    alone = [n for n, pn in split.nodes.items() if pn.standalone]
    assert alone and all(split.nodes[n].computer != split.nodes["manager"].computer for n in alone)
    assert split.extra["membership"]["standalone"] == alone
    # not driven (as init drafts the nodelet fixture): the copy a fixed charge, the same split
    fixed = solve(parse_system(_not_driven(_doc()), "s.yaml"), 1, "exact")
    assert fixed.objective is not None and fixed.objective > kept.objective + 1e-6
    lone = [n for n, pn in fixed.nodes.items() if pn.standalone]
    assert lone and check_plan(parse_system(_not_driven(_doc()), "s.yaml"), fixed) == []
    s0 = next(s for s in _not_driven(_doc())["nodes"] if s["name"] == lone[0])
    own = next(x["cpu"] for x in s0["settings"] if x["value"] == fixed.nodes[lone[0]].value)
    assert fixed.nodes[lone[0]].cpu == pytest.approx(own + PRICE * 10 * FRAME / 1e6)
    for n in alone:  # its CPU: its setting at its input rate plus the copy, by hand
        pn = split.nodes[n]
        s = next(s for s in choose.node[n].settings if s.value == pn.value)
        assert pn.input_hz is not None
        assert pn.cpu == pytest.approx(s.cpu + (s.cpu_per_hz or 0) * pn.input_hz + PRICE * FRAME / 1e6 * pn.input_hz)
    # plan.json keeps the flag; the checks that read a plan with its system accept it
    save_plan(split, tmp_path / "plan.json")
    again = load_plan(tmp_path / "plan.json")
    assert [n for n, pn in again.nodes.items() if pn.standalone] == alone
    check_against_system(again, choose, tmp_path / "plan.json")
    with pytest.raises(InputError, match=r"standalone, but the system's membership is keep"):
        check_against_system(again, keep, tmp_path / "plan.json")
    assert any("membership" in p for p in check_plan(keep, again))
    # the checker's own copy of the charge: the same plan without the copy is refused
    cheap = load_plan(tmp_path / "plan.json")
    cheap.nodes[alone[0]].cpu -= PRICE * FRAME / 1e6 * (cheap.nodes[alone[0]].input_hz or 0)
    assert any(alone[0] in p for p in check_plan(choose, cheap))
    # a hosted node away from its container without the flag is still a split
    unflagged = load_plan(tmp_path / "plan.json")
    unflagged.nodes[alone[0]].standalone = False
    assert any(p.startswith("container:") for p in check_plan(choose, unflagged))
    with pytest.raises(InputError, match=r"container manager: its nodes are on different computers"):
        check_against_system(unflagged, choose, tmp_path / "plan.json")


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("problem", [1, 2])
@pytest.mark.parametrize("driven", [True, False], ids=["driven", "not_driven"])
def test_exact_is_the_best_brute_force_over_every_freed_subset(seed: int, problem: int, driven: bool) -> None:
    rng = random.Random(seed)
    doc = _doc(robot=rng.uniform(12, 35), server=rng.uniform(15, 50))
    doc["nodes"][1]["copy_cpu_per_MBps"] = rng.choice([0.0, 1.0, 4.0])
    for n in doc["nodes"][2:]:
        for s in n["settings"]:
            s["cpu_per_hz"] = round(rng.uniform(0.3, 5.0), 2)
    if not driven:
        doc = _not_driven(doc)
    if problem == 2:  # every node at one setting: the server sized to the plan
        for n in doc["nodes"]:
            n["settings"] = n["settings"][:1]
            n.pop("parameter", None)
    choose = parse_system(doc, "s.yaml")
    exact = solve(choose, problem, "exact")
    best = None  # the test's own loop over the subsets, each solved by brute force
    for k in range(3):
        for subset in itertools.combinations(("people", "smooth"), k):
            plan = solve(choose.freed(subset), problem, "bruteforce")
            if plan.status == Status.INFEASIBLE or plan.objective is None:
                continue
            if best is None or (plan.objective > best if problem == 1 else plan.objective < best):
                best = plan.objective
    if best is None:
        assert exact.status == Status.INFEASIBLE
        return
    assert exact.status == Status.OPTIMAL and exact.objective == pytest.approx(best, abs=1e-6)
    assert check_plan(choose, exact) == []
    for method in ("greedy", "greedy+", "bruteforce"):
        plan = solve(choose, problem, method)
        assert plan.status == Status.INFEASIBLE or check_plan(choose, plan) == [], method


def test_nodes_that_cannot_leave_stay_with_a_warning_and_too_many_are_refused() -> None:
    doc = _doc()
    del doc["nodes"][1]["copy_cpu_per_MBps"]
    with pytest.warns(match=r"people, smooth stay in their container"):
        plan = solve(parse_system(doc, "s.yaml"), 1, "exact")
    assert not any(pn.standalone for pn in plan.nodes.values())
    many = _doc()
    for i in range(7):
        many["nodes"].append({**copy.deepcopy(many["nodes"][3]), "name": f"extra{i}", "topics": [f"/extra{i}/out"]})
    with pytest.raises(InputError, match=r"membership: choose: 9 hosted nodes may leave .* at most 6"):
        solve(parse_system(many, "s.yaml"), 1, "exact")


def test_problem_2_takes_its_settings_from_a_plan_that_split_the_container() -> None:
    """``solve --problem 2 --settings plan.json`` after a Problem 1 plan that ran a nodelet
    standalone: that node's CPU in the plan holds its copy (a fixed charge when not driven),
    which is not a setting of the model; the settings are read without it, and Problem 2
    keeps every node's value, whichever membership it then chooses."""
    from perfros_bag.solver import settings_from_plan

    system = parse_system(_not_driven(_doc()), "s.yaml")
    first = solve(system, 1, "exact")
    alone = sorted(first.standalone)
    assert alone, "the instance is built so that Problem 1 splits the manager"
    levels = settings_from_plan(first, system)
    for n in alone:  # the setting's own CPU, by hand: the plan's less the copy of 10 frames a second
        assert levels[n] == pytest.approx(first.nodes[n].cpu - PRICE * 10 * FRAME / 1e6)
    second = solve(system, 2, "exact", settings=levels)
    assert second.status == Status.OPTIMAL and check_plan(system, second) == []
    assert {n: pn.value for n, pn in second.nodes.items()} == {n: pn.value for n, pn in first.nodes.items()}


def test_residences_that_only_a_split_can_meet_are_planned_under_choose_and_refused_under_keep() -> None:
    """The detector may run only on the server and the smoother only on the robot, both
    nodelets of one manager: under ``keep`` no computer can host that process (refused, one
    line naming both); under ``choose`` one of them leaves, and every method finds that plan
    (the kept membership's own variant has no plan, and the exact one is brute force's best)."""
    def doc(membership: str) -> dict[str, Any]:
        d = _not_driven(_doc(robot=30.0, server=45.0, membership=membership))
        d["nodes"][2]["residence"] = ["server"]
        d["nodes"][3]["residence"] = ["robot"]
        return d

    with pytest.raises(InputError, match=r"'people' \(allowed on server\) and 'smooth' \(allowed on robot\)"):
        parse_system(doc("keep"), "s.yaml")
    choose = parse_system(doc("choose"), "s.yaml")
    assert solve(choose.freed(()), 1, "bruteforce").status == Status.INFEASIBLE
    best = max((p.objective for k in range(1, 3) for sub in itertools.combinations(("people", "smooth"), k)
                if (p := solve(choose.freed(sub), 1, "bruteforce")).objective is not None), default=None)
    assert best is not None
    for method in ("exact", "greedy", "greedy+", "bruteforce"):
        plan = solve(choose, 1, method)
        assert plan.status != Status.INFEASIBLE and check_plan(choose, plan) == [], method
        assert plan.standalone
        assert plan.nodes["people"].computer == "server" and plan.nodes["smooth"].computer == "robot"
        if method in ("exact", "bruteforce"):
            assert plan.objective == pytest.approx(best, abs=1e-6)
