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
host's interfaces and routes are never touched.

A shared medium (system.yaml ``media:``, links naming it with ``medium:``: one wifi channel
several robots share) caps the sum of its links' traffic. It is emulated where all of its
links share one computer, the hub (the server every robot's wifi link goes to; where two
computers qualify, the one :meth:`Network.master_computer` would prefer): an IFB device
``pfr-m<j>`` (``j``: the medium's index in ``media:``) in the hub's namespace, with a
``tbf`` at the medium's ``bandwidth_kBps``, and on every hub-side veth end of the medium's
links a ``clsact`` qdisc whose egress and ingress filters (``matchall``, or ``u32 match u32
0 0`` on kernels without it) redirect every frame to the IFB. Both directions of every link
of the medium then pass that one queue, on top of each link's own ``tbf``: the clsact
egress hook runs before the veth's root qdisc and the IFB hands the frame back to the
veth's root ``tbf``; ingress frames, already shaped by the far end's ``tbf``, are queued on
the IFB before the hub's stack sees them. Traffic a hub forwards from one link of a medium
to another crosses the medium twice, as the model counts it (the load of both links). A
medium whose links share no computer is not emulated (a warning; :meth:`Network.describe`
says why): its links are shaped to their own bandwidths only. On a kernel where ``ifb`` is
a module not yet loaded it is loaded with ``numifbs=0``, so no ``ifb0`` appears in the host.

Where namespaces cannot be made (no root, no ``ip``, a kernel or container that refuses),
the network falls back to ``unshaped``: a clear warning, every computer shares the host's
loopback, links are not shaped, and the run is marked unshaped. :meth:`Network.remove`
kills what still runs inside the namespaces, deletes the veths (and their qdiscs), the IFBs
and the namespaces; :func:`leftover_namespaces` finds any of a run, :func:`remove_leftover_namespaces`
deletes them.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
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
MEDIUM_PREFIX = "pfr-m"
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


@dataclass(frozen=True)
class MediumPlan:
    """How a shared medium is emulated: its IFB ``ifname`` in ``hub``'s namespace, or why not."""

    medium: int  # index in System.media
    name: str
    links: tuple[int, ...]  # indices in System.links
    hub: str | None  # the computer all its links share; None when there is none
    ifname: str
    reason: str = ""  # why it is not emulated; "" when it is

    @property
    def emulated(self) -> bool:
        return not self.reason


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


def link_counts(system: System) -> dict[str, int]:
    """Per computer, how many links it has."""
    count = {c.name: 0 for c in system.computers}
    for link in system.links:
        for end in link.between:
            count[end] = count.get(end, 0) + 1
    return count


def plan_media(system: System) -> list[MediumPlan]:
    """Per medium of ``media:``, its hub: the computer all of its links share (of two, the one
    with more links, then a server, then the first listed). A medium without links, or whose
    links share no computer, gets the reason it is not emulated."""
    count = link_counts(system)
    kind = {c.name: c.kind for c in system.computers}
    order = {c.name: k for k, c in enumerate(system.computers)}
    plans: list[MediumPlan] = []
    for j, (name, links) in enumerate(system.medium_links.items()):
        ifname = f"{MEDIUM_PREFIX}{j}"
        if not links:
            plans.append(MediumPlan(j, name, links, None, ifname, "no link is on it"))
            continue
        common = set(system.links[links[0]].between)
        for li in links[1:]:
            common &= set(system.links[li].between)
        if not common:
            plans.append(MediumPlan(j, name, links, None, ifname,
                                    "its links share no computer (only a medium whose links all meet at one "
                                    "computer is emulated); each link is shaped to its own bandwidth only"))
            continue
        hub = min(common, key=lambda c: (-count.get(c, 0), kind.get(c) != "server", order.get(c, 0)))
        plans.append(MediumPlan(j, name, links, hub, ifname))
    return plans


def tbf_rate_bit(bandwidth_kBps: float) -> int:
    """A link's ``tbf`` rate in bit/s (kB = 1000 bytes)."""
    return max(MIN_RATE_BIT, int(round(bandwidth_kBps * 8000)))


def tbf_burst_bytes(rate_bit: int) -> int:
    """Bucket size: four full frames, or 10 ms at the rate when that is more."""
    return max(4 * 1514, rate_bit // 8 // 100)


def link_burst(rate_bit: int, running_burst: int) -> int:
    """The bucket for a ``tbf`` changed in place to ``rate_bit``: the rate's own
    (:func:`tbf_burst_bytes`), but never smaller than ``running_burst``, the bucket of the
    qdisc being changed, whose queued packets can be that large (see
    :meth:`Network.set_link_rate`)."""
    return max(tbf_burst_bytes(rate_bit), running_burst)


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
    media: list[MediumPlan] = field(default_factory=list)
    media_filter: str = ""  # the classifier redirecting to the IFBs: "matchall" or "u32"
    killed: list[int] = field(default_factory=list)  # PIDs remove() found still inside
    bursts: dict[int, int] = field(default_factory=dict)  # link index -> bucket bytes of its running tbf

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
            self._make_media()
            if shaped:
                self.apply()
            if not quiet:
                for m in self.media:
                    if m.reason and m.links:
                        warnings.warn(f"{self.system.source or 'system'}: medium {m.name!r} is not emulated: "
                                      f"{m.reason}", PerfrosWarning, stacklevel=2)
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

    def _make_media(self) -> None:
        """An IFB ``pfr-m<j>`` in each emulated medium's hub namespace (a medium whose IFB
        cannot be made is not emulated, with the reason)."""
        self.media = plan_media(self.system)
        if any(m.emulated for m in self.media):
            _load_ifb()
        for k, m in enumerate(self.media):
            if m.emulated and m.hub is not None:
                ns = self.namespaces[m.hub]
                try:
                    _run([self.ip, "-n", ns, "-batch", "-"], f"link add {m.ifname} type ifb\nlink set {m.ifname} up\n")
                except OSError as exc:
                    self.media[k] = dataclasses.replace(m, reason=f"cannot make an IFB device ({exc})")

    def _medium_ends(self, m: MediumPlan) -> list[LinkEnd]:
        """The hub-side veth ends of ``m``'s links."""
        return [e for e in self.ends if e.computer == m.hub and e.link in m.links]

    def _shape_medium(self, m: MediumPlan) -> None:
        """``tbf`` on the IFB at the medium's rate; every hub-side end redirected to it."""
        ns = self.namespaces[str(m.hub)]
        rate = tbf_rate_bit(self.system.medium[m.name].bandwidth_kBps)
        ends = self._medium_ends(m)
        for end in ends:  # apply() again: the redirects start afresh
            subprocess.run([self.tc, "-n", ns, "qdisc", "del", "dev", end.ifname, "clsact"], capture_output=True,
                           timeout=30, check=False)
        lines = [f"qdisc replace dev {m.ifname} root tbf rate {rate}bit burst {tbf_burst_bytes(rate)} "
                 f"latency {LATENCY_MS}ms\n"]
        lines += [f"qdisc add dev {end.ifname} clsact\n" for end in ends]
        _run([self.tc, "-n", ns, "-batch", "-"], "".join(lines))
        for name in ([self.media_filter] if self.media_filter else ["matchall", "u32"]):
            match = "matchall" if name == "matchall" else "u32 match u32 0 0"
            try:
                _run([self.tc, "-n", ns, "-batch", "-"], "".join(
                    f"filter add dev {end.ifname} {hook} protocol all pref 1 {match} "
                    f"action mirred egress redirect dev {m.ifname}\n"
                    for end in ends for hook in ("egress", "ingress")))
            except OSError:
                if name == "u32" or self.media_filter:
                    raise
                for end in ends:  # no matchall in this kernel: drop what was added, try u32
                    subprocess.run([self.tc, "-n", ns, "filter", "del", "dev", end.ifname, "egress"],
                                   capture_output=True, timeout=30, check=False)
                    subprocess.run([self.tc, "-n", ns, "filter", "del", "dev", end.ifname, "ingress"],
                                   capture_output=True, timeout=30, check=False)
                continue
            self.media_filter = name
            return

    def apply(self) -> None:
        """Shape every link to its bandwidth, both directions (``tbf`` on both veth ends), and
        every emulated medium to its own (see the module's text). A medium the kernel cannot
        redirect is left unemulated, with the reason."""
        if not self.emulated:
            return
        for comp, ns in self.namespaces.items():
            lines = []
            for end in self.ends:
                if end.computer == comp:
                    rate = tbf_rate_bit(self.system.links[end.link].bandwidth_kBps)
                    self.bursts[end.link] = tbf_burst_bytes(rate)
                    lines.append(f"qdisc replace dev {end.ifname} root tbf rate {rate}bit "
                                 f"burst {self.bursts[end.link]} latency {LATENCY_MS}ms\n")
            if lines:
                _run([self.tc, "-n", ns, "-batch", "-"], "".join(lines))
        for k, m in enumerate(self.media):
            if not m.emulated:
                continue
            try:
                self._shape_medium(m)
            except OSError as exc:
                ns = self.namespaces[str(m.hub)]
                for end in self._medium_ends(m):
                    subprocess.run([self.tc, "-n", ns, "qdisc", "del", "dev", end.ifname, "clsact"],
                                   capture_output=True, timeout=30, check=False)
                subprocess.run([self.ip, "-n", ns, "link", "del", m.ifname], capture_output=True, timeout=30,
                               check=False)
                self.media[k] = dataclasses.replace(m, reason=f"cannot redirect its links to an IFB ({exc})")
        self.shaped = True

    def set_link_rate(self, link: int, bandwidth_kBps: float) -> None:
        """Link ``link`` (its index in the system's links) shaped to ``bandwidth_kBps``, both
        directions, in place: ``tc qdisc change`` on the running ``tbf`` of each veth end
        (its queue, counters and the connections across it stay). ``self.system`` then
        names the new bandwidth, so what is measured afterwards is judged against it.

        The bucket is never made smaller than the one running (:func:`link_burst`): the
        queue keeps the packets the old bucket let in, up to its size (TCP's GSO packets of
        tens of kB), and a ``tbf`` whose bucket is smaller than the packet at its head never
        sends it, nor anything behind it. Lowering a busy 3,000 kB/s link to 1,000 kB/s with
        the new rate's own 10 kB bucket stopped the link for good (RQ4 2026-11-28 04:30: no
        byte crossed it again, and the re-plan's restarted nodes never reached the master)."""
        import math

        if not (isinstance(bandwidth_kBps, int | float) and math.isfinite(bandwidth_kBps) and bandwidth_kBps > 0):
            raise PerfrosError(f"a link's bandwidth must be a finite number > 0 kB/s, got {bandwidth_kBps!r}")
        if not 0 <= link < len(self.system.links):
            raise PerfrosError(f"no link {link} in this run (it has {len(self.system.links)})")
        if self.emulated and self.shaped:
            rate = tbf_rate_bit(bandwidth_kBps)
            burst = link_burst(rate, self.bursts.get(link, 0))
            for end in self.ends:
                if end.link == link:
                    _run([self.tc, "-n", self.namespaces[end.computer], "qdisc", "change", "dev", end.ifname,
                          "root", "tbf", "rate", f"{rate}bit", "burst", str(burst),
                          "latency", f"{LATENCY_MS}ms"])
            self.bursts[link] = burst
        links = list(self.system.links)
        links[link] = dataclasses.replace(links[link], bandwidth_kBps=float(bandwidth_kBps))
        self.system = dataclasses.replace(self.system, links=tuple(links))

    # ---- use --------------------------------------------------------------------------------
    def master_computer(self) -> str:
        """Where a run's ROS master goes: the computer with the most links (the hub every
        other computer reaches, in a robots + server system), ties to the first listed."""
        count = link_counts(self.system)
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

    def media_stats(self) -> list[dict[str, object]]:
        """Per emulated medium, what its IFB's ``tbf`` counted so far (both directions of all
        its links): bytes and packets sent, packets dropped, ``overlimits``."""
        stats: list[dict[str, object]] = []
        if not self.emulated:
            return stats
        for m in self.media:
            if not m.emulated or m.hub not in self.namespaces:
                continue
            done = subprocess.run([self.tc, "-n", self.namespaces[m.hub], "-s", "-j", "qdisc", "show", "dev",
                                   m.ifname], capture_output=True, text=True, timeout=30, check=False)
            try:
                qdiscs = json.loads(done.stdout or "[]")
            except ValueError:
                qdiscs = []
            for q in qdiscs:
                if q.get("kind") == "tbf":
                    stats.append({"medium": m.name, "hub": m.hub, "interface": m.ifname,
                                  "bytes": int(q.get("bytes", 0)), "packets": int(q.get("packets", 0)),
                                  "drops": int(q.get("drops", 0)), "overlimits": int(q.get("overlimits", 0))})
        return stats

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
        """What the run emulated, for its record (run.json, deploy.json): links, and per shared
        medium whether it is emulated (its hub and IFB) or why not."""
        links = []
        for a, b in zip(self.ends[::2], self.ends[1::2], strict=True):
            bw = self.system.links[a.link].bandwidth_kBps
            links.append({"between": [a.computer, b.computer], "bandwidth_kBps": bw, "interface": a.ifname,
                          "addresses": {a.computer: str(a.address.ip), b.computer: str(b.address.ip)},
                          "tbf_rate_bit": tbf_rate_bit(bw) if self.shaped else None})
        media = []
        for m in self.media:
            bw = self.system.medium[m.name].bandwidth_kBps
            media.append({"name": m.name, "bandwidth_kBps": bw, "links": list(m.links), "emulated": m.emulated,
                          "reason": m.reason, "hub": m.hub if m.emulated else None,
                          "interface": m.ifname if m.emulated else None,
                          "filter": self.media_filter if m.emulated and self.shaped else None,
                          "tbf_rate_bit": tbf_rate_bit(bw) if m.emulated and self.shaped else None})
        return {"mode": str(self.mode), "reason": self.reason, "shaped": self.shaped,
                "namespaces": dict(self.namespaces), "links": links if self.emulated else [],
                "media": media if self.emulated else [],
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
        # deleting one end of a veth deletes the pair and the qdiscs on both ends; an IFB, its tbf
        subprocess.run([ip, "-n", ns, "link", "del", ifname], capture_output=True, timeout=30, check=False)
    done = subprocess.run([ip, "netns", "del", ns], capture_output=True, timeout=30, check=False)
    return done.returncode == 0 or ns not in leftover_namespaces(ip=ip)


def _pids_in(ip: str, ns: str) -> list[int]:
    done = subprocess.run([ip, "netns", "pids", ns], capture_output=True, text=True, timeout=30, check=False)
    return [int(p) for p in done.stdout.split() if p.isdigit() and int(p) != os.getpid()]


def _load_ifb() -> None:
    """Where ``ifb`` is a module not loaded yet, load it without devices of its own (loaded
    on demand it would make ``ifb0`` and ``ifb1`` in the host's namespace)."""
    modprobe = shutil.which("modprobe")
    if modprobe is not None and not Path("/sys/module/ifb").exists():
        subprocess.run([modprobe, "-q", "ifb", "numifbs=0"], capture_output=True, timeout=30, check=False)


def _links_in(ip: str, ns: str) -> list[str]:
    """The run's veths (``pfr-l<i>``) and IFBs (``pfr-m<j>``) inside ``ns``."""
    done = subprocess.run([ip, "-n", ns, "-o", "link", "show"], capture_output=True, text=True, timeout=30,
                          check=False)
    names = [line.split(":")[1].strip().split("@")[0] for line in done.stdout.splitlines() if line.count(":") >= 2]
    return [n for n in names if n.startswith((LINK_PREFIX, MEDIUM_PREFIX))]


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
