"""A shaped link's head start (issue 29, ``latency.link_burst_ms``): what one camera frame
takes across a link shaped as ``deploy`` shapes it, against the latency model.

Two network namespaces of our own joined by a veth pair, each end under the ``tbf`` qdisc
``deploy`` writes (rosrun/network.py: ``tbf_rate_bit``, ``tbf_burst_bytes``, a 100 ms queue),
and, for contrast, the same link with a bucket of four full frames only. A sender writes a
``--kB`` message every ``--period`` s over TCP (a ROS 1 image publisher's pattern); the
receiver takes the time from the sender's clock reading before the write to the last byte
read (one machine, one clock). Printed per bucket: p50 / mean / p95 of the transfer, beside
the model's ``kB / (0.96 x bandwidth)`` less the bucket's ms (``link_burst_ms``).

    .venv/bin/python tests/bench/bench_link_burst.py [--kBps 3000] [--kB 230.4] [--period 0.2]
        [--messages 40]

Needs root and iproute2. Traffic goes only to the addresses it gives the veth ends inside its
own namespaces; both namespaces (and with them the veth pair and qdiscs) are removed on exit,
Ctrl-C and error. ~20 s.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from perfros_bag.rosrun.network import LATENCY_MS, tbf_burst_bytes, tbf_rate_bit  # noqa: E402

RECEIVER = r"""
import socket, struct, sys, time
s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind((sys.argv[1], int(sys.argv[2]))); s.listen(1)
c, _ = s.accept()
while True:
    h = b""
    while len(h) < 12:
        x = c.recv(12 - len(h))
        if not x:
            sys.exit(0)
        h += x
    t0, n = struct.unpack("!dI", h)
    got = 0
    while got < n:
        got += len(c.recv(min(65536, n - got)))
    print((time.time() - t0) * 1000, flush=True)
"""

SENDER = r"""
import socket, struct, sys, time
s = socket.create_connection((sys.argv[1], int(sys.argv[2]))); s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
msg = b"x" * int(float(sys.argv[3]) * 1000)
for _ in range(int(sys.argv[5])):
    s.sendall(struct.pack("!dI", time.time(), len(msg)) + msg)
    time.sleep(float(sys.argv[4]))
s.close()
"""


def run(cmd: list[str]) -> None:
    subprocess.run(cmd, check=True, capture_output=True)


def measure(kbps: float, kb: float, period: float, messages: int, burst: int) -> list[float]:
    tag = uuid.uuid4().hex[:6]
    a, b = f"pfblb{tag}a", f"pfblb{tag}b"
    ip_a, ip_b = "10.231.78.1", "10.231.78.2"
    try:
        run(["ip", "netns", "add", a])
        run(["ip", "netns", "add", b])
        run(["ip", "link", "add", f"lb{tag}a", "type", "veth", "peer", "name", f"lb{tag}b"])
        for ns, dev, addr in ((a, f"lb{tag}a", ip_a), (b, f"lb{tag}b", ip_b)):
            run(["ip", "link", "set", dev, "netns", ns])
            run(["ip", "-n", ns, "addr", "add", f"{addr}/30", "dev", dev])
            run(["ip", "-n", ns, "link", "set", dev, "up"])
            run(["ip", "-n", ns, "link", "set", "lo", "up"])
            rate = tbf_rate_bit(kbps)
            run(["ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", dev, "root", "tbf", "rate", f"{rate}bit",
                 "burst", str(burst), "latency", f"{LATENCY_MS}ms"])
        port = "47124"
        recv = subprocess.Popen(["ip", "netns", "exec", b, sys.executable, "-c", RECEIVER, ip_b, port],
                                stdout=subprocess.PIPE, text=True)
        try:
            for _ in range(50):  # until the receiver listens
                if subprocess.run(["ip", "netns", "exec", b, "ss", "-ltn", f"sport = :{port}"], capture_output=True,
                                  text=True).stdout.count("LISTEN"):
                    break
                subprocess.run(["sleep", "0.1"], check=True)
            run(["ip", "netns", "exec", a, sys.executable, "-c", SENDER, ip_b, port, str(kb), str(period),
                 str(messages)])
            out, _ = recv.communicate(timeout=30)
        finally:
            if recv.poll() is None:
                recv.kill()
        return [float(x) for x in out.split()][3:]  # the first messages open TCP's window
    finally:
        for ns in (a, b):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--kBps", type=float, default=3000.0)
    ap.add_argument("--kB", type=float, default=230.4, help="message size (the case study's 320x240 RGB frame)")
    ap.add_argument("--period", type=float, default=0.2)
    ap.add_argument("--messages", type=int, default=40)
    args = ap.parse_args(argv)
    if os.geteuid() != 0:
        print("needs root (ip netns, tc)", file=sys.stderr)
        return 1
    full = args.kB / (0.96 * args.kBps) * 1000
    deploy_burst = tbf_burst_bytes(tbf_rate_bit(args.kBps))
    print(f"{args.kB:g} kB every {args.period:g} s over {args.kBps:g} kB/s; the model without a head start: "
          f"{full:.1f} ms; load {os.getloadavg()[0]:.2f}")
    for label, burst in (("deploy's bucket", deploy_burst), ("four frames", 4 * 1514)):
        head = burst / (tbf_rate_bit(args.kBps) / 8) * 1000
        got = measure(args.kBps, args.kB, args.period, args.messages, burst)
        print(f"{label:16s} {burst:6d} B = {head:4.1f} ms: model {max(0.0, full - head):5.1f} ms, measured p50 "
              f"{statistics.median(got):5.1f} mean {statistics.mean(got):5.1f} p95 "
              f"{sorted(got)[int(0.95 * len(got))]:5.1f} ms over {len(got)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
