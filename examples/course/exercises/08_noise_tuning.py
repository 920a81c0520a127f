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
# # Exercise 8: noise tuning and consistency
#
# A Kalman filter is only as good as its covariances $Q$ and $R$, and on measured data
# nobody tells you them. This exercise asks two questions of a filter: **is its covariance
# honest** (does $P_k$ match its errors, does $S_k$ match its innovations?), and **which
# $Q$ and $R$ does the record itself point to** (maximum likelihood)?
#
# The model is the car of exercise 1 (Särkkä & Svensson, *Bayesian Filtering and
# Smoothing*, 2nd ed., 2023, example 4.3): the state $x = (p_x, p_y, v_x, v_y)$, sampled
# every $\Delta t = 0.1$ s,
#
# $$x_k = A x_{k-1} + q_{k-1},\quad q_{k-1} \sim N(0,\, q\, Q_1), \qquad
#   y_k = H x_k + r_k,\quad r_k \sim N(0,\, r\, I),$$
#
# where $Q_1$ is the process noise of a white acceleration of unit spectral density:
# the two numbers $q$ (how hard the driver accelerates) and $r$ (the sensor's variance)
# are the whole tuning. The filter starts from the prior $x_0 \sim N(m_0, P_0)$ at the
# first sample and alternates
#
# * (eq. 1) the prediction $\bar m_k = A m_{k-1}$, $\bar P_k = A P_{k-1} A^\top + Q$
#   for $k \ge 1$ (and $\bar m_0 = m_0$, $\bar P_0 = P_0$);
# * (eq. 2) the **innovation** $e_k = y_k - H \bar m_k$ and its covariance
#   $S_k = H \bar P_k H^\top + R$;
# * the update $K_k = \bar P_k H^\top S_k^{-1}$, $m_k = \bar m_k + K_k e_k$,
#   $P_k = \bar P_k - K_k S_k K_k^\top$.
#
# The filter is given below (`kalman_filter`); you write the checks of its consistency
# and the likelihood of its innovations with numpy. estim gives the model, the reference
# filter, the chi-square bounds and the maximum-likelihood fit the grader compares yours
# with.

# %%
import numpy as np
import scipy.optimize
import scipy.stats

import estim
from estim.grading import as_log
from estim.plotting import plot_errors

dt = 0.1
model = estim.models.constant_velocity(dt=dt)
A = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
H = np.eye(2, 4)
Q1 = np.block([[dt**3 / 3 * np.eye(2), dt**2 / 2 * np.eye(2)],
               [dt**2 / 2 * np.eye(2), dt * np.eye(2)]])  # the noise of q = 1
m0, P0 = np.array([0.0, 0.0, 1.0, -1.0]), np.eye(4)
q_true, r_true = 1.0, 0.25  # the simulation study of parts 1-4 (the book's car)
Q, R = q_true * Q1, r_true * np.eye(2)


def simulate(q, r, T, rng):
    """A record of T samples of the car: true states X (T, 4), measurements Y (T, 2);
    the first state drawn from the prior N(m0, P0)."""
    LQ, LP = np.linalg.cholesky(q * Q1), np.linalg.cholesky(P0)
    X, Y = np.empty((T, 4)), np.empty((T, 2))
    x = m0 + LP @ rng.normal(size=4)
    for k in range(T):
        if k:
            x = A @ x + LQ @ rng.normal(size=4)
        X[k], Y[k] = x, H @ x + np.sqrt(r) * rng.normal(size=2)
    return X, Y


def kalman_filter(Y, Q, R):
    """The Kalman filter of eqs. (1)-(2) with the covariances Q, R, from the prior
    (m0, P0) at the first sample. Returns the predicted means and covariances (before
    each measurement) and the updated ones (after it): (T, 4), (T, 4, 4), (T, 4), (T, 4, 4)."""
    T = len(Y)
    m_pred, P_pred = np.empty((T, 4)), np.empty((T, 4, 4))
    m_upd, P_upd = np.empty((T, 4)), np.empty((T, 4, 4))
    m, P = m0, P0
    for k, y in enumerate(Y):
        if k:
            m, P = A @ m, A @ P @ A.T + Q
        m_pred[k], P_pred[k] = m, P
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        m, P = m + K @ (y - H @ m), P - K @ S @ K.T
        m_upd[k], P_upd[k] = m, P
    return m_pred, P_pred, m_upd, P_upd


# the simulation study: M records of T samples with the true q and r
M, T = 20, 100
rng = np.random.default_rng(8)
runs = [simulate(q_true, r_true, T, rng) for _ in range(M)]
X_runs, Y_runs = np.array([X for X, _ in runs]), np.array([Y for _, Y in runs])
X_runs.shape, Y_runs.shape

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (3 points): innovations and NIS.** Write `innovations(Y, m_pred, P_pred, R)`,
# returning the innovations $e_k$ `(T, 2)` and their covariances $S_k$ `(T, 2, 2)` of
# eq. (2) from the filter's predictions, and `nis(E, S)`, returning the **normalised
# innovation squared** of every sample `(T,)`:
#
# (eq. 3) $\quad \epsilon^y_k = e_k^\top S_k^{-1} e_k .$
#
# If the filter's $Q$ and $R$ are the true ones, $e_k \sim N(0, S_k)$ and
# $\epsilon^y_k \sim \chi^2(n_y)$, with mean $n_y = 2$. (Solve with $S_k$ rather than
# inverting it; `np.linalg.solve` takes a stack of matrices.)

# %% [raw]
# # BEGIN SOLUTION

# %%
def innovations(Y, m_pred, P_pred, R):
    # BEGIN SOLUTION
    E = Y - m_pred @ H.T
    S = H @ P_pred @ H.T + R
    # END SOLUTION
    return E, S


def nis(E, S):
    # BEGIN SOLUTION
    return np.einsum("ki,ki->k", E, np.linalg.solve(S, E[..., None])[..., 0])
    # END SOLUTION


m_pred, P_pred, m_upd, P_upd = kalman_filter(Y_runs[0], Q, R)
E0, S0 = innovations(Y_runs[0], m_pred, P_pred, R)
nis(E0, S0).mean()

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: innovations must return E (T, 2) and S (T, 2, 2), nis a (T,) array (eqs. 2-3)
""" # END TEST CONFIG
mp_, Pp_, _, _ = kalman_filter(Y_runs[0], Q, R)
E_, S_ = innovations(Y_runs[0], mp_, Pp_, R)
assert np.shape(E_) == (T, 2) and np.shape(S_) == (T, 2, 2), (np.shape(E_), np.shape(S_))
assert np.shape(nis(E_, S_)) == (T,), np.shape(nis(E_, S_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the innovations are not estim's Kalman filter's
""" # END TEST CONFIG
from estim.grading import check_arrays

ref_ = estim.EKF(model, Q=Q, R=R, x0=m0, P0=P0).filter(Y_runs[1])
mp_, Pp_, _, _ = kalman_filter(Y_runs[1], Q, R)
E_, S_ = innovations(Y_runs[1], mp_, Pp_, R)
_ = check_arrays(E_, ref_.innovation, quantity="the innovations",
                 equation="eq. (2): e = y - H m̄ with the predicted mean m̄")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the NIS is not estim.nis
""" # END TEST CONFIG
from estim.grading import check_arrays

ekf_ = estim.EKF(model, Q=Q / 10, R=R, x0=m0, P0=P0)
mp_, Pp_, _, _ = kalman_filter(Y_runs[2], Q / 10, R)
_ = check_arrays(nis(*innovations(Y_runs[2], mp_, Pp_, R)),
                 estim.nis(estim.replay(ekf_, Y_runs[2])), quantity="the NIS",
                 equation="eq. (3): eᵀ S⁻¹ e, with S = H P̄ Hᵀ + R of eq. (2)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (2 points): NEES.** In a simulation you know the true states, and can ask the
# same of the estimate: write `nees(X, m, P)` returning the **normalised estimation
# error squared** `(T,)`
#
# (eq. 4) $\quad \epsilon^x_k = (x_k - m_k)^\top P_k^{-1} (x_k - m_k),$
#
# which is $\chi^2(n_x)$, mean $n_x = 4$, for a consistent filter.

# %% [raw]
# # BEGIN SOLUTION

# %%
def nees(X, m, P):
    # BEGIN SOLUTION
    e = X - m
    return np.einsum("ki,ki->k", e, np.linalg.solve(P, e[..., None])[..., 0])
    # END SOLUTION


nees(X_runs[0], m_upd, P_upd).mean()

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: nees must return a (T,) array of non-negative numbers (eq. 4)
""" # END TEST CONFIG
_, _, m_, P_ = kalman_filter(Y_runs[0], Q, R)
got_ = nees(X_runs[0], m_, P_)
assert np.shape(got_) == (T,), f"nees returned {got_!r}, of shape {np.shape(got_)}; expected ({T},)"
assert np.all(np.asarray(got_) >= 0), np.min(got_)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the NEES is not estim.nees
""" # END TEST CONFIG
from estim.grading import check_arrays

ref_ = estim.EKF(model, Q=Q / 10, R=R, x0=m0, P0=P0).filter(Y_runs[3])
_, _, m_, P_ = kalman_filter(Y_runs[3], Q / 10, R)
_ = check_arrays(nees(X_runs[3], m_, P_), estim.nees(ref_, truth=X_runs[3]),
                 quantity="the NEES", equation="eq. (4): (x - m)ᵀ P⁻¹ (x - m), the "
                 "updated mean and covariance")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (2 points): chi-square bounds.** One run's $\epsilon^x_k$ scatters too much to
# judge a filter by. Averaged over $n$ independent values, $n$ times the average is
# $\chi^2(d\, n)$ ($d$ the degrees of freedom of one value), so a consistent filter's
# average lies with probability $1 - \alpha$ in
#
# (eq. 5) $\quad \left[\ \tfrac1n\, \chi^2_{\alpha/2}(d\,n),\ \
#   \tfrac1n\, \chi^2_{1-\alpha/2}(d\,n)\ \right]$
#
# ($\chi^2_p(\nu)$ the $p$-quantile, `scipy.stats.chi2.ppf(p, nu)`; Bar-Shalom, Li &
# Kirubarajan, *Estimation with Applications to Tracking and Navigation*, 2001,
# sec. 5.4). Write `chi2_interval(dof, n, confidence=0.95)` returning `(lower, upper)`
# for $1 - \alpha$ = `confidence`.

# %% [raw]
# # BEGIN SOLUTION

# %%
def chi2_interval(dof, n, confidence=0.95):
    # BEGIN SOLUTION
    alpha = 1.0 - confidence
    lower = scipy.stats.chi2.ppf(alpha / 2, dof * n) / n
    upper = scipy.stats.chi2.ppf(1 - alpha / 2, dof * n) / n
    # END SOLUTION
    return lower, upper


chi2_interval(4, M)

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: chi2_interval(4, 20) must be a pair (lower, upper) around the mean 4 (eq. 5)
""" # END TEST CONFIG
lo_, hi_ = chi2_interval(4, 20)
assert lo_ < 4 < hi_, (lo_, hi_)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: chi2_interval is not estim.chi2_bounds
""" # END TEST CONFIG
from estim.grading import check_arrays

for dof_, n_, c_ in [(4, 20, 0.95), (2, 2000, 0.99), (1, 1, 0.9), (3, 7, 0.5)]:
    _ = check_arrays(np.ravel(chi2_interval(dof_, n_, c_)), estim.chi2_bounds(dof_, n_, c_),
                     quantity=f"chi2_interval({dof_}, {n_}, {c_})", index="bound",
                     equation="eq. (5): the α/2 and 1 - α/2 quantiles of χ²(dof · n), "
                     "divided by n")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q4

# %% [markdown]
# **Part 4 (3 points): a verdict over $M = 20$ runs.** Run `kalman_filter` on each of the
# $M$ simulated records (`X_runs[i]`, `Y_runs[i]`) and write `monte_carlo(Q, R)`,
# returning
#
# * (eq. 6) the NEES of each sample averaged over the runs,
#   $\bar\epsilon^x_k = \frac1M \sum_{i=1}^M \epsilon^x_{k,i}$ `(T,)`: with
#   eq. (5) for $d = n_x$, $n = M$, about 95 % of the samples should lie inside;
# * (eq. 7) the NIS averaged over the runs **and** the samples,
#   $\bar\epsilon^y = \frac{1}{MT} \sum_{i,k} \epsilon^y_{k,i}$ (a float). The
#   innovations of a consistent filter are independent in time, so
#   $MT\,\bar\epsilon^y \sim \chi^2(n_y M T)$ exactly: eq. (5) with $d = n_y$,
#   $n = MT$. (The errors $x_k - m_k$ are correlated in time, so no such exact law holds
#   for the NEES averaged over the samples.)
#
# Then write `verdict(value, lower, upper)`: `"overconfident"` above the interval (the
# covariance too small for the errors), `"pessimistic"` below it, `"consistent"` inside.
# Judge the filter tuned with the true $Q$ and the one with $Q/10$ by their average NIS
# with the 99 % interval (a consistent filter is then called inconsistent with
# probability 1 %): `verdict_true` and `verdict_low`.

# %% [raw]
# # BEGIN SOLUTION

# %%
def monte_carlo(Q, R):
    # BEGIN SOLUTION
    ne, ni = [], []
    for X, Y in zip(X_runs, Y_runs, strict=True):
        mp, Pp, m, P = kalman_filter(Y, Q, R)
        ne.append(nees(X, m, P))
        ni.append(nis(*innovations(Y, mp, Pp, R)))
    anees, anis = np.mean(ne, axis=0), float(np.mean(ni))
    # END SOLUTION
    return anees, anis


def verdict(value, lower, upper):
    # BEGIN SOLUTION
    return "overconfident" if value > upper else "pessimistic" if value < lower \
        else "consistent"
    # END SOLUTION


anees_true, anis_true = monte_carlo(Q, R)
anees_low, anis_low = monte_carlo(Q / 10, R)
# BEGIN SOLUTION
bounds = chi2_interval(2, M * T, 0.99)
verdict_true = verdict(anis_true, *bounds)
verdict_low = verdict(anis_low, *bounds)
# END SOLUTION
lo, hi = chi2_interval(4, M)
inside = [np.mean((a >= lo) & (a <= hi)) for a in (anees_true, anees_low)]
print(f"average NIS: true Q {anis_true:.3f} ({verdict_true}), Q/10 {anis_low:.3f} "
      f"({verdict_low}); samples with the average NEES inside [{lo:.2f}, {hi:.2f}]: "
      f"{inside[0]:.0%} and {inside[1]:.0%}")

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: each verdict must be "consistent", "overconfident" or "pessimistic"
""" # END TEST CONFIG
words_ = ("consistent", "overconfident", "pessimistic")
assert verdict_true in words_ and verdict_low in words_, (verdict_true, verdict_low)
assert np.shape(anees_true) == (T,) and np.ndim(anis_true) == 0, np.shape(anees_true)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the averages over the runs are not those of estim's filter
""" # END TEST CONFIG
from estim.grading import check_arrays

for Qf_, name_ in [(Q, "true Q"), (Q / 10, "Q/10")]:
    ne_, ni_ = [], []
    ekf_ = estim.EKF(model, Q=Qf_, R=R, x0=m0, P0=P0)
    for X_, Y_ in zip(X_runs, Y_runs, strict=True):
        res_ = ekf_.filter(Y_)
        ne_.append(estim.nees(res_, truth=X_))
        ni_.append(res_.nis)
    got_ = monte_carlo(Qf_, R)
    _ = check_arrays(got_[0], np.mean(ne_, axis=0), quantity=f"the average NEES ({name_})",
                     equation="eq. (6): the mean over the M runs at each sample")
    _ = check_arrays(got_[1], np.mean(ni_), quantity=f"the average NIS ({name_})",
                     equation="eq. (7): the mean over the runs and the samples")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the verdicts are not estim's
""" # END TEST CONFIG
from estim.grading import check_consistent

for args_, want_ in [((5.0, 1.0, 3.0), "overconfident"), ((0.5, 1.0, 3.0), "pessimistic"),
                     ((2.0, 1.0, 3.0), "consistent")]:
    assert verdict(*args_) == want_, f"verdict{args_} must be {want_!r}, got {verdict(*args_)!r}"
scenario_ = estim.Scenario("car", model, x0=m0, n_steps=T, Q=Q, R=R,
                           tuning={"Q": Q, "R": R, "x0": m0, "P0": P0})


def estims_verdict_(Qf_):
    """estim's NEES verdict on the filter with Qf_ (20 seeds, level 0.99)."""
    try:
        check_consistent(estim.EKF(model, Q=Qf_, R=R, x0=m0, P0=P0), scenario_)
    except AssertionError as exc_:
        return "overconfident" if "overconfident" in str(exc_) else "pessimistic"
    return "consistent"


for Qf_, got_, name_ in [(Q, verdict_true, "verdict_true"), (Q / 10, verdict_low,
                                                              "verdict_low")]:
    assert got_ == estims_verdict_(Qf_), (
        f"{name_} is {got_!r}, estim's NEES verdict is {estims_verdict_(Qf_)!r}: compare "
        f"the average NIS (eq. 7) with the 99 % interval of eq. (5) for d = 2, n = M T")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# The errors of the two filters on the first record, with their $\pm 2\sigma$ bands,
# drawn by estim: the filter told $Q/10$ believes its estimate far more than its errors
# allow (narrow bands the errors leave), and lags the car.

# %%
fits = {name: kalman_filter(Y_runs[0], Qf, R) for name, Qf in [("true Q", Q), ("Q / 10", Q / 10)]}
plot_errors({name: as_log(f[2], f[3], truth=X_runs[0], model=model, name=name)
             for name, f in fits.items()});

# %% [markdown]
# ## Tuning from a record
#
# Now a record of another car, whose $q$ and $r$ are drawn at random below: don't print
# them, find them. For a linear-Gaussian model the innovations are independent Gaussians
# $e_k \sim N(0, S_k)$, so the record's likelihood is the product of theirs (Schweppe
# 1965; Särkkä & Svensson 2023, the chapter on parameter estimation), and its negative
# logarithm is
#
# (eq. 8) $\quad \ell(q, r) = \tfrac12 \sum_{k=0}^{T-1} \left( \log\det S_k
#   + e_k^\top S_k^{-1} e_k + n_y \log 2\pi \right),$
#
# with $e_k, S_k$ those of the filter run with $Q = q\,Q_1$, $R = r\,I$. Its minimiser is
# the maximum-likelihood estimate $(\hat q, \hat r)$.

# %%
rng_field = np.random.default_rng(2025)
_q_field = float(np.exp(rng_field.uniform(np.log(0.2), np.log(5.0))))
_r_field = float(np.exp(rng_field.uniform(np.log(0.05), np.log(1.0))))
X_field, Y_field = simulate(_q_field, _r_field, 300, rng_field)
Y_field.shape

# %% [raw]
# # BEGIN QUESTION
# name: q5

# %% [markdown]
# **Part 5 (3 points).** Write `neg_log_likelihood(q, r, Y)`, $\ell(q, r)$ of eq. (8)
# on the record `Y` (use `kalman_filter` and your `innovations`; `np.linalg.slogdet`
# gives $\log\det$ of a stack of matrices).

# %% [raw]
# # BEGIN SOLUTION

# %%
def neg_log_likelihood(q, r, Y):
    # BEGIN SOLUTION
    Rq = r * np.eye(2)
    m_pred, P_pred, _, _ = kalman_filter(Y, q * Q1, Rq)
    E, S = innovations(Y, m_pred, P_pred, Rq)
    value = 0.5 * float(np.sum(np.linalg.slogdet(S)[1] + nis(E, S) + 2 * np.log(2 * np.pi)))
    # END SOLUTION
    return value


neg_log_likelihood(1.0, 0.25, Y_field)

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: neg_log_likelihood must return a finite number (eq. 8)
""" # END TEST CONFIG
val_ = neg_log_likelihood(1.0, 0.25, Y_field)
assert np.ndim(val_) == 0 and np.isfinite(val_), val_

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 2
failure_message: neg_log_likelihood is not -estim.tuning.log_likelihood
""" # END TEST CONFIG
from estim.grading import check_arrays
from estim.tuning import log_likelihood

points_ = [(1.0, 0.25), (0.3, 0.1), (3.0, 0.5), (0.05, 1.0)]
got_ = [neg_log_likelihood(q_, r_, Y_field) for q_, r_ in points_]
ref_ = [-log_likelihood(model, Y_field, Q=q_ * Q1, R=r_ * np.eye(2), x0=m0, P0=P0)
        for q_, r_ in points_]
_ = check_arrays(got_, ref_, quantity="ℓ(q, r) at (q, r) = " + ", ".join(map(str, points_)),
                 index="point", atol=1e-8, rtol=1e-12,
                 equation="eq. (8): ½ Σ (log det S + eᵀ S⁻¹ e + n_y log 2π) over every sample")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q6

# %% [markdown]
# **Part 6 (2 points).** Minimise $\ell$ with `scipy.optimize.minimize` to find
# $(\hat q, \hat r)$: `q_hat`, `r_hat`. Both must stay positive: optimise over
# $(\log q, \log r)$ (eq. 9: $q = e^{\theta_1}$, $r = e^{\theta_2}$), from, say,
# $q = 1$, $r = 0.25$.
#
# estim's `maximum_likelihood` maximises the same likelihood, with exact gradients and a
# Newton polish. It estimates a $Q$ of a structure (`"scalar"`: $Q = qI$), and ours,
# $q\,Q_1$, is $qI$ in the coordinates $z = L^{-1}x$ with $Q_1 = LL^\top$; the likelihood
# does not depend on the coordinates. The grader compares your estimates with it to 1 %:
# two optimisers of one function differ by their stopping rules only (far below 1 %),
# while the estimates' own standard errors are 6 % for $r$ and 16 % for $q$: a
# likelihood with a term missing lands well outside.

# %% [raw]
# # BEGIN SOLUTION

# %%
# BEGIN SOLUTION
fit = scipy.optimize.minimize(lambda th: neg_log_likelihood(np.exp(th[0]), np.exp(th[1]),
                                                            Y_field),
                              np.log([1.0, 0.25]), method="L-BFGS-B")
q_hat, r_hat = np.exp(fit.x)
# END SOLUTION
q_hat, r_hat

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: q_hat and r_hat must be positive and at least as likely as the start (1, 0.25)
""" # END TEST CONFIG
assert q_hat > 0 and r_hat > 0, (q_hat, r_hat)
assert (neg_log_likelihood(q_hat, r_hat, Y_field)
        <= neg_log_likelihood(1.0, 0.25, Y_field)), (q_hat, r_hat)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: (q_hat, r_hat) is not estim's maximum-likelihood estimate
""" # END TEST CONFIG
from estim.grading import check_arrays
from estim.tuning import maximum_likelihood

L_ = np.linalg.cholesky(Q1)
Li_ = np.linalg.inv(L_)
white_ = estim.Model(states=["z1", "z2", "z3", "z4"], outputs=["px", "py"],
                     dynamics=lambda z, u, p: (Li_ @ A @ L_) @ z,
                     output=lambda z, u, p: (H @ L_) @ z, dt=dt, name="car, z = L⁻¹x")
ml_ = maximum_likelihood(white_, Y_field, x0=Li_ @ m0, P0=Li_ @ P0 @ Li_.T,
                         structure="scalar", starts=1)
_ = check_arrays([q_hat, r_hat], [ml_.Q[0, 0], ml_.R[0, 0]], atol=0, rtol=0.01,
                 quantity="(q_hat, r_hat)", index="parameter (0: q, 1: r)",
                 equation="eq. (9): the minimiser of ℓ of eq. (8) over (log q, log r)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# The truth, and a second opinion: autocovariance least squares (`estim.tuning.als`, two
# passes) estimates $q$ and $r$ from the correlation in time of a filter's innovations
# instead of their likelihood, with $Q = q\,LL^\top$ given as its noise shape `G = L`.
# Both should lie within a few standard errors of the truth.

# %%
L = np.linalg.cholesky(Q1)
Li = np.linalg.inv(L)
white = estim.Model(states=["z1", "z2", "z3", "z4"], outputs=["px", "py"], dt=dt,
                    dynamics=lambda z, u, p: (Li @ A @ L) @ z,
                    output=lambda z, u, p: (H @ L) @ z, name="car, z = L⁻¹x")
ml = estim.tuning.maximum_likelihood(white, Y_field, x0=Li @ m0, P0=Li @ P0 @ Li.T,
                                     structure="scalar", starts=1)
als = estim.tuning.als(model, Y_field, x0=m0, P0=P0, structure="scalar", G=L, iterations=2)
print(f"truth: q = {_q_field:.3f}, r = {_r_field:.4f}")
print(f"yours: q = {q_hat:.3f}, r = {r_hat:.4f}")
print(f"ML:    q = {ml.Q[0, 0]:.3f} ± {ml.stderr['Q'][0, 0]:.3f}, "
      f"r = {ml.R[0, 0]:.4f} ± {ml.stderr['R'][0, 0]:.4f}")
print(f"ALS:   q = {als.Q[2, 2] / Q1[2, 2]:.3f} ± {als.stderr['Q'][2, 2] / Q1[2, 2]:.3f}, "
      f"r = {als.R[0, 0]:.4f} ± {als.stderr['R'][0, 0]:.4f}")
