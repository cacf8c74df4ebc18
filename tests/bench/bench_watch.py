"""``watch``'s own CPU: the watcher's process CPU time over its wall time while it watches
N publishers (default 12, the case study's three robots' and servers' nodes and more), each
answering ``getBusStats`` and ``getPid`` over real XML-RPC from another process (a fake ROS 1
master and nodes on loopback, so only the watcher's own work is in its CPU time).

    .venv/bin/python tests/bench/bench_watch.py [--nodes 12] [--window 5] [--windows 6]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

FAKE = r'''
import json, os, sys, threading, time
from xmlrpc.server import SimpleXMLRPCServer
n = int(sys.argv[1]); t0 = time.time(); uris = {}
def serve(funcs):
    s = SimpleXMLRPCServer(("127.0.0.1", 0), logRequests=False, allow_none=True)
    for k, f in funcs.items():
        s.register_function(f, k)
    threading.Thread(target=s.serve_forever, daemon=True).start()
    return f"http://127.0.0.1:{s.server_address[1]}/"
def node(i):
    def stats(caller):
        m = int((time.time() - t0) * 10)
        return [1, "", [[[f"/n{i}/out", [[1, m * 1010, m * 1000, m, 0]]]], [], []]]
    return {"getBusStats": stats, "getPid": lambda caller: [1, "", os.getpid()]}
for i in range(n):
    uris[f"/n{i}"] = serve(node(i))
pubs = [[f"/n{i}/out", [f"/n{i}"]] for i in range(n)]
master = serve({"getSystemState": lambda c: [1, "", [pubs, [], []]],
                "lookupNode": lambda c, name: [1, "", uris[name]],
                "getPid": lambda c: [1, "", os.getpid()],
                "getTopicTypes": lambda c: [1, "", [[t, "std_msgs/String"] for t, _ in pubs]]})
print(master, flush=True)
time.sleep(3600)
'''


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--nodes", type=int, default=12)
    ap.add_argument("--window", type=float, default=5.0)
    ap.add_argument("--windows", type=int, default=6)
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from perfros_bag.watch.loop import watch

    fake = subprocess.Popen([sys.executable, "-c", FAKE, str(args.nodes)], stdout=subprocess.PIPE, text=True)
    try:
        assert fake.stdout is not None
        uri = fake.stdout.readline().strip()
        with tempfile.TemporaryDirectory() as d:
            plan = Path(d) / "plan.json"
            plan.write_text(json.dumps({
                "format": "perfros-bag/plan@1", "problem": 1, "method": "bench", "status": "optimal",
                "computers": {"host": {"kind": "server", "capacity": 400, "cpu": 0}}, "links": [],
                "nodes": {f"n{i}": {"computer": "host", "cpu": 1, "performance": 50, "weight": 1,
                                    "topics": {f"/n{i}/out": {"frequency_hz": 10.0, "bandwidth_kBps": 10.0}}}
                          for i in range(args.nodes)}}))
            cpu0, wall0 = time.process_time(), time.monotonic()
            result = watch(plan, master_uri=uri, window_s=args.window, windows=args.windows,
                           on_window=lambda doc, new: None)
            cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    finally:
        fake.kill()
        fake.wait()
    print("| nodes | window s | windows | wall s | watcher CPU s | % of one core | alarms |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    print(f"| {args.nodes} | {args.window:g} | {result.windows} | {wall:.1f} | {cpu:.3f} | "
          f"{100 * cpu / wall:.2f} | {len(result.alarms)} |")


if __name__ == "__main__":
    main()
