"""Defects that were silent or misleading, each with the test that failed before its fix:
a step that said "ok" without doing its work, a collapsed particle cloud reported healthy,
inputs accepted that made results wrong, and messages that did not name the cause
(docs/failures.md, "What estim promises when data go wrong")."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import estim


def _singular_dae() -> estim.Model:
    """``0 = z^3 - x_1``: at ``x_1 = 0`` the Newton solve finds ``z = 0`` where
    ``dg/dz = 3 z^2`` vanishes, so ``dz/dx`` (and the model's Jacobians) cannot be
    evaluated there."""
    return estim.Model(states=["x1", "x2"], algebraic=["z"], outputs=["y"],
                       ode=lambda x, z, u, p: ca.vertcat(x[1], -x[0] + z[0]),
                       alg=lambda x, z, u, p: z[0] ** 3 - x[0],
                       output=lambda x, z, u, p: x[0], z0=[0.0], dt=0.1)


def test_a_linearisation_that_fails_is_a_failed_step():
    """A DAE whose dg/dz is singular at the estimate: before, the EKF said "ok" at every
    step, its estimate never moved and P stayed P0 (the failed derivative of the Newton
    solve read as zeros inside the step), and the MHE did the same or, with Ipopt, ran
    for minutes. Now the first update (h does not need z) moves the estimate, every step
    that needs z fails and re-anchors, in the step loop and in filter() alike, and the
    MHE's steps are never "ok"."""
    m = _singular_dae()
    Y = np.full((6, 1), 3.0 * np.sqrt(2.0))
    ekf = estim.EKF(m, Q=0.01, R=1.0, x0=[0.0, 0.0], P0=1.0)
    log = estim.replay(ekf, Y, None, warn=False)
    assert log.status[0] == "ok" and log.x_hat[0, 0] == pytest.approx(Y[0, 0] / 2)
    assert all(s.startswith("failed: non-finite prediction") for s in log.status[1:])
    result = ekf.filter(Y)
    assert result.status == tuple(log.status) and not result.success
    np.testing.assert_array_equal(result.x, log.x_hat)
    for solver in ("auto", "ipopt"):
        mhe = estim.MHE(m, horizon=3, Q=0.01, R=1.0, x0=[0.0, 0.0], P0=1.0, solver=solver)
        statuses = estim.replay(mhe, Y, None, warn=False).status
        assert not any(s == "ok" for s in statuses), (solver, statuses)


@pytest.mark.parametrize("jit", [False, True])
def test_a_collapsed_particle_cloud_is_suspect(jit):
    """A bootstrap filter told Q = 0 on a plant with process noise: the resampled copies
    are never spread apart, and a cloud of 200 shrinks to a handful of particles with
    healthy weights (before: every status "ok"); now "suspect", on both paths."""
    vdp = estim.scenarios.get("van_der_pol")
    pf = estim.ParticleFilter(vdp.model, n_particles=200, seed=0, jit=jit,
                              **{**vdp.tuning, "Q": 0.0})
    log = estim.simulate(vdp, pf, seed=0)
    collapsed = [s for s in log.status if "distinct particles of 200" in s]
    assert len(collapsed) > len(log) // 2, set(log.status)
    counts = [int(s.split("only ")[1].split()[0]) for s in collapsed]
    assert max(counts) < 20
    healthy = estim.ParticleFilter(vdp.model, n_particles=200, seed=0, jit=jit, **vdp.tuning)
    assert not any("distinct" in s for s in estim.simulate(vdp, healthy, seed=0).status)


def _oscillator(dt: float = 0.1, variable_dt: bool = False, inputs=None) -> estim.Model:
    return estim.Model(states=["a", "b"], outputs=["y"], dt=dt, variable_dt=variable_dt,
                       inputs=inputs, ode=lambda x, u, p: ca.vertcat(x[1], -x[0]),
                       output=lambda x, u, p: x[0])


@pytest.mark.parametrize(("other", "why"), [
    ({"dt": 0.2}, "its model's dt is 0.2, the first mode's 0.1"),
    ({"variable_dt": True}, "its model's variable_dt is True, the first mode's False"),
    ({"inputs": ["u"]}, r"has other input names than the first mode: \['u'\] against \[\]")])
def test_imm_modes_must_predict_alike(other, why):
    """Before, modes with another dt or a variable_dt among fixed ones were accepted (they
    then predicted over different intervals), other inputs failed at the first step with
    numpy's shape errors."""
    tuning = {"Q": 0.01, "R": 1.0, "x0": [0.0, 0.0], "P0": 1.0}
    modes = {"a": estim.EKF(_oscillator(), **tuning), "b": estim.EKF(_oscillator(**other),
                                                                      **tuning)}
    with pytest.raises(ValueError, match=rf"estimators\['b'\]:? .*{why}"):
        estim.IMM(modes, transition=[[0.9, 0.1], [0.1, 0.9]])


def test_merge_reads_datetimes_as_seconds_and_refuses_repeated_outputs():
    """numpy.datetime64 stamps were read as their integer count (milliseconds here) and
    used as seconds; a name twice in outputs= was accepted."""
    from estim import records

    stamps = np.array(["2024-01-01T00:00:00.000", "2024-01-01T00:00:00.500",
                       "2024-01-01T00:00:02.000"], dtype="datetime64[ms]")
    rec = records.merge({"y": (stamps, [1.0, 2.0, 3.0])}, ["y"])
    np.testing.assert_allclose(np.diff(rec.t), [0.5, 1.5])
    np.testing.assert_allclose(rec.dt[1:], [0.5, 1.5])
    shifted = records.merge({"y": (stamps - stamps[0], [1.0, 2.0, 3.0])}, ["y"])
    np.testing.assert_allclose(shifted.t, [0.0, 0.5, 2.0])
    with pytest.raises(ValueError, match=r"outputs names \['y'\] more than once"):
        records.merge({"y": ([0.0, 1.0], [1.0, 2.0])}, ["y", "y"])


def test_algebraic_names_are_their_own():
    def build(**names):
        return estim.Model(outputs=["y"], ode=lambda x, z, u, p: x[:1],
                           alg=lambda x, z, u, p: z[0] - x[0],
                           output=lambda x, z, u, p: x[0], z0=[0.0], dt=0.1, **names)

    with pytest.raises(ValueError, match=r"algebraic and states share names \['z'\]"):
        build(states=["z"], algebraic=["z"])
    with pytest.raises(ValueError, match=r"algebraic and params share names \['k'\]"):
        build(states=["x"], algebraic=["k"], params={"k": 1.0})


def test_a_second_disturbance_keeps_the_first():
    m = estim.models.batch_reactor(feed=True)
    once = m.with_disturbances(inputs=["feed"], at=([0.5, 0.05, 0.0], [0.005]))
    with pytest.warns(UserWarning, match="2 disturbances .* but 1 output"):
        twice = once.with_disturbances(outputs=[once.output_names[0]], check=False)
    assert twice.disturbances["inputs"] == {"feed": "d_feed"}
    assert twice.disturbances["outputs"] == {once.output_names[0]: f"d_{once.output_names[0]}"}


def test_compare_names_what_it_cannot_use():
    vdp = estim.scenarios.get("van_der_pol", n_steps=10)
    with pytest.raises(ValueError, match="backend must be one of .* got 'lokky'; did you "
                                         "mean 'loky'"):
        estim.compare(vdp, {"ekf": estim.EKF}, seeds=range(2), backend="lokky")
    pytest.importorskip("dask.distributed")
    with pytest.raises(ValueError, match='backend="dask" .* there is none: create one'):
        estim.compare(vdp, {"ekf": estim.EKF}, seeds=range(2), n_jobs=2, backend="dask")
    res = estim.compare(vdp, {"none": lambda m, t: None, "ekf": estim.EKF}, seeds=range(2))
    assert res.rows[0].errors[0].startswith("TypeError: the factory <lambda> returned "
                                            "NoneType, not an estimator")
    assert res.rows[1].runs == 2  # the other row goes on


def test_equations_and_callables_are_named():
    with pytest.raises(TypeError, match="ode must return a CasADi expression or a list of "
                                        "them: its entry 1 is NoneType"):
        estim.Model(states=["a", "b"], outputs=["y"], ode=lambda x, u, p: [x[1], None],
                    output=lambda x, u, p: x[0], dt=0.1)
    vdp = estim.scenarios.get("van_der_pol")
    with pytest.raises(TypeError, match=r"loglik: calling loglik\(y, yhat, p\) on symbols"):
        estim.ParticleFilter(vdp.model, n_particles=10, loglik=lambda e: -e ** 2, **vdp.tuning)
    with pytest.raises(ValueError, match="loglik must depend on y or yhat, got the constant"):
        estim.ParticleFilter(vdp.model, n_particles=10, loglik=lambda y, yhat, p: -1.0,
                             **vdp.tuning)
    from estim._sympy import function_to_sympy

    x = ca.SX.sym("x", 2)
    with pytest.raises(NotImplementedError, match="'fmod' .* use method='numeric'"):
        function_to_sympy(ca.Function("f", [x], [ca.fmod(x[0], x[1])]))


def test_an_absurd_measurement_is_named():
    vdp = estim.scenarios.get("van_der_pol")
    log = estim.replay(estim.EKF(vdp.model, **vdp.tuning), np.array([[1e200, 0.0]] * 3), None,
                       warn=False)
    assert log.status[0].startswith("failed: non-finite update: the measurement "
                                    "x1_meas = 1e+200 overflows the update") or \
        "= 1e+200 overflows the update" in log.status[0], log.status[0]


def test_the_square_root_ekf_runs_where_the_covariance_form_does():
    """R = 1e-300: the square-root EKF failed every step (the posterior factor lost
    K R K^T and came out zero); in Joseph's form it gives the covariance form's numbers."""
    vdp = estim.scenarios.get("van_der_pol")
    Y = estim.simulate(vdp, None, seed=0).y[:40]
    for R in (1e-300, 1e-100):
        a = estim.replay(estim.EKF(vdp.model, **{**vdp.tuning, "R": R}, form="sqrt"), Y, None,
                         warn=False)
        b = estim.replay(estim.EKF(vdp.model, **{**vdp.tuning, "R": R}), Y, None, warn=False)
        assert a.failures == 0 and list(a.status) == list(b.status)
        np.testing.assert_allclose(a.x_hat, b.x_hat, rtol=1e-9, atol=1e-9)


def test_a_blown_up_covariance_is_suspect():
    """Five 100-sigma outliers on van der Pol (the fault matrix, seed 13): the EKF absorbed
    them and its estimate went to 1e12 with a covariance to match, so its NIS looked
    fine and the step said "ok"; now "suspect", in the step loop and in filter()."""
    vdp = estim.scenarios.get("van_der_pol", n_steps=200)
    log = estim.simulate(vdp, None, seed=13)
    Y = log.y.copy()
    Y[80:85] += 100.0
    ekf = estim.EKF(vdp.model, **vdp.tuning)
    out = estim.replay(ekf, Y, None, log.x, warn=False)
    err = np.linalg.norm(out.x_hat - log.x, axis=1)
    huge = np.flatnonzero(err > 1e3)
    assert huge.size and all(out.status[k] != "ok" for k in huge), \
        [(k, out.status[k]) for k in huge]
    assert any("the covariance blew up" in s for s in out.status)
    assert ekf.filter(Y).status == tuple(out.status)


def test_filterpy_adapter_checks_what_it_is_given():
    from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter

    from estim import adapters

    A, C = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[1.0, 0.0]])
    model = estim.Model(states=["p", "v"], outputs=["y"], dynamics=lambda x, u, p: A @ x,
                        output=lambda x, u, p: C @ x)
    two = KalmanFilter(dim_x=2, dim_z=2)
    with pytest.raises(ValueError, match=r"filt measures 2 outputs \(dim_z\) but model has 1"):
        adapters.from_filterpy(two, model)
    with pytest.raises(TypeError, match="model must be an estim.Model .* got str"):
        adapters.from_filterpy(KalmanFilter(dim_x=2, dim_z=1), "model")
    ekf = ExtendedKalmanFilter(dim_x=2, dim_z=1)
    with pytest.raises(TypeError, match="hx must be a function"):
        adapters.from_filterpy(ekf, model, hx=C)
    with pytest.raises(ValueError, match=r"HJacobian\(x, u\) must give \(1, 2\) values"):
        adapters.from_filterpy(ekf, model, HJacobian=lambda x, u: np.eye(2))
    flat = ExtendedKalmanFilter(dim_x=2, dim_z=1)
    flat.x = np.zeros(2)
    with pytest.raises(ValueError, match=r"filt.x must be an \(2, 1\) column .* predicts "
                                         r"x = F x unless predict_x is overridden"):
        adapters.from_filterpy(flat, model)


def test_the_command_line_splits_the_file_at_its_own_py(tmp_path):
    from estim.cli import load_scenario

    folder = tmp_path / "a.py-runs"
    folder.mkdir()
    (folder / "b.py").write_text("import estim\n"
                                 "mine = estim.scenarios.get('van_der_pol', n_steps=5)\n")
    assert load_scenario(f"{folder}/b.py:mine").n_steps == 5
    with pytest.raises(ValueError, match="write path/to/file.py or path/to/file.py:name"):
        load_scenario(f"{folder}/b.pyc")


def test_consistency_of_runs_without_covariances_is_refused():
    """Logs without covariances gave a NaN interval (a pass or a failure that said
    nothing); now a ValueError says there is nothing to test."""
    from estim import adapters, testing

    vdp = estim.scenarios.get("van_der_pol", n_steps=30)
    blind = adapters.from_function(lambda y, u: np.zeros(2), vdp.model, name="zero")
    logs = [estim.simulate(vdp, blind, seed=s) for s in range(3)]
    with pytest.raises(ValueError, match="no log with a covariance to test"):
        testing.assert_consistent(logs)
    res = estim.compare(vdp, {"zero": blind}, seeds=range(3))
    with pytest.raises(ValueError, match="no seed with a covariance to test"):
        testing.assert_consistent(res)
