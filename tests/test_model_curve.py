"""Curve.inverse: the closed forms agree with bisection and with the curve itself."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from perfros_bag.system.types import Curve

coef = st.floats(min_value=-50, max_value=50, allow_nan=False).filter(lambda v: abs(v) > 1e-3)


@st.composite
def monotone_curves(draw: st.DrawFn) -> Curve:
    form = draw(st.sampled_from(["linear", "log", "quadratic", "power"]))
    lo = draw(st.floats(min_value=0.5, max_value=100))
    hi = lo + draw(st.floats(min_value=0.5, max_value=200))
    scale = draw(st.sampled_from([1.0, 100.0]))
    if form == "quadratic":
        a, b = draw(coef), draw(coef)
        # keep the vertex outside the domain so the curve is monotone on it
        vertex = -b / (2 * a) * scale
        if lo <= vertex <= hi:
            b = -2 * a * (lo / scale - 1.0)
        coefs: tuple[float, ...] = (a, b, draw(coef))
    elif form == "power":
        coefs = (draw(coef), draw(st.floats(min_value=-3, max_value=3).filter(lambda v: abs(v) > 0.05)))
    else:
        coefs = (draw(coef), draw(coef))
    return Curve(form, coefs, (lo, hi), scale)


@settings(max_examples=300, deadline=None)
@given(monotone_curves(), st.floats(min_value=0, max_value=1))
def test_inverse_matches_bisection(curve: Curve, t: float) -> None:
    lo, hi = curve.domain
    target_x = lo + t * (hi - lo)
    y = curve(target_x)
    x = curve.inverse(y)
    assert lo <= x <= hi
    assert math.isclose(curve(x), y, rel_tol=1e-6, abs_tol=1e-6)
    ref = curve._bisect(y, lo, hi, curve(hi) >= curve(lo), 1e-12)
    assert math.isclose(x, ref, rel_tol=1e-6, abs_tol=1e-6 * max(1.0, hi))


def test_inverse_clamps_outside_the_range() -> None:
    c = Curve("log", (66.62, 56.308), (80.0, 200.0), 100.0)
    assert c.inverse(-1000.0) == 80.0
    assert c.inverse(1000.0) == 200.0
    assert math.isclose(c.inverse(c(123.0)), 123.0, rel_tol=1e-12)
    flat = Curve("linear", (0.0, 5.0), (1.0, 2.0))
    assert 1.0 <= flat.inverse(5.0) <= 2.0
