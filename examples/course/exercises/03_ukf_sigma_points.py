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
# # Exercise 3: sigma points and the unscented Kalman filter
#
# The pendulum of exercise 2 (Särkkä & Svensson, *Bayesian Filtering and Smoothing*,
# 2nd ed., 2023, example 5.1): $x = (\theta, \omega)$, Euler steps of
# $\Delta t = 0.01$ s, $f(x) = (\theta + \omega \Delta t,\ \omega - g \sin(\theta) \Delta t)$,
# $h(x) = \sin\theta$, $R = 0.1$, $Q = 0.01 \begin{bmatrix} \Delta t^3/3 & \Delta t^2/2 \\
# \Delta t^2/2 & \Delta t \end{bmatrix}$, the prior $m_0 = (0, 0)$, $P_0 = I$ one step
# before the first measurement, and the same record.
#
# Instead of linearising $f$ and $h$, the unscented Kalman filter (the book's chapter 8)
# pushes a few deterministic **sigma points** through them. For a state of dimension $n$
# and the parameters $\alpha, \beta, \kappa$ (the book's choice here: $\alpha = 1$,
# $\beta = 0$, $\kappa = 3 - n$):
#
# * (eq. 1) $\lambda = \alpha^2 (n + \kappa) - n$;
# * (eq. 2) the weights $W^{(m)}_0 = \dfrac{\lambda}{n + \lambda}$,
#   $W^{(c)}_0 = \dfrac{\lambda}{n + \lambda} + (1 - \alpha^2 + \beta)$,
#   $W^{(m)}_i = W^{(c)}_i = \dfrac{1}{2 (n + \lambda)}$ for $i = 1, \dots, 2n$;
# * (eq. 3) the $2n + 1$ sigma points of a mean $m$ and covariance $P = L L^\top$
#   ($L$ the lower Cholesky factor, `np.linalg.cholesky(P)`, $L_i$ its $i$-th column):
#   $\mathcal X_0 = m$, $\mathcal X_i = m + \sqrt{n + \lambda}\, L_i$,
#   $\mathcal X_{n+i} = m - \sqrt{n + \lambda}\, L_i$, $i = 1, \dots, n$.
#
# The **unscented transform** of a function $g$ at $(m, P)$: with
# $\mathcal Z_i = g(\mathcal X_i)$,
#
# (eq. 4) $\mu = \sum_i W^{(m)}_i \mathcal Z_i$,
# $S = \sum_i W^{(c)}_i (\mathcal Z_i - \mu)(\mathcal Z_i - \mu)^\top$,
# $C = \sum_i W^{(c)}_i (\mathcal X_i - m)(\mathcal Z_i - \mu)^\top$.
#
# The filter alternates
#
# * **prediction** (eq. 5): $(\bar m_k, S_f, \cdot)$ the transform of $f$ at
#   $(m_{k-1}, P_{k-1})$, $\bar P_k = S_f + Q$;
# * **update** (eq. 6): $(\mu_k, S_h, C_k)$ the transform of $h$ at $(\bar m_k, \bar P_k)$
#   (new sigma points), $S_k = S_h + R$, $K_k = C_k S_k^{-1}$;
#   (eq. 7) $m_k = \bar m_k + K_k (y_k - \mu_k)$, $P_k = \bar P_k - K_k S_k K_k^\top$.
#
# You write these with numpy. estim gives the model, the book's record and the reference
# filter the grader compares yours with.

# %%
import numpy as np

import estim
from estim.grading import as_log
from estim.plotting import plot_errors

dt, g = 0.01, 9.81
model = estim.models.sine_pendulum(g=g, dt=dt, integrator="euler")
Q = 0.01 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
R = np.array([[0.1]])
m0, P0 = np.zeros(2), np.eye(2)
n = 2
ALPHA, BETA, KAPPA = 1.0, 0.0, 3.0 - n  # the book's unscented transform


def f(x):
    """The pendulum's transition (Euler step)."""
    return np.array([x[0] + x[1] * dt, x[1] - g * np.sin(x[0]) * dt])


def h(x):
    """The measurement function, as a vector of one entry."""
    return np.array([np.sin(x[0])])


pendulum = np.load("book_pendulum.npz")
T, X = pendulum["T"], pendulum["X"]  # (500,) sample times, (500, 2) true states
Y = pendulum["Y"][:, None]           # (500, 1) measurements of sin(theta)
Y.shape, X.shape

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (3 points).** Write `ut_weights(n, alpha, beta, kappa)`, returning the mean and
# covariance weights $(W^{(m)}, W^{(c)})$ of eq. (2), two arrays `(2n + 1,)`, and
# `sigma_points(m, P, alpha, kappa)`, returning the sigma points of eq. (3), one a row:
# an array `(2n + 1, n)` in the order $\mathcal X_0, \mathcal X_1, \dots, \mathcal X_{2n}$.
# Write them for any $n$ and any $\alpha, \beta, \kappa$ (the grader tries others than
# the book's).

# %% [raw]
# # BEGIN SOLUTION

# %%
def ut_weights(n, alpha, beta, kappa):
    # BEGIN SOLUTION
    lam = alpha**2 * (n + kappa) - n
    Wm = np.full(2 * n + 1, 1.0 / (2 * (n + lam)))
    Wc = Wm.copy()
    Wm[0] = lam / (n + lam)
    Wc[0] = lam / (n + lam) + (1 - alpha**2 + beta)
    # END SOLUTION
    return Wm, Wc


def sigma_points(m, P, alpha, kappa):
    # BEGIN SOLUTION
    n = len(m)
    lam = alpha**2 * (n + kappa) - n
    D = np.sqrt(n + lam) * np.linalg.cholesky(P).T  # row i: sqrt(n + lam) L_i
    points = np.vstack([m, m + D, m - D])
    # END SOLUTION
    return points


ut_weights(n, ALPHA, BETA, KAPPA)

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the book's weights (n = 2, alpha = 1, beta = 0, kappa = 1) are both
  (1/3, 1/6, 1/6, 1/6, 1/6); sigma_points gives 5 rows of 2 entries, the first the mean
""" # END TEST CONFIG
Wm_, Wc_ = ut_weights(2, 1.0, 0.0, 1.0)
assert np.allclose(Wm_, [1 / 3, 1 / 6, 1 / 6, 1 / 6, 1 / 6]), Wm_
assert np.allclose(Wc_, [1 / 3, 1 / 6, 1 / 6, 1 / 6, 1 / 6]), Wc_
pts_ = sigma_points(np.array([0.5, -1.0]), np.diag([0.2, 0.3]), 1.0, 1.0)
assert np.shape(pts_) == (5, 2), np.shape(pts_)
assert np.allclose(pts_[0], [0.5, -1.0]), pts_[0]

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your sigma points or weights are not the unscented transform's (eqs. 1-3)
""" # END TEST CONFIG
from estim.estimators.kalman.ukf import sigma_weights as estims_weights_
from estim.grading import check_arrays

rng_ = np.random.default_rng(11)
for n_, (a_, b_, k_) in [(2, (1.0, 0.0, 1.0)), (2, (0.5, 2.0, 0.0)), (3, (0.8, 2.0, 1.0))]:
    M_ = rng_.normal(size=(n_, n_))
    mm_, PP_ = rng_.normal(size=n_), M_ @ M_.T + 0.1 * np.eye(n_)
    case_ = f"(n = {n_}, alpha = {a_}, beta = {b_}, kappa = {k_})"
    c_, Wm_, Wc_ = estims_weights_("merwe", n_, a_, b_, k_)  # c = n + lambda
    Wm_got_, Wc_got_ = ut_weights(n_, a_, b_, k_)
    _ = check_arrays(Wm_got_, Wm_, quantity=f"the vector of mean weights W(m) {case_}",
                     index="point",
                     equation="eq. (2): W(m)_0 = lambda / (n + lambda), the others "
                              "1 / (2 (n + lambda)), with lambda of eq. (1)")
    _ = check_arrays(Wc_got_, Wc_, quantity=f"the vector of covariance weights W(c) {case_}",
                     index="point", equation="eq. (2): W(c)_0 = lambda / (n + lambda) + "
                     "(1 - alpha² + beta), the others 1 / (2 (n + lambda))")
    model_ = estim.Model(states=[f"s{i}" for i in range(n_)], outputs=["y"], dt=1.0,
                         ode=lambda x, u, p: -x, output=lambda x, u, p: x[0],
                         integrator="euler", name="points")
    ukf_ = estim.UKF(model_, Q=np.eye(n_), R=1.0, x0=np.zeros(n_), P0=np.eye(n_),
                     alpha=a_, beta=b_, kappa=k_)
    _ = check_arrays(sigma_points(mm_, PP_, a_, k_), ukf_.sigma_points(mm_, PP_),
                     quantity=f"the array of sigma points {case_}", index="point",
                     equation="eq. (3): m, then m + sqrt(n + lambda) L_i, then "
                              "m - sqrt(n + lambda) L_i, L_i the columns of the lower "
                              "Cholesky factor of P")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your sigma points and weights do not give back the mean and covariance
  they were drawn from
""" # END TEST CONFIG
from estim.grading import check_arrays

rng_ = np.random.default_rng(12)
for n_, (a_, b_, k_) in [(2, (1.0, 0.0, 1.0)), (3, (0.5, 2.0, 0.0)), (4, (1.0, 0.0, -1.0))]:
    M_ = rng_.normal(size=(n_, n_))
    mm_, PP_ = rng_.normal(size=n_), M_ @ M_.T + 0.1 * np.eye(n_)
    case_ = f"(n = {n_}, alpha = {a_}, beta = {b_}, kappa = {k_})"
    Wm_got_, Wc_got_ = ut_weights(n_, a_, b_, k_)
    pts_ = np.asarray(sigma_points(mm_, PP_, a_, k_))
    _ = check_arrays(np.asarray(Wm_got_) @ pts_, mm_, index="entry",
                     quantity=f"the weighted mean of the sigma points {case_}",
                     equation="eqs. (2)-(3): sum_i W(m)_i X_i must be m")
    d_ = pts_ - mm_
    _ = check_arrays(np.einsum("i,ia,ib->ab", Wc_got_, d_, d_), PP_, index="row",
                     quantity=f"the weighted covariance of the sigma points {case_}",
                     equation="eqs. (2)-(3): sum_i W(c)_i (X_i - m)(X_i - m)ᵀ must be P")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (2 points).** Write `unscented_transform(func, m, P, alpha, beta, kappa)`,
# returning $(\mu, S, C)$ of eq. (4) for a function `func` of a vector `(n,)` returning
# a vector `(d,)`: $\mu$ `(d,)`, $S$ `(d, d)`, $C$ `(n, d)`. For a linear function
# $g(x) = A x + b$ the transform is exact: $\mu = A m + b$, $S = A P A^\top$,
# $C = P A^\top$.

# %% [raw]
# # BEGIN SOLUTION

# %%
def unscented_transform(func, m, P, alpha, beta, kappa):
    # BEGIN SOLUTION
    Wm, Wc = ut_weights(len(m), alpha, beta, kappa)
    Xs = sigma_points(m, P, alpha, kappa)
    Zs = np.array([func(x) for x in Xs])
    mu = Wm @ Zs
    dZ, dX = Zs - mu, Xs - m
    S = np.einsum("i,ia,ib->ab", Wc, dZ, dZ)
    C = np.einsum("i,ia,ib->ab", Wc, dX, dZ)
    # END SOLUTION
    return mu, S, C


unscented_transform(h, np.array([1.0, 0.0]), 0.1 * np.eye(2), ALPHA, BETA, KAPPA)

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the transform of a linear g(x) = A x + b must be exact, mu = A m + b,
  S = A P Aᵀ, C = P Aᵀ (eq. 4)
""" # END TEST CONFIG
A_, b_ = np.array([[1.0, 2.0], [0.5, -1.0], [0.0, 3.0]]), np.array([1.0, -2.0, 0.5])
mm_, PP_ = np.array([0.3, -0.4]), np.array([[0.5, 0.2], [0.2, 0.4]])
mu_, S_, C_ = unscented_transform(lambda x: A_ @ x + b_, mm_, PP_, ALPHA, BETA, KAPPA)
assert np.shape(mu_) == (3,) and np.shape(S_) == (3, 3) and np.shape(C_) == (2, 3), \
    (np.shape(mu_), np.shape(S_), np.shape(C_))
assert np.allclose(mu_, A_ @ mm_ + b_), mu_
assert np.allclose(S_, A_ @ PP_ @ A_.T), S_
assert np.allclose(C_, PP_ @ A_.T), C_

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your unscented transform of the pendulum's f and h is not estim's
""" # END TEST CONFIG
from estim.estimators.kalman.ukf import sigma_weights as estims_weights_
from estim.grading import check_arrays

mm_, PP_ = np.array([1.3, -0.5]), np.array([[0.4, 0.1], [0.1, 0.6]])
# estim's UKF from the prior (mm_, PP_), two samples with no measurement: its estimate at
# the second is the prediction alone, the transform of f plus Q (eq. 5)
ref_ = estim.UKF(model, Q=Q, R=R, x0=mm_, P0=PP_, alpha=ALPHA, beta=BETA, kappa=KAPPA
                 ).filter(np.full((2, 1), np.nan))
mu_, S_, C_ = unscented_transform(f, mm_, PP_, ALPHA, BETA, KAPPA)
_ = check_arrays(mu_, ref_.x[1], quantity="the transform's mean mu of f", index="entry",
                 equation="eq. (4): sum_i W(m)_i f(X_i)")
_ = check_arrays(S_, ref_.P[1] - Q, quantity="the transform's covariance S of f",
                 index="row", equation="eq. (4): sum_i W(c)_i (Z_i - mu)(Z_i - mu)ᵀ")
# the cross-covariance of h, from estim's sigma points and weights
ukf_ = estim.UKF(model, Q=Q, R=R, x0=mm_, P0=PP_, alpha=ALPHA, beta=BETA, kappa=KAPPA)
pts_ = ukf_.sigma_points(mm_, PP_)
_, Wm_, Wc_ = estims_weights_("merwe", 2, ALPHA, BETA, KAPPA)
Z_ = np.array([h(x_) for x_ in pts_])
muh_ = Wm_ @ Z_
mu_, S_, C_ = unscented_transform(h, mm_, PP_, ALPHA, BETA, KAPPA)
_ = check_arrays(C_, np.einsum("i,ia,ib->ab", Wc_, pts_ - mm_, Z_ - muh_), index="row",
                 quantity="the transform's cross-covariance C of h",
                 equation="eq. (4): sum_i W(c)_i (X_i - m)(Z_i - mu)ᵀ, of shape (n, d)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (3 points).** Write `ukf_predict(m, P)`, returning $(\bar m, \bar P)$ of
# eq. (5), and `ukf_update(m, P, y)`, returning $(m, P)$ after the measurement `y` (an
# array of one entry) by eqs. (6)–(7). Use your `unscented_transform` with `f`, `h`, `Q`,
# `R` and the book's `ALPHA, BETA, KAPPA`.

# %% [raw]
# # BEGIN SOLUTION

# %%
def ukf_predict(m, P):
    # BEGIN SOLUTION
    m_pred, S_f, _ = unscented_transform(f, m, P, ALPHA, BETA, KAPPA)
    P_pred = S_f + Q
    # END SOLUTION
    return m_pred, P_pred


def ukf_update(m, P, y):
    # BEGIN SOLUTION
    mu, S_h, C = unscented_transform(h, m, P, ALPHA, BETA, KAPPA)
    S = S_h + R
    K = np.linalg.solve(S, C.T).T
    m_new = m + K @ (y - mu)
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
failure_message: ukf_predict and ukf_update must each return a pair (m, P) of shapes (2,) and (2, 2)
""" # END TEST CONFIG
m_, P_ = ukf_predict(m0, P0)
assert np.shape(m_) == (2,) and np.shape(P_) == (2, 2), (np.shape(m_), np.shape(P_))
m_, P_ = ukf_update(m0, P0, Y[0])
assert np.shape(m_) == (2,) and np.shape(P_) == (2, 2), (np.shape(m_), np.shape(P_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the prediction is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

rng_ = np.random.default_rng(15)
M_ = rng_.normal(size=(2, 2))
mm_, PP_ = np.array([1.2, -0.7]), M_ @ M_.T + 0.1 * np.eye(2)
ref_ = estim.UKF(model, Q=Q, R=R, x0=mm_, P0=PP_, alpha=ALPHA, beta=BETA, kappa=KAPPA
                 ).filter(np.full((2, 1), np.nan))  # the prediction alone at the second
got_ = ukf_predict(mm_, PP_)
_ = check_arrays(got_[0], ref_.x[1], quantity="the predicted mean", index="entry",
                 equation="eq. (5): the mean of the transform of f")
_ = check_arrays(got_[1], ref_.P[1], quantity="the predicted covariance", index="row",
                 equation="eq. (5): the transform's covariance of f plus Q")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the update is wrong
""" # END TEST CONFIG
from estim.grading import check_arrays

rng_ = np.random.default_rng(16)
M_ = rng_.normal(size=(2, 2))
mm_, PP_, yy_ = np.array([0.9, 0.4]), M_ @ M_.T + 0.1 * np.eye(2), np.array([0.35])
ref_ = estim.UKF(model, Q=Q, R=R, x0=mm_, P0=PP_, alpha=ALPHA, beta=BETA, kappa=KAPPA
                 ).filter(yy_[None])  # the prior updated by yy_
got_ = ukf_update(mm_, PP_, yy_)
_ = check_arrays(got_[0], ref_.x[0], quantity="the updated mean", index="entry",
                 equation="eq. (7): m + K (y - mu), with K = C S⁻¹ and S = S_h + R (eq. 6)")
_ = check_arrays(got_[1], ref_.P[0], quantity="the updated covariance", index="row",
                 equation="eq. (7): P - K S Kᵀ, with S = S_h + R (eq. 6)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q4

# %% [markdown]
# **Part 4 (3 points).** Write `ukf(Y, m0, P0)`: starting from the prior $(m_0, P_0)$ one
# step *before* the first measurement, predict then update at every sample. Return the
# means `(T, 2)` and covariances `(T, 2, 2)` after each update. The book reports an angle
# RMSE of **0.0952** for this record (the extended Kalman filter's: 0.1683).

# %% [raw]
# # BEGIN SOLUTION

# %%
def ukf(Y, m0, P0):
    means, covs = [], []
    m, P = m0, P0
    for y in Y:
        # BEGIN SOLUTION
        m, P = ukf_predict(m, P)
        m, P = ukf_update(m, P, y)
        # END SOLUTION
        means.append(m)
        covs.append(P)
    return np.array(means), np.array(covs)


means, covs = ukf(Y, m0, P0)
rmse = np.sqrt(np.mean((means[:, 0] - X[:, 0]) ** 2))
rmse

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the angle RMSE is not the book's 0.0952439
""" # END TEST CONFIG
assert abs(rmse - 0.09524392125923083) < 1e-9, rmse

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 2
failure_message: your filter leaves estim's unscented Kalman filter
""" # END TEST CONFIG
from estim.grading import check_filter, from_steps

equations_ = {"x": "the update m + K (y - mu), eq. (7), and the predicted mean, eq. (5)",
              "P": "the predicted covariance S_f + Q (eq. 5), the gain K = C S⁻¹ (eq. 6) "
                   "and the update P - K S Kᵀ (eq. 7)"}
mine_ = from_steps(model, ukf_predict, ukf_update, m0, P0)
reference_ = estim.UKF(model, Q=Q, R=R, x0=m0, P0=P0, alpha=ALPHA, beta=BETA, kappa=KAPPA)
record_ = (np.vstack([[np.nan], Y]), None)  # the prior one step before Y[0]
_ = check_filter(mine_, reference_, record_, equations=equations_, loop=(means, covs),
                 loop_name="ukf")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# Your filter's errors against those of the extended Kalman filter (estim's, with the same
# tuning), each with its $\pm 2\sigma$ band, drawn by estim. Near the turning points,
# where $|\theta|$ comes close to $\pi/2$, the linearisation of $\sin\theta$ misleads the
# extended filter; the sigma points, spread over the uncertainty, average over the
# curvature instead, and the unscented filter's errors stay smaller there.

# %%
ekf_result = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0).filter(np.vstack([[np.nan], Y]))
plot_errors({"EKF (estim)": as_log(ekf_result.x[1:], ekf_result.P[1:], truth=X, t=T, model=model),
             "your UKF": as_log(means, covs, truth=X, t=T, model=model)});
