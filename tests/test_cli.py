"""The command line: the README's main job and option parsing."""

from __future__ import annotations

import re

import pytest

from estim import cli


def test_main_job_prints_table_and_writes_png(tmp_path, capsys):
    out = tmp_path / "run.png"
    assert cli.main(["run", "batch_reactor", "--seeds", "2", "--plot", str(out)]) == 0
    text = capsys.readouterr().out
    assert "RMSE mean" in text and "ekf:clip=true" in text and "ukf" in text
    assert "mhe-25" in text
    assert out.stat().st_size > 20_000


def test_list(capsys):
    assert cli.main(["list"]) == 0
    text = capsys.readouterr().out
    for name in ("lorenz", "van_der_pol", "batch_reactor", "runaway", "satellite", "ekf",
                 "pf", "enkf", "imm"):
        assert re.search(rf"^  {name} ", text, re.M), name


def test_run_beyond_gaussian(capsys):
    """The particle filter, the EnKF and the two-mode IMM from the command line."""
    assert cli.main(["run", "van_der_pol", "--seeds", "1", "--steps", "60", "--plot", "",
                     "-e", "pf:n_particles=200", "-e", "enkf:n_ensemble=20",
                     "-e", "imm:kind=ukf,high=20"]) == 0
    text = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in text.splitlines()
            if line.startswith(("pf:", "enkf:", "imm:"))}
    assert set(rows) == {"pf:n_particles=200", "enkf:n_ensemble=20", "imm:kind=ukf,high=20"}
    assert all(float(r[1]) < 1.0 for r in rows.values()), rows  # RMSE


def test_parse_estimator():
    label, cls, kwargs = cli.parse_estimator("ekf:clip=true")
    assert cls.__name__ == "EKF" and kwargs == {"clip": True} and label == "ekf:clip=true"
    _, cls, kwargs = cli.parse_estimator("ukf:alpha=0.5,kappa=1")
    assert cls.__name__ == "UKF" and kwargs == {"alpha": 0.5, "kappa": 1}
    # the Gaussian filters' family: iterated, damped, other rules, the PF's rule
    _, cls, kwargs = cli.parse_estimator("iekf=ekf:iterations=10,damping=line-search")
    assert cls.__name__ == "EKF" and kwargs == {"iterations": 10, "damping": "line-search"}
    _, cls, kwargs = cli.parse_estimator("ukf:points=gauss-hermite,order=3,iterations=30,"
                                         "damping=relaxed")
    assert kwargs == {"points": "gauss-hermite", "order": 3, "iterations": 30,
                      "damping": "relaxed"}
    _, cls, kwargs = cli.parse_estimator("pf:proposal=ukf,points=cubature5")
    assert cls.__name__ == "ParticleFilter" and kwargs["points"] == "cubature5"
    label, cls, kwargs = cli.parse_estimator("mhe-25=mhe:horizon=25,solver=gauss-newton")
    assert label == "mhe-25" and cls.__name__ == "MHE"
    assert kwargs == {"horizon": 25, "solver": "gauss-newton"}
    with pytest.raises(ValueError, match="unknown estimator"):
        cli.parse_estimator("kalman")
    with pytest.raises(ValueError, match="key=value"):
        cli.parse_estimator("ekf:clip")


def test_options_are_literals_and_a_broken_estimator_is_a_row(capsys):
    """Lists and dicts, nested, inside an option (the commas inside their brackets do not
    split the spec); an estimator whose constructor refuses its options is a row with the
    reason, the others run, and the exit status is 1."""
    _, cls, kwargs = cli.parse_estimator('m=mhe:horizon=20,Q=[1e-6, 0.01],'
                                         'solver_options={"max_iter": [5, {"a": 1}]}')
    assert kwargs == {"horizon": 20, "Q": [1e-6, 0.01],
                      "solver_options": {"max_iter": [5, {"a": 1}]}}
    with pytest.raises(ValueError, match="an unclosed bracket"):
        cli.parse_estimator("mhe:Q=[1, 2")
    assert cli.main(["run", "van_der_pol", "--seeds", "2", "--steps", "20", "--plot", "",
                     "-e", "ekf", "-e", "bad=mhe:horizon=0"]) == 1
    out, err = capsys.readouterr()
    assert "bad: 2 of 2 runs raised and are left out (seed 0: ValueError: horizon" in out
    assert "ekf " in out and "estim run: bad raised on every seed" in err


def test_bad_option_is_an_error_not_a_traceback(capsys):
    assert cli.main(["run", "van_der_pol", "--estimator", "nope", "--plot", ""]) == 2
    assert "unknown estimator" in capsys.readouterr().err


def _estimate(text: str, entry: str) -> tuple[float, float]:
    m = re.search(re.escape(entry) + r" = ([-+.\deE]+) ± ([-+.\deE]+)", text)
    assert m, text
    return float(m[1]), float(m[2])


@pytest.mark.parametrize("method, label", [("als", "als: ok"),
                                           ("ml", "maximum likelihood: ok")])
def test_tune_estimates_q_and_r_and_compares_the_ekf(method, label, capsys):
    assert cli.main(["tune", "van_der_pol", "--steps", "300", "--method", method,
                     "--check-seeds", "2"]) == 0
    text = capsys.readouterr().out
    assert label in text and "Ljung-Box" in text
    assert "scenario tuning" in text and "this record" in text and "2 new records" in text
    for entry in ("R[0,0]", "R[1,1]"):  # both outputs are measured with std 1
        value, se = _estimate(text, entry)
        assert abs(value - 1.0) < 3 * se


def test_tune_rejects_an_unknown_method(capsys):
    with pytest.raises(SystemExit):
        cli.main(["tune", "van_der_pol", "--method", "guess"])
    assert "invalid choice" in capsys.readouterr().err


USER_FILE = '''
import casadi as ca
import numpy as np

import estim


def scenario():
    m = estim.Model(states=["h1", "h2"], inputs=["q"], outputs=["h2_m"], params={"a": 0.5},
                    ode=lambda x, u, p: ca.vertcat(u[0] - p["a"] * ca.sqrt(ca.fmax(x[0], 0)),
                                                   p["a"] * ca.sqrt(ca.fmax(x[0], 0))
                                                   - 0.4 * ca.sqrt(ca.fmax(x[1], 0))),
                    output=lambda x, u, p: x[1], dt=0.5, lower=0.0, name="two tanks")
    return estim.Scenario("tanks", m, x0=[1.0, 1.0], n_steps=60, Q=1e-4, R=1e-3,
                          inputs=lambda t: [0.5 + 0.1 * np.sin(0.2 * t)],
                          tuning=dict(Q=1e-4, R=1e-3, x0=[0.8, 1.2], P0=0.1))


FIXED = scenario()
'''


def test_run_and_tune_take_a_scenario_from_the_users_file(tmp_path, capsys):
    path = tmp_path / "experiment.py"
    path.write_text(USER_FILE)
    assert cli.main(["run", f"{path}:scenario", "-e", "ekf", "-e", "ukf", "--seeds", "2",
                     "--plot", ""]) == 0
    out = capsys.readouterr().out
    assert out.startswith("tanks: 2 seed(s)") and "ukf" in out
    assert cli.main(["run", f"{path}:FIXED", "-e", "ekf", "--seeds", "2", "--plot", ""]) == 0
    assert cli.main(["tune", f"{path}", "--steps", "400", "--check-seeds", "1"]) == 0
    assert "scenario tuning" in capsys.readouterr().out
    assert cli.main(["run", f"{path}:nothing", "--plot", ""]) == 2
    assert "has no 'nothing'; give file.py:name, one of ['scenario', 'FIXED']" in \
        capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["run", "van_der_pool"])
    assert "unknown scenario 'van_der_pool'" in capsys.readouterr().err
