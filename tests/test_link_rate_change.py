"""A link re-shaped in place (``Network.set_link_rate``, RQ4's link scenario) keeps carrying.

``tc qdisc change`` keeps a ``tbf``'s queue. Packets the old, larger bucket let in (TCP's GSO
packets of tens of kB) stay queued, and a ``tbf`` whose new bucket is smaller than the packet
at its head never sends it nor anything behind it: RQ4 2026-11-28 04:30 lowered a busy
3,000 kB/s link to 1,000 kB/s with the new rate's own 10 kB bucket, and no byte crossed the
link again (the re-plan's restarted nodes never reached the master).
"""

from __future__ import annotations

import re
import subprocess
import sys
import threading
import time
import uuid
import warnings

import pytest

from perfros_bag.rosrun import network as network_module
from perfros_bag.rosrun.network import NetMode, Network, plan_ends
from perfros_bag.system.types import Computer, Link, System


def _system(kBps: float) -> System:
    return System((Computer("robot1", "robot", 100.0), Computer("server", "server", 400.0)), (),
                  (Link(("robot1", "server"), kBps),))


def _bursts(lines: list[str]) -> list[tuple[int, int]]:
    """(rate bit/s, burst bytes) of every tbf a command line sets."""
    return [(int(r), int(b)) for r, b in re.findall(r"tbf rate (\d+)bit burst (\d+)", "\n".join(lines))]


def test_a_rate_changed_in_place_never_shrinks_the_running_bucket(monkeypatch: pytest.MonkeyPatch) -> None:
    commands: list[str] = []

    def record(argv: list[str], stdin: str | None = None) -> None:
        commands.append(stdin if stdin is not None else " ".join(argv))

    monkeypatch.setattr(network_module, "_run", record)
    system = _system(3000.0)
    net = Network(f"t{uuid.uuid4().hex[:8]}", system, mode=NetMode.NAMESPACES)
    net.ends = plan_ends(system)
    net.namespaces = {"robot1": "ns-robot1", "server": "ns-server"}
    net.apply()
    # 3,000 kB/s = 24 Mbit/s; its bucket holds 10 ms at that rate: 30,000 bytes
    assert _bursts(commands) == [(24_000_000, 30_000)] * 2
    expected = [(1000.0, 8_000_000, 30_000),  # lowered: the 30 kB bucket stays (its queue holds such packets)
                (6000.0, 48_000_000, 60_000),  # raised: its own 10 ms, larger
                (500.0, 4_000_000, 60_000),  # lowered again: the largest bucket it ran with
                (250.0, 2_000_000, 60_000)]
    for kBps, rate_bit, burst in expected:
        commands.clear()
        net.set_link_rate(0, kBps)
        got = _bursts(commands)
        assert got == [(rate_bit, burst)] * 2, (kBps, commands)
        assert all(" change " in c for c in commands)
        assert net.system.links[0].bandwidth_kBps == kBps


RECEIVER = r"""
import socket, sys, threading, time
srv = socket.socket(); srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
srv.bind((sys.argv[1], int(sys.argv[2]))); srv.listen(16)
total = [0]
def read(c):
    while True:
        b = c.recv(65536)
        if not b:
            return
        total[0] += len(b)
def accept():
    while True:
        c, _ = srv.accept()
        threading.Thread(target=read, args=(c,), daemon=True).start()
threading.Thread(target=accept, daemon=True).start()
print("ready", flush=True)
while True:
    time.sleep(0.1)
    print(time.time(), total[0], flush=True)
"""

# an image publisher: 230 kB every 0.2 s (1,150 kB/s), as the case study's camera
SENDER = r"""
import socket, sys, time
s = socket.create_connection((sys.argv[1], int(sys.argv[2])))
msg = b"x" * 230000
while True:
    t = time.time()
    s.sendall(msg)
    time.sleep(max(0.0, 0.2 - (time.time() - t)))
"""

CONNECT = r"""
import socket, sys, time
t = time.time()
socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=float(sys.argv[3])).close()
print(time.time() - t)
"""


@pytest.mark.net
def test_a_busy_link_lowered_in_place_keeps_carrying_and_takes_new_connections() -> None:
    """Three image streams (3,450 kB/s) over a 3,000 kB/s link keep its queue full of GSO
    packets; the link lowered to 1,000 kB/s in place must then carry about 1,000 kB/s and
    accept a new connection (a node reaching the master), not stall."""
    with Network(f"t{uuid.uuid4().hex[:8]}", _system(3000.0)) as net:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            net.create(shaped=True)
        if not net.emulated:  # no namespaces here: the fallback must say why
            assert net.reason
            return
        dst = net.address("server")
        recv = subprocess.Popen(net.wrap("server", [sys.executable, "-c", RECEIVER, dst, "5101"]),
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        senders: list[subprocess.Popen[bytes]] = []
        samples: list[tuple[float, int]] = []
        try:
            assert recv.stdout is not None
            assert recv.stdout.readline().strip() == "ready"
            out = recv.stdout

            def read() -> None:
                for line in out:
                    t, n = line.split()
                    samples.append((float(t), int(n)))

            threading.Thread(target=read, daemon=True).start()
            senders = [subprocess.Popen(net.wrap("robot1", [sys.executable, "-c", SENDER, dst, "5101"]),
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for _ in range(3)]
            time.sleep(3.0)  # the queue fills: 3,450 kB/s offered to 3,000
            net.set_link_rate(0, 1000.0)
            changed = time.time()
            time.sleep(1.0)
            connect = subprocess.run(net.wrap("robot1", [sys.executable, "-c", CONNECT, dst, "5101", "3"]),
                                     capture_output=True, text=True, timeout=20)
            time.sleep(max(0.0, changed + 4.5 - time.time()))

            def received(t: float) -> int:
                return max((n for s, n in samples if s <= t), default=0)

            carried_kBps = (received(changed + 4.0) - received(changed + 1.0)) / 3.0 / 1000.0
        finally:
            for proc in [*senders, recv]:
                proc.kill()
                proc.wait()
        assert connect.returncode == 0, "no new connection across the lowered link: it stalled"
        # tbf counts whole frames: TCP payload is ~96 % of the rate; at least half of it
        assert 500.0 <= carried_kBps <= 1050.0, carried_kBps
