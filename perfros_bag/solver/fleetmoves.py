"""Relocation moves of greedy+ (Problem 1) at fleet scale, where :class:`~perfros_bag.solver.local.Improver`
re-sets only settings (groups x computers above :data:`~perfros_bag.solver.local.MOVES_LIMIT`).

A fleet's movable groups belong to one robot each (their allowed computers: that robot and
servers). Per robot, the moves are: a group leaves for a server, a group comes home from
its server, or both at once (one home, one out: a swap through the servers). They are:

- **valued cheaply**: the robot's side exactly (its settings re-set by Algorithm 2's rule
  on it alone, :func:`refit`), each server's side by its *prices*: what one CPU unit buys
  there (the best next step not taken) when a group leaves it, what one costs (the worst
  step taken) when a group comes, zero within its free CPU;
- **ranked by that estimate** over the whole fleet, then each, best first, **re-valued
  exactly** on the state as it is then (every computer it touches re-set by :func:`refit`,
  a server downgrading its least efficient steps to make room and upgrading its best with
  what it freed), and applied only when Σ w·P rises and CPU, links and media hold
  (:meth:`State.change`); the touched servers' prices are then read again.

Rounds repeat until one applies nothing or the deadline. Bookkeeping is incremental: a
move touches its robot and at most two servers, and a server's re-fit starts from its
current levels (a heap over its members' steps), never from scratch.
"""

from __future__ import annotations

import heapq
import time
from collections.abc import Iterable

from perfros_bag.solver.state import EPS, State

#: moves valued exactly per round, at most (the best estimates first)
VERIFY_PER_ROUND = 400
#: a leaving group is tried on this many servers (the cheapest prices first)
OUT_SERVERS = 3
PAIRS = True


def _step_gain(s: State, n: str, k: int) -> tuple[float, float]:
    """(CPU, w·P) of node ``n``'s step from level ``k`` to ``k + 1``."""
    lad = s.ladder[n]
    return lad[k + 1].cpu - lad[k].cpu, s.weight[n] * (lad[k + 1].performance - lad[k].performance)


def _grad(du: float, dp: float) -> float:
    return dp / du if du > EPS else float("inf")


def refit(s: State, c: str, levels: dict[str, int], load: float | None = None) -> dict[str, int] | None:
    """Levels for the nodes of ``levels`` (node -> level to start from) that fit computer
    ``c``: the least efficient steps taken are undone until the load fits, then the best
    steps are taken while they fit (Algorithm 2's rule). None when even every node at its
    lowest level does not fit. ``load``: their CPU at those levels, when the caller knows it."""
    out = dict(levels)
    if load is None:
        load = sum(s.ladder[n][k].cpu for n, k in out.items())
    cap = s.cap[c] + EPS * max(1.0, s.cap[c])
    if load > cap:
        down = [(_grad(*_step_gain(s, n, k - 1)), s.order[n], n) for n, k in out.items() if k > 0]
        heapq.heapify(down)
        while load > cap:
            if not down:
                return None
            _, _, n = heapq.heappop(down)
            k = out[n]
            du, _ = _step_gain(s, n, k - 1)
            out[n], load = k - 1, load - du
            if k - 1 > 0:
                heapq.heappush(down, (_grad(*_step_gain(s, n, k - 2)), s.order[n], n))
        return out  # it was full: nothing left to take
    up = [(-_grad(*_step_gain(s, n, k)), s.order[n], n) for n, k in out.items() if k + 1 < len(s.ladder[n])]
    heapq.heapify(up)
    while up:
        _, _, n = heapq.heappop(up)
        k = out[n]
        du, _ = _step_gain(s, n, k)
        if load + du > cap:
            continue
        out[n], load = k + 1, load + du
        if k + 2 < len(s.ladder[n]):
            heapq.heappush(up, (-_grad(*_step_gain(s, n, k + 1)), s.order[n], n))
    return out


def _value(s: State, levels: dict[str, int]) -> float:
    return sum(s.weight[n] * s.ladder[n][k].performance for n, k in levels.items())


class _Prices:
    """Per server: what one more CPU unit buys (``up``) and what one less costs (``down``)."""

    def __init__(self, s: State, servers: Iterable[str]) -> None:
        self.s = s
        self.up: dict[str, float] = {}
        self.down: dict[str, float] = {}
        for c in servers:
            self.read(c)

    def read(self, c: str) -> None:
        s = self.s
        up = [_grad(*_step_gain(s, n, s.level[n])) for n in s.members[c] if not s.at_max(n)]
        down = [_grad(*_step_gain(s, n, s.level[n] - 1)) for n in s.members[c] if s.level[n] > 0]
        self.up[c] = max(up, default=0.0)
        self.down[c] = min(down, default=0.0)

    def leave(self, c: str, cpu: float, value: float) -> float:
        """The estimated change of ``c``'s value when nodes of ``cpu`` and ``value`` leave it."""
        return self.up[c] * cpu - value

    def come(self, c: str, cpu: float, value: float) -> float:
        """... when nodes of ``cpu`` and ``value`` come to it (its free CPU costs nothing)."""
        return value - self.down[c] * max(0.0, cpu - self.s.free(c))


Move = tuple[str, tuple[int, ...], dict[int, str]]  # robot, its groups that move, group -> target


def fleet_moves(s: State, deadline: float) -> int:
    """Relocation moves between each robot and the servers (the module's description) on
    state ``s`` until none improves or ``deadline`` (``time.monotonic()``); the number
    applied. Every applied move was checked by :meth:`State.change`."""
    servers = [c for c in s.computers if s.kind[c] == "server"]
    robots = {c for c in s.computers if s.kind[c] == "robot"}
    block: dict[str, list[int]] = {}
    for gi, allowed in enumerate(s.group_allowed):
        mine = [c for c in allowed if c in robots]
        if len(mine) == 1 and len(allowed) > 1 and all(c in robots or s.kind[c] == "server" for c in allowed):
            block.setdefault(mine[0], []).append(gi)
    if not block or not servers:
        return 0
    prices = _Prices(s, servers)
    index = {c: i for i, c in enumerate(s.computers)}
    fits: dict[str, dict[tuple[tuple[int, ...], tuple[int, ...]], float | None]] = {}  # per robot, until it changes
    applied = 0
    while time.monotonic() < deadline:
        heap: list[tuple[float, int, float, Move]] = []
        for r in sorted(block, key=index.__getitem__):
            for robot_side, move in _robot_moves(s, prices, r, block[r], index, fits.setdefault(r, {})):
                est = robot_side + _servers_side(s, prices, move)
                if est > 1e-9:
                    heap.append((-est, len(heap), robot_side, move))
            if time.monotonic() > deadline:
                break
        heapq.heapify(heap)
        done = tried = 0
        moved: set[str] = set()  # robots whose estimates are stale: valued again next round
        while heap and tried < VERIFY_PER_ROUND and time.monotonic() < deadline:
            neg, tie, robot_side, move = heapq.heappop(heap)
            if move[0] in moved:
                continue
            est = robot_side + _servers_side(s, prices, move)  # the servers' prices may have moved
            if est <= 1e-9:
                continue
            if heap and est < -heap[0][0] - 1e-12 and est < -neg - 1e-12:
                heapq.heappush(heap, (-est, tie, robot_side, move))  # valued again when it is the best
                continue
            tried += 1
            touched = _apply(s, move)
            if touched:
                done += 1
                moved.add(move[0])
                for c in touched:
                    fits.pop(c, None)
                    if c in prices.up:
                        prices.read(c)
        applied += done
        if not done:
            break
    return applied


def _servers_side(s: State, prices: _Prices, move: Move) -> float:
    """The estimated change of the servers' values by ``move`` at their current prices."""
    r, gis, where = move
    est = 0.0
    for gi in gis:
        cpu, value = _group_cpu_value(s, gi)
        src, dst = s.place[s.groups[gi][0]], where[gi]
        if src != r:
            est += prices.leave(src, cpu, value) if src in prices.up else -value
        if dst != r:
            est += prices.come(dst, cpu, value)
    return est


def _group_cpu_value(s: State, gi: int) -> tuple[float, float]:
    g = s.groups[gi]
    return sum(s.cpu(n) for n in g), sum(s.weight[n] * s.choice(n).performance for n in g)


def _robot_moves(s: State, prices: _Prices, r: str, groups: list[int], index: dict[str, int],
                 fits: dict[tuple[tuple[int, ...], tuple[int, ...]], float | None]) -> list[tuple[float, Move]]:
    """Robot ``r``'s moves with their robot's side (the change of its value): each group
    out (to the :data:`OUT_SERVERS` cheapest allowed servers), home, and one home with one out.
    ``fits``: the robot's side of each move, kept while the robot is unchanged."""
    here = [gi for gi in groups if s.place[s.groups[gi][0]] == r]
    away = [gi for gi in groups if s.place[s.groups[gi][0]] not in (r, None)]
    base = {n: s.level[n] for n in s.members[r]}
    now = _value(s, base)

    def robot_gain(out: tuple[int, ...], home: tuple[int, ...]) -> float | None:
        key = (out, home)
        if key not in fits:
            lv = {n: k for n, k in base.items() if s.group_of[n] not in out}
            for gi in home:
                lv.update({n: s.level[n] for n in s.groups[gi]})
            new = refit(s, r, lv)
            fits[key] = None if new is None else _value(s, new) - now
        return fits[key]

    def targets(gi: int) -> list[str]:
        cpu, value = _group_cpu_value(s, gi)
        opts = [c for c in s.group_allowed[gi] if c in prices.up]
        opts.sort(key=lambda c: (-prices.come(c, cpu, value), index[c]))
        return opts[:OUT_SERVERS]

    out_moves: list[tuple[float, Move]] = []
    for gi in here:
        g = robot_gain((gi,), ())
        if g is None:
            continue
        for c in targets(gi):
            out_moves.append((g, (r, (gi,), {gi: c})))
    moves = list(out_moves)
    for gi in away:
        g = robot_gain((), (gi,))
        if g is not None:
            moves.append((g, (r, (gi,), {gi: r})))
        for go in (here if PAIRS else []):
            g2 = robot_gain((go,), (gi,))
            if g2 is None:
                continue
            best = targets(go)
            if best:
                moves.append((g2, (r, (gi, go), {gi: r, go: best[0]})))
    return moves


def _apply(s: State, move: Move) -> set[str]:
    """Re-value ``move`` exactly on the state as it is and apply it when Σ w·P rises and it
    holds (:meth:`State.change`); the computers it touched (empty: not applied)."""
    r, gis, where = move
    moving = {n: where[gi] for gi in gis for n in s.groups[gi]}
    if any(s.place[n] == c for n, c in moving.items()):
        return set()  # stale: a group already there
    comps = {s.place[n] for n in moving} | set(moving.values())
    comps.discard(None)
    gain = 0.0
    changes: dict[str, tuple[str | None, int]] = {}
    for c in comps:
        assert c is not None
        lv = {n: s.level[n] for n in s.members[c] if n not in moving}
        load = s.load[c] - sum(s.cpu(n) for n in s.members[c] if n in moving)
        for n, t in moving.items():
            if t == c:
                lv[n] = s.level[n]
                load += s.cpu(n)
        new = refit(s, c, lv, load)
        if new is None:
            return set()
        for n, k in new.items():
            if s.place[n] != c or s.level[n] != k:
                changes[n] = (c, k)
                gain += s.weight[n] * (s.ladder[n][k].performance - s.choice(n).performance)
    if gain <= 1e-9 or s.change(changes) is not None:
        return set()
    return {c for c in comps if c is not None}
