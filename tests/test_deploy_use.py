"""deploy.json's ``links_measured`` and ``media_measured`` (perfros_bag/sweep/deploy.py) from two
readings of qdisc counters, without ROS or privileges: each row against the arithmetic done
here from the counters and the system's bandwidths."""

from __future__ import annotations

from typing import Any

from perfros_bag.rosrun.network import Network
from perfros_bag.sweep.deploy import _link_use, _medium_use
from perfros_bag.system.types import Computer, Link, Medium, System

SYSTEM = System((Computer("robot1", "robot", 100.0), Computer("server", "server", 400.0),
                 Computer("robot2", "robot", 100.0)), (),
                (Link(("robot1", "server"), 500.0, "wifi"), Link(("server", "robot2"), 250.0, "wifi")),
                (Medium("wifi", 600.0), Medium("spare", 100.0)))


def _reading(t: float, n: int, **key: Any) -> dict[str, Any]:
    return {**key, "bytes": 1000 * n, "packets": n, "drops": n // 7, "overlimits": n // 3, "t": t}


def test_rows_are_the_counters_differences_over_the_seconds_between_the_readings() -> None:
    net = Network("u1", SYSTEM)
    ends = [("robot1", "server", 0), ("server", "robot1", 0), ("server", "robot2", 1), ("robot2", "server", 1)]
    before = [_reading(10.0, 100 * k, link=li, **{"from": a, "to": b}) for k, (a, b, li) in enumerate(ends)]
    after = [_reading(12.5, 100 * k + 50 * (k + 1), link=li, **{"from": a, "to": b})
             for k, (a, b, li) in enumerate(ends)]
    rows = _link_use(before, after, net)
    assert [(r["link"], r["from"], r["to"]) for r in rows] == [(li, a, b) for a, b, li in ends]
    for k, (row, b0, b1) in enumerate(zip(rows, before, after, strict=True)):
        shaped = SYSTEM.links[b0["link"]].bandwidth_kBps
        assert row["sent_kBps"] == round(50 * (k + 1) * 1000 / 1000 / 2.5, 3)
        assert row["shaped_kBps"] == shaped and row["utilisation"] == round(row["sent_kBps"] / shaped, 4)
        assert row["drops"] == b1["drops"] - b0["drops"] and row["overlimits"] == b1["overlimits"] - b0["overlimits"]

    m0 = [_reading(3.0, 40, medium="wifi", hub="server", interface="pfr-m0")]
    m1 = [_reading(7.0, 440, medium="wifi", hub="server", interface="pfr-m0")]
    [row] = _medium_use(m0, m1, net)
    assert row == {"medium": "wifi", "hub": "server", "sent_kBps": 100.0, "shaped_kBps": 600.0,
                   "utilisation": round(100.0 / 600.0, 4), "drops": 440 // 7 - 40 // 7,
                   "overlimits": 440 // 3 - 40 // 3}
    assert _medium_use([], m1, net) == []  # a medium read only once has no row
