"""Computers as network namespaces joined by tc-shaped links (perfros_bag/rosrun/network.py).

The plan (addresses, routes) is checked without privileges against an independent
simulation of IP forwarding. The tests marked ``net`` make real namespaces (root, as on
CI): the addresses and routes the kernel holds (``ip -j``) against the plan, a TCP stream
across two links, the shaped rate measured by a receiver in another namespace against the
link's bandwidth and an unshaped control, and nothing left - no namespace, no process in one,
no interface on the host - after success, an exception, and SIGINT to the process that made
them. Shared media: which computer hosts a medium's queue, checked against a brute-force
search, and (``net``) concurrent TCP streams whose aggregate rate, measured by the receivers,
is capped at the medium's bandwidth, against a control whose medium is wider than its links.
Where namespaces cannot be made here, each test asserts that the fallback is reported.
"""

from __future__ import annotations

import ipaddress
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
import warnings
from collections import deque
from pathlib import Path

import psutil
import pytest

from perfros_bag.errors import PerfrosWarning
from perfros_bag.rosrun.network import (
    SUBNET,
    Network,
    leftover_namespaces,
    plan_ends,
    plan_media,
    plan_routes,
    remove_leftover_namespaces,
)
from perfros_bag.system.types import Computer, Link, Medium, System

ROOT = Path(__file__).resolve().parent.parent
NETNS_DIR = Path("/run/netns")

RECEIVER = r"""
import json, socket, sys, time
srv = socket.socket()
srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
srv.bind((sys.argv[1], int(sys.argv[2])))
srv.listen(1)
srv.settimeout(10)
print("ready", flush=True)
conn, peer = srv.accept()
conn.settimeout(10)
got, first, first_len, last = 0, None, 0, None
while True:
    chunk = conn.recv(65536)
    if not chunk:
        break
    now = time.monotonic()
    if first is None:
        first, first_len = now, len(chunk)
    got += len(chunk)
    last = now
print(json.dumps({"bytes": got, "after_first": got - first_len, "seconds": last - first, "peer": peer[0],
                  "first": first, "last": last}))
"""

SENDER = r"""
import socket, sys
s = socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=10)
s.sendall(b"x" * int(sys.argv[3]))
s.close()
"""


def chain(bandwidths: tuple[float, ...] = (500.0, 2000.0), lonely: bool = False) -> System:
    """robot1 - server - robot2 (- robot3 ...), plus a computer without links if ``lonely``."""
    names = ["robot1", "server"] + [f"robot{k}" for k in range(2, len(bandwidths) + 1)]
    computers = [Computer(n, "server" if n == "server" else "robot", 100.0) for n in names]
    if lonely:
        computers.append(Computer("lonely", "robot", 100.0))
    links = tuple(Link((a, b), bw) for a, b, bw in zip(names, names[1:], bandwidths, strict=False))
    return System(tuple(computers), (), links)


def with_medium(system: System, bandwidth_kBps: float, links: tuple[int, ...], name: str = "wifi") -> System:
    """``system`` with its ``links`` on one shared medium."""
    on = tuple(Link(li.between, li.bandwidth_kBps, name if i in links else li.medium)
               for i, li in enumerate(system.links))
    return System(system.computers, system.nodes, on, (*system.media, Medium(name, bandwidth_kBps)))


def triangle_with_tail() -> System:
    comps = tuple(Computer(n, "robot", 100.0) for n in ("a", "b", "c", "d", "e"))
    links = (Link(("a", "b"), 100.0), Link(("b", "c"), 100.0), Link(("c", "a"), 100.0),
             Link(("c", "d"), 100.0), Link(("d", "e"), 100.0))
    return System(comps, (), links)


def _run_id() -> str:
    return "t" + uuid.uuid4().hex[:8]


# ---- the plan, without privileges ------------------------------------------------------------
@pytest.mark.parametrize("system", [chain(lonely=True), chain((1.0, 2.0, 3.0, 4.0)), triangle_with_tail()])
def test_planned_addresses_and_routes_reach_exactly_the_connected_computers(system: System) -> None:
    ends = plan_ends(system)
    assert len(ends) == 2 * len(system.links)
    addresses = [e.address.ip for e in ends]
    assert len(set(addresses)) == len(addresses)
    for i, link in enumerate(system.links):
        a, b = (e for e in ends if e.link == i)
        assert (a.computer, b.computer) == link.between
        assert a.address.network == b.address.network and a.address.network.subnet_of(SUBNET)
        assert a.peer == b.address.ip and b.peer == a.address.ip
    assert len({e.address.network for e in ends}) == len(system.links)

    # forward hop by hop through the planned tables (connected /30s, then /32 routes)
    routes = plan_routes(system, ends)
    owner = {e.address.ip: e.computer for e in ends}

    def deliver(src: str, dst: ipaddress.IPv4Address) -> str | None:
        at, hops = src, 0
        while owner[dst] != at and hops <= len(system.computers):
            mine = [e for e in ends if e.computer == at]
            on_link = [e for e in mine if dst in e.address.network]
            if on_link:
                at = owner[dst]
                break
            via = [r for r in routes[at] if r.destination == dst]
            if not via:
                return None
            assert any(r.ifname == e.ifname and r.via in e.address.network for e in mine for r in via)
            at, hops = owner[via[0].via], hops + 1
        return at if owner[dst] == at else None

    # independent reachability: breadth-first over the links
    def reachable(src: str) -> set[str]:
        seen, queue = {src}, deque([src])
        while queue:
            cur = queue.popleft()
            for link in system.links:
                if cur in link.between:
                    nxt = link.between[1] if link.between[0] == cur else link.between[0]
                    if nxt not in seen:
                        seen.add(nxt)
                        queue.append(nxt)
        return seen

    for comp in system.computers:
        for dst in addresses:
            if owner[dst] == comp.name:
                continue
            expected = owner[dst] if owner[dst] in reachable(comp.name) else None
            assert deliver(comp.name, dst) == expected, (comp.name, dst)


def star(media_links: tuple[tuple[int, ...], ...]) -> System:
    """A server with three robots, a link robot1 - robot2, two parallel links robot3 - server,
    and one medium per entry of ``media_links`` (plus one no link names)."""
    comps = (Computer("robot1", "robot", 100.0), Computer("server", "server", 400.0),
             Computer("robot2", "robot", 100.0), Computer("robot3", "robot", 100.0))
    pairs = [("robot1", "server"), ("server", "robot2"), ("robot3", "server"), ("robot1", "robot2"),
             ("server", "robot3")]
    name = {li: f"m{k}" for k, group in enumerate(media_links) for li in group}
    links = tuple(Link(p, 100.0, name.get(i)) for i, p in enumerate(pairs))
    media = tuple(Medium(f"m{k}", 50.0) for k in range(len(media_links))) + (Medium("unused", 10.0),)
    return System(comps, (), links, media)


@pytest.mark.parametrize("media_links", [((0, 1, 2),), ((0, 3), (1,)), ((3,), (2, 4)), ((0, 4), (1,), (2,))])
def test_each_medium_is_hosted_by_the_computer_all_its_links_share(media_links: tuple[tuple[int, ...], ...]) -> None:
    system = star(media_links)
    plans = plan_media(system)
    assert [p.name for p in plans] == [m.name for m in system.media]
    assert [p.ifname for p in plans] == [f"pfr-m{j}" for j in range(len(system.media))]
    degree = {c.name: sum(c.name in li.between for li in system.links) for c in system.computers}
    for plan, group in zip(plans, (*media_links, ()), strict=True):
        assert plan.links == group
        # brute force: every computer that is an end of every link of the medium
        shared = [c.name for c in system.computers if group and all(c.name in system.links[i].between for i in group)]
        if not shared:
            assert plan.hub is None and not plan.emulated and plan.reason
            continue
        best = max(degree[c] for c in shared)
        first = [c for c in shared if degree[c] == best]
        servers = [c for c in first if system.computer[c].kind == "server"]
        assert plan.emulated and plan.hub == (servers or first)[0]


def _fake_ip(tmp_path: Path) -> str:
    fake = tmp_path / "ip"
    fake.write_text("#!/bin/sh\necho 'mount --make-shared /run/netns failed: Operation not permitted' >&2\nexit 1\n")
    fake.chmod(0o755)
    return str(fake)


def test_namespaces_refused_fall_back_to_unshaped_with_a_warning(tmp_path: Path) -> None:
    net = Network(_run_id(), chain(), ip=_fake_ip(tmp_path))
    with pytest.warns(PerfrosWarning, match="UNSHAPED"):
        net.create()
    assert not net.emulated and "Operation not permitted" in net.reason
    assert net.wrap("robot1", ["/bin/true"]) == ["/bin/true"]
    assert net.address("robot1") == "127.0.0.1"
    assert net.ros_addresses("robot1", "server", 11311) == {"ROS_IP": "127.0.0.1",
                                                           "ROS_MASTER_URI": "http://127.0.0.1:11311"}
    assert net.describe()["mode"] == "unshaped"
    assert net.describe()["media"] == [] and net.media_stats() == []
    assert net.remove() == []


def test_missing_iproute2_falls_back_with_a_warning() -> None:
    net = Network(_run_id(), chain(), ip="/nonexistent/ip")
    with pytest.warns(PerfrosWarning, match="iproute2"):
        net.create()
    assert not net.emulated and net.namespaces == {}


def test_a_system_without_links_has_nothing_to_emulate() -> None:
    net = Network(_run_id(), System((Computer("r", "robot", 100.0),), ()))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        net.create()
    assert not net.emulated and "no links" in net.reason


# ---- real namespaces (root) --------------------------------------------------------------------
def _create(net: Network, *, shaped: bool = True) -> bool:
    """Create; True when namespaces were made. Otherwise the fallback must have said why."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        net.create(shaped=shaped)
    if net.emulated:
        return True
    assert net.reason, "an unshaped network must say why"
    assert any("UNSHAPED" in str(w.message) for w in caught), [str(w.message) for w in caught]
    assert leftover_namespaces(net.run_id) == []
    return False


def _ip_json(*args: str) -> list[dict[str, object]]:
    done = subprocess.run(["ip", "-j", *args], capture_output=True, text=True, timeout=10, check=True)
    return json.loads(done.stdout or "[]")  # type: ignore[no-any-return]


def _host_state() -> tuple[list[str], str]:
    if shutil.which("ip") is None:  # no iproute2: the network falls back (asserted by _create)
        return [], ""
    links = sorted(str(x["ifname"]) for x in _ip_json("link", "show"))
    routes = subprocess.run(["ip", "route", "show", "table", "all"], capture_output=True, text=True,
                            timeout=10).stdout
    return links, routes


def _ns_inodes(net: Network) -> set[int]:
    return {os.stat(NETNS_DIR / ns).st_ino for ns in net.namespaces.values() if (NETNS_DIR / ns).exists()}


def _processes_in(inodes: set[int]) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if os.stat(entry / "ns" / "net").st_ino in inodes:
                    found.append(int(entry.name))
            except OSError:
                continue
    return found


def _nothing_left(run_id: str, inodes: set[int], host_before: tuple[list[str], str]) -> None:
    assert leftover_namespaces(run_id) == []
    assert _processes_in(inodes) == [], "a process still holds a namespace of the run"
    links, routes = _host_state()
    assert not any(name.startswith("pfr") for name in links), links
    assert (links, routes) == host_before


@pytest.mark.net
def test_namespaces_hold_the_planned_addresses_and_routes_only() -> None:
    system = chain((500.0, 2000.0), lonely=True)
    before = _host_state()
    with Network(_run_id(), system) as net:
        if not _create(net):
            return
        inodes = _ns_inodes(net)
        assert len(inodes) == len(system.computers)
        assert set(net.namespaces) == {c.name for c in system.computers}
        for comp, ns in net.namespaces.items():
            mine = {e.ifname: e for e in net.ends if e.computer == comp}
            held = {str(x["ifname"]): x for x in _ip_json("-n", ns, "addr", "show")}
            assert set(held) == {"lo", *mine}
            assert "UP" in held["lo"]["flags"]  # type: ignore[operator]
            for ifname, end in mine.items():
                addrs = [(a["family"], a["local"], a["prefixlen"]) for a in held[ifname]["addr_info"]]  # type: ignore[union-attr]
                assert addrs == [("inet", str(end.address.ip), 30)], (comp, ifname, addrs)  # IPv6 off
            # routes: the connected /30s and the planned /32s, all inside the run's /16
            table = _ip_json("-n", ns, "route", "show")
            assert all(r["dst"] != "default" for r in table)
            dests = {ipaddress.ip_network(str(r["dst"])) for r in table}
            assert all(d.subnet_of(SUBNET) for d in dests), dests
            assert dests == ({e.address.network for e in mine.values()}
                             | {ipaddress.ip_network(f"{r.destination}/32") for r in net.routes[comp]})
            for r in table:
                if str(r["dst"]).count(".") == 3 and "/" not in str(r["dst"]):
                    assert any(str(p.via) == r["gateway"] and p.ifname == r["dev"] for p in net.routes[comp])
            # nothing else is reachable: the kernel has no route to an outside address
            outside = subprocess.run(["ip", "-n", ns, "route", "get", "192.0.2.1"], capture_output=True, text=True,
                                     timeout=10)
            assert outside.returncode != 0 and "unreachable" in outside.stderr.lower()
        assert net.routes["robot1"] and net.address("lonely") == "127.0.0.1"
        assert net.ros_addresses("robot1", "robot2", 11311) == {
            "ROS_IP": net.address("robot1"), "ROS_MASTER_URI": f"http://{net.address('robot2')}:11311"}

        # two links away: robot1 -> robot2 through the server, seen on the server's counters
        server = net.namespaces["server"]
        rx0 = {str(x["ifname"]): x["stats64"]["rx"]["bytes"] for x in _ip_json("-s", "-n", server, "link")}  # type: ignore[index]
        got = _transfer(net, "robot1", "robot2", 50_000)
        assert got["bytes"] == 50_000 and got["peer"] == net.address("robot1")
        rx1 = {str(x["ifname"]): x["stats64"]["rx"]["bytes"] for x in _ip_json("-s", "-n", server, "link")}  # type: ignore[index]
        assert rx1["pfr-l0"] - rx0["pfr-l0"] >= 50_000  # robot1's data in on link 0 ...
        assert rx1["pfr-l1"] > rx0["pfr-l1"]  # ... and robot2's acknowledgements in on link 1
    _nothing_left(net.run_id, inodes, before)


def _transfer(net: Network, src: str, dst: str, size: int, port: int = 5001) -> dict[str, float | str]:
    """``size`` bytes over TCP from a sender on ``src`` to a receiver on ``dst``."""
    recv = subprocess.Popen(net.wrap(dst, [sys.executable, "-c", RECEIVER, net.address(dst), str(port)]),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert recv.stdout is not None
        assert recv.stdout.readline().strip() == "ready"
        subprocess.run(net.wrap(src, [sys.executable, "-c", SENDER, net.address(dst), str(port), str(size)]),
                       check=True, timeout=15, capture_output=True)
        out, err = recv.communicate(timeout=15)
        assert recv.returncode == 0, err
    finally:
        if recv.poll() is None:
            recv.kill()
            recv.wait()
    return json.loads(out)  # type: ignore[no-any-return]


def _transfers(net: Network, flows: list[tuple[str, str]], size: int) -> list[dict[str, float | str]]:
    """``size`` bytes over TCP on each ``(src, dst)`` flow, all at the same time (one receiver
    per flow, ports 5001...); each receiver's result, in ``flows`` order."""
    recvs: list[subprocess.Popen[str]] = []
    senders: list[subprocess.Popen[bytes]] = []
    try:
        for k, (_, dst) in enumerate(flows):
            recvs.append(subprocess.Popen(net.wrap(dst, [sys.executable, "-c", RECEIVER, net.address(dst),
                                                         str(5001 + k)]),
                                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        for recv in recvs:
            assert recv.stdout is not None
            assert recv.stdout.readline().strip() == "ready"
        for k, (src, dst) in enumerate(flows):
            senders.append(subprocess.Popen(net.wrap(src, [sys.executable, "-c", SENDER, net.address(dst),
                                                           str(5001 + k), str(size)]),
                                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
        for sender in senders:
            _, err = sender.communicate(timeout=30)
            assert sender.returncode == 0, err
        results = []
        for recv in recvs:
            out, err = recv.communicate(timeout=30)
            assert recv.returncode == 0, err
            results.append(json.loads(out))
        return results
    finally:
        for proc in [*recvs, *senders]:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def _tc_json(net: Network, comp: str, *args: str) -> list[dict[str, object]]:
    done = subprocess.run(["tc", "-j", "-n", net.namespaces[comp], *args], capture_output=True, text=True,
                          timeout=10, check=True)
    return json.loads(done.stdout or "[]")  # type: ignore[no-any-return]


def _ifb_in(ns: str) -> list[str]:
    """The IFB devices inside namespace ``ns``."""
    return sorted(str(x["ifname"]) for x in _ip_json("-n", ns, "-d", "link", "show", "type", "ifb"))


def _tbf_sent_bytes(net: Network, comp: str, ifname: str) -> int:
    done = subprocess.run(["tc", "-j", "-s", "-n", net.namespaces[comp], "qdisc", "show", "dev", ifname],
                          capture_output=True, text=True, timeout=10, check=True)
    return sum(int(q["bytes"]) for q in json.loads(done.stdout) if q["kind"] == "tbf")


@pytest.mark.net
def test_links_are_shaped_to_their_bandwidth_in_both_directions() -> None:
    # 1 MB: a TCP retransmission timeout (seen in ~1 of 4 400 kB transfers here, ~0.3 s) costs
    # ~13 % of the rate, not the ~30 % that failed the 25 % bound
    rate_kBps, size = 500.0, 1_000_000
    system = System((Computer("robot1", "robot", 100.0), Computer("server", "server", 400.0)), (),
                    (Link(("robot1", "server"), rate_kBps),))
    before = _host_state()
    with Network(_run_id(), system) as net:
        if not _create(net, shaped=False):
            return
        inodes = _ns_inodes(net)
        control = _transfer(net, "robot1", "server", size)
        control_kBps = float(control["after_first"]) / max(float(control["seconds"]), 1e-6) / 1000
        net.apply()
        for src, dst in (("robot1", "server"), ("server", "robot1")):
            sent0 = _tbf_sent_bytes(net, src, "pfr-l0")
            got = _transfer(net, src, dst, size)
            assert got["bytes"] == size and got["peer"] == net.address(src)
            measured_kBps = float(got["after_first"]) / float(got["seconds"]) / 1000
            # tbf counts whole frames: TCP payload is ~96 % of the rate
            assert abs(measured_kBps / rate_kBps - 1) < 0.25, (src, dst, measured_kBps)
            assert measured_kBps < control_kBps / 4, (measured_kBps, control_kBps)
            assert _tbf_sent_bytes(net, src, "pfr-l0") - sent0 >= size  # it went through the qdisc
    _nothing_left(net.run_id, inodes, before)


@pytest.mark.net
def test_an_exception_removes_everything_and_kills_what_runs_inside() -> None:
    before = _host_state()
    net = Network(_run_id(), with_medium(chain((100.0, 100.0, 100.0)), 150.0, (0, 1)))
    sleeper: subprocess.Popen[bytes] | None = None
    inodes: set[int] = set()
    with pytest.raises(RuntimeError, match="boom"), net:
        if not _create(net):
            raise RuntimeError("boom (unshaped)")
        inodes = _ns_inodes(net)
        assert _ifb_in(net.namespaces["server"]) == ["pfr-m0"]
        sleeper = subprocess.Popen(net.wrap("server", ["sleep", "60"]))
        deadline = time.monotonic() + 5
        while not _processes_in(inodes) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _processes_in(inodes) == [sleeper.pid]
        raise RuntimeError("boom")
    if sleeper is not None:
        assert sleeper.wait(5) == -signal.SIGKILL
        assert net.killed == [sleeper.pid]
    _nothing_left(net.run_id, inodes, before)


CHILD = r"""
import os, subprocess, sys, time, warnings
from perfros_bag.rosrun.network import Network
from perfros_bag.system.types import Computer, Link, Medium, System
system = System((Computer("robot1", "robot", 100.0), Computer("server", "server", 400.0),
                 Computer("robot2", "robot", 100.0)), (),
                (Link(("robot1", "server"), 500.0, "wifi"), Link(("server", "robot2"), 500.0, "wifi")),
                (Medium("wifi", 800.0),))
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    with Network(sys.argv[1], system) as net:
        net.create()
        sleeper = subprocess.Popen(net.wrap("robot2", ["sleep", "60"]), stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL)
        if net.emulated:  # "ready" once the sleeper has entered robot2 (ip netns exec joins it after fork)
            inode = os.stat("/run/netns/" + net.namespaces["robot2"]).st_ino
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                try:
                    if os.stat(f"/proc/{sleeper.pid}/ns/net").st_ino == inode:
                        break
                except OSError:
                    pass
                time.sleep(0.02)
        media = net.describe()["media"]
        hub = "hub" if media and media[0]["emulated"] else "nohub"
        print(("ready " if net.emulated else "unshaped ") + str(sleeper.pid) + " " + hub, flush=True)
        print("\n".join(str(w.message) for w in caught), file=sys.stderr, flush=True)
        time.sleep(60)
"""


def _start_child(run_id: str) -> subprocess.Popen[str]:
    """CHILD in a process of its own: it makes the run's namespaces and says "ready PID"."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-c", CHILD, run_id], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)


@pytest.mark.net
def test_sigint_to_the_process_that_made_them_removes_everything() -> None:
    before = _host_state()
    run_id = _run_id()
    proc = _start_child(run_id)
    try:
        assert proc.stdout is not None
        state, pid, hub = proc.stdout.readline().split()
        if state == "unshaped":
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=20)
            assert "UNSHAPED" in err
            return
        inodes = {os.stat(NETNS_DIR / ns).st_ino for ns in leftover_namespaces(run_id)}
        assert len(inodes) == 3 and int(pid) in _processes_in(inodes)
        assert hub == "hub" and _ifb_in(f"pfr-{run_id}-server") == ["pfr-m0"]
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
        assert proc.returncode != 0 and "KeyboardInterrupt" in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
            # the child cannot clean up after SIGKILL: a failed assertion above must not leave
            # its namespaces to the next run (CI's failure on 2026-11-28 left three)
            remove_leftover_namespaces(run_id)
    deadline = time.monotonic() + 5
    while psutil.pid_exists(int(pid)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not psutil.pid_exists(int(pid)) or psutil.Process(int(pid)).status() == psutil.STATUS_ZOMBIE
    _nothing_left(run_id, inodes, before)


@pytest.mark.net
def test_namespaces_of_a_killed_run_are_found_and_removed() -> None:
    before = _host_state()
    run_id = _run_id()
    proc = _start_child(run_id)
    try:
        assert proc.stdout is not None
        state, pid, hub = proc.stdout.readline().split()
        proc.kill()  # SIGKILL: no cleanup runs
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    if state == "unshaped":
        assert "UNSHAPED" in err
        return
    made = leftover_namespaces(run_id)
    assert made == sorted(f"pfr-{run_id}-{c}" for c in ("robot1", "server", "robot2"))
    inodes = {os.stat(NETNS_DIR / ns).st_ino for ns in made}
    assert int(pid) in _processes_in(inodes)  # the sleeper outlived its parent, inside robot2
    assert hub == "hub" and _ifb_in(f"pfr-{run_id}-server") == ["pfr-m0"]  # the medium's IFB outlived it too
    assert remove_leftover_namespaces(run_id) == made
    deadline = time.monotonic() + 5
    while psutil.pid_exists(int(pid)) and psutil.Process(int(pid)).status() != psutil.STATUS_ZOMBIE \
            and time.monotonic() < deadline:
        time.sleep(0.05)
    _nothing_left(run_id, inodes, before)


# ---- shared media -----------------------------------------------------------------------------
ROBOTS_TO_SERVER = (("robot1", "server"), ("robot2", "server"))
EACH_WAY = (("robot1", "server"), ("server", "robot2"))


@pytest.mark.net
@pytest.mark.parametrize("flows", [ROBOTS_TO_SERVER, EACH_WAY], ids=["robots_to_server", "each_way"])
@pytest.mark.parametrize("medium_kBps", [400.0, 2000.0], ids=["medium_400", "medium_2000"])
def test_a_medium_caps_the_sum_of_its_links(flows: tuple[tuple[str, str], ...], medium_kBps: float) -> None:
    """robot1 - server - robot2, both links 400 kB/s on one medium; two streams at once. A
    medium of 400 kB/s holds their sum to it (not 2x); one of 2000 kB/s (more than the two
    links) leaves each stream at its own link's rate: the link's tbf still applies."""
    # 1 MB per stream: a TCP retransmission timeout (~0.3 s, which a tbf's tail drops cause now
    # and then) costs a stream ~12 % of its rate, not the ~30 % it costs a 400 kB one
    link_kBps, size = 400.0, 1_000_000
    system = with_medium(chain((link_kBps, link_kBps)), medium_kBps, (0, 1))
    before = _host_state()
    with Network(_run_id(), system) as net:
        if not _create(net):
            return
        inodes = _ns_inodes(net)
        net.apply()  # again: the redirects are made afresh, not doubled
        qdiscs = [(str(q["kind"]), str(q["dev"])) for q in _tc_json(net, "server", "qdisc", "show")]
        assert sorted(q for q in qdiscs if q[0] in ("tbf", "clsact")) == [
            ("clsact", "pfr-l0"), ("clsact", "pfr-l1"), ("tbf", "pfr-l0"), ("tbf", "pfr-l1"), ("tbf", "pfr-m0")]
        [medium] = net.describe()["media"]  # type: ignore[misc]
        assert medium["emulated"] and medium["hub"] == "server" and medium["interface"] == "pfr-m0"
        assert medium["filter"] in ("matchall", "u32") and medium["tbf_rate_bit"] == int(medium_kBps * 8000)
        assert {c: _ifb_in(ns) for c, ns in net.namespaces.items()} == {"robot1": [], "server": ["pfr-m0"],
                                                                        "robot2": []}
        [m0] = net.media_stats()
        link0 = {(end, dev): _tbf_sent_bytes(net, end, dev)
                 for end, dev in (("server", "pfr-l0"), ("server", "pfr-l1"))}
        got = _transfers(net, list(flows), size)
        [m1] = net.media_stats()
        assert [g["bytes"] for g in got] == [size, size]
        for g, (src, _) in zip(got, flows, strict=True):  # from one of the sender's own addresses
            assert g["peer"] in {str(e.address.ip) for e in net.ends if e.computer == src}
        rates = [float(g["after_first"]) / float(g["seconds"]) / 1000 for g in got]
        span = max(float(g["last"]) for g in got) - min(float(g["first"]) for g in got)
        aggregate = sum(float(g["after_first"]) for g in got) / span / 1000
        # both directions of both links passed the medium's one queue ...
        assert int(m1["bytes"]) - int(m0["bytes"]) >= 2 * size  # type: ignore[call-overload]
        # ... and what the server sends still passed its link's own tbf after the IFB
        for src, dst in flows:
            if src == "server":
                dev = next(e.ifname for e in net.ends if e.computer == "server" and dst in system.links[e.link].between)
                assert _tbf_sent_bytes(net, "server", dev) - link0[("server", dev)] >= size
        print(f"medium {medium_kBps:g} kB/s, flows {flows}: per flow {[round(r) for r in rates]} kB/s, "
              f"aggregate {aggregate:.0f} kB/s, medium queue {m1['overlimits']} overlimits {m1['drops']} drops")
        # A shaper only slows: the cap is sharp from above (within 25 %), while a TCP
        # retransmission timeout after a tbf tail drop can cost a stream a third of its rate
        # (a CI dry run, 2026-11-28 04:17 UTC: 292 kB/s through the 400 kB/s medium). So the
        # floor is 60 %, which still tells the cases apart: without the medium the two streams
        # would make 800 kB/s (> 1.25 x 400), and a medium of 2000 wrongly held to 400 would
        # give at most 500 (< 0.6 x 800).
        if medium_kBps < 2 * link_kBps:
            assert 0.6 < aggregate / medium_kBps < 1.25, (aggregate, rates)
        else:
            for rate in rates:
                assert 0.6 < rate / link_kBps < 1.25, (rate, rates)
            assert 0.6 < aggregate / (2 * link_kBps) < 1.25, (aggregate, rates)
    _nothing_left(net.run_id, inodes, before)


@pytest.mark.net
def test_a_medium_whose_links_share_no_computer_is_not_emulated_and_says_so() -> None:
    system = with_medium(chain((400.0, 400.0, 400.0)), 400.0, (0, 2))  # robot1-server and robot2-robot3
    before = _host_state()
    with Network(_run_id(), system) as net:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            net.create()
        said = [str(w.message) for w in caught if issubclass(w.category, PerfrosWarning)]
        if not net.emulated:
            assert any("UNSHAPED" in m for m in said), said
            return
        assert [m for m in said if "medium" in m] == [
            "system: medium 'wifi' is not emulated: its links share no computer (only a medium whose links all "
            "meet at one computer is emulated); each link is shaped to its own bandwidth only"]
        inodes = _ns_inodes(net)
        described = net.describe()
        [medium] = described["media"]  # type: ignore[misc]
        assert medium["emulated"] is False and medium["hub"] is None and medium["interface"] is None
        assert "share no computer" in medium["reason"] and medium["links"] == [0, 2]
        assert all(link["tbf_rate_bit"] == 3_200_000 for link in described["links"])  # type: ignore[attr-defined]
        assert all(_ifb_in(ns) == [] for ns in net.namespaces.values())
        assert net.media_stats() == []
    _nothing_left(net.run_id, inodes, before)
