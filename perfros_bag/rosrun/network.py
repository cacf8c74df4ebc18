"""Computers as network namespaces joined by ``tc``-shaped links: a system's links emulated.

Each computer of a system becomes a network namespace ``pfr-<run id>-<computer>`` with its
loopback up. Each link (system.yaml ``links:``) becomes a veth pair created directly inside
its two namespaces (the pair never exists in the host's namespace), named ``pfr-l<i>`` on
both sides (``i``: the link's index in ``links:``; interface names stay within Linux's 15
characters, :attr:`LinkEnd.ifname` keeps the mapping). Link ``i`` takes the ``i``-th /30 of
:data:`SUBNET` (10.213.0.0/16): its ``between[0]`` end the first host address, its
``between[1]`` end the second. A ``tbf`` qdisc on both ends shapes each direction to the
link's ``bandwidth_kBps`` (whole frames, headers included: a TCP stream's payload gets
about 96 % of it).

A computer reaches every other computer the system connects: besides the connected /30s,
each namespace has a /32 route to every address of the run that is more than one link away,
via the first link of the system's route (:meth:`System.route`), and namespaces with
several links forward. There is no default route and no NAT: a process inside a namespace
reaches loopback and the run's own addresses, nothing else; IPv6 is off on the veths. The
host's interfaces and routes are never touched. Shared media are not emulated: each link is
shaped to its own bandwidth.

Where namespaces cannot be made (no root, no ``ip``, a kernel or container that refuses),
the network falls back to ``unshaped``: a clear warning, every computer shares the host's
loopback, links are not shaped, and the run is marked unshaped. :meth:`Network.remove`
kills what still runs inside the namespaces, deletes the veths (and their qdiscs) and the
namespaces; :func:`leftover_namespaces` finds any of a run, :func:`remove_leftover_namespaces`
deletes them.
"""

from __future__ import annotations

import contextlib
import ctypes
import ipaddress
import json
import os
import re
import shutil
import signal
import subprocess
import threading
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from types import TracebackType

from perfros_bag.errors import PerfrosError, PerfrosWarning
from perfros_bag.system.types import System

#: The one private range every run takes its link addresses from.
SUBNET = ipaddress.IPv4Network("10.213.0.0/16")
PREFIX = "pfr-"
LINK_PREFIX = "pfr-l"
LOOPBACK = "127.0.0.1"
LATENCY_MS = 100  # tbf queue: this long at the link's rate
MIN_RATE_BIT = 8000  # tc takes no zero rate: a 0 kB/s link gets 1 kB/s
MAX_NAMESPACE = 200  # namespace names are files under /run/netns (NAME_MAX 255)
_RUN_ID = re.compile(r"[A-Za-z0-9_]+")


class NetMode(StrEnum):
    """How a run's links are emulated."""

    NAMESPACES = "netns"  # a namespace per computer, veth links shaped with tc
    UNSHAPED = "unshaped"  # every computer on the host's loopback, links not emulated


@dataclass(frozen=True)
class LinkEnd:
    """One end of a link: its veth inside ``computer``'s namespace."""

    link: int  # index in System.links
    computer: str
    ifname: str
    address: ipaddress.IPv4Interface  # e.g. 10.213.0.1/30
    peer: ipaddress.IPv4Address  # the other end's address


@dataclass(frozen=True)
class Route:
    """A /32 route inside a computer's namespace to an address more than one link away."""

    destination: ipaddress.IPv4Address
    via: ipaddress.IPv4Address
    ifname: str


def namespace_name(run_id: str, computer: str) -> str:
    """``pfr-<run_id>-<computer>`` (a very long computer name is cut and given a hash)."""
    name = f"{PREFIX}{run_id}-{computer}"
    if len(name) <= MAX_NAMESPACE:
        return name
    import hashlib

    digest = hashlib.sha1(computer.encode()).hexdigest()[:8]
    return f"{name[:MAX_NAMESPACE - 9]}-{digest}"


def plan_ends(system: System) -> list[LinkEnd]:
    """Both ends of every link, in ``links:`` order: link ``i`` takes the ``i``-th /30."""
    subnets = SUBNET.subnets(new_prefix=30)
    ends: list[LinkEnd] = []
    for i, link in enumerate(system.links):
        try:
            net = next(subnets)
        except StopIteration:
            raise PerfrosError(f"{system.source or 'system'}: {len(system.links)} links do not fit in "
                               f"{SUBNET} (one /30 each)") from None
        first, second = list(net.hosts())
        ifname = f"{LINK_PREFIX}{i}"
        a, b = link.between
        ends.append(LinkEnd(i, a, ifname, ipaddress.IPv4Interface(f"{first}/{net.prefixlen}"), second))
        ends.append(LinkEnd(i, b, ifname, ipaddress.IPv4Interface(f"{second}/{net.prefixlen}"), first))
    return ends


def plan_routes(system: System, ends: list[LinkEnd]) -> dict[str, list[Route]]:
    """Per computer, a /32 route to each address of another computer that is not on the
    first link of the system's route to it (the connected /30 covers those); addresses of
    computers no path reaches get none."""
    end_of = {(e.link, e.computer): e for e in ends}
    routes: dict[str, list[Route]] = {c.name: [] for c in system.computers}
    for me in routes:
        for end in ends:
            if end.computer == me:
                continue
            path = system.route(me, end.computer)
            if not path or path[0] == end.link:
                continue
            out = end_of[(path[0], me)]
            routes[me].append(Route(end.address.ip, out.peer, out.ifname))
    return routes


def tbf_rate_bit(bandwidth_kBps: float) -> int:
    """A link's ``tbf`` rate in bit/s (kB = 1000 bytes)."""
    return max(MIN_RATE_BIT, int(round(bandwidth_kBps * 8000)))


def tbf_burst_bytes(rate_bit: int) -> int:
    """Bucket size: four full frames, or 10 ms at the rate when that is more."""
    return max(4 * 1514, rate_bit // 8 // 100)


@dataclass
class Network:
    """The namespaces and links of run ``run_id`` for ``system`` (see the module's text)."""

    run_id: str
    system: System
    ip: str = "ip"  # iproute2's tools (a path or a name on PATH)
    tc: str = "tc"
    mode: NetMode = NetMode.UNSHAPED
    reason: str = ""
    shaped: bool = False
    namespaces: dict[str, str] = field(default_factory=dict)  # computer -> namespace created
    ends: list[LinkEnd] = field(default_factory=list)
    routes: dict[str, list[Route]] = field(default_factory=dict)
    killed: list[int] = field(default_factory=list)  # PIDs remove() found still inside

    def __post_init__(self) -> None:
        if not _RUN_ID.fullmatch(self.run_id):
            raise ValueError(f"run id {self.run_id!r}: letters, digits and '_' only")

    @property
    def emulated(self) -> bool:
        return self.mode is NetMode.NAMESPACES

    def __enter__(self) -> Network:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.remove()

    # ---- create ---------------------------------------------------------------------------
    def create(self, *, shaped: bool = True, quiet: bool = False) -> None:
        """Make the namespaces, veths, addresses and routes; shape the links unless
        ``shaped=False`` (see :meth:`apply`). Where that fails: everything made is removed,
        the mode is ``unshaped`` with the reason, and a warning says so (none when ``quiet``).
        Any other exception (Ctrl-C) removes what was made and propagates."""
        if not self.system.links:
            self.mode, self.reason = NetMode.UNSHAPED, "the system has no links (no network to emulate)"
            return
        try:
            self.ip, self.tc = _tool(self.ip), _tool(self.tc)
            self.ends = plan_ends(self.system)
            self.routes = plan_routes(self.system, self.ends)
            self._make_namespaces()
            self._make_links()
            self.mode = NetMode.NAMESPACES
            if shaped:
                self.apply()
        except OSError as exc:
            self.remove()
            self.mode, self.reason = NetMode.UNSHAPED, str(exc)
            if not quiet:
                warnings.warn(f"cannot emulate the links as network namespaces ({exc}); the links run UNSHAPED: "
                              "every computer shares the host's loopback (results are marked unshaped: link "
                              "overloads will not show)", PerfrosWarning, stacklevel=2)
        except BaseException:
            self.remove()
            raise

    def _make_namespaces(self) -> None:
        links_of: dict[str, int] = {}
        for end in self.ends:
            links_of[end.computer] = links_of.get(end.computer, 0) + 1
        for comp in self.system.computers:
            ns = namespace_name(self.run_id, comp.name)
            _run([self.ip, "netns", "add", ns])
            self.namespaces[comp.name] = ns
            # before any veth exists: no reverse-path filter (routes may be asymmetric),
            # forwarding where the computer relays, IPv6 off on the veths to come
            forward = 1 if links_of.get(comp.name, 0) > 1 else 0
            _run([self.ip, "netns", "exec", ns, "/bin/sh", "-ec",
                  "echo 0 > /proc/sys/net/ipv4/conf/all/rp_filter; "
                  "echo 0 > /proc/sys/net/ipv4/conf/default/rp_filter; "
                  f"echo {forward} > /proc/sys/net/ipv4/ip_forward; "
                  "if [ -d /proc/sys/net/ipv6/conf ]; then "
                  "echo 1 > /proc/sys/net/ipv6/conf/default/disable_ipv6; fi"])
            _run([self.ip, "-n", ns, "link", "set", "lo", "up"])

    def _make_links(self) -> None:
        pairs = [(a, b) for a, b in zip(self.ends[::2], self.ends[1::2], strict=True)]
        _run([self.ip, "-batch", "-"], "".join(
            f"link add {a.ifname} netns {self.namespaces[a.computer]} type veth "
            f"peer name {b.ifname} netns {self.namespaces[b.computer]}\n" for a, b in pairs))
        for comp, ns in self.namespaces.items():
            mine = [e for e in self.ends if e.computer == comp]
            if mine:
                _run([self.ip, "-n", ns, "-batch", "-"], "".join(
                    f"addr add {e.address} dev {e.ifname}\nlink set {e.ifname} up\n" for e in mine))
        for comp, ns in self.namespaces.items():
            if self.routes.get(comp):
                _run([self.ip, "-n", ns, "-batch", "-"], "".join(
                    f"route add {r.destination}/32 via {r.via} dev {r.ifname} onlink\n" for r in self.routes[comp]))

    def apply(self) -> None:
        """Shape every link to its bandwidth, both directions (``tbf`` on both veth ends)."""
        if not self.emulated:
            return
        for comp, ns in self.namespaces.items():
            lines = []
            for end in self.ends:
                if end.computer == comp:
                    rate = tbf_rate_bit(self.system.links[end.link].bandwidth_kBps)
                    lines.append(f"qdisc replace dev {end.ifname} root tbf rate {rate}bit "
                                 f"burst {tbf_burst_bytes(rate)} latency {LATENCY_MS}ms\n")
            if lines:
                _run([self.tc, "-n", ns, "-batch", "-"], "".join(lines))
        self.shaped = True

    # ---- use --------------------------------------------------------------------------------
    def master_computer(self) -> str:
        """Where a run's ROS master goes: the computer with the most links (the hub every
        other computer reaches, in a robots + server system), ties to the first listed."""
        count = {c.name: 0 for c in self.system.computers}
        for link in self.system.links:
            for end in link.between:
                count[end] = count.get(end, 0) + 1
        kind = {c.name: c.kind for c in self.system.computers}
        return max(count, key=lambda c: (count[c], kind.get(c) == "server"))

    @contextlib.contextmanager
    def inside(self, computer: str) -> Iterator[None]:
        """This thread in ``computer``'s namespace for the block (nothing when unshaped):
        sockets opened and processes started meanwhile belong to it. The host's namespace
        is restored on the way out, also on an exception or Ctrl-C."""
        ns = self.namespaces.get(computer)
        if ns is None:
            yield
            return
        with enter_namespace(Path("/run/netns") / ns):
            yield

    def link_stats(self) -> list[dict[str, object]]:
        """Per link end, what its ``tbf`` qdisc counted so far: bytes and packets sent,
        packets dropped, times the rate held a packet back (``overlimits``)."""
        stats: list[dict[str, object]] = []
        if not self.emulated:
            return stats
        for comp, ns in self.namespaces.items():
            done = subprocess.run([self.tc, "-n", ns, "-s", "-j", "qdisc", "show"], capture_output=True, text=True,
                                  timeout=30, check=False)
            try:
                qdiscs = json.loads(done.stdout or "[]")
            except ValueError:
                qdiscs = []
            for q in qdiscs:
                dev = q.get("dev", "")
                end = next((e for e in self.ends if e.computer == comp and e.ifname == dev), None)
                if end is None or q.get("kind") != "tbf":
                    continue
                a, b = self.system.links[end.link].between
                stats.append({"link": end.link, "from": comp, "to": b if comp == a else a,
                              "bytes": int(q.get("bytes", 0)), "packets": int(q.get("packets", 0)),
                              "drops": int(q.get("drops", 0)), "overlimits": int(q.get("overlimits", 0))})
        return sorted(stats, key=lambda s: (str(s["link"]).zfill(6), str(s["from"])))

    def wrap(self, computer: str, argv: list[str]) -> list[str]:
        """``argv`` run inside ``computer``'s namespace (unchanged when unshaped)."""
        ns = self.namespaces.get(computer)
        return argv if ns is None else [self.ip, "netns", "exec", ns, *argv]

    def address(self, computer: str) -> str:
        """The address ``computer``'s processes advertise (``ROS_IP``): its end of its first
        link; loopback when unshaped or when it has no link."""
        if self.emulated:
            for end in self.ends:
                if end.computer == computer:
                    return str(end.address.ip)
        return LOOPBACK

    def ros_addresses(self, computer: str, master: str, port: int) -> dict[str, str]:
        """``ROS_IP`` and ``ROS_MASTER_URI`` for a process on ``computer`` when roscore runs
        on ``master``; a :class:`PerfrosError` when no link path joins the two."""
        if self.emulated and self.system.route(computer, master) is None:
            raise PerfrosError(f"{self.system.source or 'system'}: no link path joins computer {computer!r} "
                               f"to {master!r}, where the ROS master runs")
        return {"ROS_IP": self.address(computer), "ROS_MASTER_URI": f"http://{self.address(master)}:{port}"}

    def describe(self) -> dict[str, object]:
        """What the run emulated, for its record (run.json)."""
        links = []
        for a, b in zip(self.ends[::2], self.ends[1::2], strict=True):
            bw = self.system.links[a.link].bandwidth_kBps
            links.append({"between": [a.computer, b.computer], "bandwidth_kBps": bw, "interface": a.ifname,
                          "addresses": {a.computer: str(a.address.ip), b.computer: str(b.address.ip)},
                          "tbf_rate_bit": tbf_rate_bit(bw) if self.shaped else None})
        return {"mode": str(self.mode), "reason": self.reason, "shaped": self.shaped,
                "namespaces": dict(self.namespaces), "links": links if self.emulated else [],
                "addresses": {c.name: self.address(c.name) for c in self.system.computers}}

    # ---- remove -----------------------------------------------------------------------------
    def remove(self, timeout: float = 5.0) -> list[str]:
        """Kill what still runs inside the run's namespaces, delete their veths (with the
        qdiscs) and the namespaces; returns the namespaces left."""
        ip = shutil.which(self.ip)
        if ip is None:
            self.namespaces.clear()
            return []
        todo = dict.fromkeys([*self.namespaces.values(), *leftover_namespaces(self.run_id, ip=ip)])
        left = [ns for ns in todo if not _delete_namespace(ip, ns, self.killed, timeout)]
        self.namespaces = {c: ns for c, ns in self.namespaces.items() if ns in left}
        self.shaped = self.shaped and bool(self.namespaces)
        return left


CLONE_NEWNET = 0x40000000


@contextlib.contextmanager
def enter_namespace(path: Path) -> Iterator[None]:
    """The calling thread in the network namespace at ``path`` (``setns(2)``) for the block;
    its own namespace back afterwards. Only network namespaces may be entered per thread,
    which is all this does; an :class:`OSError` when the kernel refuses."""
    libc = ctypes.CDLL(None, use_errno=True)
    own = os.open(f"/proc/self/task/{threading.get_native_id()}/ns/net", os.O_RDONLY)
    try:
        target = os.open(path, os.O_RDONLY)
        try:
            if libc.setns(target, CLONE_NEWNET) != 0:
                err = ctypes.get_errno()
                raise OSError(err, f"cannot enter network namespace {path.name}: {os.strerror(err)}")
        finally:
            os.close(target)
        try:
            yield
        finally:
            if libc.setns(own, CLONE_NEWNET) != 0:  # pragma: no cover - the kernel gave it out
                err = ctypes.get_errno()
                raise OSError(err, f"cannot return to this process's network namespace: {os.strerror(err)}")
    finally:
        os.close(own)


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise OSError(f"{name!r} not found (iproute2 is not installed)")
    return path


def _run(argv: list[str], stdin: str | None = None) -> None:
    """Run one iproute2 command; OSError with its message when it fails."""
    try:
        done = subprocess.run(argv, input=stdin, capture_output=True, text=True, timeout=30, check=False)
    except subprocess.TimeoutExpired:
        raise OSError(f"{' '.join(argv[:4])} timed out") from None
    if done.returncode != 0:
        problem = (done.stderr.strip() or done.stdout.strip() or f"exit {done.returncode}").splitlines()
        raise OSError(f"{' '.join(argv[:4])}: {'; '.join(problem[:3])}")


def _delete_namespace(ip: str, ns: str, killed: list[int], timeout: float) -> bool:
    """SIGKILL the processes inside ``ns``, delete its veths, then ``ns``; True when it is gone."""
    deadline = time.monotonic() + timeout
    while pids := _pids_in(ip, ns):
        if time.monotonic() > deadline:
            return False
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
                if pid not in killed:
                    killed.append(pid)
            except ProcessLookupError:
                pass
        time.sleep(0.05)
    for ifname in _links_in(ip, ns):
        # deleting one end of a veth deletes the pair and the qdiscs on both ends
        subprocess.run([ip, "-n", ns, "link", "del", ifname], capture_output=True, timeout=30, check=False)
    done = subprocess.run([ip, "netns", "del", ns], capture_output=True, timeout=30, check=False)
    return done.returncode == 0 or ns not in leftover_namespaces(ip=ip)


def _pids_in(ip: str, ns: str) -> list[int]:
    done = subprocess.run([ip, "netns", "pids", ns], capture_output=True, text=True, timeout=30, check=False)
    return [int(p) for p in done.stdout.split() if p.isdigit() and int(p) != os.getpid()]


def _links_in(ip: str, ns: str) -> list[str]:
    """The run's veths inside ``ns`` (``pfr-l<i>``)."""
    done = subprocess.run([ip, "-n", ns, "-o", "link", "show"], capture_output=True, text=True, timeout=30,
                          check=False)
    names = [line.split(":")[1].strip().split("@")[0] for line in done.stdout.splitlines() if line.count(":") >= 2]
    return [n for n in names if n.startswith(LINK_PREFIX)]


def leftover_namespaces(run_id: str | None = None, *, ip: str = "ip") -> list[str]:
    """perfros network namespaces still present (of one run, or of any)."""
    path = shutil.which(ip)
    if path is None:
        return []
    done = subprocess.run([path, "netns", "list"], capture_output=True, text=True, timeout=30, check=False)
    prefix = f"{PREFIX}{run_id}-" if run_id else PREFIX
    names = [line.split()[0] for line in done.stdout.splitlines() if line.strip()]
    return sorted(n for n in names if n.startswith(prefix))


def remove_leftover_namespaces(run_id: str | None = None, *, ip: str = "ip") -> list[str]:
    """Delete the namespaces of a run (of ``run_id``, or any) with what runs inside; returns
    the namespaces deleted."""
    path = shutil.which(ip)
    if path is None:
        return []
    killed: list[int] = []
    return [ns for ns in leftover_namespaces(run_id, ip=path) if _delete_namespace(path, ns, killed, 5.0)]
