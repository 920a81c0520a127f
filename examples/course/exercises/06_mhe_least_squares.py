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
# # Exercise 6: moving horizon estimation as a least-squares problem
#
# The pendulum of Särkkä & Svensson, *Bayesian Filtering and Smoothing*, 2nd ed., 2023,
# on the book's record (its companion code's `pendulum.json`): the angle $\theta$ and the
# angular rate $\omega$, Euler steps of $\Delta t = 0.01$ s, and the sine of the angle
# measured with noise of variance $R = 0.1$:
#
# $$x_{k+1} = f(x_k) + q_k,\quad f(x) = \begin{bmatrix} \theta + \Delta t\,\omega \\
#   \omega - \Delta t\, g \sin\theta \end{bmatrix},\quad q_k \sim N(0, Q), \qquad
#   y_k = h(x_k) + r_k = \sin\theta_k + r_k,\quad r_k \sim N(0, R),$$
#
# with $Q = 0.01 \begin{bmatrix} \Delta t^3/3 & \Delta t^2/2 \\ \Delta t^2/2 & \Delta t
# \end{bmatrix}$ and $g = 9.81$.
#
# A moving horizon estimator (Rao, Rawlings & Mayne, IEEE TAC 2003) keeps the last $N$
# measurements $y_s, \dots, y_T$ ($s = \max(0, T - N + 1)$) and, at every sample, finds
# the most probable trajectory $x_s, \dots, x_T$ of the window: the minimiser of a sum of
# squares. Each covariance $C$ becomes a **weight** $L$ with
#
# $$L^\top L = C^{-1}, \qquad L = G^\top \text{ where } C^{-1} = G G^\top
#   \text{ (Cholesky, } G \text{ lower triangular)} \tag{eq. 1}$$
#
# so that $\|L v\|^2 = v^\top C^{-1} v$. The window's **residual vector** $r$ stacks, in
# this order,
#
# * (eq. 2) the arrival term $L_0 (x_s - \bar x_s)$, with $L_0^\top L_0 = \bar P_s^{-1}$:
#   what the samples before the window say about $x_s$;
# * (eq. 3) the process terms $L_q (x_{k+1} - f(x_k))$ for $k = s, \dots, T-1$, with
#   $L_q^\top L_q = Q^{-1}$;
# * (eq. 4) the measurement terms $L_r (y_k - h(x_k))$ for $k = s, \dots, T$, with
#   $L_r^\top L_r = R^{-1}$;
#
# and the window's estimate minimises the cost
#
# $$V(x_s, \dots, x_T) = \|r\|^2 = \|x_s - \bar x_s\|^2_{\bar P_s^{-1}}
#   + \sum_{k=s}^{T-1} \|x_{k+1} - f(x_k)\|^2_{Q^{-1}}
#   + \sum_{k=s}^{T} \|y_k - h(x_k)\|^2_{R^{-1}}, \tag{eq. 5}$$
#
# twice the negative log-posterior of the window's trajectory (up to a constant): over a
# whole record it is the maximum a posteriori trajectory that the book's iterated
# extended Rauch-Tung-Striebel smoother reaches by Gauss-Newton steps.
#
# You write the residuals with numpy, minimise them with `scipy.optimize.least_squares`,
# and slide the window along the record. estim gives the model, the book's record and the
# reference estimators (`estim.FullInformation`, `estim.MHE`) the grader compares yours
# with.

# %%
import numpy as np
from scipy.optimize import least_squares

import estim
from estim.grading import as_log
from estim.plotting import plot_estimates

dt, g = 0.01, 9.81
model = estim.models.sine_pendulum(integrator="euler")  # the book's Euler steps
Q = 0.01 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
R = np.array([[0.1]])
x0, P0 = np.zeros(2), np.eye(2)  # the prior of the first sample's state


def f(x):
    """The transition of eq. (3), for one state (2,) or a stack of states (n, 2)."""
    x = np.asarray(x, dtype=float)
    theta, omega = x[..., 0], x[..., 1]
    return np.stack([theta + dt * omega, omega - dt * g * np.sin(theta)], axis=-1)


def h(x):
    """The output of eq. (4): (1,) for one state, (n, 1) for a stack of states."""
    return np.sin(np.asarray(x, dtype=float)[..., :1])


pendulum = np.load("book_pendulum.npz")
Y, X = pendulum["Y"][:, None], pendulum["X"]  # (500, 1) measurements, (500, 2) true states
Y.shape, X.shape

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (3 points): the residual vector.** Write `weight(C)`, the factor $L$ of
# eq. (1), and `window_residuals(Xw, Yw, xbar, L0, Lq, Lr)`: for the window's states
# `Xw` $(n, 2)$ (oldest first), its measurements `Yw` $(n, 1)$ and the arrival mean
# `xbar` $(2,)$, the residual vector of eqs. (2)–(4), flat, of length
# $2 + 2(n - 1) + n$: first the arrival term, then the process terms in time order, then
# the measurement terms in time order.

# %% [raw]
# # BEGIN SOLUTION

# %%
def weight(C):
    # BEGIN SOLUTION
    L = np.linalg.cholesky(np.linalg.inv(np.atleast_2d(C))).T
    # END SOLUTION
    return L


def window_residuals(Xw, Yw, xbar, L0, Lq, Lr):
    # BEGIN SOLUTION
    Xw = np.asarray(Xw, dtype=float)
    arrival = L0 @ (Xw[0] - xbar)
    process = (Xw[1:] - f(Xw[:-1])) @ Lq.T
    measurement = (np.asarray(Yw, dtype=float) - h(Xw)) @ Lr.T
    r = np.concatenate([arrival, process.ravel(), measurement.ravel()])
    # END SOLUTION
    return r


L0, Lq, Lr = weight(P0), weight(Q), weight(R)

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: weight(C) must be upper triangular with Lᵀ L = C⁻¹ (eq. 1), and the
  residual vector of a window of n samples has 2 + 2 (n - 1) + n entries
""" # END TEST CONFIG
L_ = np.asarray(weight(Q))
assert L_.shape == (2, 2) and np.allclose(np.tril(L_, -1), 0), L_
assert np.allclose(L_.T @ L_, np.linalg.inv(Q), rtol=1e-9), L_.T @ L_
r_ = np.ravel(window_residuals(X[:5], Y[:5], x0, L0, Lq, Lr))
assert r_.shape == (2 + 2 * 4 + 5,), r_.shape

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the residuals differ from those of estim's model
""" # END TEST CONFIG
from estim.grading import check_arrays
from estim.solvers.weights import weight_factor

rng_ = np.random.default_rng(3)
n_ = 6
Xw_ = X[10:10 + n_] + 0.1 * rng_.normal(size=(n_, 2))
Yw_, xb_ = Y[10:10 + n_], X[10] + rng_.normal(size=2)
Pbar_ = np.array([[0.5, 0.3], [0.3, 2.0]])  # an arrival covariance other than P0 = I
W0_, WQ_, WR_ = weight_factor(Pbar_), weight_factor(Q), weight_factor(R)
_ = check_arrays(weight(Q), WQ_, quantity="weight(Q)",
                 equation="eq. (1): L = Gᵀ with G Gᵀ = Q⁻¹, G the lower Cholesky factor")
# estim's transition and output (CasADi functions of the model)
Fx_ = np.array([model.F(x, [], model.p).full().ravel() for x in Xw_[:-1]])
Hx_ = np.array([model.H(x, [], model.p).full().ravel() for x in Xw_])
r_ = np.ravel(window_residuals(Xw_, Yw_, xb_, W0_, WQ_, WR_))
m_ = 2 + 2 * (n_ - 1)
assert r_.shape == (m_ + n_,), (f"a window of {n_} samples has {m_ + n_} residuals "
                                f"(2 + 2 (n-1) + n), yours has {r_.size}")
_ = check_arrays(r_[:2], W0_ @ (Xw_[0] - xb_), quantity="the arrival term",
                 equation="eq. (2): L0 (x_s - x̄_s), first in the vector")
_ = check_arrays(r_[2:m_].reshape(n_ - 1, 2), (Xw_[1:] - Fx_) @ WQ_.T,
                 quantity="the block of process terms",
                 equation="eq. (3): Lq (x_{k+1} - f(x_k)), after the arrival term",
                 index="transition")
_ = check_arrays(r_[m_:].reshape(n_, 1), (Yw_ - Hx_) @ WR_.T,
                 quantity="the block of measurement terms",
                 equation="eq. (4): Lr (y_k - h(x_k)), last in the vector", index="sample")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: at estim's full-information optimum your residuals do not give estim's cost
""" # END TEST CONFIG
from estim.grading import check_arrays
from estim.solvers.weights import weight_factor

W0_, WQ_, WR_ = weight_factor(P0), weight_factor(Q), weight_factor(R)
fit_ = estim.FullInformation(model, Q=Q, R=R, x0=x0, P0=P0).fit(Y[:30])
r_ = np.ravel(window_residuals(fit_.x, Y[:30], x0, W0_, WQ_, WR_))
assert r_.shape == (2 + 2 * 29 + 30,), r_.shape
_ = check_arrays(r_[2:60].reshape(29, 2), fit_.w @ WQ_.T,
                 quantity="the block of process terms at the optimum (estim's ŵ_k = "
                          "x̂_{k+1} - F(x̂_k))",
                 equation="eq. (3)", index="transition")
_ = check_arrays(r_[60:].reshape(30, 1), fit_.v @ WR_.T,
                 quantity="the block of measurement terms at the optimum (estim's v̂_k = "
                          "y_k - h(x̂_k))",
                 equation="eq. (4)", index="sample")
_ = check_arrays(np.sum(r_**2), fit_.cost, quantity="the cost ‖r‖² at the optimum",
                 equation="eq. (5): the sum of the squares of eqs. (2)-(4)", rtol=1e-9)

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (3 points): solving one window.** Write `solve_window(Yw, xbar, guess, L0, Lq,
# Lr)`, returning the minimiser $(n, 2)$ of eq. (5) over the window's states, from the
# initial trajectory `guess` $(n, 2)$, with `scipy.optimize.least_squares` on your
# `window_residuals` (the decision vector is the window's states, flattened). The
# problem is badly scaled (the entries of $L_q$ reach $3.5 \cdot 10^4$): ask for tight
# tolerances, `xtol=ftol=gtol=1e-12`.
#
# The grader compares your minimiser with that of `estim.FullInformation` (estim's
# Gauss-Newton solver, exact derivatives) on the same window, prior and weights, to
# $10^{-5}$: two solvers stop at slightly different points near the same minimiser (on
# these windows about $10^{-7}$ apart, the finite-difference Jacobian of
# `least_squares` and the weak determination of $\omega$ by 30 samples setting that
# size), and a wrong term moves it by far more.

# %% [raw]
# # BEGIN SOLUTION

# %%
def solve_window(Yw, xbar, guess, L0, Lq, Lr):
    # BEGIN SOLUTION
    n = len(Yw)
    sol = least_squares(lambda z: window_residuals(z.reshape(n, 2), Yw, xbar, L0, Lq, Lr),
                        np.ravel(guess), xtol=1e-12, ftol=1e-12, gtol=1e-12)
    Xw = sol.x.reshape(n, 2)
    # END SOLUTION
    return Xw


X30 = solve_window(Y[:30], x0, np.zeros((30, 2)), L0, Lq, Lr)
X30[-1], X[29]

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: solve_window must return the window's states (n, 2), with a cost (eq. 5)
  no larger than the true trajectory's
""" # END TEST CONFIG
Xs_ = np.asarray(solve_window(Y[:30], x0, np.zeros((30, 2)), L0, Lq, Lr))
assert Xs_.shape == (30, 2), Xs_.shape
cost_ = np.sum(np.square(window_residuals(Xs_, Y[:30], x0, L0, Lq, Lr)))
cost_true_ = np.sum(np.square(window_residuals(X[:30], Y[:30], x0, L0, Lq, Lr)))
assert cost_ <= cost_true_, (cost_, cost_true_)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 2
failure_message: your window's minimiser is not estim's
""" # END TEST CONFIG
from estim.grading import check_arrays
from estim.solvers.weights import weight_factor

WQ_, WR_ = weight_factor(Q), weight_factor(R)
tight_ = {"xtol": 1e-12}
windows_ = ((0, 30, x0, P0),
            (120, 25, X[120] + np.array([0.3, -0.5]), np.array([[0.5, 0.3], [0.3, 2.0]])))
for start_, n_, xb_, Pb_ in windows_:
    Yw_ = Y[start_:start_ + n_]
    ref_ = estim.FullInformation(model, Q=Q, R=R, x0=xb_, P0=Pb_,
                                 solver_options=tight_).fit(Yw_).x
    got_ = solve_window(Yw_, xb_, np.tile(xb_, (n_, 1)), weight_factor(Pb_), WQ_, WR_)
    _ = check_arrays(got_, ref_, atol=1e-5, rtol=0, index="window row",
                     quantity=f"the minimiser of the window y_{start_}..y_{start_ + n_ - 1}",
                     equation="eq. (5) minimised over all the window's states by "
                              "least_squares on window_residuals (tolerances 1e-12)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (3 points): the moving window.** Complete the class `MovingHorizon`: its
# `step(y)` adds the measurement $y_T$ to the window (dropping the oldest one once it
# holds $N$), solves the window and returns $\hat x_T$, the window's last state. The
# arrival cost is the *fixed* one:
#
# * while the window still starts at the first sample ($T < N$), $\bar x_0 = x_0$ and
#   $\bar P_0 = P_0$ (the window is the whole record so far);
# * once it slides, $\bar P_s = P_0$ and the arrival mean is the previous window's
#   estimate of the new first state:
#   $$\bar x_s = \hat x_{s|T-1} \quad \text{(the second row of the previous
#   solution)}. \tag{eq. 6}$$
#
# Warm-start each window from the previous solution moved by one sample (a sliding
# window drops its first row), with $f$ of its last state as the new last row. The
# grader runs your `step` sample by sample (`estim.adapters.from_function`) against
# `estim.MHE(model, horizon=N, arrival_cost="fixed", ...)` on the first 60 samples and
# checks every estimate to $10^{-5}$, for the reason of part 2 (on each window the two
# solvers agree to a few $10^{-7}$; eq. 6 carries a window's difference into the next,
# but the windows do not amplify it).

# %% [raw]
# # BEGIN SOLUTION

# %%
class MovingHorizon:
    def __init__(self, N):
        self.N = N
        self.reset()

    def reset(self):
        self.Yw = []               # the window's measurements, oldest first
        self.Xw = None             # the previous window's solution
        self.xbar = x0.copy()      # the arrival mean

    def step(self, y, u=None):
        # BEGIN SOLUTION
        if self.Xw is None:
            guess = self.xbar[None, :]
        elif len(self.Yw) == self.N:  # the window slides: eq. (6)
            self.xbar = self.Xw[1].copy()
            guess = np.vstack([self.Xw[1:], f(self.Xw[-1])])
        else:
            guess = np.vstack([self.Xw, f(self.Xw[-1])])
        self.Yw = (self.Yw + [np.asarray(y, dtype=float)])[-self.N:]
        self.Xw = solve_window(np.array(self.Yw), self.xbar, guess, L0, Lq, Lr)
        x_hat = self.Xw[-1].copy()
        # END SOLUTION
        return x_hat


N, T = 20, 60
mhe = MovingHorizon(N)
estimates = np.array([mhe.step(y) for y in Y[:T]])
rmse = np.sqrt(np.mean((estimates[:, 0] - X[:T, 0]) ** 2))
rmse

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: before the window is full, step's estimate is the last state of the
  whole record's window (prior x0, P0)
""" # END TEST CONFIG
assert np.shape(estimates) == (T, 2), np.shape(estimates)
full_ = solve_window(Y[:N], x0, np.zeros((N, 2)), L0, Lq, Lr)
assert np.allclose(estimates[N - 1], full_[-1], atol=1e-5), (estimates[N - 1], full_[-1])

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 2
failure_message: your moving horizon estimator leaves estim.MHE's
""" # END TEST CONFIG
from estim.adapters import from_function
from estim.grading import check_filter

mine_ = MovingHorizon(N)
student_ = from_function(lambda y, u: mine_.step(y), model, reset=mine_.reset,
                         name="your MHE")
reference_ = estim.MHE(model, horizon=N, Q=Q, R=R, x0=x0, P0=P0, arrival_cost="fixed",
                       solver_options={"xtol": 1e-12})
_ = check_filter(student_, reference_, (Y[:T], None), atol=1e-5, name="your MHE",
                 equations={"x": "the arrival mean of eq. (6) (the previous window's "
                                 "estimate of x_s, with P̄ = P0), the window of the last N "
                                 "measurements and its solve (part 2)"})

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# The truth and your moving horizon estimates, drawn by estim:

# %%
plot_estimates(as_log(estimates, truth=X[:T], model=model, name="your MHE"));
