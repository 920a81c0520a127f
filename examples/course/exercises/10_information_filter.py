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
# files: []

# %% [markdown]
# # Exercise 10: the information filter
#
# The Kalman filter carries a Gaussian $N(m, P)$ by its mean and covariance. The
# **information filter** carries the same Gaussian by its *information matrix* and
# *information vector*
#
# $$Y = P^{-1}, \qquad y = P^{-1} m .$$
#
# It is the same filter, written in other coordinates: a measurement update becomes a
# sum, and a prior of no information ($Y = 0$) can be written down, where $P = \infty$
# cannot.
#
# The model is the target in the plane at a nearly constant velocity of exercise 1
# (`estim.models.constant_velocity(dt=0.1)`): the state is $x = (p_x, p_y, v_x, v_y)$ and
#
# $$x_k = A x_{k-1} + q_{k-1},\quad q_{k-1} \sim N(0, Q), \qquad
#   z_k = H x_k + r_k,\quad r_k \sim N(0, R),$$
#
# with $A = \begin{bmatrix} I & \Delta t I \\ 0 & I \end{bmatrix}$, $H = [I\ 0]$,
# $R = 0.25 I$ and the $Q$ of a white acceleration of spectral density $q = 1$. The
# measurements are called $z_k$ here, so that $y$ is free for the information vector.
#
# The information filter alternates
#
# * **prediction** (eq. 1) $\bar Y_k = \left(A Y_{k-1}^{-1} A^\top + Q\right)^{-1}$,
#   (eq. 2) $\bar y_k = \bar Y_k A Y_{k-1}^{-1} y_{k-1}$;
# * **update** (eq. 3) $Y_k = \bar Y_k + H^\top R^{-1} H$,
#   (eq. 4) $y_k = \bar y_k + H^\top R^{-1} z_k$;
#
# and the moments are recovered by (eq. 5) $P = Y^{-1}$, $m = Y^{-1} y$.
#
# You write these with numpy. estim gives the model, a simulated record and the reference
# filter (its Kalman filter, in covariance form) that the grader compares yours with.

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
y0, Y0 = np.linalg.solve(P0, m0), np.linalg.inv(P0)  # the prior in information form

scenario = estim.Scenario("constant velocity", model, x0=m0, n_steps=100, Q=Q, R=R,
                          tuning={"Q": Q, "R": R, "x0": m0, "P0": P0})
record = estim.simulate(scenario, None, seed=0)  # the plant alone, no estimator
Z, X = record.y, record.x  # (100, 2) measured positions, (100, 4) true states
# what estim's Kalman filter (covariance form) gets on this record, the prior one step
# before the first measurement: the position RMSE your filter must give
kalman = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0).filter(np.vstack([[np.nan, np.nan], Z]))
kalman_rmse = np.sqrt(np.mean(np.sum((kalman.x[1:, :2] - X[:, :2]) ** 2, axis=1)))
kalman_rmse

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (2 points).** Write `info_predict(y, Y, A, Q)`, returning the predicted
# information vector and matrix $(\bar y, \bar Y)$ of eqs. (1)–(2).

# %% [raw]
# # BEGIN SOLUTION

# %%
def info_predict(y, Y, A, Q):
    # BEGIN SOLUTION
    P = np.linalg.inv(Y)
    Y_pred = np.linalg.inv(A @ P @ A.T + Q)
    y_pred = Y_pred @ (A @ (P @ y))
    # END SOLUTION
    return y_pred, Y_pred

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: info_predict must return the pair (y_pred, Y_pred) of eqs. (1)-(2)
""" # END TEST CONFIG
y_, Y_ = info_predict(y0, Y0, A, Q)
assert np.shape(y_) == (4,) and np.shape(Y_) == (4, 4), (np.shape(y_), np.shape(Y_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the prediction in information form is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

rng_ = np.random.default_rng(7)
M_ = rng_.normal(size=(4, 4))
PP_ = M_ @ M_.T + np.eye(4)
mm_ = rng_.normal(size=4)
Ypred_ = np.linalg.inv(A @ PP_ @ A.T + Q)
got_ = info_predict(np.linalg.solve(PP_, mm_), np.linalg.inv(PP_), A, Q)
_ = check_arrays(got_[1], Ypred_, quantity="the predicted information matrix",
                 equation="eq. (1): (A Y⁻¹ Aᵀ + Q)⁻¹", index="row")
_ = check_arrays(got_[0], Ypred_ @ A @ mm_, quantity="the predicted information vector",
                 equation="eq. (2): Ȳ A Y⁻¹ y", index="entry")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (2 points).** Write `info_update(y, Y, z, H, R)`, returning $(y, Y)$ after the
# measurement $z$ (eqs. 3–4).

# %% [raw]
# # BEGIN SOLUTION

# %%
def info_update(y, Y, z, H, R):
    # BEGIN SOLUTION
    HtRinv = np.linalg.solve(R, H).T  # Hᵀ R⁻¹ (R is symmetric)
    Y_new = Y + HtRinv @ H
    y_new = y + HtRinv @ z
    # END SOLUTION
    return y_new, Y_new

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: info_update must return the pair (y, Y) of eqs. (3)-(4)
""" # END TEST CONFIG
y_, Y_ = info_update(y0, Y0, Z[0], H, R)
assert np.shape(y_) == (4,) and np.shape(Y_) == (4, 4), (np.shape(y_), np.shape(Y_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the update in information form is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

ref_ = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0).filter(Z[:1])  # the prior updated by Z[0]
Yref_ = np.linalg.inv(ref_.P[0])
got_ = info_update(y0, Y0, Z[0], H, R)
_ = check_arrays(got_[1], Yref_, quantity="the updated information matrix",
                 equation="eq. (3): Ȳ + Hᵀ R⁻¹ H", index="row")
_ = check_arrays(got_[0], Yref_ @ ref_.x[0], quantity="the updated information vector",
                 equation="eq. (4): ȳ + Hᵀ R⁻¹ z", index="entry")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (2 points).** Write `to_moments(y, Y)`, returning the mean and covariance
# $(m, P)$ of the Gaussian with information vector $y$ and matrix $Y$ (eq. 5).

# %% [raw]
# # BEGIN SOLUTION

# %%
def to_moments(y, Y):
    # BEGIN SOLUTION
    P = np.linalg.inv(Y)
    m = P @ y
    # END SOLUTION
    return m, P

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: to_moments(y0, Y0) must give back the prior (m0, P0)
""" # END TEST CONFIG
m_, P_ = to_moments(y0, Y0)
assert np.allclose(m_, m0) and np.allclose(P_, P0), (m_, P_)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: to_moments is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

rng_ = np.random.default_rng(11)
M_ = rng_.normal(size=(4, 4))
PP_ = M_ @ M_.T + np.eye(4)
mm_ = rng_.normal(size=4)
got_ = to_moments(np.linalg.solve(PP_, mm_), np.linalg.inv(PP_))
_ = check_arrays(got_[1], PP_, quantity="the covariance", equation="eq. (5): P = Y⁻¹",
                 index="row")
_ = check_arrays(got_[0], mm_, quantity="the mean", equation="eq. (5): m = Y⁻¹ y",
                 index="entry")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q4

# %% [markdown]
# **Part 4 (3 points).** Write `information_filter(Z, y0, Y0)`: starting from the prior
# $(y_0, Y_0)$ one step *before* the first measurement, predict then update at every
# sample, in information form. Return the means `(T, 4)` and covariances `(T, 4, 4)`
# after each update (`to_moments` does the conversion). The position RMSE must be the
# Kalman filter's, `kalman_rmse` above.

# %% [raw]
# # BEGIN SOLUTION

# %%
def information_filter(Z, y0, Y0):
    means, covs = [], []
    y, Y = y0, Y0
    for z in Z:
        # BEGIN SOLUTION
        y, Y = info_predict(y, Y, A, Q)
        y, Y = info_update(y, Y, z, H, R)
        # END SOLUTION
        m, P = to_moments(y, Y)
        means.append(m)
        covs.append(P)
    return np.array(means), np.array(covs)


means, covs = information_filter(Z, y0, Y0)
rmse = np.sqrt(np.mean(np.sum((means[:, :2] - X[:, :2]) ** 2, axis=1)))
rmse

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the position RMSE is not the Kalman filter's (kalman_rmse)
""" # END TEST CONFIG
assert abs(rmse - kalman_rmse) < 1e-9, (rmse, kalman_rmse)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 2
failure_message: your information filter leaves estim's Kalman filter
""" # END TEST CONFIG
from estim.grading import check_filter, from_steps


def predict_(m, P):  # estim's loop carries (m, P): convert, predict, convert back
    Yinf_ = np.linalg.inv(P)
    yinf_, Yinf_ = info_predict(Yinf_ @ m, Yinf_, A, Q)
    Pn_ = np.linalg.inv(Yinf_)
    return Pn_ @ yinf_, Pn_


def update_(m, P, z):
    Yinf_ = np.linalg.inv(P)
    yinf_, Yinf_ = info_update(Yinf_ @ m, Yinf_, z, H, R)
    Pn_ = np.linalg.inv(Yinf_)
    return Pn_ @ yinf_, Pn_


equations_ = {"x": "the information vector: ȳ = Ȳ A Y⁻¹ y (eq. 2) and y = ȳ + Hᵀ R⁻¹ z "
                   "(eq. 4)",
              "P": "the information matrix: Ȳ = (A Y⁻¹ Aᵀ + Q)⁻¹ (eq. 1) and "
                   "Y = Ȳ + Hᵀ R⁻¹ H (eq. 3)"}
mine_ = from_steps(model, predict_, update_, m0, P0, name="your information filter")
reference_ = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0)
record_ = (np.vstack([[np.nan, np.nan], Z]), None)  # the prior one step before Z[0]
_ = check_filter(mine_, reference_, record_, equations=equations_,
                 name="your information filter", loop=(means, covs),
                 loop_name="information_filter",
                 loop_equation="the loop: predict, update, then to_moments, at every sample")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# Your filter's errors and their $\pm 2\sigma$ bands, drawn by estim:

# %%
plot_errors(as_log(means, covs, truth=X, model=model, name="your information filter"));
