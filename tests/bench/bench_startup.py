"""Start-up of the command line, and ``characterise`` as a whole process against AnyReader.

1. ``perfros-bag --help`` and every ``perfros-bag VERB --help`` as whole processes, next to
   ``python -c pass`` and ``python -c 'import typer'`` (target: each --help <= 0.12 s).
2. ``perfros-bag characterise BAG --out CSV`` on the ~1M small-message ROS 1 bag of
   bench_ingest.py (same generator, same tests/bench/data/ingest/ cache) against a plain
   rosbags AnyReader loop over every raw message, both whole processes, in the same run
   (target >= 20x); with the floors below the CLI: the library's ``read_recording`` and
   ``characterise`` alone, each as a whole ``python -c`` process.

Every command runs ``--repeat`` times, interleaved; reported: best and median wall seconds
and best CPU seconds (user + system of the child). On a shared machine the best figures are
the steadier ones.

    .venv/bin/python tests/bench/bench_startup.py [--scale 1] [--repeat 15] [--skip-characterise]
        [--compare TREE ...]

``--compare TREE`` times another source tree's perfros_bag in the same run (before/after):
    git archive 12880b8 | tar -x -C /tmp/before   # + the built decoder, ingest/_sqlitecells*.so
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
sys.path.insert(0, str(ROOT))

from tests.bench.bench_ingest import generate  # noqa: E402

ANYREADER_SCRIPT = r"""
import sys
from pathlib import Path
from rosbags.highlevel import AnyReader
n = size = 0
with AnyReader([Path(sys.argv[1])]) as reader:
    for _conn, _ts, raw in reader.messages():
        n += 1
        size += len(raw)
print(n, size)
"""

#: the floors: the library alone as a whole process (no CLI), reading only / characterising
READ_SCRIPT = "import sys; from perfros_bag.ingest import read_recording; read_recording(sys.argv[1])"
LIBRARY_SCRIPT = ("import sys; from perfros_bag.characterisation.table import characterise, find_entries; "
                  "characterise(find_entries(sys.argv[1])[0])")

#: the verbs' --help, as the README lists them (casestudy's two sub-commands included)
HELP_ARGS = [[], ["characterise"], ["export"], ["fit"], ["info"], ["record-cpu"], ["report"],
             ["solve"], ["validate"], ["version"], ["casestudy"], ["casestudy", "run"],
             ["casestudy", "cleanup"]]


def _env(tree: Path = ROOT) -> dict[str, str]:
    """``tree``'s perfros_bag (this checkout's by default) first on the path, whatever is installed."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tree), env.get("PYTHONPATH")]))
    return env


def _cli() -> list[str]:
    script = Path(sys.executable).parent / "perfros-bag"  # the installed console script
    return [str(script)] if script.exists() else [sys.executable, "-m", "perfros_bag"]


Command = tuple[list[str], Path]  # argv, and the tree whose perfros_bag it runs


def _run_once(cmd: Command) -> tuple[float, float]:
    """Wall and CPU (user + system) seconds of one whole process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(cmd[0], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, env=_env(cmd[1]))
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def measure(commands: dict[str, Command], repeat: int) -> dict[str, dict[str, float]]:
    """Each command ``repeat`` times, interleaved (so load changes hit every row alike)."""
    walls: dict[str, list[float]] = {name: [] for name in commands}
    cpus: dict[str, list[float]] = {name: [] for name in commands}
    for cmd in commands.values():  # warm-up: page cache, .pyc files
        _run_once(cmd)
    for _ in range(repeat):
        for name, cmd in commands.items():
            wall, cpu = _run_once(cmd)
            walls[name].append(wall)
            cpus[name].append(cpu)
    return {name: {"best": min(walls[name]), "median": statistics.median(walls[name]),
                   "cpu": min(cpus[name])} for name in commands}


def _table(results: dict[str, dict[str, float]]) -> str:
    lines = ["| command | best wall s | median wall s | best CPU s |", "|---|---|---|---|"]
    for name, r in results.items():
        lines.append(f"| `{name}` | {r['best']:.3f} | {r['median']:.3f} | {r['cpu']:.3f} |")
    return "\n".join(lines)


def startup(repeat: int, trees: dict[str, Path]) -> None:
    cli = _cli()
    commands: dict[str, Command] = {"python -c pass": ([sys.executable, "-c", "pass"], ROOT),
                                    "python -c 'import typer'": ([sys.executable, "-c", "import typer"], ROOT)}
    for args in HELP_ARGS:
        for label, tree in trees.items():
            commands[" ".join(["perfros-bag", *args, "--help"]) + label] = ([*cli, *args, "--help"], tree)
    results = measure(commands, repeat)
    print(_table(results))
    slow = [name for name, r in results.items() if name.endswith("--help") and r["best"] > 0.12]
    print(f"target every --help <= 0.12 s (best wall): {'met' if not slow else 'MISSED: ' + ', '.join(slow)}")


def characterise_vs_anyreader(scale: float, data: Path, repeat: int, trees: dict[str, Path]) -> None:
    bag = generate(data, "small", "ros1", scale)
    subprocess.run(["cat", str(bag)], stdout=subprocess.DEVNULL, check=True)  # warm the page cache
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "characterisation.csv"
        anyreader = "python -c '<AnyReader loop>' BAG"
        commands: dict[str, Command] = {
            anyreader: ([sys.executable, "-c", ANYREADER_SCRIPT, str(bag)], ROOT),
            "python -c '<read_recording(BAG)>'": ([sys.executable, "-c", READ_SCRIPT, str(bag)], ROOT),
            "python -c '<characterise(find_entries(BAG))>'": ([sys.executable, "-c", LIBRARY_SCRIPT, str(bag)], ROOT),
        }
        for label, tree in trees.items():
            commands["perfros-bag characterise BAG --out CSV" + label] = (
                [*_cli(), "characterise", str(bag), "--out", str(csv)], tree)
        results = measure(commands, repeat)
        rows = csv.read_text().count("\n") - 1
    check = subprocess.run([sys.executable, "-c", ANYREADER_SCRIPT, str(bag)], capture_output=True,
                           text=True, check=True, env=_env())
    messages = int(check.stdout.split()[0])
    print(f"\n{bag.relative_to(data)}: {bag.stat().st_size / 1e6:.0f} MB, {messages} messages, "
          f"characterise wrote {rows} rows")
    print(_table(results))
    for name, ours in results.items():
        if name == anyreader:
            continue
        wall, cpu = (results[anyreader][key] / ours[key] for key in ("best", "cpu"))
        verdict = f"  target >= 20x {'met' if min(wall, cpu) >= 20 else 'MISSED'}" if "perfros-bag" in name else ""
        print(f"{name}: {wall:5.1f}x faster than the AnyReader loop (wall), {cpu:5.1f}x (CPU){verdict}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=1.0, help="bag size factor (1 = 1M messages)")
    ap.add_argument("--data", type=Path, default=HERE / "data" / "ingest")
    ap.add_argument("--repeat", type=int, default=15, help="runs of each --help command")
    ap.add_argument("--skip-characterise", action="store_true", help="the --help rows only")
    ap.add_argument("--compare", type=Path, action="append", default=[], metavar="TREE",
                    help="also time the perfros_bag of this source tree (e.g. `git archive` of an "
                         "earlier commit) in the same run; repeatable")
    args, _ = ap.parse_known_args()
    args.data.mkdir(parents=True, exist_ok=True)
    trees = {"": ROOT} | {f" [{tree.name}]": tree.resolve() for tree in args.compare}
    startup(args.repeat, trees)
    if not args.skip_characterise:
        characterise_vs_anyreader(args.scale, args.data, max(3, args.repeat // 3), trees)


if __name__ == "__main__":
    main()
