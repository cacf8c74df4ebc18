"""Curve fitting for the paper's regressions (section IV-B, Fig 3 and 4).

Each relation (parameter -> CPU, CPU -> performance, ...) is fitted with every candidate
form of :class:`~perfros_bag.system.types.Curve` (linear, log, quadratic, power) by least squares
on transformed features (scikit-learn's ``LinearRegression``; power in log space, then
refined by nonlinear least squares), and the form with the smallest leave-one-out error
is kept. A form never has as many coefficients as there are points, except that two
points get the (exact) line. Constraints the solver relies on are enforced here:

- ``monotone="nondecreasing"`` (CPU -> performance) or ``"either"`` (parameter -> CPU,
  whose inverse maps a CPU level back to a parameter value): a form that breaks it on the
  domain is skipped for the next best, and the line is the last resort (its slope is
  clamped at 0 for "nondecreasing");
- :func:`clip_domain` narrows a non-decreasing curve's domain so that its output stays
  within ``[lo, hi]`` (performance within ``[0, max observed]``).

Every such decision is recorded in :attr:`FittedRelation.warnings` (callers warn with them).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt

from perfros_bag.errors import PerfrosError
from perfros_bag.fitting.modelfile import FittedRelation
from perfros_bag.limits import MAX_COEFFICIENT
from perfros_bag.system.types import CURVE_FORMS, CURVE_NCOEF, Curve, CurveForm

Monotone = Literal["nondecreasing", "either"] | None
FloatArray = npt.NDArray[np.float64]

#: warn below this R².
R2_WARN = 0.9
#: points whose range is below this fraction of their mean are "constant": R² says nothing
#: about them (it only measures noise), so no R² warning.
FLAT_SPREAD = 0.05
#: a simpler form is preferred when its leave-one-out RMSE is within this fraction of the best.
PARSIMONY = 0.05
#: a power form's exponent beyond this is treated as a failed fit (overflow territory).
_MAX_EXPONENT = 50.0
#: how many points the monotonicity check samples on a domain.
_GRID = 513


class FitError(PerfrosError):
    """The points cannot be fitted at all (fewer than 2 distinct inputs, non-finite values).
    A user error like any other: uncaught, it is one line, not a traceback."""


# --- one form ---------------------------------------------------------------------------

def _features(form: CurveForm, x: FloatArray) -> FloatArray:
    if form == "linear":
        return x[:, None]
    if form == "log":
        return np.log(x)[:, None]
    if form == "quadratic":
        return np.column_stack([x * x, x])
    if form == "power":
        return np.log(x)[:, None]
    raise ValueError(f"unknown form {form!r}")


def fit_form(form: CurveForm, x: Sequence[float] | FloatArray, y: Sequence[float] | FloatArray) -> tuple[float, ...]:
    """Least-squares coefficients of ``form`` (in :class:`Curve` order) for points (x, y),
    x already divided by the scale: scikit-learn's ``LinearRegression`` on the transformed
    features (power: on logs, then refined by Gauss-Newton in the original space)."""
    from sklearn.linear_model import LinearRegression

    xa = np.asarray(x, dtype=float)
    ya = np.asarray(y, dtype=float)
    if form == "power":
        reg = LinearRegression().fit(_features(form, xa), np.log(ya))
        return _power_start(xa, ya, float(reg.intercept_), float(reg.coef_[0]))
    reg = LinearRegression().fit(_features(form, xa), ya)
    coefs = [float(c) for c in reg.coef_]
    return (*coefs, float(reg.intercept_))


def _lstsq_form(form: CurveForm, x: FloatArray, y: FloatArray) -> tuple[float, ...]:
    """The same fit as :func:`fit_form` with numpy alone (leave-one-out refits: no
    scikit-learn overhead per fold)."""
    feats = _features(form, x)
    design = np.column_stack([feats, np.ones(len(x))])
    target = np.log(y) if form == "power" else y
    sol = np.linalg.lstsq(design, target, rcond=None)[0]
    if form == "power":
        return _power_start(x, y, float(sol[1]), float(sol[0]))
    return tuple(float(v) for v in sol)


def _power_start(x: FloatArray, y: FloatArray, log_a: float, b: float) -> tuple[float, float]:
    """Refine the log-space solution; NaNs when it is out of floating-point range."""
    if not (math.isfinite(log_a) and math.isfinite(b)) or abs(log_a) > 700 or abs(b) > _MAX_EXPONENT:
        return math.nan, math.nan
    return _refine_power(x, y, math.exp(log_a), b)


def _refine_power(x: FloatArray, y: FloatArray, a: float, b: float) -> tuple[float, float]:
    """Least squares of a*x**b in the original space (the log-space fit weighs small y too
    much): Gauss-Newton with step halving from the log-space solution."""
    lx = np.log(x)

    def sse(pa: float, pb: float) -> float:
        with np.errstate(all="ignore"):
            r = pa * x ** pb - y
            v = float(np.sum(r * r))
        return v if math.isfinite(v) else math.inf

    cur = sse(a, b)
    for _ in range(50):
        with np.errstate(all="ignore"):
            xb = x ** b
            jac = np.column_stack([xb, a * xb * lx])
            resid = a * xb - y
        if not (np.all(np.isfinite(jac)) and np.all(np.isfinite(resid))):
            break
        step = np.linalg.lstsq(jac, -resid, rcond=None)[0]
        t = 1.0
        while t > 1e-6:
            na, nb = a + t * float(step[0]), b + t * float(step[1])
            new = sse(na, nb)
            if new < cur:
                break
            t /= 2
        else:
            break
        improved = cur - new
        a, b, cur = na, nb, new
        if improved <= 1e-14 * max(1.0, cur):
            break
    return a, b


def predict(form: CurveForm, coef: Sequence[float], x: Sequence[float] | FloatArray) -> FloatArray:
    """The curve's outputs at (already scaled) inputs ``x``."""
    xa = np.asarray(x, dtype=float)
    c = coef
    with np.errstate(all="ignore"):
        if form == "linear":
            return np.asarray(c[0] * xa + c[1], dtype=float)
        if form == "log":
            return np.asarray(c[0] * np.log(xa) + c[1], dtype=float)
        if form == "quadratic":
            return np.asarray(c[0] * xa * xa + c[1] * xa + c[2], dtype=float)
        return np.asarray(c[0] * xa ** c[1], dtype=float)


def r_squared(y: FloatArray, yhat: FloatArray) -> float:
    """1 - SS_res/SS_tot; for constant data 1.0 when the fit is exact, else 0.0."""
    ss_res = float(np.sum((y - yhat) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    scale = max(1.0, float(np.max(np.abs(y))))
    if ss_tot <= 1e-18 * scale * scale * len(y):
        return 1.0 if ss_res <= 1e-12 * scale * scale * len(y) else 0.0
    return 1.0 - ss_res / ss_tot


def loo_rmse(form: CurveForm, x: FloatArray, y: FloatArray) -> float:
    """Root mean squared leave-one-out prediction error of ``form``."""
    errs = []
    idx = np.arange(len(x))
    for i in idx:
        keep = idx != i
        coef = _lstsq_form(form, x[keep], y[keep])
        errs.append(float(predict(form, coef, x[i:i + 1])[0] - y[i]))
    e = np.asarray(errs)
    return float(math.sqrt(float(np.mean(e * e)))) if np.all(np.isfinite(e)) else math.inf


def eligible_forms(x: FloatArray, y: FloatArray, forms: Sequence[CurveForm] = CURVE_FORMS) -> list[CurveForm]:
    """Forms that may be fitted to these points: fewer coefficients than points (the line
    alone for 2 points), positive inputs for log and power, positive outputs for power."""
    n = len(x)
    out = []
    for f in forms:
        k = CURVE_NCOEF[f]
        if n == 2 and f != "linear":
            continue
        if n > 2 and k >= n:
            continue
        if f in ("log", "power") and np.any(x <= 0):
            continue
        if f == "power" and np.any(y <= 0):
            continue
        out.append(f)
    return out


# --- monotonicity and range -------------------------------------------------------------

def is_monotone(curve: Curve, kind: Literal["nondecreasing", "either"], tol: float = 1e-9) -> bool:
    """Whether ``curve`` is non-decreasing (or monotone either way) on its domain."""
    lo, hi = curve.domain
    if hi <= lo:
        return True
    grid = np.linspace(lo, hi, _GRID) / curve.scale
    v = predict(curve.form, curve.coef, grid)
    if not np.all(np.isfinite(v)):
        return False
    d = np.diff(v)
    span = max(1.0, float(np.max(np.abs(v))))
    up = bool(np.all(d >= -tol * span))
    if kind == "nondecreasing":
        return up
    return up or bool(np.all(d <= tol * span))


def clip_domain(curve: Curve, lo_y: float, hi_y: float) -> tuple[Curve, str | None]:
    """Narrow a non-decreasing curve's domain so its outputs stay within ``[lo_y, hi_y]``;
    the message says what changed (None when nothing did)."""
    lo, hi = curve.domain
    new_lo, new_hi = lo, hi
    eps = 1e-9 * max(1.0, abs(hi_y))
    if curve(hi) > hi_y + eps:
        new_hi = curve.inverse(hi_y)
    if curve(lo) < lo_y - eps:
        new_lo = curve.inverse(lo_y)
    if new_lo == lo and new_hi == hi:
        return curve, None
    if new_hi < new_lo:  # pragma: no cover - impossible for a non-decreasing curve and lo_y <= hi_y
        new_lo = new_hi
    clipped = Curve(curve.form, curve.coef, (new_lo, new_hi), curve.scale)
    parts = []
    if new_hi != hi:
        parts.append(f"reaches {hi_y:g} at {new_hi:.4g} (it would give {curve(hi):.4g} at {hi:g})")
    if new_lo != lo:
        parts.append(f"reaches {lo_y:g} at {new_lo:.4g} (it would give {curve(lo):.4g} at {lo:g})")
    return clipped, (f"domain narrowed from [{lo:g}, {hi:g}] to [{new_lo:.4g}, {new_hi:.4g}] to keep the output "
                     f"within [{lo_y:g}, {hi_y:g}]: " + "; ".join(parts))


# --- model selection --------------------------------------------------------------------

def _usable(form: CurveForm, coef: tuple[float, ...]) -> bool:
    """Finite coefficients in a range where evaluating the curve cannot overflow."""
    if not all(math.isfinite(c) and abs(c) <= MAX_COEFFICIENT for c in coef):
        return False
    return not (form == "power" and abs(coef[1]) > _MAX_EXPONENT)


def _rank(forms: list[CurveForm], loo: dict[str, float | None], tiny: float = 0.0) -> list[CurveForm]:
    """Forms by leave-one-out RMSE, except that a form with fewer coefficients whose error
    is within :data:`PARSIMONY` of the best goes first (noise alone should not buy a
    coefficient). Errors below ``tiny`` (exact fits, up to rounding) tie, and ties go to
    the earlier form of ``forms`` (linear first)."""
    def err(f: str) -> float:
        v = loo[f]
        return 0.0 if v is None or v <= tiny else v

    ranked = sorted(forms, key=lambda f: (err(f), CURVE_NCOEF[f], forms.index(f)))
    if not ranked:
        return ranked
    best = err(ranked[0])
    close = [f for f in ranked if err(f) <= best * (1 + PARSIMONY) + 1e-12]
    first = min(close, key=lambda f: (CURVE_NCOEF[f], err(f), forms.index(f)))
    return [first] + [f for f in ranked if f != first]


def fit_curve(x: Sequence[float], y: Sequence[float], *, scale: float = 1.0,
              forms: Sequence[CurveForm] = CURVE_FORMS, monotone: Monotone = None) -> FittedRelation:
    """Fit every eligible form to (x, y) and keep the one with the smallest leave-one-out
    RMSE that satisfies ``monotone`` on ``[min x, max x]``.

    Raises :class:`FitError` for fewer than 2 distinct inputs or non-finite values.
    """
    xs = np.asarray(x, dtype=float)
    ys = np.asarray(y, dtype=float)
    if xs.shape != ys.shape or xs.ndim != 1:
        raise FitError("x and y must be 1-D sequences of the same length")
    if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(ys))):
        raise FitError("the points contain non-finite values")
    order = np.argsort(xs, kind="stable")
    xs, ys = xs[order], ys[order]
    if len(np.unique(xs)) < 2:
        raise FitError(f"{len(np.unique(xs))} distinct input value(s): at least 2 are needed")
    xn = xs / scale
    domain = (float(xs[0]), float(xs[-1]))
    notes: list[str] = []
    n = len(xs)
    distinct = len(np.unique(xs))
    if distinct < 3:
        notes.append(f"only {distinct} distinct points: the line through them is exact, nothing checks it")

    forms_ok: list[CurveForm] = eligible_forms(xn, ys, forms) if distinct > 2 else ["linear"]
    candidates: dict[str, float | None] = {}
    for f in forms_ok:
        candidates[f] = loo_rmse(f, xn, ys) if n > 2 and distinct > 2 else None

    ranked = _rank(forms_ok, candidates, tiny=1e-9 * max(1.0, float(np.max(np.abs(ys)))))
    chosen: tuple[CurveForm, tuple[float, ...]] | None = None
    rejected: list[str] = []
    for f in ranked:
        coef = fit_form(f, xn, ys)
        if not _usable(f, coef):
            rejected.append(f"{f} (no finite fit)")
            continue
        if monotone is not None and not is_monotone(Curve(f, coef, domain, scale), monotone):
            rejected.append(f)
            continue
        chosen = (f, coef)
        break
    want = "non-decreasing" if monotone == "nondecreasing" else "monotone"
    form: CurveForm
    if chosen is None:
        form, coef = "linear", fit_form("linear", xn, ys)
        if monotone == "nondecreasing" and coef[0] < 0:
            coef = (0.0, float(ys.mean()))
            notes.append(f"no candidate form is {want} on [{domain[0]:g}, {domain[1]:g}] "
                         f"({', '.join(rejected)}) and the data decrease: fell back to the constant {coef[1]:.4g}")
        else:
            notes.append(f"no candidate form is {want} on [{domain[0]:g}, {domain[1]:g}] "
                         f"({', '.join(rejected)}): fell back to linear")
    else:
        form, coef = chosen
        if rejected and monotone is not None:
            notes.append(f"{', '.join(rejected)} fitted better but {'is' if len(rejected) == 1 else 'are'} not "
                         f"{want} on [{domain[0]:g}, {domain[1]:g}]: chose {form}")
    if monotone == "either" and abs(predict(form, coef, xn[-1:])[0] - predict(form, coef, xn[:1])[0]) <= 1e-12:
        notes.append("the fitted curve is flat: its inverse is not defined")
    r2 = r_squared(ys, predict(form, coef, xn))
    spread = float(ys.max() - ys.min())
    flat = spread <= FLAT_SPREAD * max(abs(float(ys.mean())), 1e-12)
    if r2 < R2_WARN and not flat:
        notes.append(f"R² = {r2:.3f} < {R2_WARN}: the {form} fit explains the points poorly")
    return FittedRelation(form, tuple(float(c) for c in coef), domain, float(scale), float(r2), candidates.get(form),
                          tuple((float(a), float(b)) for a, b in zip(xs, ys, strict=True)), candidates, tuple(notes))
