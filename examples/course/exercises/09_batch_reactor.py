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
# # Exercise 9: state estimation on a batch reactor
#
# The exercise session on state estimation of the KU Leuven course *Model Predictive
# Control* (H0E76A, session 5), after Rawlings & Bakshi, "Particle filtering and moving
# horizon estimation", *Comput. Chem. Eng.* 30, 2006. A batch reactor runs the reversible
# reactions $A \rightleftharpoons B + C$ and $2B \rightleftharpoons C$:
#
# $$r_1 = k_1 C_A - k_{-1} C_B C_C,\quad r_2 = k_2 C_B^2 - k_{-2} C_C,\qquad
#   \dot x = \begin{bmatrix} -r_1 \\ r_1 - 2 r_2 \\ r_1 + r_2 \end{bmatrix},\qquad
#   x = (C_A, C_B, C_C) \ge 0,$$
#
# integrated by RK4 over $\Delta t = 0.25$ s into the transition $x_{k+1} = F(x_k) + w_k$.
# A single sensor measures the total pressure, $y_k = h(x_k) + v_k$ with
# $h(x) = 32.84\,(C_A + C_B + C_C)$. The noises are $w_k \sim N(0, \sigma_w^2 I)$,
# $\sigma_w = 0.002$, and $v_k \sim N(0, \sigma_v^2)$, $\sigma_v = 0.25$; the truth starts
# at $(0.5, 0.05, 0)$ and runs 400 samples (100 s), clipped to $x \ge 0$ as in the
# course's simulator. The estimators start from the **bad guess** $\bar x_0 = (1, 0, 4)$
# with $\bar P_0 = 0.5^2 I$.
#
# estim writes the model once (`estim.models.batch_reactor()`): `MODEL.F`, `MODEL.H` and
# their Jacobians `MODEL.F_x`, `MODEL.H_x` are CasADi functions of `(x, u, p)`; the reactor
# has no inputs (`u = np.zeros(0)`) and its parameters are `p = MODEL.p`. Evaluate one with
# `.full()`: `MODEL.H_x(x, u, p).full()` is the $1 \times 3$ matrix
# $\partial h/\partial x$, `MODEL.F(x, u, p).full().ravel()` the vector $F(x)$.

# %%
import numpy as np

import estim
from estim.grading import as_log
from estim.plotting import plot_estimates

SC = estim.scenarios.batch_reactor()  # truth, noise, 400 steps of 0.25 s, plant x >= 0
MODEL = SC.model
SIG_W, SIG_V, SIG_P = 0.002, 0.25, 0.5  # model noise, measurement noise, the guess's spread
GUESS = np.array([1.0, 0.0, 4.0])       # the bad initial guess of the estimators
BURN_IN = 200                           # samples left out of the second RMSE (50 s)
Q, R, P0 = SIG_W**2 * np.eye(3), SIG_V**2 * np.eye(1), SIG_P**2 * np.eye(3)
u, p = np.zeros(MODEL.nu), MODEL.p

record = estim.simulate(SC, None, seed=0)  # the course's run (seed 0)
X, Y = record.x, record.y                  # (400, 3) true concentrations, (400, 1) measured
plot_estimates({"the guess": as_log(np.tile(GUESS, (len(Y), 1)), truth=X, model=MODEL,
                                    name="the guess")}, title="the truth and the guess");

# %% [markdown]
# ## The extended Kalman filter
#
# At every sample the course's EKF first corrects its prediction $(\bar x_k, \bar P_k)$
# with the measurement $y_k$, then predicts the next sample:
#
# * (eq. 1) $C = \frac{\partial h}{\partial x}(\bar x_k)$,
#   $S = C \bar P_k C^\top + R$, the gain $L = \bar P_k C^\top S^{-1}$;
# * (eq. 2) $\hat x_k = \bar x_k + L\,(y_k - h(\bar x_k))$,
#   $P_k = \bar P_k - L C \bar P_k$;
# * (eq. 3) $A = \frac{\partial F}{\partial x}(\hat x_k)$,
#   $\bar x_{k+1} = F(\hat x_k)$, $\bar P_{k+1} = A P_k A^\top + Q$,
#
# from $(\bar x_0, \bar P_0)$ = (`GUESS`, `P0`) at the first sample.

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (2 points).** Write `ekf_predict(x, P)`, the time update of eq. (3), with
# `MODEL.F` and `MODEL.F_x`; return $(\bar x_{k+1}, \bar P_{k+1})$, shapes `(3,)` and
# `(3, 3)`.

# %% [raw]
# # BEGIN SOLUTION

# %%
def ekf_predict(x, P):
    # BEGIN SOLUTION
    A = MODEL.F_x(x, u, p).full()
    x_pred = MODEL.F(x, u, p).full().ravel()
    P_pred = A @ P @ A.T + Q
    # END SOLUTION
    return x_pred, P_pred

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: ekf_predict must return (x_pred, P_pred) of eq. (3), shapes (3,) and (3, 3)
""" # END TEST CONFIG
x_, P_ = ekf_predict(GUESS, P0)
assert np.shape(x_) == (3,) and np.shape(P_) == (3, 3), (np.shape(x_), np.shape(P_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the time update is not estim.EKF's
""" # END TEST CONFIG
from estim.grading import check_arrays

rng_ = np.random.default_rng(3)
M_ = rng_.normal(size=(3, 3))
xx_, PP_ = rng_.uniform(0.1, 2.0, 3), M_ @ M_.T + 0.1 * np.eye(3)
# estim's EKF from the prior (xx_, PP_) with two missing samples: the second is its prediction
ref_ = estim.EKF(MODEL, Q=Q, R=R, x0=xx_, P0=PP_).filter(np.full((2, 1), np.nan))
got_ = ekf_predict(xx_, PP_)
_ = check_arrays(got_[0], ref_.x[1], quantity="the predicted state", index="entry",
                 equation="eq. (3): F(x̂) by MODEL.F")
_ = check_arrays(got_[1], ref_.P[1], quantity="the predicted covariance", index="row",
                 equation="eq. (3): A P Aᵀ + Q with A = MODEL.F_x at x̂")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (2 points).** Write `ekf_update(x, P, y)`, the measurement update of
# eqs. (1)-(2) at the prediction `(x, P)`, with `MODEL.H` and `MODEL.H_x`; return
# $(\hat x_k, P_k)$.

# %% [raw]
# # BEGIN SOLUTION

# %%
def ekf_update(x, P, y):
    # BEGIN SOLUTION
    C = MODEL.H_x(x, u, p).full()
    S = C @ P @ C.T + R
    L = np.linalg.solve(S, C @ P).T
    x_new = x + L @ (y - MODEL.H(x, u, p).full().ravel())
    P_new = P - L @ C @ P
    # END SOLUTION
    return x_new, P_new

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: ekf_update must return the pair (x, P) of eq. (2), shapes (3,) and (3, 3)
""" # END TEST CONFIG
x_, P_ = ekf_update(GUESS, P0, Y[0])
assert np.shape(x_) == (3,) and np.shape(P_) == (3, 3), (np.shape(x_), np.shape(P_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the measurement update is not estim.EKF's
""" # END TEST CONFIG
from estim.grading import check_arrays

ref_ = estim.EKF(MODEL, Q=Q, R=R, x0=GUESS, P0=P0).filter(Y[:1])  # the guess updated by Y[0]
got_ = ekf_update(GUESS, P0, Y[0])
_ = check_arrays(got_[0], ref_.x[0], quantity="the updated state", index="entry",
                 equation="eq. (2): x̄ + L (y - h(x̄)) with the gain L of eq. (1)")
_ = check_arrays(got_[1], ref_.P[0], quantity="the updated covariance", index="row",
                 equation="eq. (2): P̄ - L C P̄ (and S = C P̄ Cᵀ + R, L = P̄ Cᵀ S⁻¹, eq. 1)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (3 points).** Write `ekf(Y, update=ekf_update)`: from the prior
# $(\bar x_0, \bar P_0)$ = (`GUESS`, `P0`) at the first sample, at every sample `update`
# with $y_k$, keep $(\hat x_k, P_k)$, then `ekf_predict`. Return the estimates `(T, 3)`
# and covariances `(T, 3, 3)`, and compute the RMSE over all states and samples,
#
# (eq. 4) $\quad \text{RMSE} = \sqrt{\tfrac{1}{3T} \sum_{k,i} (\hat x_{k,i} - x_{k,i})^2}$
#
# (`estim.rmse` does it on a log: `estim.rmse(as_log(x_ekf, P_ekf, truth=X))`). The
# course's solution gives **0.4212**: the filter settles on a wrong, partly negative state
# that explains the one measured sum as well as the truth.

# %% [raw]
# # BEGIN SOLUTION

# %%
def ekf(Y, update=ekf_update):
    x, P = GUESS, P0
    estimates, covariances = [], []
    for y in Y:
        # BEGIN SOLUTION
        x, P = update(x, P, y)
        estimates.append(x)
        covariances.append(P)
        x, P = ekf_predict(x, P)
        # END SOLUTION
    return np.array(estimates), np.array(covariances)


x_ekf, P_ekf = ekf(Y)
# BEGIN SOLUTION
rmse_ekf = float(estim.rmse(as_log(x_ekf, P_ekf, truth=X, model=MODEL)))
# END SOLUTION
rmse_ekf, x_ekf.min()

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the EKF's RMSE (eq. 4) is not the course's 0.4212 (its smallest estimate -1.4829)
""" # END TEST CONFIG
assert abs(rmse_ekf - 0.42115766462402576) < 1e-6, rmse_ekf
assert abs(x_ekf.min() - -1.4828997) < 1e-6, x_ekf.min()

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your EKF leaves estim.EKF on the course's record
""" # END TEST CONFIG
from estim.grading import check_filter, from_steps

equations_ = {"x": "the update x̄ + L (y - h(x̄)) (eq. 2) and the prediction F(x̂) (eq. 3)",
              "P": "the update P̄ - L C P̄ (eqs. 1-2) and the prediction A P Aᵀ + Q (eq. 3)"}
mine_ = from_steps(MODEL, ekf_predict, ekf_update, GUESS, P0, name="your EKF")
reference_ = estim.EKF(MODEL, Q=Q, R=R, x0=GUESS, P0=P0)
_ = check_filter(mine_, reference_, (Y, None), equations=equations_, name="your EKF",
                 loop=(x_ekf, P_ekf), loop_name="ekf",
                 loop_equation="the loop: update with y, keep the estimate and its "
                               "covariance, then predict")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your EKF is not as accurate as estim.EKF over 10 seeds
""" # END TEST CONFIG
from estim.grading import check_over_seeds, from_steps

# the same filter on 10 other records of 100 samples: equal RMSE within 1e-6 times the
# reference's median (two one-sided Wilcoxon tests: an EKF outside that band passes with
# probability at most 5 %; a correct EKF equals estim's to rounding and always passes)
_ = check_over_seeds(from_steps(MODEL, ekf_predict, ekf_update, GUESS, P0, name="your EKF"),
                     estim.EKF(MODEL, Q=Q, R=R, x0=GUESS, P0=P0), SC.replace(n_steps=100),
                     seeds=range(1, 11), tolerance=1e-6, name="your EKF")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q4

# %% [markdown]
# **Part 4 (2 points): the clipped EKF.** Concentrations are not negative. Write
# `clip(x)`, the projection of an estimate onto $x \ge 0$,
#
# (eq. 5) $\quad \hat x_k \leftarrow \max(\hat x_k, 0)$ entry by entry, after eq. (2) and
# before eq. (3), the covariance left as it is,
#
# and `ekf_update_clipped(x, P, y)`: `ekf_update`, then `clip`. Run `ekf` with it. The
# course's solution gives an RMSE of **20.0813**: what happens at the start?

# %% [raw]
# # BEGIN SOLUTION

# %%
def clip(x):
    # BEGIN SOLUTION
    return np.maximum(x, 0.0)
    # END SOLUTION


def ekf_update_clipped(x, P, y):
    # BEGIN SOLUTION
    x, P = ekf_update(x, P, y)
    x = clip(x)
    # END SOLUTION
    return x, P


x_clip, P_clip = ekf(Y, update=ekf_update_clipped)
rmse_clip = float(estim.rmse(as_log(x_clip, P_clip, truth=X, model=MODEL)))
rmse_clip, x_clip.min(), x_clip.max()

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the clipped EKF stays at x >= 0, peaks above 100, and has the course's RMSE 20.0813
""" # END TEST CONFIG
assert x_clip.min() == 0.0 and x_clip.max() > 100, (x_clip.min(), x_clip.max())
assert abs(rmse_clip - 20.081290644265803) < 1e-5, rmse_clip

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your clipped EKF leaves estim.EKF(clip=True)
""" # END TEST CONFIG
from estim.grading import check_arrays, check_filter, from_steps

_ = check_arrays(clip(np.array([-1.0, 2.0, -0.5])), [0.0, 2.0, 0.0], index="entry",
                 quantity="clip([-1, 2, -0.5])", equation="eq. (5): max(x, 0) entry by entry")
equations_ = {"x": "the clip max(x̂, 0) after the update (eq. 5), then F at the clipped "
                   "estimate (eq. 3)",
              "P": "eq. (5): the clip leaves P as the update made it; A at the clipped "
                   "estimate (eq. 3)"}
mine_ = from_steps(MODEL, ekf_predict, ekf_update_clipped, GUESS, P0, name="your clipped EKF")
reference_ = estim.EKF(MODEL, Q=Q, R=R, x0=GUESS, P0=P0, clip=True)
_ = check_filter(mine_, reference_, (Y, None), equations=equations_, name="your clipped EKF")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# ## Moving horizon estimation
#
# The MHE of the course keeps the last $N$ measurements and, at time $T$, with
# $s = \max(0, T - N + 1)$ (fewer samples while the window fills), solves
#
# (eq. 6) $\quad \min_{x_s, \dots, x_T}\ \sum_{k=s}^{T-1}
#   \frac{\lVert x_{k+1} - F(x_k)\rVert^2}{\sigma_w^2}
#   + \sum_{k=s}^{T} \frac{(y_k - h(x_k))^2}{\sigma_v^2}
#   \quad \text{subject to}\quad 0 \le x_k \le 10,$
#
# without a prior on $x_s$ (no arrival cost: $\Gamma = 0$); its estimate is $x_T$. The
# course gave students a builder for this problem; estim's is `estim.MHE`: its cost is
# $\sum \lVert x_{k+1} - F(x_k)\rVert^2_{Q^{-1}} + \sum \lVert y_k - h(x_k)\rVert^2_{R^{-1}}$
# over a window of `horizon` measurements, with `arrival_cost="none"` and the bounds
# `lower`, `upper`.

# %% [raw]
# # BEGIN QUESTION
# name: q5

# %% [markdown]
# **Part 5 (3 points).** Write `mhe(horizon)`, returning
# `estim.MHE(MODEL, horizon=horizon, Q=..., R=..., x0=GUESS, arrival_cost="none",
# lower=..., upper=..., solver="fatrop")` for the problem of eq. (6). Which covariances
# $Q$ and $R$ weigh it as eq. (6) does? `x0` is only the solver's first guess here. The
# cell then runs it on the course's record with $N = 10$ and $N = 25$ (about 2 s).

# %% [raw]
# # BEGIN SOLUTION

# %%
def mhe(horizon):
    # BEGIN SOLUTION
    return estim.MHE(MODEL, horizon=horizon, Q=SIG_W**2, R=SIG_V**2, x0=GUESS,
                     arrival_cost="none", lower=0.0, upper=10.0, solver="fatrop")
    # END SOLUTION


logs_mhe = {n: estim.simulate(SC, mhe(n), seed=0) for n in (10, 25)}
{n: float(estim.rmse(log)) for n, log in logs_mhe.items()}

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the MHE's RMSE are not the course's 0.1326 (N = 10) and 0.0496 (N = 25)
""" # END TEST CONFIG
got_ = [float(estim.rmse(logs_mhe[n])) for n in (10, 25)]
assert abs(got_[0] - 0.1326) < 1e-4 and abs(got_[1] - 0.0496) < 1e-4, f"RMSE {got_}"
assert min(logs_mhe[n].x_hat.min() for n in (10, 25)) >= -1e-8, "an estimate below the bound 0"

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 2
failure_message: your MHE is not the course's (eq. 6)
""" # END TEST CONFIG
from estim.grading import check_filter

# N = 25 on the first 40 samples: the window filling, then sliding
reference_ = estim.MHE(MODEL, horizon=25, Q=SIG_W**2, R=SIG_V**2, x0=GUESS,
                       arrival_cost="none", lower=0.0, upper=10.0, solver="fatrop")
mine_ = mhe(25)
assert isinstance(mine_, estim.MHE), f"mhe must return an estim.MHE, got {type(mine_).__name__}"
assert mine_.horizon == 25, f"mhe(25) has horizon {mine_.horizon}"
_ = check_filter(mine_, reference_, (Y[:40], None), name="your MHE", atol=1e-6, rtol=1e-6,
                 equations={"x": "eq. (6): the weights Q = σ_w² I and R = σ_v² (their "
                                 "inverses weigh the cost), no arrival cost, 0 <= x <= 10",
                            "P": "eq. (6): the weights Q = σ_w² I and R = σ_v²"})

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q6

# %% [markdown]
# **Part 6 (3 points): the comparison.** With the four runs in `logs` (below), fill
# `table`: for each name, the tuple of floats (RMSE of eq. (4), the RMSE after the first
# `BURN_IN` samples, the smallest estimated concentration), e.g. with
# `estim.rmse(log, burn_in=BURN_IN)` and `log.x_hat`. Then name the best estimator
# over the whole record, `best_overall`, and after the burn-in, `best_after_burn_in`.
# Does the MHE beat the EKF? Does $N = 25$ beat $N = 10$? Does clipping help?

# %%
logs = {"EKF": as_log(x_ekf, P_ekf, truth=X, model=MODEL, name="EKF"),
        "clipped EKF": as_log(x_clip, P_clip, truth=X, model=MODEL, name="clipped EKF"),
        "MHE N=10": logs_mhe[10], "MHE N=25": logs_mhe[25]}

# %% [raw]
# # BEGIN SOLUTION

# %%
# BEGIN SOLUTION
table = {name: (float(estim.rmse(log)), float(estim.rmse(log, burn_in=BURN_IN)),
                float(log.x_hat.min())) for name, log in logs.items()}
best_overall = min(table, key=lambda name: table[name][0])
best_after_burn_in = min(table, key=lambda name: table[name][1])
# END SOLUTION
print(f"{'estimator':<12} {'RMSE':>8} {f'after {BURN_IN}':>10} {'min x̂':>8}")
for name, row in table.items():
    print(f"{name:<12} {row[0]:8.4f} {row[1]:10.4f} {row[2]:8.4f}")

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: table must hold a row of three numbers for each of the four names of logs
""" # END TEST CONFIG
assert set(table) == set(logs), sorted(table)
assert all(np.shape(row) == (3,) for row in table.values()), table

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the table's numbers are not the RMSE and smallest estimates of the logs
""" # END TEST CONFIG
from estim.grading import check_arrays

for name_, log_ in logs.items():
    ref_ = [float(estim.rmse(log_)), float(estim.rmse(log_, burn_in=BURN_IN)), log_.x_hat.min()]
    _ = check_arrays(np.ravel(table[name_]), ref_, quantity=f"the row of {name_!r}",
                     index="column (0: RMSE, 1: after BURN_IN, 2: min x̂)",
                     equation="eq. (4) over all samples, then from sample BURN_IN on")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the best estimators are not the course's
""" # END TEST CONFIG
# the course's table (seed 0): the MHE with N = 25 best overall (0.0496), the clipped EKF
# best after 50 s (0.0206) once its start-up transient is over
assert best_overall == "MHE N=25", f"best_overall is {best_overall!r}: compare the RMSE column"
assert best_after_burn_in == "clipped EKF", (
    f"best_after_burn_in is {best_after_burn_in!r}: compare the column after BURN_IN")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# The four estimates against the truth (symmetric-log axes, linear within $\pm 0.1$): the
# EKF settles on a wrong state with a negative concentration; clipping keeps it
# non-negative but its start-up transient ($\hat C_C$ beyond 100) dominates its RMSE,
# although after 50 s it is the most accurate; the MHE needs no good guess, and the longer
# window does better.

# %%
plot_estimates(logs, symlog=0.1,
               title="batch reactor from the guess (1, 0, 4) (symlog, linear within ±0.1)");
