"""A corpus of malformed calls: every public entry point refuses bad input early,
with ``ValueError`` (bad value or shape) or ``TypeError`` (wrong type, unknown
keyword) and a message naming the argument.

Each case is ``(id, call, exception type, regex the message must match)``;
command-line cases give the arguments of :func:`estim.cli.main` and the regex
that standard error must match (exit code 2, ``estim: error:`` or argparse's
usage error).
"""

from __future__ import annotations

import contextlib
import math
import sys
from functools import cache
from typing import NamedTuple

import casadi as ca
import numpy as np
import pytest

import estim
from estim import cli, observability

nan, inf = float("nan"), float("inf")


# ------------------------------------------------------------------ fixtures
def _osc(x, u, p):
    return ca.vertcat(x[1], -p["k"] * x[0] + u[0])


def _model(**changes):
    kwargs = dict(states=["x1", "x2"], outputs=["y"], inputs=["u"], ode=_osc,
                  output=lambda x, u, p: x[0], params={"k": 1.0}, dt=0.1, name="osc")
    kwargs.update(changes)
    return estim.Model(**kwargs)


M = _model()
#: A one-state discrete model (cheap NLPs).
D = estim.Model(states=1, outputs=1, dynamics=lambda x, u, p: 0.9 * x,
                output=lambda x, u, p: x, name="decay")
TUNE = dict(Q=0.01, R=0.1, x0=[0.0, 0.0], P0=1.0)
TUNE_D = dict(Q=0.01, R=0.1, x0=[0.0], P0=1.0)
SC = estim.Scenario("osc", M, x0=[1.0, 0.0], n_steps=10, Q=1e-4, R=0.01, tuning=TUNE)
Y5 = np.zeros((5, 1))


@cache
def ekf():
    return estim.EKF(M, **TUNE)


@cache
def fie():
    return estim.FullInformation(M, Q=0.01, R=0.1, x0=[0.0, 0.0], P0=1.0)


@cache
def log():
    return estim.simulate(SC, estim.EKF(M, **TUNE), seed=0)


def log_without_P():
    lg = estim.Log(["x1"])
    lg.set("t", np.arange(3.0))
    lg.set("x", np.zeros((3, 1)))
    lg.set("x_hat", np.ones((3, 1)))
    return lg


@contextlib.contextmanager
def no_module(*names):
    """A context in which importing ``names`` and their submodules fails (as if not
    installed). Only these entries of ``sys.modules`` are changed and restored: modules
    first imported inside the context stay imported after it."""
    hidden = {key: sys.modules[key] for key in list(sys.modules)
              if any(key == n or key.startswith(n + ".") for n in names)}
    for key in hidden:
        del sys.modules[key]
    sys.modules.update({n: None for n in names})
    try:
        yield
    finally:
        for n in names:
            sys.modules.pop(n, None)
        sys.modules.update(hidden)


def mhe(solver="gauss-newton", **kw):
    return estim.MHE(D, horizon=3, solver=solver, **{**TUNE_D, **kw})


def shooting(**kw):
    base = dict(window=3, every=2, R=0.1, x0=[0.0, 0.0])
    base.update(kw)
    return estim.ShootingObserver(M, **base)


def simulate(**kw):
    return estim.simulate(SC, estim.EKF(M, **TUNE), **kw)


def replay(y=Y5, **kw):
    return estim.replay(estim.EKF(M, **TUNE), y, **kw)


def compare(estimators=None, **kw):
    return estim.compare(SC, {"ekf": estim.EKF} if estimators is None else estimators, **kw)


def scenario(**kw):
    base = dict(name="osc", model=M, x0=[1.0, 0.0], n_steps=10, Q=1e-4, R=0.01, tuning=TUNE)
    base.update(kw)
    return estim.Scenario(**base)


class Case(NamedTuple):
    id: str
    call: object
    exc: type
    match: str


class CliCase(NamedTuple):
    id: str
    argv: list
    match: str
    argparse: bool = False          # argparse's own usage error (SystemExit 2)
    context: object = contextlib.nullcontext


T, V, IE = TypeError, ValueError, ImportError

CASES = [
    # ------------------------------------------------------------- Model
    Case("model-states-bool", lambda: _model(states=True), T, r"states"),
    Case("model-states-float", lambda: _model(states=3.5), T, r"states"),
    Case("model-states-nonstring", lambda: _model(states=["a", 1]), T, r"states"),
    Case("model-states-duplicate", lambda: _model(states=["a", "a"]), V, r"states"),
    Case("model-states-missing", lambda: estim.Model(outputs=1, dynamics=lambda x, u, p: x,
                                                     output=lambda x, u, p: x), T, r"states"),
    Case("model-dt-bool", lambda: _model(dt=True), T, r"dt"),
    Case("model-dt-string", lambda: _model(dt="0.1"), T, r"dt"),
    Case("model-dt-negative", lambda: _model(dt=-0.1), V, r"dt"),
    Case("model-dt-nan", lambda: _model(dt=nan), V, r"dt"),
    Case("model-dt-inf", lambda: _model(dt=inf), V, r"dt"),
    Case("model-substeps-bool", lambda: _model(substeps=True), T, r"substeps"),
    Case("model-substeps-float", lambda: _model(substeps=2.0), T, r"substeps"),
    Case("model-substeps-zero", lambda: _model(substeps=0), V, r"substeps"),
    Case("model-integrator-unknown", lambda: _model(integrator="rk45"), V, r"integrator"),
    Case("model-integrator-none", lambda: _model(integrator=None), T, r"integrator"),
    Case("model-params-bool", lambda: _model(params={"k": True}), T, r"params\['k'\]"),
    Case("model-params-string", lambda: _model(params={"k": "fast"}), T, r"params\['k'\]"),
    Case("model-params-inf", lambda: _model(params={"k": inf}), V, r"params\['k'\]"),
    Case("model-params-not-dict", lambda: _model(params=3), T, r"params"),
    Case("model-params-key", lambda: _model(params={1: 2.0, "k": 1.0}), T, r"params"),
    Case("model-ode-not-callable", lambda: _model(ode=3), T, r"ode"),
    Case("model-ode-and-dynamics", lambda: _model(dynamics=lambda x, u, p: x), V, r"ode"),
    Case("model-output-missing", lambda: _model(output=None), V, r"output"),
    Case("model-ode-wrong-size", lambda: _model(ode=lambda x, u, p: x[0]), V, r"ode"),
    Case("model-ode-math-sqrt", lambda: _model(
        ode=lambda x, u, p: [x[1], math.sqrt(x[0])]), V, r"ode.*x2.*math"),
    Case("model-output-math-exp", lambda: _model(
        output=lambda x, u, p: [math.exp(x[0])]), V, r"output.*\by\b.*math"),
    Case("model-dynamics-math", lambda: estim.Model(
        states=1, outputs=1, dynamics=lambda x, u, p: [math.log(x[0])],
        output=lambda x, u, p: x), V, r"dynamics.*x1"),
    Case("model-lower-string", lambda: _model(lower="a"), T, r"lower"),
    Case("model-lower-unknown-state", lambda: _model(lower={"z": 0.0}), V, r"lower"),
    Case("model-lower-bools", lambda: _model(lower=[True, False]), T, r"lower"),
    Case("model-upper-nan", lambda: _model(upper=[nan, 1.0]), V, r"upper"),
    Case("model-name-not-string", lambda: _model(name=3), T, r"name"),
    Case("model-unknown-keyword", lambda: _model(outpt=lambda x, u, p: x[0]), T,
         r"unknown option 'outpt'.*did you mean 'output'"),
    # ----------------------------------------------------- Model methods
    Case("model-f-shape", lambda: M.f([1.0]), V, r"\bx\b"),
    Case("model-f-bools", lambda: M.f([True, False]), T, r"\bx\b"),
    Case("model-f-string", lambda: M.f("ab"), T, r"\bx\b"),
    Case("model-f-u-nan", lambda: M.f([1.0, 2.0], [nan]), V, r"\bu\b"),
    Case("model-h-inf", lambda: M.h([inf, 0.0]), V, r"\bx\b"),
    Case("model-jacobians-u-string", lambda: M.jacobians([1.0, 2.0], "a"), T, r"\bu\b"),
    Case("with-params-string", lambda: M.with_params(k="fast"), T, r"'k'"),
    Case("with-params-bool", lambda: M.with_params(k=True), T, r"'k'"),
    Case("with-params-nan", lambda: M.with_params(k=nan), V, r"'k'"),
    Case("with-params-unknown", lambda: M.with_params(kk=1.0), V, r"'kk'"),
    Case("augment-nothing", lambda: M.augment(), V, r"augment"),
    Case("augment-unknown", lambda: M.augment("nope"), V, r"'nope'"),
    Case("augment-duplicate", lambda: M.augment("k", "k"), V, r"duplicate"),
    Case("augment-lower-string", lambda: M.augment("k", lower="x"), T, r"lower"),
    # --------------------------------------------------------------- EKF
    Case("ekf-unknown-option", lambda: estim.EKF(M, clipp=True, **TUNE), T,
         r"unknown option 'clipp'.*did you mean 'clip'"),
    Case("ekf-typo-required", lambda: estim.EKF(M, Q=0.01, R=0.1, x0=[0, 0], P_0=1.0), T,
         r"unknown option 'P_0'.*'P0'"),
    Case("ekf-missing-required", lambda: estim.EKF(M, R=0.1, x0=[0, 0], P0=1.0), T, r"'Q'"),
    Case("ekf-clip-string", lambda: estim.EKF(M, clip="no", **TUNE), T, r"clip"),
    Case("ekf-clip-int", lambda: estim.EKF(M, clip=1, **TUNE), T, r"clip"),
    Case("ekf-clip-none", lambda: estim.EKF(M, clip=None, **TUNE), T, r"clip"),
    Case("ekf-Q-bool", lambda: estim.EKF(M, **{**TUNE, "Q": True}), T, r"\bQ\b"),
    Case("ekf-x0-bools", lambda: estim.EKF(M, **{**TUNE, "x0": [True, False]}), T, r"x0"),
    Case("ekf-x0-string", lambda: estim.EKF(M, **{**TUNE, "x0": "ab"}), T, r"x0"),
    Case("ekf-R-negative", lambda: estim.EKF(M, **{**TUNE, "R": -1.0}), V, r"\bR\b"),
    Case("ekf-P0-asymmetric", lambda: estim.EKF(M, **{**TUNE, "P0": [[1, 2], [3, 4]]}), V,
         r"P0"),
    Case("ekf-model-string", lambda: estim.EKF("model", **TUNE), T, r"model"),
    Case("ekf-lower-string-entry", lambda: estim.EKF(M, lower=[0.0, "a"], **TUNE), T,
         r"lower"),
    # --------------------------------------------------------------- UKF
    Case("ukf-alpha-zero", lambda: estim.UKF(M, alpha=0.0, **TUNE), V, r"alpha"),
    Case("ukf-alpha-string", lambda: estim.UKF(M, alpha="big", **TUNE), T, r"alpha"),
    Case("ukf-beta-nan", lambda: estim.UKF(M, beta=nan, **TUNE), V, r"beta"),
    Case("ukf-kappa-bool", lambda: estim.UKF(M, kappa=True, **TUNE), T, r"kappa"),
    Case("ukf-clip-string", lambda: estim.UKF(M, clip="yes", **TUNE), T, r"clip"),
    Case("ukf-unknown-option", lambda: estim.UKF(M, horizon=5, **TUNE), T,
         r"unknown option 'horizon'"),
    # --------------------------------------------------------------- MHE
    Case("mhe-typo-horizon", lambda: estim.MHE(D, horizn=15, **TUNE_D), T,
         r"unknown option 'horizn'.*did you mean 'horizon'"),
    Case("mhe-missing-horizon", lambda: estim.MHE(D, **TUNE_D), T, r"'horizon'"),
    Case("mhe-horizon-bool", lambda: estim.MHE(D, horizon=True, **TUNE_D), T, r"horizon"),
    Case("mhe-horizon-float", lambda: estim.MHE(D, horizon=2.5, **TUNE_D), T, r"horizon"),
    Case("mhe-horizon-zero", lambda: estim.MHE(D, horizon=0, **TUNE_D), V, r"horizon"),
    Case("mhe-arrival-unknown", lambda: mhe(arrival_cost="ekf"), V, r"arrival_cost"),
    Case("mhe-arrival-none", lambda: mhe(arrival_cost=None), T, r"arrival_cost"),
    Case("mhe-solver-unknown", lambda: mhe("snopt"), V, r"solver"),
    Case("mhe-Q-singular-gauss-newton", lambda: estim.MHE(
        M, horizon=3, solver="gauss-newton", **{**TUNE, "Q": [0.01, 0.0]}), V,
        r"\bQ\b is singular.*solver='gauss-newton'"),
    Case("mhe-Q-negative", lambda: estim.MHE(M, horizon=3, **{**TUNE, "Q": [0.01, -1.0]}), V,
         r"\bQ\b"),
    Case("mhe-jit-contradiction", lambda: mhe(jit=True, solver_options={"jit": False}), V,
         r"jit=True contradicts solver_options\['jit'\]"),
    Case("mhe-options-not-dict", lambda: mhe(solver_options=[("max_iter", 3)]), T,
         r"solver_options"),
    Case("mhe-gn-max-iter-string", lambda: mhe(solver_options={"max_iter": "many"}), T,
         r"solver_options\['max_iter'\]"),
    Case("mhe-gn-max-iter-zero", lambda: mhe(solver_options={"max_iter": 0}), V,
         r"solver_options\['max_iter'\]"),
    Case("mhe-gn-xtol-negative", lambda: mhe(solver_options={"xtol": -1.0}), V,
         r"solver_options\['xtol'\]"),
    Case("mhe-gn-ftol-zero", lambda: mhe(solver_options={"ftol": 0.0}), V,
         r"solver_options\['ftol'\]"),
    Case("mhe-gn-ftol-ipopt", lambda: mhe("ipopt", solver_options={"ftol": 1e-8}), V,
         r"ftol.*gauss-newton"),
    Case("mhe-gn-newton-string", lambda: mhe(solver_options={"newton": "yes"}), T,
         r"solver_options\['newton'\]"),
    Case("mhe-gn-jit-int", lambda: mhe(solver_options={"jit": 1}), T,
         r"solver_options\['jit'\]"),
    Case("mhe-gn-mode-unknown", lambda: mhe(solver_options={"mode": "fast"}), V,
         r"solver_options\['mode'\]"),
    Case("mhe-gn-option-typo", lambda: mhe(solver_options={"max_iters": 3}), V,
         r"'max_iters'.*did you mean 'max_iter'"),
    Case("mhe-ipopt-option-type", lambda: mhe("ipopt", solver_options={"ipopt.tol": "tight"}),
         V, r"ipopt.*ipopt\.tol"),
    Case("mhe-ipopt-option-unknown", lambda: mhe("ipopt", solver_options={"ipopt.tolx": 1e-3}),
         V, r"ipopt\.tolx"),
    Case("mhe-ipopt-option-unprefixed", lambda: mhe("ipopt", solver_options={"max_iter": 5}),
         V, r"'max_iter'"),
    Case("mhe-sqp-option-type", lambda: mhe("sqp", solver_options={"tol_pr": "a"}), V,
         r"tol_pr"),
    Case("mhe-fatrop-option-type", lambda: mhe("fatrop", solver_options={"fatrop.tol": "a"}),
         V, r"fatrop\.tol"),
    Case("mhe-gn-only-option", lambda: mhe("ipopt", solver_options={"mode": "mapped"}), V,
         r"mode"),
    # ---------------------------------------------------------------- FIE
    Case("fie-solver-unknown", lambda: estim.FullInformation(M, Q=0.01, R=0.1, solver="newton"),
         V, r"solver"),
    Case("fie-xtol-string", lambda: estim.FullInformation(
        M, Q=0.01, R=0.1, solver_options={"xtol": "small"}), T, r"solver_options\['xtol'\]"),
    Case("fie-ipopt-option", lambda: estim.FullInformation(
        M, Q=0.01, R=0.1, solver="ipopt", solver_options={"ipopt.max_iter": "x"}), V,
         r"ipopt\.max_iter"),
    Case("fie-P0-without-x0", lambda: estim.FullInformation(M, Q=0.01, R=0.1, P0=1.0), V,
         r"P0"),
    Case("fie-unknown-option", lambda: estim.FullInformation(M, Q=0.01, R=0.1, windw=3), T,
         r"unknown option 'windw'"),
    Case("fit-Y-string", lambda: fie().fit("abc"), T, r"\bY\b"),
    Case("fit-Y-bools", lambda: fie().fit(np.zeros((5, 1), dtype=bool)), T, r"\bY\b"),
    Case("fit-Y-shape", lambda: fie().fit(np.zeros((5, 2))), V, r"\bY\b"),
    Case("fit-Y-inf", lambda: fie().fit(np.r_[0.0, inf, 0.0][:, None]), V, r"\bY\b"),
    Case("fit-Y-all-nan", lambda: fie().fit(np.full((3, 1), nan)), V, r"\bY\b"),
    Case("fit-U-string", lambda: fie().fit(Y5, U=[["a"]] * 5), T, r"\bU\b"),
    Case("fit-U-shape", lambda: fie().fit(Y5, U=np.zeros((2, 1))), V, r"\bU\b"),
    Case("fit-U-nan", lambda: fie().fit(Y5, U=np.full((5, 1), nan)), V, r"\bU\b"),
    Case("fit-guess-shape", lambda: fie().fit(Y5, 0, guess=np.zeros((4, 2))), V, r"guess"),
    Case("fit-guess-nan", lambda: fie().fit(Y5, 0, guess=np.full((5, 2), nan)), V, r"guess"),
    Case("fit-guess-string", lambda: fie().fit(Y5, 0, guess="x"), T, r"guess"),
    # --------------------------------------------------------- shooting
    Case("shooting-window-zero", lambda: shooting(window=0), V, r"window"),
    Case("shooting-window-bool", lambda: shooting(window=True), T, r"window"),
    Case("shooting-every-zero", lambda: shooting(every=0), V, r"every"),
    Case("shooting-every-float", lambda: shooting(every=2.0), T, r"every"),
    Case("shooting-derivative-samples", lambda: shooting(derivative_samples=2), V,
         r"derivative_samples"),
    Case("shooting-max-iter-bool", lambda: shooting(max_iter=True), T, r"max_iter"),
    Case("shooting-method", lambda: shooting(method="newton"), V, r"method"),
    Case("shooting-direction", lambda: shooting(direction="sideways"), V, r"direction"),
    Case("shooting-derivative-weight", lambda: shooting(derivative_weight=-1.0), V,
         r"derivative_weight"),
    Case("shooting-derivative-weight-string", lambda: shooting(derivative_weight="auto"), T,
         r"derivative_weight"),
    Case("shooting-tol-zero", lambda: shooting(tol=0.0), V, r"\btol\b"),
    Case("shooting-tol-string", lambda: shooting(tol="x"), T, r"\btol\b"),
    Case("shooting-resolution-nan", lambda: shooting(resolution=nan), V, r"resolution"),
    Case("shooting-unknown-option", lambda: shooting(windw=5), T,
         r"unknown option 'windw'.*'window'"),
    # ------------------------------------------------------ step / reset
    Case("step-y-shape", lambda: estim.EKF(M, **TUNE).step([1.0, 2.0]), V, r"\by\b"),
    Case("step-y-string", lambda: estim.EKF(M, **TUNE).step("abc"), T, r"\by\b"),
    Case("step-y-inf", lambda: estim.EKF(M, **TUNE).step([inf]), V, r"\by\b"),
    Case("step-y-bool", lambda: estim.EKF(M, **TUNE).step([True]), T, r"\by\b"),
    Case("step-u-nan", lambda: estim.EKF(M, **TUNE).step([1.0], [nan]), V, r"\bu\b"),
    Case("step-u-string", lambda: estim.EKF(M, **TUNE).step([1.0], "a"), T, r"\bu\b"),
    Case("ukf-step-y-inf", lambda: estim.UKF(M, **TUNE).step([-inf]), V, r"\by\b"),
    Case("reset-x0-shape", lambda: estim.EKF(M, **TUNE).reset(x0=[1.0]), V, r"x0"),
    Case("reset-x0-bools", lambda: estim.EKF(M, **TUNE).reset(x0=[True, False]), T, r"x0"),
    Case("reset-P0-negative", lambda: estim.EKF(M, **TUNE).reset(P0=-1.0), V, r"P0"),
    # ---------------------------------------------------------- simulate
    Case("simulate-estimator", lambda: estim.simulate(SC, object()), T, r"estimator"),
    Case("simulate-target", lambda: estim.simulate("osc", ekf()), T, r"target"),
    Case("simulate-n-steps-zero", lambda: simulate(n_steps=0), V, r"n_steps"),
    Case("simulate-n-steps-bool", lambda: simulate(n_steps=True), T, r"n_steps"),
    Case("simulate-n-steps-float", lambda: simulate(n_steps=5.0), T, r"n_steps"),
    Case("simulate-seed-negative", lambda: simulate(seed=-1), V, r"seed"),
    Case("simulate-seed-bool", lambda: simulate(seed=True), T, r"seed"),
    Case("simulate-seed-float", lambda: simulate(seed=1.5), T, r"seed"),
    Case("simulate-seed-string", lambda: simulate(seed="a"), T, r"seed"),
    Case("simulate-clip-string", lambda: simulate(clip="no"), T, r"clip"),
    Case("simulate-x0-bools", lambda: simulate(x0=[True, False]), T, r"x0"),
    Case("simulate-Q-bool", lambda: simulate(Q=True), T, r"\bQ\b"),
    Case("simulate-R-string", lambda: simulate(R="a"), T, r"\bR\b"),
    Case("simulate-missing-probability", lambda: simulate(missing=1.5), V, r"missing"),
    Case("simulate-missing-bool", lambda: simulate(missing=True), T, r"missing"),
    Case("simulate-missing-float-mask", lambda: simulate(missing=np.full((10, 1), 0.5)), T,
         r"missing"),
    Case("simulate-missing-mask-shape", lambda: simulate(missing=np.zeros((3, 1), bool)), V,
         r"missing"),
    Case("simulate-plant-changes-string-time",
         lambda: simulate(plant_changes=[("0.5", {"k": 2.0})]), T, r"plant_changes"),
    Case("simulate-plant-changes-unknown-param",
         lambda: simulate(plant_changes=[(0.5, {"kk": 2.0})]), V, r"plant_changes.*kk"),
    Case("simulate-plant-changes-not-dict",
         lambda: simulate(plant_changes=[(0.5, 2.0)]), T, r"plant_changes"),
    Case("simulate-plant-changes-not-pair", lambda: simulate(plant_changes=[0.5]), T,
         r"plant_changes"),
    Case("simulate-plant-changes-string-value",
         lambda: simulate(plant_changes=[(0.5, {"k": "x"})]), T, r"plant_changes"),
    Case("simulate-plant-changes-nan-time",
         lambda: simulate(plant_changes=[(nan, {"k": 1.0})]), V, r"plant_changes"),
    Case("simulate-feedback", lambda: simulate(feedback="truthy"), V, r"feedback"),
    Case("simulate-controller", lambda: simulate(controller=3), T, r"controller"),
    Case("simulate-inputs-string", lambda: simulate(inputs="abc"), T, r"inputs"),
    Case("simulate-inputs-shape", lambda: simulate(inputs=np.zeros((3, 1))), V, r"inputs"),
    Case("simulate-unknown-keyword", lambda: simulate(seeds=3), T,
         r"unknown option 'seeds'.*'seed'"),
    Case("simulate-bare-model-n-steps", lambda: estim.simulate(
        M, ekf(), x0=[0.0, 0.0], Q=0.0, R=0.1), V, r"n_steps"),
    # ------------------------------------------------------------ replay
    Case("replay-estimator", lambda: estim.replay(object(), Y5), T, r"estimator"),
    Case("replay-y-string", lambda: replay("abc"), T, r"\by\b"),
    Case("replay-y-shape", lambda: replay(np.zeros((5, 2))), V, r"\by\b"),
    Case("replay-y-inf", lambda: replay(np.r_[0.0, 1.0, inf][:, None]), V,
         r"\by\b.*row 2.*NaN"),
    Case("replay-y-bools", lambda: replay(np.zeros((5, 1), bool)), T, r"\by\b"),
    Case("replay-u-nan", lambda: replay(u=np.full((5, 1), nan)), V, r"\bu\b"),
    Case("replay-u-shape", lambda: replay(u=np.zeros((5, 3))), V, r"\bu\b"),
    Case("replay-u-string", lambda: replay(u="x"), T, r"\bu\b"),
    Case("replay-x-shape", lambda: replay(x=np.zeros((4, 2))), V, r"\bx\b"),
    Case("replay-t-nan", lambda: replay(t=np.r_[0.0, 1, nan, 3, 4]), V, r"\bt\b"),
    Case("replay-t-not-increasing", lambda: replay(t=np.r_[0.0, 1, 1, 3, 4]), V, r"\bt\b"),
    Case("replay-t-string", lambda: replay(t="abc"), T, r"\bt\b"),
    Case("replay-t-shape", lambda: replay(t=np.arange(3.0)), V, r"\bt\b"),
    # ----------------------------------------------------------- compare
    Case("compare-estimators-list", lambda: compare([estim.EKF, estim.UKF]), T,
         r"estimators must be a dict"),
    Case("compare-estimators-empty", lambda: compare({}), V, r"estimators"),
    Case("compare-estimators-number", lambda: compare({"e": 3}), T, r"estimators\['e'\]"),
    Case("compare-estimators-other-class", lambda: compare({"e": dict}), T,
         r"estimators\['e'\]"),
    Case("compare-scenario", lambda: estim.compare(M, {"ekf": estim.EKF}), T, r"scenario"),
    Case("compare-seeds-int", lambda: compare(seeds=5), T, r"seeds"),
    Case("compare-seeds-empty", lambda: compare(seeds=[]), V, r"seeds"),
    Case("compare-seeds-bool", lambda: compare(seeds=[True]), T, r"seeds"),
    Case("compare-seeds-negative", lambda: compare(seeds=[-1]), V, r"seeds"),
    Case("compare-seeds-float", lambda: compare(seeds=[0.5]), T, r"seeds"),
    Case("compare-seeds-repeated", lambda: compare(seeds=[1, 1]), V, r"seeds"),
    Case("compare-n-jobs-zero", lambda: compare(n_jobs=0), V, r"n_jobs"),
    Case("compare-n-jobs-bool", lambda: compare(n_jobs=True), T, r"n_jobs"),
    Case("compare-n-jobs-float", lambda: compare(n_jobs=1.5), T, r"n_jobs"),
    Case("compare-backend-number", lambda: compare(n_jobs=2, backend=3), T, r"backend"),
    Case("compare-keep-logs-string", lambda: compare(keep_logs="yes"), T, r"keep_logs"),
    Case("compare-progress-string", lambda: compare(progress="no"), T, r"progress"),
    Case("compare-burn-in-negative", lambda: compare(burn_in=-1), V, r"burn_in"),
    Case("compare-burn-in-bool", lambda: compare(burn_in=True), T, r"burn_in"),
    Case("compare-burn-in-too-long", lambda: compare(burn_in=10), V, r"burn_in"),
    Case("compare-unknown-keyword", lambda: compare(seed=3), T,
         r"unknown option 'seed'.*'seeds'"),
    Case("compare-no-joblib", lambda: _without(("joblib",), lambda: compare(n_jobs=2)), IE,
         r"n_jobs.*pip install joblib"),
    Case("compare-no-dask", lambda: _without(("dask", "dask.distributed"),
                                             lambda: compare(n_jobs=2, backend="dask")), IE,
         r"dask.*estim\[dask\]"),
    # ---------------------------------------------------------- Scenario
    Case("scenario-n-steps-zero", lambda: scenario(n_steps=0), V, r"n_steps"),
    Case("scenario-n-steps-bool", lambda: scenario(n_steps=True), T, r"n_steps"),
    Case("scenario-clip-string", lambda: scenario(clip="no"), T, r"clip"),
    Case("scenario-feedback", lambda: scenario(feedback="x"), V, r"feedback"),
    Case("scenario-model", lambda: scenario(model="m"), T, r"model"),
    Case("scenario-plant-changes", lambda: scenario(plant_changes=[("1", {"k": 2.0})]), T,
         r"plant_changes"),
    Case("scenario-tuning", lambda: scenario(tuning=3), T, r"tuning"),
    Case("scenario-controller", lambda: scenario(controller=3), T, r"controller"),
    Case("scenario-inputs-shape", lambda: scenario(inputs=np.zeros((3, 1))), V, r"inputs"),
    Case("scenario-replace", lambda: SC.replace(n_steps=-3), V, r"n_steps"),
    Case("scenarios-get-unknown", lambda: estim.scenarios.get("lorenzz"), V,
         r"lorenzz.*did you mean 'lorenz'"),
    Case("scenarios-get-typo", lambda: estim.scenarios.get("lorenz", n_step=10), T,
         r"n_step.*'n_steps'"),
    Case("scenarios-get-name", lambda: estim.scenarios.get(3), T, r"name"),
    Case("scenarios-get-n-steps", lambda: estim.scenarios.get("lorenz", n_steps=0), V,
         r"n_steps"),
    Case("scenarios-satellite-fault", lambda: estim.scenarios.satellite(fault="no"), T,
         r"fault"),
    # ------------------------------------------------------ observability
    Case("analyze-model", lambda: observability.analyze("robot"), T, r"model"),
    Case("analyze-rtol-nan", lambda: observability.analyze(M, rtol=nan), V, r"rtol"),
    Case("analyze-rtol-zero", lambda: observability.analyze(M, rtol=0.0), V, r"rtol"),
    Case("analyze-rtol-big", lambda: observability.analyze(M, rtol=2.0), V, r"rtol"),
    Case("analyze-max-order-negative", lambda: observability.analyze(M, max_order=-1), V,
         r"max_order"),
    Case("analyze-max-order-bool", lambda: observability.analyze(M, max_order=True), T,
         r"max_order"),
    Case("analyze-order-negative", lambda: observability.analyze(M, order=-1), V, r"order"),
    Case("analyze-order-float", lambda: observability.analyze(M, order=1.5), T, r"order"),
    Case("analyze-order-bool", lambda: observability.analyze(M, order=True), T, r"order"),
    Case("analyze-inputs-unknown", lambda: observability.analyze(M, inputs="random"), V,
         r"inputs"),
    Case("analyze-inputs-value", lambda: observability.analyze(M, inputs={"u": "x"}), T,
         r"inputs"),
    Case("analyze-inputs-name", lambda: observability.analyze(M, inputs={"thrust": 0.0}), V,
         r"inputs"),
    Case("analyze-method", lambda: observability.analyze(M, method="exact"), V, r"method"),
    Case("analyze-n-points-zero", lambda: observability.analyze(M, n_points=0), V,
         r"n_points"),
    Case("analyze-n-points-bool", lambda: observability.analyze(M, n_points=True), T,
         r"n_points"),
    Case("analyze-input-samples-zero", lambda: observability.analyze(M, input_samples=0), V,
         r"input_samples"),
    Case("analyze-input-samples-string", lambda: observability.analyze(M, input_samples="2"),
         T, r"input_samples"),
    Case("analyze-at-shape", lambda: observability.analyze(M, at=[1.0]), V, r"\bat\b"),
    Case("analyze-at-string", lambda: observability.analyze(M, at="x"), T, r"\bat\b"),
    Case("analyze-seed-negative", lambda: observability.analyze(M, seed=-1), V, r"seed"),
    Case("analyze-arrangement", lambda: observability.analyze(M, arrangement="all"), V,
         r"arrangement"),
    Case("analyze-unknown-keyword", lambda: observability.analyze(M, ordr=2), T,
         r"unknown option 'ordr'.*'order'"),
    Case("window-every-zero", lambda: observability.window(M, [1.0, 0.0], 4, every=0), V,
         r"every"),
    Case("window-every-bool", lambda: observability.window(M, [1.0, 0.0], 4, every=True), T,
         r"every"),
    Case("window-n-steps-negative", lambda: observability.window(M, [1.0, 0.0], -1), V,
         r"n_steps"),
    Case("window-n-steps-float", lambda: observability.window(M, [1.0, 0.0], 2.5), T,
         r"n_steps"),
    Case("window-x0-shape", lambda: observability.window(M, [1.0], 4), V, r"x0"),
    Case("window-inputs-shape", lambda: observability.window(
        M, [1.0, 0.0], 4, inputs=np.zeros((3, 1))), V, r"inputs"),
    Case("window-inputs-nan", lambda: observability.window(
        M, [1.0, 0.0], 4, inputs=np.full((4, 1), nan)), V, r"inputs"),
    Case("window-R-negative", lambda: observability.window(M, [1.0, 0.0], 4, R=-1.0), V,
         r"\bR\b"),
    Case("window-rtol-nan", lambda: observability.window(M, [1.0, 0.0], 4, rtol=nan), V,
         r"rtol"),
    Case("window-model", lambda: observability.window("m", [1.0, 0.0], 4), T, r"model"),
    # ------------------------------------------------------------ metrics
    Case("rmse-estimate-none", lambda: estim.rmse(None), T, r"\bestimate\b"),
    Case("rmse-burn-in-negative", lambda: estim.rmse(log(), burn_in=-1), V, r"burn_in"),
    Case("rmse-burn-in-bool", lambda: estim.rmse(log(), burn_in=True), T, r"burn_in"),
    Case("rmse-burn-in-too-long", lambda: estim.rmse(log(), burn_in=1000), V, r"burn_in"),
    Case("rmse-states-unknown", lambda: estim.rmse(log(), states=["z"]), V, r"states"),
    Case("rmse-states-number", lambda: estim.rmse(log(), states=[1]), T, r"states"),
    Case("rmse-empty-log", lambda: estim.rmse(estim.Log()), V, r"\blog\b.*'x'"),
    Case("errors-burn-in-float", lambda: estim.errors(log(), burn_in=1.5), T, r"burn_in"),
    Case("nees-without-P", lambda: estim.nees(log_without_P()), V, r"'P'"),
    Case("nis-without-nis", lambda: estim.nis(log_without_P()), V, r"'nis'"),
    Case("chi2-dof-zero", lambda: estim.chi2_bounds(0, 10), V, r"dof"),
    Case("chi2-dof-float", lambda: estim.chi2_bounds(2.5, 10), T, r"dof"),
    Case("chi2-n-bool", lambda: estim.chi2_bounds(2, True), T, r"\bn\b"),
    Case("chi2-confidence", lambda: estim.chi2_bounds(2, 10, confidence=1.5), V,
         r"confidence"),
    Case("convergence-tol-negative", lambda: estim.convergence_time(log(), tol=-1.0), V,
         r"\btol\b"),
    Case("convergence-tol-string", lambda: estim.convergence_time(log(), tol="a"), T,
         r"\btol\b"),
    Case("convergence-relative-string",
         lambda: estim.convergence_time(log(), 0.1, relative="yes"), T, r"relative"),
    # ---------------------------------------------------------------- Log
    Case("log-dt-bool", lambda: estim.Log(dt=True), T, r"\bdt\b"),
    Case("log-dt-negative", lambda: estim.Log(dt=-1.0), V, r"\bdt\b"),
    Case("log-state-names-float", lambda: estim.Log(state_names=3.5), T, r"state_names"),
    Case("log-estimator-number", lambda: estim.Log(estimator=3), T, r"estimator"),
    Case("log-output-state-list", lambda: estim.Log(output_state=[1]), T, r"output_state"),
    Case("log-unknown-keyword", lambda: estim.Log(dtt=0.1), T,
         r"unknown option 'dtt'.*'dt'"),
    Case("log-call-key", lambda: estim.Log()("1x", 3.0), V, r"key"),
    Case("log-set-key", lambda: estim.Log().set("a b", np.zeros(3)), V, r"key"),
    Case("log-plot-sigma", lambda: log().plot(sigma="no"), T, r"sigma"),
    Case("log-plot-states", lambda: log().plot(states=["z"]), V, r"states"),
]


def _without(modules, call):
    with no_module(*modules):
        return call()


RUN = ["run", "van_der_pol", "--plot", "", "--seeds", "1", "--steps", "10"]

CLI_CASES = [
    CliCase("cli-steps-zero", ["run", "van_der_pol", "--steps", "0", "--plot", ""],
            r"--steps", argparse=True),
    CliCase("cli-steps-text", ["run", "van_der_pol", "--steps", "ten", "--plot", ""],
            r"--steps", argparse=True),
    CliCase("cli-seeds-zero", ["run", "van_der_pol", "--seeds", "0", "--plot", ""],
            r"--seeds", argparse=True),
    CliCase("cli-seeds-negative", ["run", "van_der_pol", "--seeds", "-1", "--plot", ""],
            r"--seeds", argparse=True),
    CliCase("cli-jobs-zero", [*RUN, "--jobs", "0"], r"--jobs", argparse=True),
    CliCase("cli-order-negative", ["observe", "martinelli_simple", "--order", "-1"],
            r"--order", argparse=True),
    CliCase("cli-bool-word", [*RUN, "-e", "ekf:clip=maybe"], r"clip"),
    CliCase("cli-unknown-option", [*RUN, "-e", "ekf:clipp=no"],
            r"unknown option 'clipp'.*did you mean 'clip'"),
    CliCase("cli-duplicate-label", [*RUN, "-e", "a=ekf", "-e", "a=ukf"], r"label 'a'"),
    CliCase("cli-unknown-estimator", [*RUN, "-e", "kalman"], r"kalman"),
    CliCase("cli-horizon-text", [*RUN, "-e", "mhe:horizon=x"], r"horizon"),
    CliCase("cli-horizon-zero", [*RUN, "-e", "mhe:horizon=0"], r"horizon"),
    CliCase("cli-option-without-value", [*RUN, "-e", "ekf:clip"], r"clip.*key=value"),
    CliCase("cli-missing-required", [*RUN, "-e", "shooting"], r"'window'"),
    CliCase("cli-alpha-negative", [*RUN, "-e", "ukf:alpha=-1"], r"alpha"),
    CliCase("cli-solver-unknown", [*RUN, "-e", "mhe:horizon=5,solver=snopt"], r"solver"),
    CliCase("cli-P0-negative", [*RUN, "-e", "ekf:P0=-1"], r"P0"),
    CliCase("cli-plot-folder", ["run", "van_der_pol", "--seeds", "1", "--steps", "10",
                                "-e", "ekf", "--plot", "/nonexistent/folder/run.png"],
            r"--plot"),
    CliCase("cli-observe-unknown", ["observe", "nonexistent"], r"nonexistent"),
    CliCase("cli-no-joblib", [*RUN, "-e", "ekf", "--jobs", "2"], r"pip install joblib",
            context=lambda: no_module("joblib")),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_call_is_refused_naming_the_argument(case):
    with pytest.raises(case.exc, match=case.match) as info:
        case.call()
    assert type(info.value) in (TypeError, ValueError, ImportError)


@pytest.mark.parametrize("case", CLI_CASES, ids=[c.id for c in CLI_CASES])
def test_bad_command_line_is_an_error_not_a_traceback(case, capsys):
    with case.context():
        if case.argparse:
            with pytest.raises(SystemExit) as info:
                cli.main(case.argv)
            code = info.value.code
        else:
            code = cli.main(case.argv)
    err = capsys.readouterr().err
    assert code == 2
    assert ("usage:" in err) if case.argparse else err.startswith("estim: error: "), err
    assert "Traceback" not in err
    import re

    assert re.search(case.match, err), err


def test_corpus_size():
    assert len(CASES) + len(CLI_CASES) >= 120
    assert len({c.id for c in CASES + CLI_CASES}) == len(CASES) + len(CLI_CASES)
