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
# files: [book_pendulum.npz]

# %% [markdown]
# # Exercise 2: the extended Kalman filter on a pendulum
#
# A frictionless pendulum swings with angle $\theta$ and angular rate $\omega$; a sensor
# measures only the sine of the angle, with noise of variance $R = 0.1$, every
# $\Delta t = 0.01$ s (Särkkä & Svensson, *Bayesian Filtering and Smoothing*, 2nd ed.,
# 2023, example 5.1 and its companion notebook `pendulum_ekf`). With Euler steps and
# $g = 9.81$, the state $x = (\theta, \omega)$ follows
#
# $$x_k = f(x_{k-1}) + q_{k-1},\quad q_{k-1} \sim N(0, Q), \qquad
#   y_k = h(x_k) + r_k,\quad r_k \sim N(0, R),$$
#
# (eq. 1) $f(x) = \begin{bmatrix} \theta + \omega\,\Delta t \\
#   \omega - g \sin(\theta)\,\Delta t \end{bmatrix}$, (eq. 2) $h(x) = \sin\theta$,
#
# with $Q = 0.01 \begin{bmatrix} \Delta t^3/3 & \Delta t^2/2 \\ \Delta t^2/2 & \Delta t
# \end{bmatrix}$ and the prior $m_0 = (0, 0)$, $P_0 = I$ one step before the first
# measurement.
#
# The extended Kalman filter (the book's chapter 7) linearises $f$ and $h$ about the
# current estimate with their Jacobians (eq. 3) $F_x(x) = \partial f / \partial x$ and
# $H_x(x) = \partial h / \partial x$, and alternates
#
# * **prediction** (eq. 4) $\bar m_k = f(m_{k-1})$,
#   $\bar P_k = F_x(m_{k-1})\, P_{k-1}\, F_x(m_{k-1})^\top + Q$;
# * **update**, with $H = H_x(\bar m_k)$: (eq. 5) $S_k = H \bar P_k H^\top + R$,
#   $K_k = \bar P_k H^\top S_k^{-1}$,
#   (eq. 6) $m_k = \bar m_k + K_k \bigl(y_k - h(\bar m_k)\bigr)$,
#   (eq. 7) $P_k = \bar P_k - K_k S_k K_k^\top$.
#
# You write these with numpy. estim gives the model, the book's record and the reference
# filter the grader compares yours with.

# %%
import numpy as np

import estim
from estim.grading import as_log
from estim.plotting import plot_errors, plot_estimates

dt, g = 0.01, 9.81
model = estim.models.sine_pendulum(g=g, dt=dt, integrator="euler")  # eqs. (1)-(2)
Q = 0.01 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
R = np.array([[0.1]])
m0, P0 = np.zeros(2), np.eye(2)


def f(x):
    """The transition of eq. (1)."""
    return np.array([x[0] + x[1] * dt, x[1] - g * np.sin(x[0]) * dt])


def h(x):
    """The measurement function of eq. (2), as a vector of one entry."""
    return np.array([np.sin(x[0])])


pendulum = np.load("book_pendulum.npz")
T, X = pendulum["T"], pendulum["X"]  # (500,) sample times, (500, 2) true states
Y = pendulum["Y"][:, None]           # (500, 1) measurements of sin(theta)
Y.shape, X.shape

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (2 points).** Write `jacobian_f(x)`, the $2 \times 2$ matrix $F_x(x)$, and
# `jacobian_h(x)`, the $1 \times 2$ matrix $H_x(x)$ of eq. (3), by differentiating
# eqs. (1) and (2) by hand.

# %% [raw]
# # BEGIN SOLUTION

# %%
def jacobian_f(x):
    # BEGIN SOLUTION
    F = np.array([[1.0, dt], [-g * np.cos(x[0]) * dt, 1.0]])
    # END SOLUTION
    return F


def jacobian_h(x):
    # BEGIN SOLUTION
    H = np.array([[np.cos(x[0]), 0.0]])
    # END SOLUTION
    return H

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: at x = 0, F_x must be [[1, dt], [-g dt, 1]] (2 x 2) and H_x [[1, 0]] (1 x 2)
""" # END TEST CONFIG
F_, H_ = jacobian_f(np.zeros(2)), jacobian_h(np.zeros(2))
assert np.shape(F_) == (2, 2) and np.shape(H_) == (1, 2), (np.shape(F_), np.shape(H_))
assert np.allclose(F_, [[1.0, dt], [-g * dt, 1.0]]) and np.allclose(H_, [[1.0, 0.0]]), (F_, H_)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your Jacobians are not those of the model away from x = 0
""" # END TEST CONFIG
from estim.grading import check_arrays

points_ = np.random.default_rng(2).uniform([-3.0, -4.0], [3.0, 4.0], size=(8, 2))
refs_ = [model.jacobians(x_) for x_ in points_]  # estim's (CasADi) dF/dx and dh/dx
_ = check_arrays([jacobian_f(x_) for x_ in points_], [r_[0] for r_ in refs_],
                 quantity="F_x at 8 points (theta, omega)", index="point",
                 equation="eq. (3): the derivatives of eq. (1) by theta and by omega")
_ = check_arrays([jacobian_h(x_) for x_ in points_], [r_[1] for r_ in refs_],
                 quantity="H_x at 8 points (theta, omega)", index="point",
                 equation="eq. (3): the derivatives of h = sin(theta), eq. (2)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (2 points).** Write `ekf_predict(m, P)`, returning the predicted mean and
# covariance $(\bar m, \bar P)$ of eq. (4). Use `f`, your `jacobian_f` and `Q`.

# %% [raw]
# # BEGIN SOLUTION

# %%
def ekf_predict(m, P):
    # BEGIN SOLUTION
    F = jacobian_f(m)
    m_pred = f(m)
    P_pred = F @ P @ F.T + Q
    # END SOLUTION
    return m_pred, P_pred

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: ekf_predict must return the pair (m_pred, P_pred) of eq. (4), shapes (2,), (2, 2)
""" # END TEST CONFIG
m_, P_ = ekf_predict(m0, P0)
assert np.shape(m_) == (2,) and np.shape(P_) == (2, 2), (np.shape(m_), np.shape(P_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the prediction is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

rng_ = np.random.default_rng(5)
M_ = rng_.normal(size=(2, 2))
mm_, PP_ = np.array([1.2, -0.7]), M_ @ M_.T + 0.1 * np.eye(2)
# estim's EKF from the prior (mm_, PP_), two samples with no measurement: its estimate at
# the second is the prediction alone
ref_ = estim.EKF(model, Q=Q, R=R, x0=mm_, P0=PP_).filter(np.full((2, 1), np.nan))
got_ = ekf_predict(mm_, PP_)
_ = check_arrays(got_[0], ref_.x[1], quantity="the predicted mean", index="entry",
                 equation="eq. (4): f(m), eq. (1)")
_ = check_arrays(got_[1], ref_.P[1], quantity="the predicted covariance", index="row",
                 equation="eq. (4): F_x(m) P F_x(m)ᵀ + Q (F_x at the previous mean m)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (2 points).** Write `ekf_update(m, P, y)`, returning $(m, P)$ after the
# measurement `y` (an array of one entry) by eqs. (5)–(7). Use `h`, your `jacobian_h`
# and `R`.

# %% [raw]
# # BEGIN SOLUTION

# %%
def ekf_update(m, P, y):
    # BEGIN SOLUTION
    H = jacobian_h(m)
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    m_new = m + K @ (y - h(m))
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
failure_message: ekf_update must return the pair (m, P) of eqs. (6)-(7), of shapes (2,) and (2, 2)
""" # END TEST CONFIG
m_, P_ = ekf_update(m0, P0, Y[0])
assert np.shape(m_) == (2,) and np.shape(P_) == (2, 2), (np.shape(m_), np.shape(P_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the update is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

rng_ = np.random.default_rng(6)
M_ = rng_.normal(size=(2, 2))
mm_, PP_, yy_ = np.array([0.9, 0.4]), M_ @ M_.T + 0.1 * np.eye(2), np.array([0.35])
ref_ = estim.EKF(model, Q=Q, R=R, x0=mm_, P0=PP_).filter(yy_[None])  # the prior updated by yy_
got_ = ekf_update(mm_, PP_, yy_)
_ = check_arrays(got_[0], ref_.x[0], quantity="the updated mean", index="entry",
                 equation="eq. (6): m + K (y - h(m)), with K = P Hᵀ S⁻¹ of eq. (5)")
_ = check_arrays(got_[1], ref_.P[0], quantity="the updated covariance", index="row",
                 equation="eq. (7): P - K S Kᵀ, with S = H P Hᵀ + R and H = H_x(m), eq. (5)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q4

# %% [markdown]
# **Part 4 (3 points).** Write `ekf(Y, m0, P0)`: starting from the prior $(m_0, P_0)$ one
# step *before* the first measurement, predict then update at every sample. Return the
# means `(T, 2)` and covariances `(T, 2, 2)` after each update. The book reports an angle
# RMSE of **0.1683** for this record.

# %% [raw]
# # BEGIN SOLUTION

# %%
def ekf(Y, m0, P0):
    means, covs = [], []
    m, P = m0, P0
    for y in Y:
        # BEGIN SOLUTION
        m, P = ekf_predict(m, P)
        m, P = ekf_update(m, P, y)
        # END SOLUTION
        means.append(m)
        covs.append(P)
    return np.array(means), np.array(covs)


means, covs = ekf(Y, m0, P0)
rmse = np.sqrt(np.mean((means[:, 0] - X[:, 0]) ** 2))
rmse

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the angle RMSE is not the book's 0.168309
""" # END TEST CONFIG
assert abs(rmse - 0.16830859061153763) < 1e-9, rmse

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 2
failure_message: your filter leaves estim's extended Kalman filter
""" # END TEST CONFIG
from estim.grading import check_filter, from_steps

equations_ = {"x": "the update m + K (y - h(m)), eq. (6), and the prediction f(m), eq. (4)",
              "P": "the prediction F_x P F_xᵀ + Q (eq. 4), the gain (eq. 5) and the update "
                   "P - K S Kᵀ (eq. 7)"}
mine_ = from_steps(model, ekf_predict, ekf_update, m0, P0)
reference_ = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0)
record_ = (np.vstack([[np.nan], Y]), None)  # the prior one step before Y[0]
_ = check_filter(mine_, reference_, record_, equations=equations_, loop=(means, covs),
                 loop_name="ekf")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# The true angle and rate and your estimates, then your filter's errors with their
# $\pm 2\sigma$ bands, drawn by estim. At its turning points the pendulum comes close to
# $|\theta| = \pi/2$, where the slope of $\sin\theta$ vanishes: the linearised
# measurement then says little, the errors grow, and they leave the bands the filter
# believes in (the linearisation's covariance is too small).

# %%
log = as_log(means, covs, truth=X, t=T, model=model, name="your EKF")
plot_estimates(log);
plot_errors(log);
