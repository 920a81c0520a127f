r"""Checks that grade a student's estimator against estim's and say what to fix.

A course exercise asks for an algorithm written by hand (a Kalman filter, a particle
filter, ...); its graded parts call these checks on the student's function, put in estim's
loop by :func:`estim.adapters.from_function`. Each raises an ``AssertionError`` whose
message teaches: where the student's numbers first leave the reference, which quantity,
and the equation to look at; a passing check returns its verdict as text.

* :func:`check_filter`: deterministic algorithms, sample by sample against the reference
  on one record (estimates and covariances, to ``atol + rtol |reference|``). The first
  sample where either differs is named; when the covariance differs there (or earlier)
  the covariance's equation is the one to look at, since a wrong covariance makes a wrong
  gain and the estimate follows; an estimate that leaves the reference with the
  covariance still right points at the estimate's update. An exception in the student's
  step is reported with the sample it happened at.
* :func:`check_over_seeds`: randomised algorithms (particle filters), paired over seeds
  against the reference with :func:`estim.testing.assert_equivalent` (two one-sided
  Wilcoxon tests: a filter whose metric differs from the reference's by more than the
  tolerance passes with probability at most ``1 - confidence``; how often a *correct*
  filter fails depends on the seeds, the tolerance and the algorithm's spread, and must
  be measured for each exercise: e.g. 0.15-0.4 % for exercise 05's particle filter, 20
  seeds within 15 %).
* :func:`check_consistent`: the covariance the student reports, by the NEES verdict of
  :func:`estim.testing.assert_consistent` (``1 - level`` false alarms): a mean can be
  right with a covariance that is not.
* :func:`check_arrays`: any other result of a deterministic part (sigma points, a
  smoother's means, Lie derivatives, a window's residuals) against the reference's, with
  the same kind of message.

:func:`from_steps` turns a student's ``predict`` and ``update`` functions into an estimator
(the textbook's loop: the prior, then predict and update at every later sample).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from estim import testing
from estim.adapters import from_function
from estim.compare import compare
from estim.estimators.base import Estimator
from estim.experiment import Record
from estim.log import Log
from estim.model import Model
from estim.scenarios import Scenario
from estim.simulate import replay

__all__ = ["as_log", "check_arrays", "check_consistent", "check_filter", "check_over_seeds",
           "from_steps"]

#: the quantities :func:`check_filter` compares, as a message names them
QUANTITIES = {"x": "the estimate x̂", "P": "the covariance P"}


def _record(record: Record | tuple) -> tuple[Any, Any]:
    if isinstance(record, Record):
        return record.y, record.u
    if isinstance(record, tuple) and len(record) == 2:
        return record
    raise TypeError(f"record must be an estim.Record or a pair (Y, U), got "
                    f"{type(record).__name__}")


def _entry(a: np.ndarray, b: np.ndarray, atol: float, rtol: float
           ) -> tuple[int, ...] | None:
    """The first entry where ``a`` and ``b`` differ beyond the tolerance (None: none)."""
    bad = ~np.isclose(a, b, atol=atol, rtol=rtol, equal_nan=True)
    return tuple(int(i) for i in np.argwhere(bad)[0]) if bad.any() else None


def from_steps(model: Model, predict: Callable, update: Callable, x0: Any, P0: Any, *,
               name: str = "your filter") -> Estimator:
    r"""The estimator of a Gaussian filter written as two functions, for estim's loop.

    At the first sample the estimate is the prior ``(x0, P0)`` updated by ``y_0``; at
    every later sample it is ``predict`` then ``update``:

    .. math::
        (\bar x_k, \bar P_k) = \mathrm{predict}(\hat x_{k-1}, P_{k-1}), \qquad
        (\hat x_k, P_k) = \mathrm{update}(\bar x_k, \bar P_k, y_k),

    the update skipped where ``y_k`` has a NaN (a missing sample). With a NaN first
    sample the prior is one step before the first measurement, as in Särkkä & Svensson's
    *Bayesian Filtering and Smoothing* (2023).

    Parameters
    ----------
    model : Model
        The system (dimensions and names in the log).
    predict : callable
        ``predict(x, P) -> (x, P)``: ``x`` (nx,), ``P`` (nx, nx).
    update : callable
        ``update(x, P, y) -> (x, P)``: ``y`` (ny,).
    x0, P0 : array_like
        The prior mean (nx,) and covariance (nx, nx).
    name : str
        The label in logs and in the checks' messages.
    """
    if not callable(predict):
        raise TypeError(f"predict must be callable, got {type(predict).__name__}")
    if not callable(update):
        raise TypeError(f"update must be callable, got {type(update).__name__}")
    m0 = np.asarray(x0, dtype=float).reshape(-1)
    S0 = np.asarray(P0, dtype=float)
    if m0.shape != (model.nx,):
        raise ValueError(f"x0 must have {model.nx} entries, got shape {m0.shape}")
    if S0.shape != (model.nx, model.nx):
        raise ValueError(f"P0 must be {model.nx} x {model.nx}, got shape {S0.shape}")
    held: dict[str, Any] = {}

    def pair(out: Any, what: str) -> tuple[Any, Any]:
        if not (isinstance(out, tuple | list) and len(out) == 2):
            got = ("nothing (not answered yet?)" if out is None or out is ... else
                   type(out).__name__)
            raise TypeError(f"{what} must return the pair (x, P), got {got}")
        return out[0], out[1]

    def reset() -> None:
        held.update(x=m0.copy(), P=S0.copy(), k=0)

    def step(y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, P = held["x"], held["P"]
        if held["k"]:
            x, P = pair(predict(x, P), "predict")
        if np.isfinite(y).all():
            x, P = pair(update(x, P, y), "update")
        x = np.asarray(x, dtype=float).reshape(-1)
        P = np.asarray(P, dtype=float)
        held.update(x=x, P=P, k=held["k"] + 1)
        return x, P

    reset()
    return from_function(step, model, name=name, reset=reset, x0=m0)


def as_log(estimates: Any, covariances: Any = None, *, truth: Any = None, t: Any = None,
           model: Model | None = None, name: str = "your filter") -> Log:
    """A :class:`~estim.Log` of a student's arrays, for :mod:`estim.plotting` (e.g.
    ``plot_errors(as_log(m, P, truth=X))``: the errors and their ±2σ bands).

    Parameters
    ----------
    estimates : (T, nx) array
    covariances : (T, nx, nx) array, optional
    truth : (T, nx) array, optional
    t : (T,) array, optional
        Sample times (default ``0, dt, 2 dt, ...`` with the model's ``dt``, else 0, 1, ...).
    model : Model, optional
        State names and sample time.
    name : str
        The label in the figures.
    """
    x_hat = np.asarray(estimates, dtype=float)
    if x_hat.ndim != 2:
        raise ValueError(f"estimates must be (T, nx), got shape {x_hat.shape}")
    T, nx = x_hat.shape
    log = Log(state_names=model.state_names if model is not None else None,
              dt=getattr(model, "dt", None), estimator=name,
              model_name=model.name if model is not None else "")
    dt = getattr(model, "dt", None) or 1.0
    log.set("t", np.arange(T) * dt if t is None else np.asarray(t, dtype=float)[:T])
    log.set("x_hat", x_hat)
    log.set("P", np.full((T, nx, nx), np.nan) if covariances is None else
            np.asarray(covariances, dtype=float).reshape(T, nx, nx))
    if truth is not None:
        X = np.asarray(truth, dtype=float)
        if X.shape != x_hat.shape:
            raise ValueError(f"truth must have the estimates' shape {x_hat.shape}, got "
                             f"{X.shape}")
        log.set("x", X)
    return log


def check_arrays(yours: Any, reference: Any, *, quantity: str, equation: str = "its equation",
                 atol: float = 1e-8, rtol: float = 1e-6, index: str | None = None) -> str:
    """``yours`` equal to ``reference`` to ``atol + rtol |reference|``, entry by entry.

    Raises ``AssertionError`` naming ``quantity``, the first differing entry (with
    ``index``, e.g. ``"sample"`` or ``"sigma point"``, its first index is named so and
    the rest is the entry; ``"row"`` of a matrix names its row and column), both values
    and ``equation``; a wrong shape or a non-numeric answer is told as such (``None`` or
    ``...``: not answered yet). Returns the verdict.
    """
    if yours is None or yours is Ellipsis:
        raise AssertionError(f"{quantity}: not answered yet (got {yours!r})")
    try:
        a = np.asarray(yours, dtype=float)
    except (TypeError, ValueError) as exc:
        raise AssertionError(f"{quantity}: expected numbers, got {type(yours).__name__} "
                             f"({exc})") from None
    b = np.asarray(reference, dtype=float)
    if a.shape != b.shape:
        raise AssertionError(f"{quantity} has shape {a.shape}, expected {b.shape}")
    e = _entry(a, b, atol, rtol)
    if e is None:
        return f"{quantity} equals the reference (to {atol:g} + {rtol:g} |ref|)"
    if not e:
        where = "the value"
    elif index in (None, "entry"):
        where = f"entry {e}" if len(e) > 1 else f"entry {e[0]}"
    elif index == "row" and len(e) == 2:
        where = f"row {e[0]}, column {e[1]}"
    else:
        where = f"{index} {e[0]}, entry {e[1:]}" if len(e) > 1 else f"{index} {e[0]}"
    n = int((~np.isclose(a, b, atol=atol, rtol=rtol, equal_nan=True)).sum())
    raise AssertionError(f"{quantity} differs first at {where}: yours {a[e]:.6g}, the "
                         f"reference {b[e]:.6g}. Look at {equation}. ({n} of {a.size} "
                         f"entries differ, to {atol:g} + {rtol:g} |ref|)")


def check_filter(student: Estimator, reference: Estimator, record: Record | tuple, *,
                 equations: Mapping[str, str] | None = None, atol: float = 1e-8,
                 rtol: float = 1e-6, name: str = "your filter",
                 loop: tuple[Any, Any] | None = None, loop_name: str = "your loop",
                 loop_equation: str = "the loop: predict, then update, at every sample"
                 ) -> str:
    """Compare ``student`` with ``reference`` sample by sample on ``record`` (a
    :class:`~estim.Record` or ``(Y, U)``); see the module. ``equations``: for ``"x"`` and
    ``"P"``, the equation the message sends the student to (e.g. ``{"P": "the prediction
    P = F P Fᵀ + Q, eq. (2)"}``). Returns the verdict; raises ``AssertionError`` with the
    first differing sample, the quantity, both values and the equation.

    ``loop``: the means ``(T', nx)`` and covariances ``(T', nx, nx)`` that the student's
    own whole-record function returned, checked (once the steps are right) against the
    reference's last ``T'`` samples of the same run (a record whose first row is the
    prior's: all but that row), with :func:`check_arrays`, as ``loop_name``'s means and
    covariances and ``loop_equation``."""
    for label, est in (("student", student), ("reference", reference)):
        if not isinstance(est, Estimator):
            raise TypeError(f"{label} must be an estim estimator (wrap a step function "
                            f"with estim.adapters.from_function), got {type(est).__name__}")
    hints = dict(equations or {})
    Y, U = _record(record)
    ref = replay(reference, Y, U, warn=False)
    try:
        mine = replay(student, Y, U, warn=False)
    except Exception as exc:  # noqa: BLE001 - the student's code: reported, not raised
        k = len(getattr(exc, "log", []) or [])
        raise AssertionError(f"{name} raised {type(exc).__name__} at sample {k}: {exc}"
                             ) from exc
    xs, xr = np.asarray(mine.x_hat), np.asarray(ref.x_hat)
    if xs.shape != xr.shape:
        raise AssertionError(f"{name} returns estimates of shape {xs.shape[1:]}, the "
                             f"model's state has shape {xr.shape[1:]}")
    firsts: dict[str, tuple[int, ...]] = {}
    e = _entry(xs, xr, atol, rtol)
    if e is not None:
        firsts["x"] = e
    Ps, Pr = np.asarray(mine.P), np.asarray(ref.P)
    covariance = not np.isnan(Ps).all()
    if covariance:
        e = _entry(Ps, Pr, atol, rtol)
        if e is not None:
            firsts["P"] = e
    T = len(xr)
    if not firsts:
        if loop is not None:
            _check_loop(loop, xr, Pr, loop_name, loop_equation, atol, rtol)
        return (f"{name} equals the reference on all {T} samples (estimates"
                f"{' and covariances' if covariance else ''}, to {atol:g} + {rtol:g} |ref|)"
                f"{f'; so does {loop_name}' if loop is not None else ''}")
    # the covariance's error first where it comes no later than the estimate's
    key = "P" if "P" in firsts and firsts["P"][0] <= firsts.get("x", (T,))[0] else "x"
    where = firsts[key]
    k, idx = where[0], where[1:]
    yours, theirs = (Ps, Pr) if key == "P" else (xs, xr)
    at = (k, *idx)
    other = "x" if key == "P" else "P"
    still = (f"; {QUANTITIES[other]} is still right there" if other not in firsts or
             firsts[other][0] > k else "")
    if key == "x" and covariance and "P" not in firsts:
        still = f"; {QUANTITIES['P']} is right at every sample"
    if not covariance:  # nothing to say of a covariance the student does not report
        still = ""
    hint = hints.get(key, "its equation")
    t = f" (t = {ref.t[k]:g})" if hasattr(ref, "t") else ""
    raise AssertionError(
        f"{name}: {QUANTITIES[key]} differs first at sample {k}{t}, entry {idx}: yours "
        f"{yours[at]:.6g}, the reference {theirs[at]:.6g}{still}. Look at "
        f"{hint}. ({int((~np.isclose(yours, theirs, atol=atol, rtol=rtol)).sum())} "
        f"entries differ in all, to {atol:g} + {rtol:g} |ref|)")


def _check_loop(loop: tuple[Any, Any], xr: np.ndarray, Pr: np.ndarray, name: str,
                equation: str, atol: float, rtol: float) -> None:
    """The student's whole-record means and covariances against the reference's last
    samples (see :func:`check_filter`)."""
    if not (isinstance(loop, tuple | list) and len(loop) == 2):
        raise TypeError(f"loop must be the pair (means, covariances), got "
                        f"{type(loop).__name__}")
    means, covs = loop
    start = max(len(xr) - (np.shape(means)[0] if np.ndim(means) else 0), 0)
    check_arrays(means, xr[start:], quantity=f"{name}'s means", equation=equation,
                 atol=atol, rtol=rtol, index="sample")
    check_arrays(covs, Pr[start:], quantity=f"{name}'s covariances", equation=equation,
                 atol=atol, rtol=rtol, index="sample")


def check_over_seeds(student: Estimator | Callable, reference: Estimator | Callable,
                     scenario: Scenario, *, seeds: Sequence[int] = range(20),
                     metric: str = "rmse", tolerance: float = 0.1,
                     confidence: float = 0.95, name: str = "your filter") -> str:
    """Paired over ``seeds`` of ``scenario``: ``student``'s ``metric`` shown within
    ``tolerance`` × the reference's median of the reference's
    (:func:`estim.testing.assert_equivalent`: a filter outside the tolerance passes with
    probability at most ``1 - confidence``; a correct filter's failure rate is the test's
    lack of power and depends on the seeds and the tolerance: measure it). The
    estimators as :func:`~estim.compare` takes them (an estimator, or a factory
    ``(model, tuning) -> estimator``). Returns the verdict;
    raises ``AssertionError`` with the seeds where the two differ most."""
    res = compare(scenario, {name: student, "reference": reference}, seeds=list(seeds),
                  progress=False)
    n = len(list(seeds))
    try:
        testing.assert_equivalent(res, name, "reference", metric=metric,
                                  tolerance=tolerance, confidence=confidence)
    except AssertionError as exc:
        mine, ref = (np.nanmedian(np.asarray(res.rmse[k], dtype=float))
                     for k in (name, "reference"))
        how = (f"{abs(mine / ref - 1):.0%} {'worse' if mine > ref else 'better'}"
               if metric == "rmse" and ref > 0 else "")
        plain = (f" (median RMSE {mine:.4g} against the reference's {ref:.4g}: {how})"
                 if how else "")
        raise AssertionError(f"{name} is not shown as accurate as the reference over "
                             f"{n} seeds{plain}: {exc}") from None
    except ValueError as exc:  # too few seeds where both ran: the student's failed
        bad = int((~np.isfinite(np.asarray(res.rmse[name], dtype=float))).sum())
        notes = " ".join(line for line in res.notes() if name in line)
        raise AssertionError(
            f"{name} has no finite estimates on {bad} of {n} seeds, too many to compare "
            f"({notes or exc})") from None
    return (f"{name} is as accurate as the reference in {metric} within {tolerance:g} × "
            f"the reference's median over {n} seeds (at confidence {confidence})")


def check_consistent(student: Estimator, scenario: Scenario, *,
                     seeds: Sequence[int] = range(20), level: float = 0.99,
                     name: str = "your filter") -> str:
    """The NEES of ``student``'s estimates and covariances over ``seeds`` of
    ``scenario`` follows its chi-square law (:func:`estim.testing.assert_consistent`:
    ``1 - level`` false alarms). Raises ``AssertionError`` saying whether the covariance
    is too small (overconfident) or too large."""
    res = compare(scenario, {name: student}, seeds=list(seeds), progress=False)
    try:
        testing.assert_consistent(res, level=level)
    except AssertionError as exc:
        text = str(exc)
        why = ("its covariance is too small for its errors (overconfident): check that the "
               "prediction adds Q and that the update shrinks P by the gain only"
               if "overconfident" in text else
               "its covariance is too large for its errors (pessimistic): check that the "
               "update shrinks P" if "pessimistic" in text else "")
        raise AssertionError(f"{name}'s covariance does not match its errors: "
                             f"{why + '. ' if why else ''}{text}") from None
    return f"{name}'s covariance matches its errors (NEES verdict at level {level})"
