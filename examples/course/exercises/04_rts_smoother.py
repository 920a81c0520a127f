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
# # Exercise 4: the Rauch–Tung–Striebel smoother
#
# The car of exercise 1 again: it moves in the plane at a nearly constant velocity and a
# sensor measures its position every $\Delta t = 0.1$ s with noise of standard deviation
# $0.5$ (Särkkä & Svensson, *Bayesian Filtering and Smoothing*, 2nd ed., 2023, example
# 4.3). The state is $x = (p_x, p_y, v_x, v_y)$,
#
# $$x_k = A x_{k-1} + q_{k-1},\quad q_{k-1} \sim N(0, Q), \qquad
#   y_k = H x_k + r_k,\quad r_k \sim N(0, R).$$
#
# The Kalman filter gives $p(x_k \mid y_{1:k}) = N(m_k, P_k)$: the estimate of the state
# from the measurements *up to* sample $k$. Once the whole record $y_{1:T}$ is in, every
# state can be estimated from all of it, the later measurements included:
# $p(x_k \mid y_{1:T}) = N(m^s_k, P^s_k)$. The Rauch–Tung–Striebel smoother (the book's
# chapter 12) computes these by one pass *backwards* over the filter's results, starting
# from the last sample, where the two agree ($m^s_T = m_T$, $P^s_T = P_T$). For
# $k = T-1, \dots, 1$:
#
# * (eq. 1) the prediction from sample $k$: $\bar m_{k+1} = A m_k$,
#   $\bar P_{k+1} = A P_k A^\top + Q$;
# * (eq. 2) the smoother gain $G_k = P_k A^\top \bar P_{k+1}^{-1}$;
# * (eq. 3) the mean $m^s_k = m_k + G_k (m^s_{k+1} - \bar m_{k+1})$;
# * (eq. 4) the covariance $P^s_k = P_k + G_k (P^s_{k+1} - \bar P_{k+1}) G_k^\top$.
#
# You write these with numpy. estim gives the model, the book's record and the reference
# smoother the grader compares yours with.

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

# %% [markdown]
# The Kalman filter of exercise 1, written out: the prior $(m_0, P_0)$ one step *before*
# the first measurement, then predict and update at every sample. It returns the
# filtered means `(T, 4)` and covariances `(T, 4, 4)`; the book reports a position RMSE
# of **0.4254** for them.

# %%
def kalman_filter(Y, m0, P0):
    means, covs = [], []
    m, P = m0, P0
    for y in Y:
        m, P = A @ m, A @ P @ A.T + Q  # predict
        S = H @ P @ H.T + R  # update
        K = np.linalg.solve(S, H @ P).T
        m, P = m + K @ (y - H @ m), P - K @ S @ K.T
        means.append(m)
        covs.append(P)
    return np.array(means), np.array(covs)


def position_rmse(means, X):
    return np.sqrt(np.mean(np.sum((means[:, :2] - X[:, :2]) ** 2, axis=1)))


means, covs = kalman_filter(Y, m0, P0)
position_rmse(means, X)

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (2 points).** Write `smoother_gain(P, A, Q)`: from a filtered covariance
# $P_k$, the smoother gain $G_k$ `(4, 4)` of eq. (2), with $\bar P_{k+1}$ of eq. (1).
# (Solve a linear system rather than inverting $\bar P_{k+1}$: $G_k^\top$ solves
# $\bar P_{k+1} G_k^\top = A P_k$, as $P_k$ and $\bar P_{k+1}$ are symmetric.)

# %% [raw]
# # BEGIN SOLUTION

# %%
def smoother_gain(P, A, Q):
    # BEGIN SOLUTION
    P_pred = A @ P @ A.T + Q
    G = np.linalg.solve(P_pred, A @ P).T
    # END SOLUTION
    return G

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: smoother_gain must return the 4 x 4 gain G of eq. (2)
""" # END TEST CONFIG
G_ = smoother_gain(covs[0], A, Q)
assert np.shape(G_) == (4, 4), np.shape(G_)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the smoother gain is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

ref_ = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0).smooth(np.vstack([[np.nan, np.nan], Y]))
got_ = np.array([smoother_gain(P_, A, Q) for P_ in covs[:-1]])
_ = check_arrays(got_, ref_.gain[1:], quantity="the smoother gain G",
                 equation="eq. (2): G = P Aᵀ P̄⁻¹, with P̄ = A P Aᵀ + Q (eq. 1)",
                 index="sample")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (2 points).** Write `rts_step(m, P, m_s_next, P_s_next, A, Q)`: one step of the
# backward pass. From the filtered $(m_k, P_k)$ and the smoothed
# $(m^s_{k+1}, P^s_{k+1})$ of the next sample, return the smoothed $(m^s_k, P^s_k)$ of
# eqs. (3)–(4). Use your `smoother_gain`.

# %% [raw]
# # BEGIN SOLUTION

# %%
def rts_step(m, P, m_s_next, P_s_next, A, Q):
    # BEGIN SOLUTION
    m_pred, P_pred = A @ m, A @ P @ A.T + Q
    G = smoother_gain(P, A, Q)
    m_s = m + G @ (m_s_next - m_pred)
    P_s = P + G @ (P_s_next - P_pred) @ G.T
    # END SOLUTION
    return m_s, P_s

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: rts_step must return the pair (m_s, P_s) of eqs. (3)-(4)
""" # END TEST CONFIG
m_, P_ = rts_step(means[-2], covs[-2], means[-1], covs[-1], A, Q)
assert np.shape(m_) == (4,) and np.shape(P_) == (4, 4), (np.shape(m_), np.shape(P_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the backward step is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

ref_ = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0).smooth(np.vstack([[np.nan, np.nan], Y]))
# every step k from the filter's (m_k, P_k) and estim's smoothed sample k + 1
steps_ = [rts_step(means[k], covs[k], ref_.x[k + 2], ref_.P[k + 2], A, Q)
          for k in range(len(Y) - 1)]
_ = check_arrays(np.array([s_[0] for s_ in steps_]), ref_.x[1:-1],
                 quantity="the smoothed mean m_s",
                 equation="eq. (3): m + G (m_s_next - A m)", index="sample")
_ = check_arrays(np.array([s_[1] for s_ in steps_]), ref_.P[1:-1],
                 quantity="the smoothed covariance P_s",
                 equation="eq. (4): P + G (P_s_next - P̄) Gᵀ, with P̄ = A P Aᵀ + Q",
                 index="sample")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (3 points).** Write `rts_smoother(means, covs, A, Q)`: the whole backward pass
# over the filter's results, from the last sample to the first. Return the smoothed
# means `(T, 4)` and covariances `(T, 4, 4)`. The book reports a position RMSE of
# **0.2650** for the smoother on this record (against 0.4254 for the filter).
#
# The grader also runs your smoother after the filter on 20 records simulated from the
# model (the first state drawn from the prior) and tests whether its covariances match
# its errors: the normalised estimation error squared
# $(x_k - m^s_k)^\top (P^s_k)^{-1} (x_k - m^s_k)$ must follow its chi-square law with 4
# degrees of freedom (`estim.testing.assert_consistent` at level 0.99: a correct smoother
# fails it for at most 1 % of sets of records; on the grader's records it passes).

# %% [raw]
# # BEGIN SOLUTION

# %%
def rts_smoother(means, covs, A, Q):
    # BEGIN SOLUTION
    m_s, P_s = np.array(means, dtype=float), np.array(covs, dtype=float)
    for k in range(len(means) - 2, -1, -1):
        m_s[k], P_s[k] = rts_step(means[k], covs[k], m_s[k + 1], P_s[k + 1], A, Q)
    # END SOLUTION
    return m_s, P_s


smoothed, smoothed_covs = rts_smoother(means, covs, A, Q)
rmse = position_rmse(smoothed, X)
rmse

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the position RMSE is not the book's 0.26497
""" # END TEST CONFIG
assert abs(rmse - 0.26497104638205465) < 1e-9, rmse

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your smoother leaves estim's Rauch-Tung-Striebel smoother
""" # END TEST CONFIG
from estim.grading import check_arrays

ref_ = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0).smooth(np.vstack([[np.nan, np.nan], Y]))
got_ = rts_smoother(means, covs, A, Q)
_ = check_arrays(got_[0], ref_.x[1:], quantity="rts_smoother's mean",
                 equation="the mean recursion m + G (m_s_next - A m), eq. (3), run "
                          "backwards from m_s = m at the last sample", index="sample")
_ = check_arrays(got_[1], ref_.P[1:], quantity="rts_smoother's covariance",
                 equation="the covariance recursion P + G (P_s_next - P̄) Gᵀ, eq. (4), "
                          "with the gain G = P Aᵀ P̄⁻¹ (eq. 2)", index="sample")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your smoother's covariances do not match its errors (eq. 4)
""" # END TEST CONFIG
from estim.grading import as_log as as_log_
from estim.testing import assert_consistent

rng_ = np.random.default_rng(0)
LQ_, LP_ = np.linalg.cholesky(Q), np.linalg.cholesky(P0)
logs_ = []
for _record in range(20):  # 20 records of 100 samples, the state before the first drawn
    x_, X_, Y_ = m0 + LP_ @ rng_.standard_normal(4), [], []
    for _sample in range(100):
        x_ = A @ x_ + LQ_ @ rng_.standard_normal(4)
        X_.append(x_)
        Y_.append(H @ x_ + 0.5 * rng_.standard_normal(2))
    mf_, Pf_ = kalman_filter(np.array(Y_), m0, P0)
    ms_, Ps_ = rts_smoother(mf_, Pf_, A, Q)
    logs_.append(as_log_(ms_, Ps_, truth=np.array(X_), model=model, name="your smoother"))
    ratio_ = np.trace(Ps_, axis1=1, axis2=2).sum() / np.trace(Pf_, axis1=1, axis2=2).sum()
    assert ratio_ < 0.9, (f"the smoothed covariances are not smaller than the filter's "
                          f"(the sum of their traces is {ratio_:.3g} times the filter's): "
                          f"does the backward pass change P (eq. 4)?")
_ = assert_consistent(logs_, level=0.99, burn_in=0)

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# The filter's and the smoother's errors with their $\pm 2\sigma$ bands, drawn by estim:
# the smoother's errors are smaller, and its bands are about half as wide as the filter's
# in the middle of the record. At the last sample the two agree: no later measurement is
# there to use.

# %%
plot_errors({"Kalman filter": as_log(means, covs, truth=X, model=model),
             "RTS smoother": as_log(smoothed, smoothed_covs, truth=X, model=model)});
