"""What each emulated node does at a parameter value: rate, message size and CPU work.

The case-study nodes reproduce the shape of the system's own characterisation (Table I in
``system.yaml``): for a node with settings ``(value, cpu, frequency_hz, bandwidth_kBps)``
its CPU, message rate and bandwidth at any parameter value are the piecewise-linear
interpolation of those settings (extrapolated linearly past the ends, so Table III's
"above the plan" values cost more). A node without a parameter has its one setting.

CPU units become real work through the calibration (:class:`Calibration`):
``units_per_core`` CPU units are one core (default 400: a robot of capacity 100 is a
quarter of a core), ``headroom`` scales the work down (default 0.85: the emulated nodes
use 85 % of Table I's CPU, so a plan that fills a robot leaves room for rospy's own
jitter), and ``overhead_s`` is the CPU a rospy cycle costs without any work (publishing,
the rate loop; measured ~0.6 ms per cycle on the development machine). A node's work per
cycle is ``cpu * headroom / units_per_core / rate - overhead_s`` seconds of CPU time,
burnt on the node thread's own CPU clock (see nodes/casestudy_node.py).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from perfros_bag.errors import PerfrosError
from perfros_bag.system.types import Node

NODE_SCRIPT = Path(__file__).resolve().parent / "nodes" / "casestudy_node.py"
ROS_PYTHON = "/usr/bin/python3"


@dataclass(frozen=True)
class Calibration:
    units_per_core: float = 400.0
    headroom: float = 0.85
    overhead_s: float = 0.0006

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def _interp(points: list[tuple[float, float]], x: float) -> float:
    """Piecewise-linear through ``points`` (sorted by x), linear past the ends."""
    if len(points) == 1:
        return points[0][1]
    if x <= points[0][0]:
        (x0, y0), (x1, y1) = points[0], points[1]
    elif x >= points[-1][0]:
        (x0, y0), (x1, y1) = points[-2], points[-1]
    else:
        i = next(k for k in range(1, len(points)) if x <= points[k][0])
        (x0, y0), (x1, y1) = points[i - 1], points[i]
    if x1 == x0:
        return y1
    return y0 + (y1 - y0) * (x - x0) / (x1 - x0)


@dataclass(frozen=True)
class NodeProfile:
    """A node's Table I rows as functions of its parameter value."""

    name: str
    parameter: str | None
    cpu_pts: tuple[tuple[float, float], ...]
    freq_pts: tuple[tuple[float, float], ...]
    bw_pts: tuple[tuple[float, float], ...]

    @classmethod
    def of(cls, node: Node) -> NodeProfile:
        rows = [s for s in node.settings if s.value is not None] or list(node.settings[:1])
        if not rows:
            raise PerfrosError(f"node {node.name!r} has no settings to emulate")
        rows = sorted(rows, key=lambda s: (s.value or 0.0))
        for s in rows:
            if s.frequency_hz is None or s.frequency_hz <= 0:
                raise PerfrosError(f"node {node.name!r}: every setting needs frequency_hz > 0 to be emulated")
        xs = [float(s.value) if s.value is not None else 0.0 for s in rows]
        return cls(
            node.name,
            node.parameter.name if node.parameter else None,
            tuple(zip(xs, [float(s.cpu) for s in rows], strict=True)),
            tuple(zip(xs, [float(s.frequency_hz or 0.0) for s in rows], strict=True)),
            tuple(zip(xs, [float(s.bandwidth_kBps or 0.0) for s in rows], strict=True)),
        )

    @property
    def configurable(self) -> bool:
        return len(self.cpu_pts) > 1

    @property
    def values(self) -> list[float]:
        return [x for x, _ in self.cpu_pts]

    def cpu(self, value: float | None) -> float:
        return _interp(list(self.cpu_pts), self._v(value))

    def frequency_hz(self, value: float | None) -> float:
        return max(0.1, _interp(list(self.freq_pts), self._v(value)))

    def bandwidth_kBps(self, value: float | None) -> float:
        return max(0.0, _interp(list(self.bw_pts), self._v(value)))

    def value_for_cpu(self, cpu: float) -> float:
        """The parameter value whose interpolated CPU is ``cpu`` (CPU rises with the value)."""
        inv = sorted((c, x) for x, c in self.cpu_pts)
        return _interp(inv, cpu)

    def _v(self, value: float | None) -> float:
        return self.cpu_pts[0][0] if value is None else float(value)


@dataclass(frozen=True)
class NodeLaunch:
    """Everything the node script needs (see nodes/casestudy_node.py)."""

    name: str
    computer: str
    parameter: str | None
    value: float | None
    rate_hz: float
    message_bytes: int
    work_ms: float
    target_cpu: float  # CPU units the node should use (Table I x headroom)
    publishes: tuple[str, ...]
    subscribes: tuple[str, ...]

    def argv(self, run_id: str = "") -> list[str]:
        cmd = [ROS_PYTHON, str(NODE_SCRIPT), "--run", run_id, "--name", self.name, "--kind", _kind(self.name),
               "--rate", f"{self.rate_hz:g}", "--bytes", str(self.message_bytes),
               "--work-ms", f"{self.work_ms:.4f}"]
        if self.parameter and self.value is not None:
            cmd += ["--parameter", self.parameter, "--value", f"{self.value:g}"]
        for t in self.publishes:
            cmd += ["--pub", t]
        for t in self.subscribes:
            cmd += ["--sub", t]
        return cmd + [f"__name:={self.name}"]


def _kind(name: str) -> str:
    return name.rstrip("0123456789") or name


def launch_for(node: Node, computer: str, value: float | None, calib: Calibration,
               subscribes: tuple[str, ...] = ()) -> NodeLaunch:
    prof = NodeProfile.of(node)
    if not prof.configurable:
        value = None
    rate = prof.frequency_hz(value)
    topics = node.topics or (f"/{node.name}/out",)
    per_topic_kBps = prof.bandwidth_kBps(value) / len(topics)
    # a std_msgs/String serialises as a 4-byte length + the characters
    size = max(16, int(round(per_topic_kBps * 1000 / rate)) - 4)
    target = max(0.0, prof.cpu(value)) * calib.headroom
    work_s = target / calib.units_per_core / rate - calib.overhead_s
    return NodeLaunch(node.name, computer, prof.parameter, value, rate, size, max(0.0, work_s * 1000), target,
                      tuple(topics), subscribes)
