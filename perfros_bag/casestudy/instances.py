"""Instances as ``system.yaml``-shaped data: the paper's case study and random ones.

- :func:`casestudy_system`: the case study of the paper (Table I nodes, one server, robots
  on a shared wifi channel, the reference curves of Fig. 4 with x = CPU/100).
- :func:`table2_instance`: Table II instances 1-6.
- :func:`random_instance`: case-study-like with varied capacities, weights and network.
- :func:`fleet_instance`: many robots running the robot stack and camera trackers sharing
  a few servers over one wifi (the fleet benchmarks, 200 x 20 to 1,000 x 100).
- :func:`random_tiny`: at most 5 nodes on at most 3 computers, small enough for brute
  force, with links, a shared medium, edges, residence and coresidence that can bind.

Everything returned is plain data (lists, dicts, numbers) that
:func:`perfros_bag.system.systemfile.parse_system` accepts and ``yaml.safe_dump`` writes.
"""

from __future__ import annotations

import random
from typing import Any

WIFI_kBps = 37500.0  # 802.11ac, 300 Mbit/s

# Table I: name -> (weight, parameter (name, unit), settings [(value, cpu, perf, freq, kB/s)])
TABLE_I: dict[str, tuple[float, tuple[str, str] | None, list[tuple[float | None, float, float, float, float]]]] = {
    "experiment": (0.05, None, [(None, 1, 100, 10, 1.0)]),
    "tracker": (0.2, ("output_freq", "Hz"), [(10, 80, 40, 10, 1.0), (15, 120, 70, 15, 1.5),
                                             (20, 160, 90, 20, 2.0), (25, 200, 100, 25, 2.5)]),
    "environment": (0.05, None, [(None, 1, 100, 10, 0.5)]),
    "model": (0.2, ("goals", ""), [(4, 17, 20, 10, 5.0), (3500, 40, 70, 10, 5.0), (10000, 60, 100, 10, 5.0)]),
    "planner": (0.05, None, [(None, 1, 100, 10, 0.5)]),
    "amcl": (0.2, ("particles", ""), [(200, 19, 20, 2.5, 1.0), (500, 41, 50, 2.5, 1.0), (3000, 66, 100, 2.5, 1.0)]),
    "navigation": (0.2, ("controller_freq", "Hz"),
                   [(2, 25, 10, 2, 0.1), (10, 39, 65, 10, 0.5), (20, 50, 100, 20, 1.0)]),
    "youbot_core": (0.05, None, [(None, 16, 100, 10, 0.5)]),
}

# The reference implementation's regressions (Fig. 4), x = CPU units / 100, and CPU ranges.
CURVES: dict[str, dict[str, Any]] = {
    "tracker": {"form": "log", "coef": [66.62, 56.308], "cpu": [80, 200]},
    "model": {"form": "log", "coef": [63.707, 132.16], "cpu": [17, 59]},
    "amcl": {"form": "quadratic", "coef": [135.4, 55.126, 4.6383], "cpu": [19, 66]},
    "navigation": {"form": "log", "coef": [129.12, 188.36], "cpu": [25, 50]},
}

# parameter -> CPU through Table I's points (tracker and the quadratics exact; AMCL's
# points are not monotone as a quadratic, so a log fit), for the parameter value of a CPU level.
PARAMETER_CPU: dict[str, dict[str, Any]] = {
    "tracker": {"form": "linear", "coef": [8.0, 0.0], "domain": [10, 25]},
    "model": {"form": "quadratic", "coef": [-3.50342566e-07, 7.80654772e-03, 16.9687794], "domain": [4, 10000]},
    "amcl": {"form": "log", "coef": [16.88674777, -67.87245935], "domain": [200, 3000]},
    "navigation": {"form": "quadratic", "coef": [-0.0361111111, 2.18333333, 20.7777778], "domain": [2, 20]},
}
INT_PARAMETERS = {"model", "amcl"}

# Table II: instance -> (robots, cameras)
TABLE_II: dict[int, tuple[int, int]] = {1: (1, 1), 2: (1, 2), 3: (1, 3), 4: (2, 1), 5: (2, 2), 6: (2, 3)}

ROBOT_NODES = ("environment", "model", "planner", "amcl", "navigation", "youbot_core")


def _node(kind: str, name: str, weight: float, *, continuous: bool, residence: list[str] | None = None,
          coresidence: list[str] | None = None) -> dict[str, Any]:
    _, param, settings = TABLE_I[kind]
    node: dict[str, Any] = {"name": name, "weight": weight}
    if residence:
        node["residence"] = residence
    if coresidence:
        node["coresidence"] = coresidence
    if param is not None:
        node["parameter"] = {"name": param[0], "unit": param[1]} if param[1] else {"name": param[0]}
    node["topics"] = [f"/{name}/out"]
    rows = []
    for value, cpu, perf, freq, bw in settings:
        row: dict[str, Any] = {"cpu": cpu, "performance": perf, "frequency_hz": freq, "bandwidth_kBps": bw}
        if value is not None:
            row["value"] = value
        rows.append(row)
    node["settings"] = rows
    if continuous and kind in CURVES:
        node["curve"] = dict(CURVES[kind])
        node["relations"] = {"parameter->cpu": dict(PARAMETER_CPU[kind])}
    if param is not None and kind in INT_PARAMETERS:
        node["parameter"]["type"] = "int"
    return node


def stack_edges(r: int) -> list[dict[str, Any]]:
    """The edges of robot stack ``r`` (its six nodes, suffix ``r``) and the experiment's
    edge to its model."""
    return [
        {"from": f"environment{r}", "to": f"model{r}"},
        {"from": f"model{r}", "to": f"planner{r}"},
        {"from": f"planner{r}", "to": f"navigation{r}"},
        {"from": f"amcl{r}", "to": f"environment{r}"},
        {"from": f"amcl{r}", "to": f"navigation{r}"},
        {"from": f"navigation{r}", "to": f"youbot_core{r}"},
        {"from": f"youbot_core{r}", "to": f"amcl{r}"},
        {"from": "experiment", "to": f"model{r}"},
    ]


def casestudy_system(robots: int, cameras: int, *, robot_capacity: float = 100, server_capacity: float = 400,
                     continuous: bool = True, weights: dict[str, float] | None = None,
                     wifi_kBps: float = WIFI_kBps) -> dict[str, Any]:
    """The paper's case study with ``robots`` robots and ``cameras`` cameras.

    Nodes: one ``experiment`` (on the server), a ``tracker<k>`` per camera (on the server)
    and per robot ``environment<r> model<r> planner<r> amcl<r> navigation<r> youbot_core<r>``
    (``youbot_core<r>`` on ``robot<r>``, ``planner<r>`` with ``navigation<r>``). With
    ``continuous`` the four configurable nodes carry the reference curves (every CPU unit
    of their range is a choice); otherwise Table I's discrete settings. Table I's
    weights (or ``weights``: kind -> weight) are renormalised to sum 1 (eq 6).
    """
    if robots < 1 or cameras < 0:
        raise ValueError("need at least one robot and no negative number of cameras")
    base = {k: v[0] for k, v in TABLE_I.items()}
    if weights:
        base.update(weights)
    nodes: list[tuple[str, str, dict[str, Any]]] = [("experiment", "experiment", {"residence": ["server"]})]
    for k in range(1, cameras + 1):
        nodes.append(("tracker", f"tracker{k}", {"residence": ["server"]}))
    for r in range(1, robots + 1):
        for kind in ROBOT_NODES:
            extra: dict[str, Any] = {}
            if kind == "youbot_core":
                extra["residence"] = [f"robot{r}"]
            if kind == "planner":
                extra["coresidence"] = [f"navigation{r}"]
            nodes.append((kind, f"{kind}{r}", extra))
    total = sum(base[kind] for kind, _, _ in nodes)
    out_nodes = [_node(kind, name, base[kind] / total, continuous=continuous, **extra) for kind, name, extra in nodes]

    edges: list[dict[str, Any]] = []
    for r in range(1, robots + 1):
        for k in range(1, cameras + 1):
            edges.append({"from": f"tracker{k}", "to": f"environment{r}"})
        edges += stack_edges(r)
    computers = [{"name": f"robot{r}", "kind": "robot", "capacity": robot_capacity} for r in range(1, robots + 1)]
    computers.append({"name": "server", "kind": "server", "capacity": server_capacity})
    return {
        "cpu_unit": "100 = one robot on-board computer (1.6 GHz dual-core Atom)",
        "computers": computers,
        "links": [{"between": [f"robot{r}", "server"], "bandwidth_kBps": wifi_kBps, "medium": "wifi"}
                  for r in range(1, robots + 1)],
        "media": [{"name": "wifi", "bandwidth_kBps": wifi_kBps}],
        "nodes": out_nodes,
        "edges": edges,
    }


def table2_instance(i: int, *, continuous: bool = True) -> dict[str, Any]:
    """Table II instance ``i`` (1-6): 1-2 robots, 1-3 cameras, one server."""
    if i not in TABLE_II:
        raise ValueError(f"Table II has instances 1-6, not {i}")
    robots, cameras = TABLE_II[i]
    return casestudy_system(robots, cameras, continuous=continuous)


def random_instance(rng: random.Random, *, robots: tuple[int, int] = (1, 4), cameras: tuple[int, int] = (1, 4),
                    robot_capacity: tuple[float, float] = (60, 160), server_capacity: tuple[float, float] = (150, 700),
                    weight_spread: float = 2.0, tight_network: bool = False) -> dict[str, Any]:
    """A case-study-like instance: a random number of robots and cameras, random integer
    capacities and weights (Table I's times a factor in [1/spread, spread]). With
    ``tight_network`` the wifi carries only a few kB/s, so bandwidth binds."""
    nr = rng.randint(*robots)
    nc = rng.randint(*cameras)
    weights = {k: v[0] * rng.uniform(1 / weight_spread, weight_spread) for k, v in TABLE_I.items()}
    wifi = rng.uniform(8.0, 30.0) * nr if tight_network else WIFI_kBps
    # the server must at least hold the trackers' and experiment's lowest settings (80 + 1)
    lo, hi = int(server_capacity[0]), int(server_capacity[1])
    lo = max(lo, 80 * nc + 1 + 20)
    data = casestudy_system(nr, nc, robot_capacity=100, server_capacity=rng.randint(lo, max(lo, hi)),
                            weights=weights, wifi_kBps=wifi)
    for comp in data["computers"]:
        if comp["kind"] == "robot":
            comp["capacity"] = rng.randint(*map(int, robot_capacity))
    return data


def random_tiny(rng: random.Random, n_nodes: int | None = None, n_computers: int | None = None) -> dict[str, Any]:
    """At most 5 nodes on at most 3 computers with 1-3 discrete settings each, random links
    (a chain or a star, some on one shared medium), edges whose bandwidth depends on the
    publisher's setting, residence and coresidence; capacities and bandwidths are drawn so
    that every constraint sometimes binds (and the instance is sometimes infeasible)."""
    nn = n_nodes if n_nodes is not None else rng.randint(2, 5)
    nc = n_computers if n_computers is not None else rng.randint(1, 3)
    names = [f"c{i}" for i in range(nc)]
    computers = []
    for i, name in enumerate(names):
        kind = "robot" if i < nc - 1 and rng.random() < 0.6 else "server"
        computers.append({"name": name, "kind": kind, "capacity": rng.randint(15, 80)})
    links: list[dict[str, Any]] = []
    use_medium = nc >= 3 and rng.random() < 0.5
    for i in range(1, nc):
        other = names[i - 1] if rng.random() < 0.5 else names[0]
        link: dict[str, Any] = {"between": [other, names[i]], "bandwidth_kBps": rng.choice([2, 5, 10, 50])}
        if use_medium:
            link["medium"] = "air"
        links.append(link)
    nodes: list[dict[str, Any]] = []
    for j in range(nn):
        k = rng.randint(1, 3)
        cpus = sorted(rng.sample(range(2, 35), k))
        perf = sorted(rng.sample(range(0, 101), k))
        node: dict[str, Any] = {"name": f"n{j}", "weight": rng.randint(1, 10)}
        if k > 1:
            node["parameter"] = {"name": "p"}
        node["settings"] = [{"value": idx + 1, "cpu": c, "performance": p,
                             "bandwidth_kBps": rng.choice([1, 2, 3, 4, 6])}
                            for idx, (c, p) in enumerate(zip(cpus, perf, strict=True))]
        if nc > 1 and rng.random() < 0.3:
            node["residence"] = rng.sample(names, rng.randint(1, nc - 1))
        nodes.append(node)
    if nn >= 2 and rng.random() < 0.4:
        a, b = rng.sample(range(nn), 2)
        nodes[a]["coresidence"] = [nodes[b]["name"]]
        # keep the group placeable: share residence
        ra, rb = nodes[a].get("residence"), nodes[b].get("residence")
        if ra is not None and rb is not None and not set(ra) & set(rb):
            del nodes[b]["residence"]
    total = sum(n["weight"] for n in nodes)
    for n in nodes:
        n["weight"] = n["weight"] / total
    edges = []
    for _ in range(rng.randint(0, nn + 1)):
        a, b = rng.sample(range(nn), 2) if nn >= 2 else (0, 0)
        if a != b:
            edges.append({"from": f"n{a}", "to": f"n{b}"})
    data: dict[str, Any] = {"computers": computers, "nodes": nodes, "edges": edges}
    if links:
        data["links"] = links
    if use_medium:
        data["media"] = [{"name": "air", "bandwidth_kBps": rng.choice([3, 6, 20])}]
    return data


def fleet_instance(n_nodes: int, n_computers: int, *, seed: int = 0, continuous: bool = True,
                   offload_only: bool = True, stacks: int | None = None,
                   server_capacity: tuple[int, int] | None = None) -> dict[str, Any]:
    """A fleet: robots running the paper's robot stack sharing a few servers over one wifi.

    ``n_computers`` computers, one in ten a server (at least one). Every robot runs one
    stack of the six robot nodes (environment, model, planner, amcl, navigation,
    youbot_core; fewer stacks when ``n_nodes`` is too small); ``youbot_core<s>`` stays on
    its robot, and with ``offload_only`` the other five may run on their robot or on any
    server (FogROS2-like offloading), otherwise on any computer. The rest of ``n_nodes``
    are one ``experiment`` node on the first server and camera ``tracker<k>`` nodes on the
    servers, each feeding one stack's environment. Robots (capacity 60-160) reach the
    first server over one shared wifi (every robot's link on it); the other servers hang off
    the first by Ethernet. Server capacities are drawn so that the trackers at mid settings
    plus some offloaded robot nodes fill them: server CPU binds. Weights are Table I's
    times a factor in [1/2, 2] per node kind (seeded), renormalised to sum 1.

    ``stacks`` (more stacks than robots: round robin over the robots) and
    ``server_capacity`` (each server's a random integer in that range) reproduce the
    earlier benchmark fleet: ``stacks=(n_nodes - 1) // 6, server_capacity=(400, 1600),
    offload_only=False``."""
    if n_computers < 2 or n_nodes < 7:
        raise ValueError("a fleet needs at least 2 computers and 7 nodes")
    rng = random.Random(seed)
    n_servers = max(1, n_computers // 10)
    n_robots = n_computers - n_servers
    servers = [f"server{k}" for k in range(1, n_servers + 1)]
    robots = [f"robot{r}" for r in range(1, n_robots + 1)]
    stacks = min(n_robots, (n_nodes - 1) // 6) if stacks is None else min(stacks, (n_nodes - 1) // 6)
    trackers = n_nodes - 1 - 6 * stacks
    weights = {kind: v[0] * rng.uniform(0.5, 2.0) for kind, v in TABLE_I.items()}
    nodes: list[dict[str, Any]] = [_node("experiment", "experiment", weights["experiment"], continuous=continuous,
                                         residence=[servers[0]])]
    for k in range(1, trackers + 1):
        nodes.append(_node("tracker", f"tracker{k}", weights["tracker"], continuous=continuous, residence=servers))
    edges: list[dict[str, Any]] = []
    for s in range(1, stacks + 1):
        robot = robots[(s - 1) % n_robots]
        for kind in ROBOT_NODES:
            extra: dict[str, Any] = {}
            if kind == "youbot_core":
                extra["residence"] = [robot]
            elif offload_only:
                extra["residence"] = [robot, *servers]
            if kind == "planner":
                extra["coresidence"] = [f"navigation{s}"]
            nodes.append(_node(kind, f"{kind}{s}", weights[kind], continuous=continuous, **extra))
        edges += stack_edges(s)
        if trackers:
            edges.append({"from": f"tracker{1 + (s - 1) % trackers}", "to": f"environment{s}"})
    total = sum(n["weight"] for n in nodes)
    for n in nodes:
        n["weight"] /= total
    computers = [{"name": r, "kind": "robot", "capacity": rng.randint(60, 160)} for r in robots]
    per_server_trackers = trackers / n_servers
    per_server_stacks = stacks / n_servers
    for name in servers:
        if server_capacity is not None:
            cap = float(rng.randint(*server_capacity))
        else:
            cap = per_server_trackers * rng.uniform(110, 170) + per_server_stacks * rng.uniform(20, 80) + 20
        computers.append({"name": name, "kind": "server", "capacity": int(round(cap))})
    links = [{"between": [r, servers[0]], "bandwidth_kBps": WIFI_kBps, "medium": "wifi"} for r in robots]
    links += [{"between": [servers[0], s], "bandwidth_kBps": 125000.0} for s in servers[1:]]
    return {"cpu_unit": "100 = one robot on-board computer (1.6 GHz dual-core Atom)", "computers": computers,
            "links": links, "media": [{"name": "wifi", "bandwidth_kBps": WIFI_kBps}], "nodes": nodes, "edges": edges}


#: the camera and detector :func:`wifi_fleet_instance` adds per robot: settings
#: ``(value, cpu, performance, frequency_hz, bandwidth_kBps)``. The camera streams 2.3 MB/s
#: of images to the detector; the detector may run on its robot or on a server.
CAMERA_SETTING = (None, 5, 100, 30, 2300.0)
DETECTOR_SETTINGS = ((5, 30, 50, 5, 1.0), (10, 50, 80, 10, 1.0), (15, 70, 100, 15, 1.0))
AP_kBps = 9000.0  # one access point: three 2.3 MB/s camera streams fit, four do not


#: ``wifi_fleet_instance(driven=True)``: the camera's rate is a knob (value = Hz, CPU,
#: performance; 76.7 kB per image: 2.3 MB/s at 30 Hz) and the detector follows it
#: (system.yaml ``input:``): per own setting (value, base CPU, CPU per frame per second,
#: performance)
CAMERA_RATES = ((10, 3.0, 60), (20, 4.0, 85), (30, 5.0, 100))
CAMERA_FRAME_BYTES = 2300.0 * 1000 / 30
DRIVEN_DETECTOR = ((1.4, 2.0, 1.0, 50), (1.2, 2.0, 1.8, 80), (1.05, 2.0, 2.4, 100))


def wifi_fleet_instance(n_robots: int = 90, n_servers: int = 10, *, robots_per_ap: int = 9,
                        ap_kBps: float = AP_kBps, seed: int = 0, continuous: bool = True,
                        trackers: int | None = None, driven: bool = False) -> dict[str, Any]:
    """A fleet whose network binds: :func:`fleet_instance` with ``n_robots + n_servers``
    computers (one stack per robot, the rest of 1,000 nodes per 100 computers camera
    trackers; or ``trackers`` of them) plus, per robot, a ``camera<r>`` (on its robot, 2.3 MB/s) feeding a
    ``detector<r>`` (on its robot or any server) that feeds ``environment<r>``. The robots'
    links to the first server are grouped ``robots_per_ap`` at a time on access points
    ``ap<j>`` (shared media) of ``ap_kBps`` each, so at most ``ap_kBps // 2300`` of an access
    point's detectors can be offloaded. ``wifi_fleet_instance()`` (90 robots, 10 servers)
    has 1,180 nodes on 100 computers. With ``driven``, each camera's rate is a knob
    (:data:`CAMERA_RATES`) and its detector follows it (:data:`DRIVEN_DETECTOR`): a lower
    rate frees the access point and the detector's CPU wherever it runs."""
    if n_robots < 1 or n_servers < 1 or robots_per_ap < 1:
        raise ValueError("a wifi fleet needs at least one robot, one server and one robot per access point")
    n_computers = n_robots + n_servers
    if max(1, n_computers // 10) != n_servers:
        raise ValueError("fleet_instance makes one computer in ten a server: n_servers must be (robots+servers)//10")
    n_nodes = 10 * n_computers if trackers is None else 1 + 6 * n_robots + trackers
    data = fleet_instance(n_nodes, n_computers, seed=seed, continuous=continuous)
    rng = random.Random(seed + 1)
    servers = [c["name"] for c in data["computers"] if c["kind"] == "server"]
    robots = [c["name"] for c in data["computers"] if c["kind"] == "robot"]
    # weighted like a tracker (a detector) and an environment node (a camera) of this fleet
    weight = {n["name"]: n["weight"] for n in data["nodes"]}
    w_detector, w_camera = weight["amcl1"] * rng.uniform(0.5, 2.0), weight["environment1"]
    for r, robot in enumerate(robots, start=1):
        camera = {"name": f"camera{r}", "weight": w_camera, "residence": [robot], "topics": [f"/camera{r}/out"],
                  "settings": [{"cpu": CAMERA_SETTING[1], "performance": CAMERA_SETTING[2],
                                "frequency_hz": CAMERA_SETTING[3], "bandwidth_kBps": CAMERA_SETTING[4]}]}
        detector = {"name": f"detector{r}", "weight": w_detector, "residence": [robot, *servers],
                    "parameter": {"name": "rate", "unit": "Hz"}, "topics": [f"/detector{r}/out"],
                    "settings": [{"value": v, "cpu": c, "performance": p, "frequency_hz": f, "bandwidth_kBps": b}
                                 for v, c, p, f, b in DETECTOR_SETTINGS]}
        if driven:
            camera = {**camera, "parameter": {"name": "rate", "unit": "Hz"},
                      "settings": [{"value": f, "cpu": c, "performance": p, "frequency_hz": f,
                                    "bandwidth_kBps": CAMERA_FRAME_BYTES * f / 1000} for f, c, p in CAMERA_RATES]}
            detector = {**detector, "input": f"/camera{r}/out", "parameter": {"name": "scale0"},
                        "settings": [{"value": v, "cpu": c, "cpu_per_hz": k, "performance": p, "bytes_per_msg": 100.0}
                                     for v, c, k, p in DRIVEN_DETECTOR]}
        data["nodes"] += [camera, detector]
        data["edges"] += [{"from": f"camera{r}", "to": f"detector{r}"},
                          {"from": f"detector{r}", "to": f"environment{r}"}]
    total = sum(n["weight"] for n in data["nodes"])
    for n in data["nodes"]:
        n["weight"] /= total
    ap_of = {robot: f"ap{i // robots_per_ap + 1}" for i, robot in enumerate(robots)}
    for link in data["links"]:
        robot = next((c for c in link["between"] if c in ap_of), None)
        if robot is not None:
            link["medium"] = ap_of[robot]
            link["bandwidth_kBps"] = ap_kBps
    data["media"] = [{"name": ap, "bandwidth_kBps": ap_kBps}
                     for ap in sorted(set(ap_of.values()), key=lambda a: int(a[2:]))]
    return data
