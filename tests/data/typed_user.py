"""A user's script, type-checked by tests/test_packaging.py (mypy) and run by it.

It uses the public API the way a notebook or a course exercise does, with its
own annotations, so that a wrong type in estim's hints shows up as a mypy error.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

import estim


def van_der_pol(mu: float = 1.0) -> estim.Model:
    return estim.Model(
        states=["x1", "x2"], outputs=["y1"],
        ode=lambda x, u, p: ca.vertcat(x[1], p["mu"] * (1 - x[0] ** 2) * x[1] - x[0]),
        output=lambda x, u, p: x[0],
        params={"mu": mu}, dt=0.1, name="vdp",
    )


def main() -> None:
    model = van_der_pol()
    x_next: np.ndarray = model.f(np.array([1.0, 0.0]))
    y0: np.ndarray = model.h(x_next)
    assert model.nx == 2 and model.ny == 1 and y0.shape == (1,)

    ekf = estim.EKF(model, Q=0.01, R=0.1, x0=[0.0, 0.0], P0=1.0)
    log: estim.Log = estim.simulate(model, ekf, x0=[1.5, 1.5], n_steps=40, Q=0.01, R=0.1,
                                    seed=0)
    error: estim.RMSE = estim.rmse(log, burn_in=5)
    per_state: dict[str, float] = error.per_state
    assert float(error) < 1.0 and set(per_state) == {"x1", "x2"}
    t: np.ndarray = log.t
    x_hat: np.ndarray = log.x_hat
    P: np.ndarray = log.P
    assert x_hat.shape == (len(t), 2) and P.shape == (len(t), 2, 2)
    assert log.failures == 0
    info: estim.StepInfo = ekf.info
    status: str = info.status
    assert status in ("ok", "suspect") or status.startswith(("ok", "suspect"))

    mhe = estim.MHE(model, horizon=10, Q=0.01, R=0.1, x0=[0.0, 0.0], P0=1.0)
    estimate: np.ndarray = mhe.step(log.y[0])
    for k in range(1, 15):
        estimate = mhe.step(log.y[k], log.u[k - 1])
    assert estimate.shape == (2,) and mhe.info.solve_time >= 0.0
    replayed: estim.Log = estim.replay(ekf, log.y[:15])
    assert replayed.x_hat.shape == (15, 2)

    fie = estim.FullInformation(model, Q=0.01, R=0.1, x0=[0.0, 0.0], P0=1.0)
    fit: estim.FitResult = fie.fit(log.y[:20])
    assert fit.x.shape == (20, 2) and np.isfinite(fit.cost)

    nees: np.ndarray = estim.nees(log)
    lo, hi = estim.chi2_bounds(dof=2, n=1)
    assert nees.shape == (40,) and lo < hi

    scenario: estim.Scenario = estim.scenarios.van_der_pol().replace(n_steps=20)
    table: estim.Comparison = estim.compare(
        scenario, {"ekf": estim.EKF, "ukf": estim.UKF}, seeds=range(2))
    text: str = table.table()
    assert "ekf" in text and "ukf" in text

    report: estim.observability.ObservabilityReport = estim.observability.analyze(model)
    assert report is not None
    soft = estim.soft.max(np.array([-1.0, 2.0]), 0.0, width=0.01)
    assert np.allclose(soft, [0.0, 2.0], atol=0.01)


if __name__ == "__main__":
    main()
