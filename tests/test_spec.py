"""system.yaml loading: valid files load, every kind of mistake names file, node and field."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest
import yaml

from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.system.systemfile import load_system, parse_system

BASE = {
    "cpu_unit": "100 = one robot",
    "computers": [
        {"name": "robot1", "kind": "robot", "capacity": 100},
        {"name": "server", "kind": "server", "capacity": 400},
    ],
    "links": [{"between": ["robot1", "server"], "bandwidth_kBps": 37500, "medium": "wifi"}],
    "media": [{"name": "wifi", "bandwidth_kBps": 37500}],
    "nodes": [
        {"name": "tracker1", "weight": 0.5, "residence": ["server"],
         "parameter": {"name": "output_freq", "unit": "Hz"}, "topics": ["/tracker1/tracks"],
         "settings": [{"value": 10, "cpu": 80, "performance": 40, "frequency_hz": 10, "bandwidth_kBps": 1.0},
                      {"value": 25, "cpu": 200, "performance": 100, "frequency_hz": 25, "bandwidth_kBps": 2.5}]},
        {"name": "nav", "weight": 0.25, "coresidence": ["planner"],
         "curve": {"form": "log", "coef": [129.12, 188.36], "cpu": [25, 50]}},
        {"name": "planner", "weight": 0.25, "settings": [{"cpu": 1, "performance": 100}]},
    ],
    "edges": [{"from": "tracker1", "to": "nav"}],
}


def write(tmp_path: Path, data: object) -> Path:
    p = tmp_path / "system.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_valid_system_loads(tmp_path: Path) -> None:
    s = load_system(write(tmp_path, BASE))
    assert [c.name for c in s.computers] == ["robot1", "server"]
    assert s.node["nav"].curve is not None
    assert math.isclose(s.node["nav"].curve(50), 129.12 * math.log(0.5) + 188.36)
    assert s.allowed("tracker1") == ("server",)
    assert ("nav", "planner") in s.coresidence_groups
    assert s.route("robot1", "server") == (0,)
    choices = s.node["nav"].choices()
    assert [c.cpu for c in choices] == list(range(25, 51))
    assert s.node["tracker1"].choices()[1].performance == 100


def mutate(path: str, value: object) -> dict:
    data = yaml.safe_load(yaml.safe_dump(BASE))
    *parents, last = path.split(".")
    cur = data
    for key in parents:
        cur = cur[int(key)] if key.isdigit() else cur[key]
    if value is KeyError:
        del cur[int(last) if last.isdigit() else last]
    elif last.isdigit():
        cur[int(last)] = value
    else:
        cur[last] = value
    return data


@pytest.mark.parametrize(
    ("path", "value", "expected"),
    [
        ("nodes.0.settings.0.cpu", 0, "node 'tracker1': settings[0].cpu: must be > 0"),
        ("nodes.0.weight", -1, "node 'tracker1': weight: must be > 0"),
        ("nodes.0.residence", ["mars"], "node 'tracker1': residence: unknown computer 'mars'"),
        ("nodes.1.coresidence", ["ghost"], "node 'nav': coresidence: unknown node 'ghost'"),
        ("nodes.0.colour", "red", "unknown key(s) 'colour'"),
        ("nodes.1.curve", {"form": "exp", "coef": [1, 2], "cpu": [1, 2]}, "unknown form 'exp'"),
        ("nodes.1.curve", {"form": "log", "coef": [1], "cpu": [1, 2]}, "takes 2 coefficients"),
        ("computers.0.kind", "laptop", "computer 'robot1': kind: must be 'robot' or 'server'"),
        ("links.0.between", ["robot1", "moon"], "unknown computer 'moon'"),
        ("edges.0.to", "nobody", "unknown node 'nobody'"),
        ("nodes.2.settings", KeyError, "node 'planner': needs settings"),
        ("nodes.0.process", "(", "not a valid regular expression"),
    ],
)
def test_errors_name_file_node_and_field(tmp_path: Path, path: str, value: object, expected: str) -> None:
    p = write(tmp_path, mutate(path, value))
    with pytest.raises(InputError) as info:
        load_system(p)
    assert str(info.value).startswith(str(p))
    assert expected in str(info.value)


def test_coresident_nodes_without_common_computer(tmp_path: Path) -> None:
    data = mutate("nodes.2.residence", ["robot1"])
    data["nodes"][1]["residence"] = ["server"]
    with pytest.raises(InputError, match="no computer allowed for all of them"):
        load_system(write(tmp_path, data))


def test_weights_normalised_with_warning() -> None:
    data = mutate("nodes.0.weight", 1.5)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = parse_system(data)
    assert any(issubclass(w.category, PerfrosWarning) and "normalised" in str(w.message) for w in caught)
    assert math.isclose(sum(n.weight for n in s.nodes), 1.0)
    assert math.isclose(s.node["tracker1"].weight, 1.5 / 2.0)


def test_bad_yaml_and_missing_file(tmp_path: Path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("nodes: [\n  - {name: a\n")
    with pytest.raises(InputError, match=r"bad.yaml: invalid YAML at line"):
        load_system(p)
    with pytest.raises(InputError, match="file not found"):
        load_system(tmp_path / "nope.yaml")
    (tmp_path / "empty.yaml").write_text("")
    with pytest.raises(InputError, match="empty"):
        load_system(tmp_path / "empty.yaml")


def test_yaml_is_data_not_code(tmp_path: Path) -> None:
    p = tmp_path / "evil.yaml"
    p.write_text("computers: !!python/object/apply:os.system ['echo pwned']\nnodes: []\n")
    with pytest.raises(InputError, match="invalid YAML"):
        load_system(p)


def test_atomic_outputs_get_normal_permissions(tmp_path: Path) -> None:
    import os

    from perfros_bag.fileio import atomic_write_text

    umask = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "out.txt", "x")
    finally:
        os.umask(umask)
    assert (tmp_path / "out.txt").stat().st_mode & 0o777 == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
