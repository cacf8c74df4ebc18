"""The system model of the paper (section II) as plain dataclasses.

A :class:`System` has computers (robots and servers with a CPU capacity), network links
(with a bandwidth, optionally on a shared medium such as one wifi channel), nodes (each
with a weight, optional residence and coresidence constraints, and one or more settings
or a CPU -> performance :class:`Curve`) and edges (publisher -> subscriber traffic).

CPU is in normalised units (the paper: 100 = one robot's on-board computer).
Loading and validating ``system.yaml`` lives in :mod:`perfros_bag.system.systemfile`.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from enum import IntEnum, StrEnum
from functools import cached_property
from typing import Literal

from perfros_bag.errors import InputError

ComputerKind = Literal["robot", "server"]


class Problem(IntEnum):
    """The paper's two problems (section II)."""

    PERFORMANCE = 1  # eq 1: choose settings and computers to maximise Σ w·P
    SERVER_CAPACITY = 2  # eq 2: settings fixed, choose computers to minimise Σ server capacity


#: The closed set of curve forms (model.json's ``form``; see :class:`Curve`).
CurveForm = Literal["linear", "log", "quadratic", "power"]
CURVE_FORMS: tuple[CurveForm, ...] = ("linear", "log", "quadratic", "power")
CURVE_NCOEF: dict[CurveForm, int] = {"linear": 2, "log": 2, "quadratic": 3, "power": 2}


def curve_form(name: object) -> CurveForm:
    """``name`` as a :data:`CurveForm`; ValueError when it is not one."""
    for form in CURVE_FORMS:
        if name == form:
            return form
    raise ValueError(f"unknown curve form {name!r} (one of {', '.join(CURVE_FORMS)})")


@dataclass(frozen=True)
class Curve:
    """One of a fixed set of forms, evaluated at ``x = input / scale``.

    - ``linear``:    a*x + b            (coef = [a, b])
    - ``log``:       a*ln(x) + b        (coef = [a, b])
    - ``quadratic``: a*x**2 + b*x + c   (coef = [a, b, c])
    - ``power``:     a*x**b             (coef = [a, b])

    ``domain`` is the valid input range (e.g. CPU units ``[80, 200]``). Curves from input
    files are data: only these forms exist, nothing is ever evaluated as code.
    """

    form: CurveForm
    coef: tuple[float, ...]
    domain: tuple[float, float]
    scale: float = 1.0

    def __post_init__(self) -> None:
        curve_form(self.form)  # a curve read from a file is checked at run time too
        if len(self.coef) != CURVE_NCOEF[self.form]:
            raise ValueError(f"curve form {self.form!r} takes {CURVE_NCOEF[self.form]} coefficients, "
                             f"got {len(self.coef)}")
        lo, hi = self.domain
        if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
            raise ValueError(f"curve domain [{lo}, {hi}] is not a finite range")
        if self.scale <= 0:
            raise ValueError("curve scale must be > 0")
        if self.form in ("log", "power") and lo <= 0:
            raise ValueError(f"curve form {self.form!r} needs a domain above 0, got [{lo}, {hi}]")

    def __call__(self, value: float) -> float:
        x = value / self.scale
        c = self.coef
        if self.form == "linear":
            return c[0] * x + c[1]
        if self.form == "log":
            return c[0] * math.log(x) + c[1]
        if self.form == "quadratic":
            return c[0] * x * x + c[1] * x + c[2]
        return c[0] * x ** c[1]  # power

    def inverse(self, y: float, tol: float = 1e-9) -> float:
        """The input in ``domain`` whose output is ``y`` (the curve must be monotone on the
        domain). Outputs beyond the domain's ends clamp to the ends.

        Closed form for every form (solvers call this once per CPU level of every node);
        bisection only where the closed form does not apply (a flat curve, no root).
        """
        lo, hi = self.domain
        flo, fhi = self(lo), self(hi)
        increasing = fhi >= flo
        if (y <= flo) == increasing and y != flo:
            return lo
        if (y >= fhi) == increasing and y != fhi:
            return hi
        x = self._closed_form_inverse(y)
        if x is not None:
            return min(max(x * self.scale, lo), hi)
        return self._bisect(y, lo, hi, increasing, tol)

    def _closed_form_inverse(self, y: float) -> float | None:
        """``x`` (before scaling) with ``f(x) = y`` inside the domain, or None."""
        c = self.coef
        lo, hi = self.domain[0] / self.scale, self.domain[1] / self.scale
        slack = 1e-9 * max(1.0, abs(hi))
        roots: list[float] = []
        try:
            if self.form == "linear" and c[0] != 0:
                roots = [(y - c[1]) / c[0]]
            elif self.form == "log" and c[0] != 0:
                roots = [math.exp((y - c[1]) / c[0])]
            elif self.form == "power" and c[0] != 0 and c[1] != 0 and y / c[0] > 0:
                roots = [(y / c[0]) ** (1.0 / c[1])]
            elif self.form == "quadratic":
                a, b, k = c[0], c[1], c[2] - y
                if a == 0:
                    roots = [-k / b] if b != 0 else []
                else:
                    disc = b * b - 4 * a * k
                    if disc >= 0:
                        sq = math.sqrt(disc)
                        # the numerically stable pair of roots
                        q = -0.5 * (b + math.copysign(sq, b))
                        roots = [q / a] + ([k / q] if q != 0 else [])
        except (OverflowError, ZeroDivisionError, ValueError):
            return None
        inside = [r for r in roots if math.isfinite(r) and lo - slack <= r <= hi + slack]
        return inside[0] if inside else None

    def _bisect(self, y: float, lo: float, hi: float, increasing: bool, tol: float) -> float:
        for _ in range(200):
            mid = (lo + hi) / 2
            if (self(mid) < y) == increasing:
                lo = mid
            else:
                hi = mid
            if hi - lo <= tol * max(1.0, abs(hi)):
                break
        return (lo + hi) / 2

    def to_dict(self) -> dict[str, object]:
        return {"form": self.form, "coef": list(self.coef), "domain": list(self.domain), "scale": self.scale}


@dataclass(frozen=True)
class TopicRate:
    """Expected traffic of one topic: frequency and bandwidth."""

    frequency_hz: float | None = None
    bandwidth_kBps: float | None = None


@dataclass(frozen=True)
class Setting:
    """One parameter value of a node with its CPU cost and performance (a row of Table I).

    A driven node's setting (its node has an ``input``) also says how it follows its input
    rate F_in: CPU ``cpu + cpu_per_hz·F_in``, output ``min(out_per_in·F_in,
    max_frequency_hz)`` (with ``step: period``: ``x / ceil(x / max_frequency_hz)``, x =
    ``out_per_in·F_in``), ``bytes_per_msg`` per output message (:func:`driven_rates`).
    """

    cpu: float
    performance: float
    value: float | None = None
    frequency_hz: float | None = None
    bandwidth_kBps: float | None = None
    topics: dict[str, TopicRate] = field(default_factory=dict)
    cpu_per_hz: float | None = None  # driven only: CPU units per input message per second
    out_per_in: float | None = None  # driven only: output messages per input message (default 1)
    max_frequency_hz: float | None = None  # driven only: the output's cap (a throttle), none when absent
    # driven only: how the cap acts. None: min(rate, cap) (an averaging throttle); "period": a
    # message passes once 1/cap has elapsed since the last one passed (topic_tools throttle), so
    # the output steps: rate / ceil(rate / cap) (:func:`driven_rates`)
    step: Literal["period"] | None = None
    bytes_per_msg: float | None = None  # driven only: bytes of all its topics per output message
    # measured headroom (perfros_bag.system.cpuerror): CPU units it may need beyond ``cpu``;
    # a driven node's as a share of its CPU at any input rate
    cpu_error: float | None = None
    cpu_error_share: float | None = None  # driven only
    threads: float | None = None  # busy threads at this setting (None: the node's)


#: a period throttle whose free rate over its cap lies within this of a whole number n >= 1
#: (its period is then n input periods give or take this share of one) passes every n-th or
#: every (n+1)-th message as the arrival times jitter: the output there is not told by the
#: rule (measured on topic_tools/throttle, docs/formats.md "Driven nodes")
STEP_AMBIGUOUS = 0.05


def period_steps(rate: float, cap: float) -> int:
    """How many messages of a stream at ``rate`` a period throttle at ``cap`` (> 0) takes per
    message it passes: ``ceil(rate / cap)``, at least 1 (a whole ratio within 1e-9 counts as
    whole: the rule's answer at the boundary, where the real node is ambiguous)."""
    n = rate / cap
    return max(1, math.ceil(n - 1e-9 * max(1.0, n)))


def step_ambiguous(setting: Setting, input_hz: float) -> bool:
    """Is a period throttle's output at ``input_hz`` not told by the rule: its free rate over
    its cap within :data:`STEP_AMBIGUOUS` of a whole number >= 1 (:func:`period_steps`)?"""
    cap = setting.max_frequency_hz
    if setting.step != "period" or cap is None or cap <= 0:
        return False
    n = (1.0 if setting.out_per_in is None else setting.out_per_in) * input_hz / cap
    return n >= 1.0 - STEP_AMBIGUOUS and abs(n - round(n)) <= STEP_AMBIGUOUS


def driven_rates(setting: Setting, input_hz: float) -> tuple[float, float, float]:
    """The data-flow rule (docs/formats.md, "driven nodes"): a driven node's CPU, output
    frequency (Hz, every topic of it) and bandwidth (kB/s, all its topics) at ``setting``
    when its input topic runs at ``input_hz``.

    Without ``bytes_per_msg`` the bytes per message are the setting's measured
    ``bandwidth_kBps`` over its ``frequency_hz`` (both measured in one run), else 0."""
    cpu = setting.cpu + (setting.cpu_per_hz or 0.0) * input_hz
    ratio = 1.0 if setting.out_per_in is None else setting.out_per_in
    out = ratio * input_hz
    cap = setting.max_frequency_hz
    if cap is not None and setting.step == "period":
        out = out / period_steps(out, cap) if cap > 0 else 0.0
    elif cap is not None:
        out = min(out, cap)
    size = _setting_bytes_per_msg(setting)
    return cpu, out, (0.0 if size is None else size) * out / 1000.0


def _setting_bytes_per_msg(setting: Setting) -> float | None:
    """Bytes per output message of ``setting`` (all its topics): its ``bytes_per_msg``, else
    its measured ``bandwidth_kBps`` over its ``frequency_hz``; None when neither is known."""
    if setting.bytes_per_msg is not None:
        return setting.bytes_per_msg
    f, bw = setting.frequency_hz, setting.bandwidth_kBps
    return bw * 1000.0 / f if f and bw is not None else None


@dataclass(frozen=True)
class Choice:
    """What a solver picks for a node: a CPU level and what it yields.

    ``index`` is the position in :meth:`Node.choices` (stable for a given resolution).
    """

    index: int
    cpu: float
    performance: float
    value: float | None = None
    frequency_hz: float | None = None
    bandwidth_kBps: float | None = None
    topics: dict[str, TopicRate] = field(default_factory=dict)
    input_hz: float | None = None  # a driven node's input rate under this choice (None: not driven)
    setting: int | None = None  # a driven node's own setting (index into ``Node.settings``)


@dataclass(frozen=True)
class Parameter:
    name: str
    unit: str | None = None
    #: system.yaml ``parameter.type``; None when it does not say (the model treats that as
    #: ``float``; export writes such a value as an int when it is integral, as without a system)
    type: Literal["int", "float"] | None = None


class Aggregate(StrEnum):
    """How a node's metric is summarised over a recording."""

    MEAN = "mean"
    MEDIAN = "median"
    P5 = "p5"
    P95 = "p95"
    RATE = "rate"  # messages per second on the metric's topic


class Better(StrEnum):
    HIGHER = "higher"
    LOWER = "lower"


@dataclass(frozen=True)
class Metric:
    """What measures a node's performance in a recording: a field of the messages of
    ``topic`` (a path such as ``pose.covariance[0]``; a list field counts its elements),
    aggregated over the run, mapped to 0-100 over ``range`` (``better`` end = 100) or, without
    it, over the range measured across the settings."""

    topic: str
    field: str
    aggregate: Aggregate = Aggregate.MEAN
    better: Better = Better.HIGHER
    range: tuple[float, float] | None = None

    def performance(self, value: float, measured: tuple[float, float] | None = None) -> float | None:
        """``value`` on the 0-100 scale (clipped); None without a range with two ends."""
        lo, hi = self.range if self.range is not None else measured if measured is not None else (0.0, 0.0)
        if not hi > lo:
            return None
        share = min(max((value - lo) / (hi - lo), 0.0), 1.0)
        return 100.0 * (share if self.better is Better.HIGHER else 1.0 - share)


@dataclass(frozen=True)
class Computer:
    name: str
    kind: ComputerKind
    capacity: float | None = None  # None: to be sized (Problem 2 servers)
    max_capacity: float | None = None  # Problem 2: upper bound on a server's size


@dataclass(frozen=True)
class Link:
    between: tuple[str, str]
    bandwidth_kBps: float
    medium: str | None = None


@dataclass(frozen=True)
class Medium:
    """A shared channel (one wifi): the sum of the loads of its links is capped."""

    name: str
    bandwidth_kBps: float


@dataclass(frozen=True)
class Edge:
    """Traffic from ``src`` (publisher) to ``dst``.

    Its bandwidth is ``bandwidth_kBps`` when given, else the publisher's bandwidth at its
    chosen setting (the topic's when ``topic`` is set and the setting has per-topic rates).
    """

    src: str
    dst: str
    topic: str | None = None
    bandwidth_kBps: float | None = None


@dataclass(frozen=True)
class Chain:
    """A processing chain (system.yaml ``chains``): messages flow through ``topics`` in order,
    each node copying its input's ``header.stamp`` (its end-to-end latency is measured from
    the recording: :mod:`perfros_bag.ingest.chains`)."""

    name: str
    topics: tuple[str, ...]
    #: system.yaml ``budget_ms``: the most its predicted latency may be, in milliseconds
    #: (p50 and/or p95; None: not bounded). See :mod:`perfros_bag.system.latency`.
    budget_ms: Budget | None = None


@dataclass(frozen=True)
class Budget:
    """A chain's latency budget in milliseconds: its p50, its p95 or both (None: unbounded)."""

    p50: float | None = None
    p95: float | None = None

    def items(self) -> list[tuple[str, float]]:
        """(``"p50"``/``"p95"``, ms) for each bound it sets."""
        return [(k, v) for k, v in (("p50", self.p50), ("p95", self.p95)) if v is not None]

    def to_dict(self) -> dict[str, float]:
        return dict(self.items())


@dataclass(frozen=True)
class LatencyParams:
    """The latency model's parameters (system.yaml ``latency:``; ``fit`` writes them into
    model.json from the sweep's hop latencies, ``tune`` refits them from each deployment).
    The model and each parameter: :mod:`perfros_bag.system.latency`, docs/solvers.md."""

    units_per_core: float = 100.0  # CPU units of one core busy for one second per second
    overhead_ms: float = 1.0  # what every hop adds beyond its service, wait and transfer
    queue_factor: float = 1.0  # the multiplier of the M/D/1 wait behind other traffic on a link
    p95_ratio: float = 1.3  # a service time's p95 over its p50 (nodes without their own)
    queue_size: int = 1  # messages a subscriber's drop-oldest queue holds: bounds the wait
    link_efficiency: float = 0.96  # the share of a link's bandwidth a message's payload gets
    #: messages a saturated node's input holds ahead of its subscriber queue (the socket
    #: buffers: first in, first out, nothing dropped there); measured ~2 for 230 kB frames
    backlog_msgs: float = 2.0
    #: the CFS bandwidth period (ms) of the computers the plan runs on when each is a
    #: CPU-capped cgroup (``deploy``'s are: 10 ms, rosrun/cgroups.py); 0 for computers that
    #: are not capped by a quota (a robot's own CPU): no head start (system/latency.burst_time)
    cfs_period_ms: float = 0.0
    #: what a link lets through at once after an idle spell, in ms at its rate (``deploy``'s
    #: tc ``tbf`` bucket: 10 ms, rosrun/network.py): a periodic message that finds the link
    #: below its rate crosses that much sooner; 0 for a link without such a bucket
    link_burst_ms: float = 0.0
    #: per node: measured hop time over its CPU time per message (wall / CPU: 1 for a node
    #: that only computes), and its own p95 ratio
    service_scale: dict[str, float] = field(default_factory=dict)
    node_p95_ratio: dict[str, float] = field(default_factory=dict)
    #: where they came from: "default", "fit" (the sweep) or "tune" (deployments)
    source: str = "default"


@dataclass(frozen=True)
class Node:
    name: str
    weight: float
    settings: tuple[Setting, ...] = ()
    curve: Curve | None = None  # CPU -> performance over a continuum (solver's choices)
    residence: tuple[str, ...] | None = None
    coresidence: tuple[str, ...] = ()
    parameter: Parameter | None = None
    topics: tuple[str, ...] = ()
    process: str | None = None
    launch: dict[str, str] = field(default_factory=dict)
    # Fitted relations from model.json, keyed "parameter->cpu", "parameter->performance",
    # "cpu->performance", "parameter->frequency", "parameter->bandwidth", and per topic
    # "parameter->frequency:<topic>", "parameter->bandwidth:<topic>".
    relations: dict[str, Curve] = field(default_factory=dict)
    metric: Metric | None = None  # measured performance (system.yaml ``metric``)
    input: str | None = None  # the topic that drives it (system.yaml ``input``); None: a paper node
    #: a curve node: CPU units a level between its settings carries beyond their interpolated
    #: errors (perfros_bag.system.cpuerror; ``fit``: the parameter->cpu fit's leave-one-out RMSE)
    cpu_error_between: float | None = None
    #: the node that hosts it in its process (system.yaml ``container``: a nodelet's manager, a
    #: ROS 2 component's container); None: a process of its own
    container: str | None = None
    #: its busy threads (system.yaml ``threads``; ``fit`` measures them): its weight in the CFS
    #: share of an overloaded computer (perfros_bag.system.cpushare); None: one
    threads: float | None = None
    #: a container's copy price (system.yaml ``copy_cpu_per_MBps``): CPU units that one MB/s
    #: of copies costs when its nodes run standalone instead of inside it (measured by
    #: perfros_bag.characterisation.containers.copy_price); None: not measured
    copy_cpu_per_MBps: float | None = None
    #: CPU units per second a node run standalone spends on the copies of its inputs, beyond
    #: its settings (set by :meth:`System.freed` on a node that is not driven; a driven node's
    #: copy is per input message, in its settings' ``cpu_per_hz``); every candidate choice
    #: carries it (perfros_bag.solver.candidates)
    copy_cpu: float = 0.0

    def threads_at(self, value: float | None) -> float:
        """Busy threads at the setting of ``value`` (that setting's, else the node's, else 1)."""
        j = self.setting_index(value)
        at = self.settings[j].threads if j is not None else None
        return at if at is not None else (self.threads if self.threads is not None else 1.0)

    @property
    def driven(self) -> bool:
        return self.input is not None

    def setting_index(self, value: float | None) -> int | None:
        """The index of the first setting whose ``value`` is ``value`` (to 1e-9), else None."""
        if value is None:
            return None
        return next((j for j, s in enumerate(self.settings)
                     if s.value is not None and math.isclose(s.value, value, rel_tol=1e-9, abs_tol=1e-9)), None)

    @property
    def configurable(self) -> bool:
        return self.curve is not None or len(self.settings) > 1

    def choices(self, resolution: float = 1.0) -> list[Choice]:
        """The node's options for a solver, sorted by CPU.

        With a curve: every ``resolution`` CPU units of its domain (ends included), with
        performance from the curve, the parameter value from the inverse of
        ``parameter->cpu`` when fitted, and frequency/bandwidth from the fitted relations
        or, failing those, interpolated between the settings by CPU.
        Without a curve: the discrete settings.
        """
        if self.curve is None:
            ordered = sorted(enumerate(self.settings), key=lambda js: (js[1].cpu, js[1].performance))
            return [
                Choice(i, s.cpu, s.performance, s.value, s.frequency_hz, s.bandwidth_kBps, s.topics,
                       setting=j if self.driven else None)
                for i, (j, s) in enumerate(ordered)
            ]
        if resolution <= 0:
            raise ValueError("resolution must be > 0")
        lo, hi = self.curve.domain
        count = int(math.floor((hi - lo) / resolution + 1e-9))
        levels = [lo + k * resolution for k in range(count + 1)]
        if hi > levels[-1] + 1e-9:
            levels.append(hi)
        return [self.choice_at(i, c) for i, c in enumerate(levels)]

    def choice_at(self, index: int, cpu: float) -> Choice:
        assert self.curve is not None
        value: float | None = None
        p2c = self.relations.get("parameter->cpu")
        if p2c is not None:
            value = p2c.inverse(cpu)
            if self.parameter is not None and self.parameter.type == "int":
                value = float(round(value))
        freq = self._relation_or_interp("parameter->frequency", value, cpu, "frequency_hz")
        bw = self._relation_or_interp("parameter->bandwidth", value, cpu, "bandwidth_kBps")
        return Choice(index, cpu, self.curve(cpu), value, freq, bw, self._topic_rates(value))

    def _topic_rates(self, value: float | None) -> dict[str, TopicRate]:
        """Per-topic rates from relations keyed ``parameter->frequency:<topic>`` /
        ``parameter->bandwidth:<topic>`` (fitted for nodes with several topics)."""
        out: dict[str, TopicRate] = {}
        if value is None:
            return out
        for key, rel in self.relations.items():
            kind, sep, topic = key.partition(":")
            if not sep or kind not in ("parameter->frequency", "parameter->bandwidth"):
                continue
            v = rel(min(max(value, rel.domain[0]), rel.domain[1]))
            cur = out.get(topic, TopicRate())
            out[topic] = (TopicRate(v, cur.bandwidth_kBps) if kind == "parameter->frequency"
                          else TopicRate(cur.frequency_hz, v))
        return out

    @cached_property
    def _setting_points(self) -> dict[str, list[tuple[float, float]]]:
        """(CPU, value) of the settings that have it, by CPU, for the interpolated rates."""
        return {attr: sorted((s.cpu, getattr(s, attr)) for s in self.settings if getattr(s, attr) is not None)
                for attr in ("frequency_hz", "bandwidth_kBps")}

    def _relation_or_interp(self, key: str, value: float | None, cpu: float, attr: str) -> float | None:
        rel = self.relations.get(key)
        if rel is not None and value is not None:
            return rel(min(max(value, rel.domain[0]), rel.domain[1]))
        points = self._setting_points[attr]
        if not points:
            return None
        if cpu <= points[0][0]:
            return float(points[0][1])
        for (c0, y0), (c1, y1) in zip(points, points[1:], strict=False):
            if cpu <= c1:
                return float(y0 + (y1 - y0) * (cpu - c0) / (c1 - c0)) if c1 > c0 else float(y1)
        return float(points[-1][1])


@dataclass(frozen=True)
class System:
    computers: tuple[Computer, ...]
    nodes: tuple[Node, ...]
    links: tuple[Link, ...] = ()
    media: tuple[Medium, ...] = ()
    edges: tuple[Edge, ...] = ()
    cpu_unit: str | None = None
    machines: dict[str, dict[str, str]] = field(default_factory=dict)
    source: str | None = None  # the file it was loaded from, for messages
    chains: tuple[Chain, ...] = ()  # topics whose end-to-end latency is measured
    latency: LatencyParams = field(default_factory=LatencyParams)  # the latency model's parameters
    #: system.yaml ``membership``: "keep" (each ``container:`` node stays in its container, so on
    #: its computer) or "choose" (a plan may run a hosted node standalone: the solvers solve
    #: each :meth:`freed` variant and keep the best, perfros_bag.solver.membership)
    membership: str = "keep"
    #: set by :meth:`freed`: each node it ran standalone -> the copy charge it put on it
    #: (:meth:`copy_charge`: CPU units per input message per second, CPU units)
    charged: dict[str, tuple[float, float]] = field(default_factory=dict)

    @cached_property
    def computer(self) -> dict[str, Computer]:
        return {c.name: c for c in self.computers}

    @cached_property
    def node(self) -> dict[str, Node]:
        return {n.name: n for n in self.nodes}

    @cached_property
    def medium(self) -> dict[str, Medium]:
        return {m.name: m for m in self.media}

    def allowed(self, node: str) -> tuple[str, ...]:
        """Computers a node may sit on: its residence, or every computer."""
        res = self.node[node].residence
        return res if res is not None else tuple(c.name for c in self.computers)

    def allowed_to_all(self, nodes: Sequence[str]) -> tuple[str, ...]:
        """Computers every one of ``nodes`` may sit on (a coresidence group's), in system order."""
        allowed = [set(self.allowed(n)) for n in nodes]
        return tuple(c.name for c in self.computers if all(c.name in a for a in allowed))

    @cached_property
    def group_computers(self) -> list[tuple[str, ...]]:
        """Per :attr:`coresidence_groups` entry, the computers all its nodes may sit on
        (:meth:`allowed_to_all`), computed once (every heuristic run starts from them)."""
        return [self.allowed_to_all(g) for g in self.coresidence_groups]

    @cached_property
    def containers(self) -> dict[str, tuple[str, ...]]:
        """Each container (a node that hosts others: system.yaml ``container``) -> the nodes
        it hosts, in node order."""
        out: dict[str, list[str]] = {}
        for n in self.nodes:
            if n.container is not None:
                out.setdefault(n.container, []).append(n.name)
        return {k: tuple(v) for k, v in out.items()}

    def container_problem(self, where: Mapping[str, str], standalone: Iterable[str] = ()) -> str | None:
        """The first container whose nodes ``where`` (node -> computer) puts on different
        computers: a container's nodes share its process, so its computer. Under
        ``membership: choose`` a hosted node in ``standalone`` (run in a process of its own)
        may sit anywhere; under ``keep`` a standalone node is itself the problem."""
        alone = set(standalone)
        if self.membership != "choose" and alone:
            who = sorted(alone)[0]
            return (f"node {who}: standalone, but the system's membership is {self.membership}: each node stays in "
                    "its container (membership: choose lets a plan run it standalone)")
        for name in sorted(alone):
            if name in self.node and self.node[name].container is None:
                return f"node {name}: standalone, but it has no container to leave"
        for host, members in self.containers.items():
            split = {m: where[m] for m in (host, *members) if m in where and m not in alone}
            if len(set(split.values())) > 1:
                return (f"container {host}: its nodes are on different computers "
                        f"({', '.join(f'{m} on {c}' for m, c in split.items())}); a container's nodes share its "
                        "process, so its computer")
        return None

    def copy_charge(self, name: str) -> tuple[float, float] | None:
        """What hosted node ``name`` pays when it runs standalone (``membership: choose``):
        the copy of its inputs it then receives in a process of its own, at its container's
        ``copy_cpu_per_MBps``, as (CPU units per input message per second, CPU units).

        A driven node pays per input message: the price x the largest bytes per message of
        its input topic over its publisher's settings. Another node pays the price x the
        largest MB/s of every edge into it (over each publisher's settings). Both are upper
        bounds where the size or rate varies. None when the node is not hosted or its
        container has no measured copy price: such a node stays in its container."""
        node = self.node[name]
        if node.container is None:
            return None
        price = self.node[node.container].copy_cpu_per_MBps
        if price is None:
            return None
        if node.input is not None:
            publisher = self.flow_parent[name]
            sizes = [b for s in self.node[publisher].settings if (b := _bytes_per_msg(s, node.input)) is not None]
            return price * max(sizes, default=0.0) / 1e6, 0.0
        into = 0.0
        for e in self.edges:
            if e.dst == name:
                rates = [_edge_kBps(e, s) for s in self.node[e.src].settings] if e.src in self.node else []
                into += max(rates, default=0.0)
        return 0.0, price * into / 1000.0

    @cached_property
    def may_leave(self) -> tuple[str, ...]:
        """The hosted nodes a plan may run standalone under ``membership: choose``: those whose
        container has a measured copy price (:meth:`copy_charge` is not None)."""
        return tuple(n.name for n in self.nodes if n.container is not None and self.copy_charge(n.name) is not None)

    def freed(self, names: Iterable[str]) -> System:
        """This system with hosted nodes ``names`` run standalone (``membership: choose``):
        out of their container (so out of its coresidence group), paying
        :meth:`copy_charge`: a driven node in each setting's CPU per input message, another
        in its ``copy_cpu``. Membership ``keep`` for the rest: every solver solves such a
        system as it is; its :attr:`charged` holds each freed node's charge."""
        charge = {n: self.copy_charge(n) for n in set(names)}
        charged = {n: c for n, c in charge.items() if c is not None}
        missing = sorted(set(charge) - set(charged))
        if missing:
            raise ValueError(f"nodes {missing} cannot run standalone (no container or no copy price)")

        def leave(n: Node) -> Node:
            per_hz, fixed = charged[n.name]
            if n.input is None:
                return replace(n, container=None, copy_cpu=fixed)
            return replace(n, container=None,
                           settings=tuple(replace(s, cpu_per_hz=(s.cpu_per_hz or 0.0) + per_hz) for s in n.settings))

        nodes = tuple(leave(n) if n.name in charged else n for n in self.nodes)
        return replace(self, nodes=nodes, membership="keep", charged={**self.charged, **charged})

    @cached_property
    def coresidence_groups(self) -> list[tuple[str, ...]]:
        """Nodes that must share a computer (the transitive closure of coresidence), in node
        order; singletons included."""
        parent = {n.name: n.name for n in self.nodes}

        def find(x: str) -> str:
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        for n in self.nodes:  # a container's nodes share its process, so its computer
            for m in (*n.coresidence, *((n.container,) if n.container is not None else ())):
                ra, rb = find(n.name), find(m)
                if ra != rb:
                    parent[rb] = ra
        groups: dict[str, list[str]] = {}
        for n in self.nodes:
            groups.setdefault(find(n.name), []).append(n.name)
        return [tuple(g) for g in groups.values()]

    @cached_property
    def _adjacency(self) -> dict[str, list[tuple[str, int]]]:
        adj: dict[str, list[tuple[str, int]]] = {c.name: [] for c in self.computers}
        for i, link in enumerate(self.links):
            a, b = link.between
            adj[a].append((b, i))
            adj[b].append((a, i))
        return adj

    def route(self, a: str, b: str) -> tuple[int, ...] | None:
        """Indices of the links traffic from computer ``a`` to ``b`` crosses: the shortest
        path by hops (ties broken by link order). ``()`` for ``a == b``; ``None`` when no
        path exists. A system without links puts no network constraint: ``()``."""
        return self._routes.get((a, b), None if self.links else ())

    @cached_property
    def _routes(self) -> dict[tuple[str, str], tuple[int, ...]]:
        routes: dict[tuple[str, str], tuple[int, ...]] = {}
        adj = self._adjacency
        for src in adj:
            prev: dict[str, tuple[str, int] | None] = {src: None}
            queue = deque([src])
            while queue:
                cur = queue.popleft()
                for nxt, li in adj[cur]:
                    if nxt not in prev:
                        prev[nxt] = (cur, li)
                        queue.append(nxt)
            for dst in prev:
                path: list[int] = []
                at = dst
                while (step := prev[at]) is not None:
                    at, li = step
                    path.append(li)
                routes[(src, dst)] = tuple(reversed(path))
        return routes

    # ---- the data flow: driven nodes (system.yaml ``input``; docs/formats.md) ------------
    @property
    def has_flow(self) -> bool:
        """Does any node follow an input (``input:``)? Without, the system is the paper's."""
        return any(n.input is not None for n in self.nodes)

    @cached_property
    def publishers(self) -> dict[str, tuple[str, ...]]:
        """Per topic, the nodes that list it among their ``topics``."""
        out: dict[str, list[str]] = {}
        for n in self.nodes:
            for t in n.topics:
                out.setdefault(t, []).append(n.name)
        return {t: tuple(v) for t, v in out.items()}

    @cached_property
    def flow_parent(self) -> dict[str, str]:
        """Driven node -> the node publishing its input (systemfile checks there is exactly one)."""
        return {n.name: self.publishers[n.input][0] for n in self.nodes if n.input is not None}

    @cached_property
    def flow_order(self) -> tuple[str, ...]:
        """The driven nodes, each after its input's publisher (``input`` is acyclic: checked
        when the system is read, :meth:`flow_cycle`)."""
        order: list[str] = []
        done: set[str] = set()
        for n in self.nodes:
            path: dict[str, None] = {}  # this walk, in order (a dict: membership in O(1))
            at: str | None = n.name
            while at is not None and at in self.flow_parent and at not in done and at not in path:
                path[at] = None
                at = self.flow_parent[at]
            for m in reversed(path):
                if m not in done:
                    done.add(m)
                    order.append(m)
        return tuple(order)

    def flow_cycle(self) -> list[str] | None:
        """The nodes of a cycle of ``input`` (each driven by the next's output), or None.

        Linear in the nodes: each node is walked once (every node has at most one input
        publisher, so a walk either reaches a node already cleared, leaves the flow, or comes
        back onto its own path: the cycle)."""
        parent = self.flow_parent
        cleared: set[str] = set()  # no cycle is reachable from these
        for n in self.nodes:
            path: dict[str, int] = {}  # node -> its place on this walk (dicts keep order)
            at: str | None = n.name
            while at is not None and at in parent and at not in cleared:
                if at in path:
                    return list(path)[path[at]:]
                path[at] = len(path)
                at = parent[at]
            cleared.update(path)
        return None

    @cached_property
    def flow_children(self) -> dict[str, tuple[str, ...]]:
        """Per node, the driven nodes its output drives directly."""
        out: dict[str, list[str]] = {}
        for child, parent in self.flow_parent.items():
            out.setdefault(parent, []).append(child)
        return {k: tuple(v) for k, v in out.items()}

    def in_flow(self, node: str) -> bool:
        """Is ``node`` driven, or does it drive another (its choice then ties to others')?"""
        return self.node[node].input is not None or node in self.flow_children

    @staticmethod
    def topic_hz(choice: Choice, topic: str) -> float | None:
        """The frequency of ``topic`` at a publisher's choice: its per-topic rate, else the
        choice's frequency."""
        rate = choice.topics.get(topic)
        if rate is not None and rate.frequency_hz is not None:
            return rate.frequency_hz
        return choice.frequency_hz

    def driven_choice(self, node: Node, setting: int, input_hz: float, index: int = 0) -> Choice:
        """A driven node's choice at its own ``setting`` (index into ``node.settings``) and
        input rate (:func:`driven_rates`)."""
        s = node.settings[setting]
        cpu, out, bw = driven_rates(s, input_hz)
        return Choice(index, cpu, s.performance, s.value, out, bw, {}, input_hz=input_hz, setting=setting)

    def input_hz(self, node: str, parent_choice: Choice) -> float:
        """A driven node's input rate when its input's publisher runs at ``parent_choice``."""
        topic = self.node[node].input
        assert topic is not None
        f = self.topic_hz(parent_choice, topic)
        if f is None:
            parent = self.flow_parent[node]
            at = f"value {parent_choice.value:g}" if parent_choice.value is not None else f"CPU {parent_choice.cpu:g}"
            raise InputError(self.source, f"node {node!r}: its input {topic} has no frequency_hz at its publisher "
                                          f"{parent!r}'s setting ({at}): a driven node needs its input's rate")
        return f

    def flow_choice_count(self, base: Mapping[str, list[Choice]], stop: int | None = None) -> int:
        """How many choices :meth:`flow_choices` (without ``pick``) makes, every node's
        together, counted without making them: a driven node has one choice per own
        setting and distinct input rate, and its output rates (floats only) give its
        children's input rates. Counting stops once past ``stop`` (the count returned is
        then above ``stop``, not exact): a chain whose choices multiply is refused after
        about ``stop`` steps, not after building them all."""
        total = sum(len(options) for name, options in base.items() if name not in self.flow_parent)
        out_rates: dict[str, set[float]] = {}
        for name in self.flow_order:
            if stop is not None and total > stop:
                break
            parent = self.flow_parent[name]
            rates = out_rates[parent] if parent in out_rates else {self.input_hz(name, ch) for ch in base[parent]}
            own = sorted({ch.setting for ch in base[name] if ch.setting is not None})
            total += len(own) * len(rates)
            if stop is not None and total > stop:
                break
            if name in self.flow_children:  # its output rates feed another driven node
                node = self.node[name]
                out_rates[name] = {driven_rates(node.settings[j], f)[1] for j in own for f in rates}
        return total

    def flow_choices(self, base: Mapping[str, list[Choice]],
                     pick: Callable[[str, list[Choice]], list[Choice]] | None = None, *,
                     limit: int | None = None) -> dict[str, list[Choice]]:
        """``base`` with every driven node's choices made concrete: each of its own settings
        (``base``'s choices name them by ``setting``) at every input rate its input's
        publisher can give (the propagated rule, :func:`driven_rates`; a period throttle not at
        a rate where its output is ambiguous, :meth:`_told`), sorted by CPU.
        Driven nodes are expanded in :attr:`flow_order`; ``pick`` (node, expanded) may keep
        a subset of each before its children are expanded (Problem 2's fixed settings).
        ``limit`` (without ``pick``): an :class:`InputError` before anything is built when
        the choices would number more (:meth:`flow_choice_count`)."""
        if limit is not None and pick is None:
            count = self.flow_choice_count(base, stop=limit)
            if count > limit:
                raise InputError(self.source, f"the driven nodes' settings at every input rate their inputs can take "
                                              f"give more than {limit:,} choices (the most the solvers take): use a "
                                              "coarser resolution or fewer settings upstream")
        out = {name: list(options) for name, options in base.items()}
        for name in self.flow_order:
            node = self.node[name]
            parent = self.flow_parent[name]
            rates = sorted({self.input_hz(name, ch) for ch in out[parent]})
            own = sorted({ch.setting for ch in base[name] if ch.setting is not None})
            made = [self.driven_choice(node, j, f) for f in rates for j in self._told(node, own, f)]
            made.sort(key=lambda c: (c.cpu, -c.performance, c.input_hz or 0.0))
            made = [replace(c, index=i) for i, c in enumerate(made)]
            out[name] = pick(name, made) if pick is not None else made
        return out

    @staticmethod
    def _told(node: Node, own: Sequence[int], input_hz: float) -> list[int]:
        """The settings of ``own`` whose output at ``input_hz`` the rule tells: a period
        throttle at a whole ratio of its input (:func:`step_ambiguous`) is left out, unless
        every setting of ``own`` is."""
        told = [j for j in own if not step_ambiguous(node.settings[j], input_hz)]
        return told or list(own)

    def flow_violation(self, choice: Mapping[str, Choice], tol: float = 1e-9) -> str | None:
        """Why chosen settings break the data flow: a driven node whose choice was made for
        another input rate than its input's publisher gives; None when they agree."""
        for name in self.flow_order:
            parent = self.flow_parent[name]
            if name not in choice or parent not in choice:
                continue
            want = self.input_hz(name, choice[parent])
            got = choice[name].input_hz
            if got is None or abs(got - want) > tol * max(1.0, abs(want)):
                return (f"node {name!r} is planned for an input rate of {got} Hz but {parent!r} publishes "
                        f"{self.node[name].input} at {want:g} Hz")
        return None

    def edge_bandwidth(self, edge: Edge, publisher_choice: Choice) -> float:
        """kB/s an edge carries when its publisher runs at ``publisher_choice``."""
        return _edge_kBps(edge, publisher_choice)

    # ---- the model's rules on a placement (every solver, the plan and the validation use
    # these; solver/check.py keeps its own independent copy) ------------------------------
    def capacities(self, problem: int) -> dict[str, float]:
        """The most CPU each computer may hold (eq 3): its capacity, except a Problem 2
        server, which is sized, up to its ``max_capacity`` (``inf`` without one). A computer
        that needs a capacity and has none is an :class:`~perfros_bag.errors.InputError`."""
        sized = problem == Problem.SERVER_CAPACITY
        unsized = [c.name for c in self.computers if c.capacity is None and not (sized and c.kind == "server")]
        if unsized:
            needs = "Problem 1 needs every capacity" if not sized else "a robot needs a capacity"
            raise InputError(self.source, f"computer(s) {', '.join(map(repr, unsized))} have no capacity: "
                                          f"{needs} (only Problem 2 sizes servers)")
        out: dict[str, float] = {}
        for c in self.computers:
            if sized and c.kind == "server":
                out[c.name] = c.max_capacity if c.max_capacity is not None else math.inf
            else:
                assert c.capacity is not None
                out[c.name] = c.capacity
        return out

    @cached_property
    def medium_links(self) -> dict[str, tuple[int, ...]]:
        """Per shared medium, the indices of its links."""
        return {m.name: tuple(i for i, link in enumerate(self.links) if link.medium == m.name) for m in self.media}

    def medium_load(self, link_loads: Sequence[float], medium: str) -> float:
        """kB/s on a shared medium: the sum of its links' loads."""
        return sum(link_loads[li] for li in self.medium_links[medium])

    @cached_property
    def link_pairs(self) -> tuple[tuple[tuple[str, str], ...], ...]:
        """Per link, the ordered pairs of computers whose route crosses it (sorted)."""
        crossing: list[set[tuple[str, str]]] = [set() for _ in self.links]
        for (a, b), route in self._routes.items():
            if a != b:
                for li in route:
                    crossing[li].add((a, b))
        return tuple(tuple(sorted(pairs)) for pairs in crossing)

    def edge_routes(self, placement: Mapping[str, str | None]) -> Iterator[tuple[int, Edge, tuple[int, ...] | None]]:
        """Every edge (index, edge) whose two ends are placed on different computers, with
        the links its traffic crosses (:meth:`route`; None: no path joins them). Edges with
        an end not (yet) placed are left out."""
        for ei, edge in enumerate(self.edges):
            a, b = placement.get(edge.src), placement.get(edge.dst)
            if a is None or b is None or a == b:
                continue
            yield ei, edge, self.route(a, b)

    def link_loads(self, placement: Mapping[str, str | None], choice: Mapping[str, Choice]) -> list[float]:
        """kB/s on every link (``links`` order) for a placement: each edge between two
        computers loads every link of their route with its bandwidth at its publisher's
        choice. An edge without a path loads nothing (see :meth:`network_violation`)."""
        return self._loads(self.edge_routes(placement), choice)

    def _loads(self, routed: Iterable[tuple[int, Edge, tuple[int, ...] | None]],
               choice: Mapping[str, Choice]) -> list[float]:
        loads = [0.0] * len(self.links)
        for _, edge, route in routed:
            if route:
                bw = self.edge_bandwidth(edge, choice[edge.src])
                for li in route:
                    loads[li] += bw
        return loads

    def overloaded(self, link_loads: Sequence[float], tol: float = 1e-9) -> str | None:
        """The first link, then shared medium, whose load exceeds its bandwidth by more than
        ``tol`` (relative, at least absolute), named with both numbers; None when all fit."""
        for link, load in zip(self.links, link_loads, strict=True):
            if _exceeds(load, link.bandwidth_kBps, tol):
                return (f"link {link.between[0]}-{link.between[1]} would carry {load:.6g} "
                        f"> {link.bandwidth_kBps:.6g} kB/s")
        for m in self.media:
            load = self.medium_load(link_loads, m.name)
            if _exceeds(load, m.bandwidth_kBps, tol):
                return f"medium {m.name} would carry {load:.6g} > {m.bandwidth_kBps:.6g} kB/s"
        return None

    def network_violation(self, placement: Mapping[str, str], choice: Mapping[str, Choice],
                          tol: float = 1e-9) -> str | None:
        """Why the network cannot carry a (whole) placement: an edge between computers that
        no path joins, or a link or medium over its bandwidth (eq 4); None when it can."""
        routed = list(self.edge_routes(placement))
        for _, edge, route in routed:
            if route is None:
                a, b = placement[edge.src], placement[edge.dst]
                return f"no network path between {a} and {b} (edge {edge.src}->{edge.dst})"
        return self.overloaded(self._loads(routed, choice), tol)


def _bytes_per_msg(setting: Setting, topic: str) -> float | None:
    """Bytes per message of ``topic`` at a publisher's ``setting``: the topic's own measured
    bandwidth over its frequency, else a driven setting's ``bytes_per_msg``, else the
    setting's bandwidth over its frequency; None when none is known."""
    rate = setting.topics.get(topic)
    if rate is not None and rate.bandwidth_kBps is not None and rate.frequency_hz:
        return rate.bandwidth_kBps * 1000.0 / rate.frequency_hz
    return _setting_bytes_per_msg(setting)


def _edge_kBps(edge: Edge, publisher: Setting | Choice) -> float:
    """kB/s ``edge`` carries when its publisher runs at ``publisher`` (a setting or a
    solver's choice): the edge's own bandwidth, else its topic's, else the publisher's."""
    if edge.bandwidth_kBps is not None:
        return edge.bandwidth_kBps
    rate = publisher.topics.get(edge.topic) if edge.topic is not None else None
    if rate is not None and rate.bandwidth_kBps is not None:
        return rate.bandwidth_kBps
    return publisher.bandwidth_kBps or 0.0


def _exceeds(load: float, limit: float, tol: float) -> bool:
    return load > limit + tol * max(1.0, limit)
