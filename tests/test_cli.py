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
    label, cls, kwargs = cli.parse_estimator("mhe-25=mhe:horizon=25,solver=gauss-newton")
    assert label == "mhe-25" and cls.__name__ == "MHE"
    assert kwargs == {"horizon": 25, "solver": "gauss-newton"}
    with pytest.raises(ValueError, match="unknown estimator"):
        cli.parse_estimator("kalman")
    with pytest.raises(ValueError, match="key=value"):
        cli.parse_estimator("ekf:clip")


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
