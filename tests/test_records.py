"""Asynchronous sensor streams merged into one record (``estim.records.merge``): the
merged record through EKF, UKF, MHE and full information equals a Kalman filter
(filterpy) that updates sensor by sensor at each time stamp."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter, rts_smoother
from scipy.linalg import expm

import estim
from estim.records import merge

# a vertical channel: height, climb rate, acceleration (a random walk); the IMU sees the
# acceleration, the GNSS receiver and the barometer the height
A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
OUTPUTS = ["acc", "h_gnss", "h_baro"]
H_ROWS = {"acc": [0.0, 0.0, 1.0], "h_gnss": [1.0, 0.0, 0.0], "h_baro": [1.0, 0.0, 0.0]}
SENSORS = {"imu": ["acc"], "gnss": ["h_gnss"], "baro": ["h_baro"]}
VAR = {"imu": 0.05**2, "gnss": 2.0**2, "baro": 0.5**2}
Q = np.diag([1e-6, 1e-4, 1e-2])
X0, P0 = np.array([100.0, 0.0, 0.0]), np.diag([25.0, 1.0, 0.1])


def vehicle() -> estim.Model:
    # RK4 is exact for this nilpotent A (expm(A dt) = I + A dt + (A dt)^2 / 2)
    m = estim.models.vertical_channel(variable_dt=True)
    assert m.output_names == OUTPUTS
    return m


def streams(seconds: float = 3.0, seed: int = 0) -> dict:
    """IMU at 100 Hz, GNSS at 1 Hz (on IMU stamps), barometer at 20 Hz (offset 3 ms)."""
    rng = np.random.default_rng(seed)
    times = {"imu": np.arange(int(100 * seconds)) / 100,
             "gnss": np.arange(int(seconds)) * 1.0,
             "baro": np.arange(int(20 * seconds)) / 20 + 0.003}
    t_all = np.unique(np.concatenate(list(times.values())))
    x, X = X0.copy(), {}
    for k, tk in enumerate(t_all):
        if k:
            x = expm(A * (tk - t_all[k - 1])) @ x + rng.multivariate_normal(np.zeros(3), Q)
        X[tk] = x.copy()
    out = {}
    for s, ts in times.items():
        rows = [H_ROWS[SENSORS[s][0]]]
        Y = np.array([np.array(rows) @ X[tk] for tk in ts]) + \
            np.sqrt(VAR[s]) * rng.standard_normal((len(ts), 1))
        out[s] = (ts, Y, SENSORS[s])
    return out


def sequential_kalman(data: dict):
    """filterpy: at each stamp predict over the interval, then update with each sensor
    that reported, one after the other."""
    events = sorted((float(tk), s, y) for s, (ts, Y, _) in data.items()
                    for tk, y in zip(ts, Y, strict=True))
    kf = KalmanFilter(dim_x=3, dim_z=1)
    kf.x, kf.P = X0.copy(), P0.copy()
    xs, Ps, last = {}, {}, None
    for tk, s, y in events:
        if last is not None and tk != last:
            kf.F, kf.Q = expm(A * (tk - last)), Q
            kf.predict()
        kf.update(y, R=np.array([[VAR[s]]]), H=np.array([H_ROWS[SENSORS[s][0]]]))
        xs[tk], Ps[tk], last = kf.x.copy(), kf.P.copy(), tk
    t = np.array(sorted(xs))
    return t, np.array([xs[tk] for tk in t]), np.array([Ps[tk] for tk in t])


def test_merged_record_layout():
    data = streams(seconds=2.0)
    rec = merge(data, outputs=OUTPUTS)
    # 200 IMU stamps (the GNSS ones among them) and 40 barometer stamps
    assert len(rec.t) == 240 and np.all(np.diff(rec.t) > 0)
    np.testing.assert_allclose(rec.dt[1:], np.diff(rec.t))
    assert np.isnan(rec.dt[0])
    assert rec.reported["gnss"].sum() == 2 and rec.reported["imu"].sum() == 200
    both = rec.reported["imu"] & rec.reported["gnss"]
    assert both.sum() == 2 and not np.isnan(rec.Y[both][:, :2]).any()  # one row each
    np.testing.assert_array_equal(np.isnan(rec.Y[:, 1]), ~rec.reported["gnss"])
    np.testing.assert_allclose(rec.R(VAR), np.diag([VAR["imu"], VAR["gnss"], VAR["baro"]]))
    # a repeated row with the same value is kept once; pandas and dict forms
    pd = pytest.importorskip("pandas")
    ts, Y, _ = data["gnss"]
    twice = merge({"gnss": (np.r_[ts, 5.0], np.r_[Y[:, 0], 1.0], "h_gnss"),
                   "check": pd.DataFrame({"t": ts, "h_gnss": Y[:, 0]})}, outputs=OUTPUTS)
    assert len(twice.t) == 3
    as_dict = merge({"gnss": (ts, {"h_gnss": Y[:, 0]})}, outputs=OUTPUTS)
    np.testing.assert_array_equal(as_dict.Y[:, 1], Y[:, 0])


def test_merged_streams_equal_sequential_kalman_updates():
    """EKF, UKF and MHE on the merged record equal filterpy updating sensor by sensor,
    state and covariance, to 1e-10 (relative to the state's scale); full information's
    last state equals the filter's."""
    data = streams()
    rec = merge(data, outputs=OUTPUTS)
    t_ref, xs, Ps = sequential_kalman(data)
    np.testing.assert_array_equal(t_ref, rec.t)
    m = vehicle()
    tuning = dict(Q=Q, R=rec.R(VAR), x0=X0, P0=P0)
    for est in (estim.EKF(m, **tuning), estim.UKF(m, **tuning),
                estim.MHE(m, horizon=10, solver="gauss-newton", **tuning)):
        log = estim.replay(est, rec.Y, t=rec.t)
        assert np.all(log.status == "ok"), type(est).__name__
        np.testing.assert_allclose(log.x_hat, xs, rtol=1e-10, atol=1e-10 * np.abs(xs).max(),
                                   err_msg=type(est).__name__)
        if not isinstance(est, estim.MHE):
            np.testing.assert_allclose(np.asarray(log.P), Ps, rtol=1e-9, atol=1e-12)
    fit = estim.FullInformation(m, **tuning).fit(rec.Y, t=rec.t)
    np.testing.assert_allclose(fit.x[-1], xs[-1], rtol=1e-10, atol=1e-8)


def test_bad_streams_are_named():
    ts = np.arange(5.0)
    with pytest.raises(ValueError, match=r"streams\['gnss'\]: the time stamps must be "
                                         r"increasing; t\[3\]"):
        merge({"gnss": (np.array([0.0, 1.0, 2.0, 2.0, 3.0]), ts, "h_gnss")}, OUTPUTS)
    with pytest.raises(ValueError, match=r"measures \['speed'\], which are not outputs"):
        merge({"gnss": (ts, ts, ["speed"])}, OUTPUTS)
    with pytest.raises(ValueError, match=r"output 'h_gnss' at t = 2.0: 'gnss' reports 2.0 "
                                         r"and 'other' 7.0"):
        merge({"gnss": (ts, ts, "h_gnss"), "other": ([2.0], [7.0], "h_gnss")}, OUTPUTS)
    with pytest.raises(ValueError, match=r"Y must have shape \(5, 1\)"):
        merge({"gnss": (ts, np.zeros((4, 1)), "h_gnss")}, OUTPUTS)
    with pytest.raises(ValueError, match="say which outputs"):
        merge({"gnss": (ts, ts)}, OUTPUTS)
    with pytest.raises(TypeError, match=r"streams\['gnss'\] must be"):
        merge({"gnss": ts}, OUTPUTS)
    with pytest.raises(TypeError, match="non-empty dict"):
        merge({}, OUTPUTS)
    rec = merge({"gnss": (ts, ts, "h_gnss"), "baro": (ts + 0.5, ts, "h_baro")}, OUTPUTS)
    with pytest.raises(ValueError, match=r"missing: \['baro'\]"):
        rec.R({"gnss": 1.0})
    with pytest.raises(ValueError, match=r"covariances\['baro'\]"):
        rec.R({"gnss": 1.0, "baro": -1.0})
    both = merge({"gnss": (ts, ts, "h_gnss"), "gnss2": (ts + 0.5, ts, "h_gnss")}, OUTPUTS)
    with pytest.raises(ValueError, match="both measure 'h_gnss'"):
        both.R({"gnss": 1.0, "gnss2": 1.0})


def test_filter_and_smooth_take_the_merged_record():
    """``filter`` and ``smooth`` with the merged record's time stamps: the filter equals
    the sequential updates, the smoother filterpy's RTS smoother over the stamps."""
    data = streams(seconds=2.0)
    rec = merge(data, outputs=OUTPUTS)
    _, xs, Ps = sequential_kalman(data)
    Fs = [expm(A * dt) for dt in np.diff(rec.t)] + [np.eye(3)]
    xr, Pr, _, _ = rts_smoother(xs, Ps, np.array(Fs), np.array([Q] * len(Fs)))
    m = vehicle()
    tuning = dict(Q=Q, R=rec.R(VAR), x0=X0, P0=P0)
    scale = np.abs(xs).max()
    for cls in (estim.EKF, estim.UKF):
        np.testing.assert_allclose(cls(m, **tuning).filter(rec.Y, t=rec.t).x, xs,
                                   atol=1e-10 * scale)
        sm = cls(m, **tuning).smooth(rec.Y, t=rec.t)
        np.testing.assert_allclose(sm.x, xr, atol=1e-10 * scale, err_msg=cls.__name__)


def test_sensor_fusion_scenario():
    """``Scenario(sampling=...)``: each output reported at its own rate (NaN between), in
    ``simulate`` and in the batched plant of ``compare`` alike; the EKF on it is filterpy's
    Kalman filter updating with the sensors that reported; bad sampling is named."""
    T = 300
    sc = estim.scenarios.get("sensor_fusion", n_steps=T)
    assert sc.sampling == {"h_gnss": (100, 0), "h_baro": (5, 0)}
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=3)
    k = np.arange(T)
    np.testing.assert_array_equal(np.isnan(log.y),
                                  np.column_stack([k < 0, k % 100 != 0, k % 5 != 0]))
    from estim.batch import simulate_plant

    plant = simulate_plant(sc, [3])
    np.testing.assert_array_equal(plant.y[0], log.y)  # NaN in the same places
    np.testing.assert_allclose(plant.x[0], log.x, rtol=1e-12, atol=1e-12)
    kf = KalmanFilter(dim_x=3, dim_z=1)
    kf.x, kf.P = np.array(sc.tuning["x0"], dtype=float), np.array(sc.tuning["P0"], dtype=float)
    kf.F, kf.Q = expm(A * 0.01), sc.tuning["Q"]
    xs = []
    for j in range(T):
        if j:
            kf.predict()
        for i, name in enumerate(OUTPUTS):
            if not np.isnan(log.y[j, i]):
                kf.update(log.y[j, i], R=sc.R[i:i + 1, i:i + 1], H=np.array([H_ROWS[name]]))
        xs.append(kf.x.copy())
    np.testing.assert_allclose(log.x_hat, np.array(xs), atol=1e-9)
    with pytest.raises(ValueError, match="'h_gps', not an output .* did you mean 'h_gnss'"):
        sc.replace(sampling={"h_gps": 100})
    with pytest.raises(ValueError, match=r"sampling\['h_baro'\] every"):
        sc.replace(sampling={"h_baro": 0})
    with pytest.raises(TypeError, match="sampling must be a dict"):
        estim.simulate(sc.model, None, x0=sc.x0, n_steps=10, Q=sc.Q, R=sc.R, sampling=[5])
