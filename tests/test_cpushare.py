"""The fair-share rule of a capped computer (system/cpushare.py) against a brute-force
search for the water level and against hand-worked cases."""

from __future__ import annotations

import math
import random

import pytest

from perfros_bag.system.cpushare import Demand, fair_shares, share_level


def brute_level(capacity: float, demands: list[Demand], sustained: bool = False) -> float:
    """The level L with Σ min(need, k·L) = capacity (k = 1 when ``sustained``), by bisection
    (independent of the module's sort-and-sweep)."""
    lo, hi = 0.0, max(d.need for d in demands) + 1.0
    for _ in range(200):
        mid = (lo + hi) / 2
        used = sum(min(min(d.need, d.max_units), (1.0 if sustained else max(1.0, d.threads)) * mid)
                   for d in demands)
        lo, hi = (mid, hi) if used < capacity else (lo, mid)
    return lo


def test_needs_that_fit_are_met() -> None:
    ds = [Demand("a", 10), Demand("b", 20)]
    assert fair_shares(40, ds) == {"a": 10, "b": 20}
    assert share_level(40, ds) == math.inf


def test_small_need_met_first() -> None:
    # proportional sharing would give a 40 * 5/85 = 2.35; CFS gives it its 5
    shares = fair_shares(40, [Demand("a", 5), Demand("b", 40), Demand("c", 40)])
    assert shares["a"] == pytest.approx(5)
    assert shares["b"] == pytest.approx(17.5)
    assert shares["c"] == pytest.approx(17.5)


def test_threads_count_as_slices() -> None:
    shares = fair_shares(30, [Demand("one", 40), Demand("two", 40, threads=2)])
    assert shares["one"] == pytest.approx(10)
    assert shares["two"] == pytest.approx(20)


def test_a_sustained_overload_gives_one_slice_per_node() -> None:
    shares = fair_shares(30, [Demand("one", 40), Demand("two", 40, threads=2)], sustained=True)
    assert shares == pytest.approx({"one": 15, "two": 15})
    assert share_level(30, [Demand("one", 40), Demand("two", 40, threads=2)], sustained=True) == pytest.approx(15)
    # a small need is still met first, threads or not
    shares = fair_shares(30, [Demand("a", 4, threads=3), Demand("b", 40, threads=2), Demand("c", 40)], sustained=True)
    assert shares == pytest.approx({"a": 4, "b": 13, "c": 13})


def test_max_units_bounds_the_need() -> None:
    shares = fair_shares(150, [Demand("a", 200, max_units=100), Demand("b", 100)])
    # a can run 100 at most; 100 + 100 > 150, so both get the level, 75
    assert shares == pytest.approx({"a": 75, "b": 75})


@pytest.mark.parametrize("sustained", [False, True])
@pytest.mark.parametrize("seed", range(40))
def test_random_against_bisection(seed: int, sustained: bool) -> None:
    rng = random.Random(seed)
    ds = [Demand(f"n{i}", rng.uniform(0, 50), threads=rng.choice([1, 1, 2, 3]),
                 max_units=rng.choice([math.inf, rng.uniform(10, 60)])) for i in range(rng.randint(1, 8))]
    cap = rng.uniform(1, 120)
    shares = fair_shares(cap, ds, sustained=sustained)
    want = sum(min(d.need, d.max_units) for d in ds)
    if want <= cap:
        assert shares == pytest.approx({d.name: min(d.need, d.max_units) for d in ds})
        return
    assert sum(shares.values()) == pytest.approx(cap)
    level = brute_level(cap, ds, sustained)
    for d in ds:
        k = 1.0 if sustained else max(1.0, d.threads)
        assert shares[d.name] == pytest.approx(min(min(d.need, d.max_units), k * level), abs=1e-6)
