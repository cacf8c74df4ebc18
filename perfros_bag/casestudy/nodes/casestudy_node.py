#!/usr/bin/python3
"""One node of the paper's case study as a rospy node (run with Debian's /usr/bin/python3).

Plain Python 3 + rospy: this file cannot import perfros_bag (the project's venv is another
interpreter). The launcher (perfros_bag/casestudy/launcher.py) turns a node's parameter
into the numbers below with the calibrated profiles of perfros_bag/casestudy/profiles.py:

    casestudy_node.py --name tracker1 --kind tracker --parameter output_freq --value 22
        --rate 22 --bytes 96 --work-ms 18.7 --pub /tracker1/tracks --sub /experiment/status

Every cycle (``--rate`` Hz, rospy.Rate): ``--work-ms`` milliseconds of busy CPU work
(measured on the thread's CPU clock; the node's real CPU work), then one std_msgs/String of ``--bytes`` characters on
each ``--pub`` topic. Subscriptions only count messages. When the work no longer fits in
the period (its computer's CPU quota is exhausted), the rate drops: that is the overload
the model predicts.

``--calibrate`` prints, as JSON, how many busy-loop iterations one CPU-second runs on
this machine (median of several process_time measurements); for information only.
"""

import argparse
import json
import sys
import time


def burn(iterations):
    """Deterministic integer work: a linear congruential generator."""
    x = 12345
    for _ in range(iterations):
        x = (x * 1103515245 + 12345) & 0x7FFFFFFF
    return x


def burn_cpu(seconds, chunk=500):
    """Busy work until this thread has used ``seconds`` of CPU time.

    Measured on the thread's own CPU clock (what psutil and the cgroup quota count), not in
    iterations: on a shared VM the speed of a fixed loop varied by +-25 % between runs, so a
    fixed iteration count does not mean a fixed CPU cost. When the computer's quota is
    exhausted the thread waits, the cycle takes longer and the rate drops: an overload.
    """
    if seconds <= 0:
        return 0
    end = time.thread_time() + seconds
    n = 0
    while time.thread_time() < end:
        burn(chunk)
        n += chunk
    return n


def calibrate(seconds=0.2, rounds=5):
    n = 20000
    # grow the chunk until one chunk takes ~seconds of CPU
    while True:
        t0 = time.process_time()
        burn(n)
        dt = time.process_time() - t0
        if dt >= seconds / 4:
            break
        n *= 2
    speeds = []
    for _ in range(rounds):
        t0 = time.process_time()
        burn(n)
        dt = time.process_time() - t0
        if dt > 0:
            speeds.append(n / dt)
    return sorted(speeds)[len(speeds) // 2]  # the median: typical, not the best case


def _die_with_parent():
    """Linux: get SIGTERM when the launcher dies, so a killed launcher leaves no node behind."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calibrate", action="store_true")
    ap.add_argument("--name")
    ap.add_argument("--kind", default="")
    ap.add_argument("--parameter", default="")
    ap.add_argument("--value", type=float, default=None)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--bytes", type=int, default=100)
    ap.add_argument("--work-ms", type=float, default=0.0, help="CPU milliseconds of work per cycle")
    ap.add_argument("--pub", action="append", default=[])
    ap.add_argument("--sub", action="append", default=[])
    ap.add_argument("--run", default="", help="the launcher's run id (lets it find its processes)")
    args, _ros_args = ap.parse_known_args(argv)
    if args.calibrate:
        print(json.dumps({"iterations_per_cpu_s": calibrate(), "python": sys.version.split()[0]}))
        return 0
    if not args.name or args.rate <= 0:
        ap.error("--name and a --rate > 0 are required")

    _die_with_parent()
    import rospy
    from std_msgs.msg import String

    rospy.init_node(args.name, anonymous=False)
    if args.parameter and args.value is not None:
        rospy.set_param("~" + args.parameter, args.value)
    rospy.set_param("~kind", args.kind)
    received = {"n": 0}

    def on_message(_msg):
        received["n"] += 1

    pubs = [rospy.Publisher(t, String, queue_size=10) for t in args.pub]
    subs = [rospy.Subscriber(t, String, on_message, queue_size=10) for t in args.sub]
    filler = "x" * max(0, args.bytes - 12)
    rate = rospy.Rate(args.rate)
    work_s = args.work_ms / 1000.0
    seq = 0
    try:
        while not rospy.is_shutdown():
            burn_cpu(work_s)
            head = f"{seq:011d} "
            msg = String(data=(head + filler)[: max(args.bytes, 1)])
            for p in pubs:
                p.publish(msg)
            seq += 1
            rate.sleep()
    except rospy.ROSInterruptException:
        pass
    del subs
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
