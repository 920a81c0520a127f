# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [raw]
# # ASSIGNMENT CONFIG
# init_cell: true
# check_all_cell: false
# export_cell: false
# files: [book_car_track.npz]

# %% [markdown]
# # Exercise 1: the Kalman filter on a tracking problem
#
# A car moves in the plane at a nearly constant velocity; a sensor measures its position
# every $\Delta t = 0.1$ s with noise of standard deviation $0.5$ (Särkkä & Svensson,
# *Bayesian Filtering and Smoothing*, 2nd ed., 2023, example 4.3). The state is
# $x = (p_x, p_y, v_x, v_y)$ and
#
# $$x_k = A x_{k-1} + q_{k-1},\quad q_{k-1} \sim N(0, Q), \qquad
#   y_k = H x_k + r_k,\quad r_k \sim N(0, R),$$
#
# with $A = \begin{bmatrix} I & \Delta t I \\ 0 & I \end{bmatrix}$, $H = [I\ 0]$,
# $R = 0.25 I$ and the $Q$ of a white acceleration of spectral density $q = 1$.
#
# The Kalman filter (the book's eqs. (6.6)–(6.7)) alternates
#
# * **prediction** (eq. 1) $\bar m_k = A m_{k-1}$, (eq. 2) $\bar P_k = A P_{k-1} A^\top + Q$;
# * **update** (eq. 3) $S_k = H \bar P_k H^\top + R$, $K_k = \bar P_k H^\top S_k^{-1}$,
#   (eq. 4) $m_k = \bar m_k + K_k (y_k - H \bar m_k)$,
#   (eq. 5) $P_k = \bar P_k - K_k S_k K_k^\top$.
#
# You write these with numpy. estim gives the model, the book's record and the reference
# filter the grader compares yours with.

# %%
import numpy as np

import estim
from estim.grading import as_log
from estim.plotting import plot_errors

dt = 0.1
model = estim.models.constant_velocity(dt=dt)
A = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
H = np.eye(2, 4)
Q = np.block([[dt**3 / 3 * np.eye(2), dt**2 / 2 * np.eye(2)],
              [dt**2 / 2 * np.eye(2), dt * np.eye(2)]])
R = 0.25 * np.eye(2)
m0, P0 = np.array([0.0, 0.0, 1.0, -1.0]), np.eye(4)

car = np.load("book_car_track.npz")
Y, X = car["Y"], car["X"]  # (100, 2) measured positions, (100, 4) true states
Y.shape, X.shape

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (2 points).** Write `kf_predict(m, P, A, Q)`, returning the predicted mean and
# covariance $(\bar m, \bar P)$ of eqs. (1)–(2).

# %% [raw]
# # BEGIN SOLUTION

# %%
def kf_predict(m, P, A, Q):
    # BEGIN SOLUTION
    m_pred = A @ m
    P_pred = A @ P @ A.T + Q
    # END SOLUTION
    return m_pred, P_pred

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: kf_predict must return the pair (m_pred, P_pred) of eqs. (1)-(2)
""" # END TEST CONFIG
m_, P_ = kf_predict(m0, P0, A, Q)
assert np.shape(m_) == (4,) and np.shape(P_) == (4, 4), (np.shape(m_), np.shape(P_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the prediction is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

rng_ = np.random.default_rng(7)
M_ = rng_.normal(size=(4, 4))
mm_, PP_ = rng_.normal(size=4), M_ @ M_.T + np.eye(4)
got_ = kf_predict(mm_, PP_, A, Q)
_ = check_arrays(got_[0], A @ mm_, quantity="the predicted mean", equation="eq. (1)")
_ = check_arrays(got_[1], A @ PP_ @ A.T + Q, quantity="the predicted covariance",
                 equation="eq. (2): A P Aᵀ + Q")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (2 points).** Write `kf_update(m, P, y, H, R)`, returning $(m, P)$ after the
# measurement $y$ (eqs. 3–5).

# %% [raw]
# # BEGIN SOLUTION

# %%
def kf_update(m, P, y, H, R):
    # BEGIN SOLUTION
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    m_new = m + K @ (y - H @ m)
    P_new = P - K @ S @ K.T
    # END SOLUTION
    return m_new, P_new

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: kf_update must return the pair (m, P) of eqs. (4)-(5)
""" # END TEST CONFIG
m_, P_ = kf_update(m0, P0, Y[0], H, R)
assert np.shape(m_) == (4,) and np.shape(P_) == (4, 4), (np.shape(m_), np.shape(P_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the update is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

ekf_ = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0)  # estim's update of the prior by Y[0]
ref_ = ekf_.filter(Y[:1])
got_ = kf_update(m0, P0, Y[0], H, R)
_ = check_arrays(got_[0], ref_.x[0], quantity="the updated mean",
                 equation="eq. (4): m + K (y - H m) with K = P Hᵀ S⁻¹")
_ = check_arrays(got_[1], ref_.P[0], quantity="the updated covariance",
                 equation="eq. (5): P - K S Kᵀ (and S = H P Hᵀ + R, eq. 3)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (3 points).** Write `kalman_filter(Y, m0, P0)`: starting from the prior
# $(m_0, P_0)$ one step *before* the first measurement, predict then update at every
# sample. Return the means `(T, 4)` and covariances `(T, 4, 4)` after each update. The
# book reports a position RMSE of **0.4254** for this record.

# %% [raw]
# # BEGIN SOLUTION

# %%
def kalman_filter(Y, m0, P0):
    means, covs = [], []
    m, P = m0, P0
    for y in Y:
        # BEGIN SOLUTION
        m, P = kf_predict(m, P, A, Q)
        m, P = kf_update(m, P, y, H, R)
        # END SOLUTION
        means.append(m)
        covs.append(P)
    return np.array(means), np.array(covs)


means, covs = kalman_filter(Y, m0, P0)
rmse = np.sqrt(np.mean(np.sum((means[:, :2] - X[:, :2]) ** 2, axis=1)))
rmse

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the position RMSE is not the book's 0.42538
""" # END TEST CONFIG
assert abs(rmse - 0.4253824660526518) < 1e-9, rmse

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 2
failure_message: your filter leaves estim's Kalman filter
""" # END TEST CONFIG
from estim.grading import check_filter, from_steps

equations_ = {"x": "the update m + K (y - H m), eq. (4), and the prediction A m, eq. (1)",
              "P": "the prediction A P Aᵀ + Q (eq. 2) and the update P - K S Kᵀ (eq. 5)"}
mine_ = from_steps(model, lambda m, P: kf_predict(m, P, A, Q),
                   lambda m, P, y: kf_update(m, P, y, H, R), m0, P0)
reference_ = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0)
record_ = (np.vstack([[np.nan, np.nan], Y]), None)  # the prior one step before Y[0]
_ = check_filter(mine_, reference_, record_, equations=equations_, loop=(means, covs),
                 loop_name="kalman_filter")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# Your filter's errors and their $\pm 2\sigma$ bands, drawn by estim:

# %%
plot_errors(as_log(means, covs, truth=X, model=model, name="your Kalman filter"));

# %% [raw]
# # BEGIN QUESTION
# name: q4

# %% [markdown]
# **Part 4 (2 points): is the covariance right?** A filter can have the right mean and a
# wrong covariance. Over many simulated records, the normalised estimation error squared
# $\varepsilon_k = (x_k - m_k)^\top P_k^{-1} (x_k - m_k)$ of a consistent filter has mean
# $n_x = 4$. Write `nees(X, means, covs)` returning $\varepsilon_k$ for every sample
# `(T,)`. The grader runs your filter over 20 simulated records and tests the NEES
# against its chi-square law.

# %% [raw]
# # BEGIN SOLUTION

# %%
def nees(X, means, covs):
    # BEGIN SOLUTION
    e = X - means
    return np.einsum("ki,ki->k", e, np.linalg.solve(covs, e[..., None])[..., 0])
    # END SOLUTION


nees(X, means, covs).mean()

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: nees does not match estim.nees
""" # END TEST CONFIG
from estim.grading import as_log, check_arrays

_ = check_arrays(nees(X, means, covs), estim.nees(as_log(means, covs, truth=X)),
                 quantity="the NEES", equation="(x - m)ᵀ P⁻¹ (x - m) at each sample",
                 index="sample")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your filter's covariance does not match its errors
""" # END TEST CONFIG
from estim.grading import check_consistent, from_steps

scenario_ = estim.Scenario("car", model, x0=m0, n_steps=100, Q=Q, R=R,
                           tuning={"Q": Q, "R": R, "x0": m0, "P0": P0})
mine_ = from_steps(model, lambda m, P: kf_predict(m, P, A, Q),
                   lambda m, P, y: kf_update(m, P, y, H, R), m0, P0)
_ = check_consistent(mine_, scenario_, seeds=range(20))

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION
