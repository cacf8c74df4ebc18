"""The fitting library: known curves are recovered, model selection rules, monotonicity."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from perfros_bag.errors import PerfrosError
from perfros_bag.fitting.build import solver_curve
from perfros_bag.fitting.regression import (
    FitError,
    clip_domain,
    eligible_forms,
    fit_curve,
    fit_form,
    is_monotone,
    loo_rmse,
)
from perfros_bag.system.types import Curve

# (form, true coefficients, x range): shapes distinct enough that 20 noisy points decide.
KNOWN = [
    ("linear", (3.0, 2.0), (1.0, 10.0)),
    ("log", (40.0, 10.0), (0.5, 10.0)),
    ("quadratic", (2.0, -3.0, 5.0), (0.5, 6.0)),
    ("power", (10.0, 0.5), (0.2, 10.0)),
]


def _truth(form: str, coef: tuple[float, ...], x: np.ndarray) -> np.ndarray:
    if form == "linear":
        return coef[0] * x + coef[1]
    if form == "log":
        return coef[0] * np.log(x) + coef[1]
    if form == "quadratic":
        return coef[0] * x**2 + coef[1] * x + coef[2]
    return coef[0] * x ** coef[1]


def _jacobian(form: str, coef: tuple[float, ...], x: np.ndarray) -> np.ndarray:
    if form == "linear":
        return np.column_stack([x, np.ones_like(x)])
    if form == "log":
        return np.column_stack([np.log(x), np.ones_like(x)])
    if form == "quadratic":
        return np.column_stack([x**2, x, np.ones_like(x)])
    return np.column_stack([x ** coef[1], coef[0] * x ** coef[1] * np.log(x)])


@pytest.mark.parametrize("form,coef,span", KNOWN)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_known_curve_with_noise_is_recovered(form: str, coef: tuple[float, ...], span: tuple[float, float],
                                             seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = np.linspace(*span, 20)
    clean = _truth(form, coef, x)
    noise_sd = 0.01 * float(clean.max() - clean.min())
    y = clean + rng.normal(0.0, noise_sd, size=x.size)
    fit = fit_curve(x.tolist(), y.tolist())
    assert fit.form == form, fit.candidates
    # Coefficients within 4 standard errors of the truth (least-squares covariance
    # sigma² (JᵀJ)⁻¹ with J the model's Jacobian at the true coefficients).
    se = np.sqrt(np.diag(noise_sd**2 * np.linalg.inv(_jacobian(form, coef, x).T @ _jacobian(form, coef, x))))
    for got, want, s in zip(fit.coef, coef, se, strict=True):
        assert abs(got - want) <= 4 * s, (fit.coef, coef, se)
    assert fit.r2 > 0.99
    assert not fit.warnings


def test_scale_is_applied_to_the_input() -> None:
    x = np.array([80.0, 120.0, 160.0, 200.0, 240.0])
    y = 66.62 * np.log(x / 100) + 56.308
    fit = fit_curve(x.tolist(), y.tolist(), scale=100, forms=["log"])
    assert fit.coef == pytest.approx((66.62, 56.308), rel=1e-9)
    assert fit.curve(150) == pytest.approx(66.62 * math.log(1.5) + 56.308)


def test_least_squares_matches_numpy_polyfit() -> None:
    rng = np.random.default_rng(7)
    x = np.linspace(1, 9, 12)
    y = 0.5 * x**2 - 2 * x + 3 + rng.normal(0, 0.4, 12)
    assert fit_form("quadratic", x, y) == pytest.approx(tuple(np.polyfit(x, y, 2)), rel=1e-9)
    assert fit_form("linear", x, y) == pytest.approx(tuple(np.polyfit(x, y, 1)), rel=1e-9)
    assert fit_form("log", x, y) == pytest.approx(tuple(np.polyfit(np.log(x), y, 1)), rel=1e-9)


def test_power_fit_minimises_squares_in_the_original_space() -> None:
    rng = np.random.default_rng(3)
    x = np.linspace(0.5, 4, 10)
    y = 3 * x**1.5 + rng.normal(0, 0.3, 10)
    a, b = fit_form("power", x, y)
    sse = float(np.sum((a * x**b - y) ** 2))
    for da in (-0.01, 0.01):
        for db in (-0.01, 0.01):
            assert sse <= float(np.sum(((a + da) * x ** (b + db) - y) ** 2))


def test_loo_of_a_line_matches_the_hat_matrix_formula() -> None:
    rng = np.random.default_rng(11)
    x = np.linspace(0, 10, 9)
    y = 2 * x + 1 + rng.normal(0, 1, 9)
    design = np.column_stack([x, np.ones_like(x)])
    hat = design @ np.linalg.inv(design.T @ design) @ design.T
    resid = y - hat @ y
    loo = resid / (1 - np.diag(hat))
    assert loo_rmse("linear", x, y) == pytest.approx(math.sqrt(float(np.mean(loo**2))), rel=1e-9)


def test_never_as_many_coefficients_as_points() -> None:
    three = np.array([1.0, 2.0, 3.0])
    assert "quadratic" not in eligible_forms(three, three)
    assert set(eligible_forms(three, three)) == {"linear", "log", "power"}
    assert eligible_forms(three[:2], three[:2]) == ["linear"]
    four = np.array([1.0, 2.0, 3.0, 4.0])
    assert "quadratic" in eligible_forms(four, four)
    # log and power need positive inputs, power positive outputs
    assert set(eligible_forms(np.array([0.0, 1, 2, 3]), four)) == {"linear", "quadratic"}
    assert "power" not in eligible_forms(four, np.array([0.0, 1, 2, 3]))


def test_two_points_give_the_exact_line_with_a_warning() -> None:
    fit = fit_curve([10, 20], [30, 50])
    assert fit.form == "linear" and fit.coef == pytest.approx((2.0, 10.0))
    assert fit.loo_rmse is None
    assert any("2 distinct points" in w for w in fit.warnings)


def test_three_points_choose_among_two_coefficient_forms() -> None:
    fit = fit_curve([1, 2, 3], [1, 4, 9.5])
    assert fit.form != "quadratic"
    assert set(fit.candidates) == {"linear", "log", "power"}
    assert min(v for v in fit.candidates.values() if v is not None) == fit.loo_rmse


def test_poor_fit_warns() -> None:
    fit = fit_curve([1, 2, 3, 4, 5, 6], [10, 50, 5, 60, 8, 40])
    assert fit.r2 < 0.9
    assert any("R²" in w for w in fit.warnings)


def test_flat_noisy_data_is_not_flagged_for_r2() -> None:
    fit = fit_curve([200, 500, 3000], [2.501, 2.514, 2.502])
    assert not any("R²" in w for w in fit.warnings)


@pytest.mark.parametrize("x,y", [([5, 5, 5], [1, 2, 3]), ([1], [2]), ([1, 2, float("nan")], [1, 2, 3])])
def test_unfittable_points_raise(x: list[float], y: list[float]) -> None:
    with pytest.raises(FitError) as info:
        fit_curve(x, y)
    assert isinstance(info.value, PerfrosError)  # a user error: the CLI prints one line, never a traceback


def _grid_nondecreasing(curve: Curve, n: int = 2001) -> bool:
    xs = np.linspace(*curve.domain, n)
    v = np.array([curve(float(x)) for x in xs])
    return bool(np.all(np.diff(v) >= -1e-9 * max(1.0, float(np.abs(v).max()))))


def test_non_monotone_data_falls_back_to_a_monotone_form() -> None:
    # rises then falls: a quadratic fits best but decreases at the end
    x = [10, 20, 30, 40, 50, 60]
    y = [10, 45, 70, 82, 80, 70]
    free = fit_curve(x, y, scale=100)
    assert free.form == "quadratic" and not _grid_nondecreasing(free.curve)
    fit = fit_curve(x, y, scale=100, monotone="nondecreasing")
    assert fit.form != "quadratic"
    assert _grid_nondecreasing(fit.curve)
    assert any("not non-decreasing" in w for w in fit.warnings)


def test_decreasing_data_fall_back_to_a_constant() -> None:
    fit = fit_curve([1, 2, 3, 4], [40, 30, 20, 10], monotone="nondecreasing")
    assert fit.form == "linear" and fit.coef == pytest.approx((0.0, 25.0))
    assert any("constant" in w for w in fit.warnings)


def test_either_direction_accepts_a_decreasing_curve() -> None:
    fit = fit_curve([1, 2, 3, 4, 5], [50, 40, 30, 20, 10], monotone="either")
    assert fit.form == "linear" and fit.coef[0] == pytest.approx(-10.0)
    assert is_monotone(fit.curve, "either") and not is_monotone(fit.curve, "nondecreasing")


def test_clip_domain_keeps_the_output_within_range() -> None:
    c = Curve("log", (66.62, 56.308), (80, 200), 100)  # gives 102.5 at 200
    clipped, msg = clip_domain(c, 0.0, 100.0)
    assert msg is not None and "narrowed" in msg
    assert clipped.domain[0] == 80 and clipped.domain[1] < 200
    assert clipped(clipped.domain[1]) == pytest.approx(100.0, abs=1e-6)
    assert math.exp((100 - 56.308) / 66.62) * 100 == pytest.approx(clipped.domain[1], rel=1e-6)
    same, none = clip_domain(Curve("linear", (10, 0), (1, 5), 1), 0, 100)
    assert none is None and same.domain == (1, 5)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.0, 100.0), min_size=3, max_size=8))
def test_enforced_cpu_to_performance_is_monotone_and_in_range(perf: list[float]) -> None:
    cpu = [20.0 + 10 * i for i in range(len(perf))]
    c2p = fit_curve(cpu, perf, scale=100, monotone="nondecreasing")
    p2c = fit_curve(cpu, cpu, monotone="either")
    curve, _ = solver_curve(c2p, p2c, max(perf))
    assert _grid_nondecreasing(curve)
    lo, hi = curve.domain
    assert curve(lo) >= -1e-6 and curve(hi) <= max(perf) + 1e-6
    assert cpu[0] <= lo <= hi <= cpu[-1]


# The paper's Table I (CPU -> performance) and the reference implementation's Fig 4
# regressions (casestudy.md, x = CPU / 100).
TABLE_I = {
    "tracker": ([80, 120, 160, 200], [40, 70, 90, 100], lambda x: 66.62 * math.log(x) + 56.308),
    "model": ([17, 40, 60], [20, 70, 100], lambda x: 63.707 * math.log(x) + 132.16),
    "amcl": ([19, 41, 66], [20, 50, 100], lambda x: 135.4 * x * x + 55.126 * x + 4.6383),
    "navigation": ([25, 39, 50], [10, 65, 100], lambda x: 129.12 * math.log(x) + 188.36),
}


@pytest.mark.parametrize("node", sorted(TABLE_I))
def test_table_i_agrees_with_the_reference_regressions(node: str) -> None:
    cpu, perf, reference = TABLE_I[node]
    fit = fit_curve(cpu, perf, scale=100, monotone="nondecreasing")
    for c, p in zip(cpu, perf, strict=True):
        assert fit.curve(c) == pytest.approx(reference(c / 100), abs=3.0), (node, c)
        assert fit.curve(c) == pytest.approx(p, abs=3.0)
    assert fit.r2 > 0.99
    assert _grid_nondecreasing(fit.curve)


def test_navigation_reproduces_the_reference_log_fit() -> None:
    cpu, perf, _ = TABLE_I["navigation"]
    fit = fit_curve(cpu, perf, scale=100)
    assert fit.form == "log"
    assert fit.coef == pytest.approx((129.12, 188.36), abs=0.01)


def test_exactly_flat_data_give_the_constant_line() -> None:
    fit = fit_curve([4, 3500, 10000], [5.0, 5.0, 5.0])
    assert fit.form == "linear" and fit.coef == pytest.approx((0.0, 5.0), abs=1e-12)
    assert fit.r2 == 1.0 and not fit.warnings


def test_a_simpler_form_within_parsimony_of_the_best_is_preferred() -> None:
    rng = np.random.default_rng(0)
    x = np.linspace(1, 10, 20)
    y = 3 * x + 2 + rng.normal(0, 0.1, 20)
    fit = fit_curve(x.tolist(), y.tolist())
    assert fit.form == "linear"
    best = min(v for v in fit.candidates.values() if v is not None)
    assert fit.candidates["linear"] is not None and fit.candidates["linear"] <= 1.05 * best
