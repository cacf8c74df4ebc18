"""The machine's speed against a fixed reference workload: ``speed_factor``.

The same machine runs the same work at different speeds from one hour to the next (shared
hosts, frequency scaling, a neighbour's load on the cache). :func:`measure_speed` runs a
small, deterministic, CPU-bound workload (:func:`reference_workload`: a pure-Python integer
loop, zlib compression of fixed bytes and a numpy sort of fixed floats) three times and
takes the best CPU time of the calling thread (``time.thread_time``, so waiting for a core
does not count; what the workload itself costs does)::

    speed_factor = REFERENCE_S / measured_s

``REFERENCE_S`` is the workload's best CPU time on the machine the project's figures were
measured on (2 logical cores, 2026-11-26, idle), so the factor is ~1 there; > 1 means this
machine (now) is faster, < 1 slower. A node's CPU measured on a machine with factor f would
be about ``cpu x f`` on the reference machine *if* CPU time scaled with the workload's; see
docs/benchmarks.md ("Machine speed reference") for whether it does, and docs/formats.md for
where the factor is written (``# speed_factor=`` in CPU traces, ``speed_factor`` in
manifest.yaml entries, a characterisation.csv column).
"""

from __future__ import annotations

import math
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass

#: Best-of-3 thread CPU seconds of :func:`reference_workload` on the reference machine
#: (this project's 2-core machine, idle, 2026-11-26): ``speed_factor`` is ~1 there.
REFERENCE_S = 0.055
#: Repetitions of the workload; the fastest counts (the least disturbed).
REPEATS = 3
#: Two speed factors within this share of each other (either way) are the same machine speed
#: (``sweep --repeat-off-speed``, validate's note, the case study's split at and off speed).
SPEED_SHARE = 0.85


def same_speed(speed: float, reference: float, share: float = SPEED_SHARE) -> bool:
    """``speed`` within ``share`` of ``reference``, either way (``share x reference`` ..
    ``reference / share``)."""
    return share * reference <= speed <= reference / share


def speed_distance(speed: float, reference: float) -> float:
    """How far ``speed`` is from ``reference``, as the size of their log ratio (two factors 2x
    apart either way are equally far)."""
    return abs(math.log(speed / reference))

_PY_STEPS = 150_000
_ZLIB_BYTES = 600_000
_NP_SIZE = 400_000


@dataclass(frozen=True)
class Speed:
    """One measurement: the best CPU seconds of the reference workload and the factor."""

    reference_s: float  # the measured best-of-REPEATS CPU seconds
    factor: float  # REFERENCE_S / reference_s


def _python_kernel() -> int:
    x, acc = 1, 0
    for i in range(_PY_STEPS):
        x = (x * 1103515245 + 12345) & 0x7FFFFFFF
        acc ^= x >> (i & 7)
    return acc


_ZLIB_INPUT: bytes | None = None


def _zlib_input() -> bytes:
    """Fixed, mildly compressible bytes: seeded pseudo-random bytes kept to 6 bits each."""
    global _ZLIB_INPUT
    if _ZLIB_INPUT is None:
        import random

        _ZLIB_INPUT = random.Random(21).randbytes(_ZLIB_BYTES).translate(bytes(b & 0x3F for b in range(256)))
    return _ZLIB_INPUT


def _numpy_kernel() -> float:
    import numpy as np

    a = np.arange(_NP_SIZE, dtype=np.float64)
    return float(np.sort(np.sin(a) * a).sum())


def reference_workload() -> int:
    """The fixed workload (~0.06 s of CPU on the reference machine). Deterministic: the same
    result every time (returned, so nothing is optimised away)."""
    acc = _python_kernel()
    acc ^= len(zlib.compress(_zlib_input(), 6))
    acc ^= int(_numpy_kernel()) & 0xFFFF
    return acc


def measure_speed(timer: Callable[[], float] = time.thread_time, repeats: int = REPEATS) -> Speed:
    """Run :func:`reference_workload` ``repeats`` times; the best CPU time gives the factor.

    ``timer``: a CPU clock of the calling thread (tests pass a fake one)."""
    _zlib_input()  # built once, outside the timing
    best = math.inf
    for _ in range(max(1, repeats)):
        t0 = timer()
        reference_workload()
        best = min(best, timer() - t0)
    best = max(best, 1e-6)  # a clock too coarse to see the work: at most a million times faster
    return Speed(best, REFERENCE_S / best)


def speed_problem(value: object) -> str | None:
    """Why ``value`` is not a valid speed factor (a finite number > 0), or None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return f"must be a number, got {value!r}"
    if not math.isfinite(float(value)):
        return f"must be a finite number, got {value!r}"
    if value <= 0:
        return f"must be > 0, got {value!r}"
    return None
