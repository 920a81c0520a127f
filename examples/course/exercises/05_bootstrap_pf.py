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
# files: [book_pendulum_pf.npz]

# %% [markdown]
# # Exercise 5: a bootstrap particle filter
#
# A pendulum swings from an angle of 1.5 rad; its angle $\theta$ is seen only through its
# sine, measured every $\Delta t = 0.01$ s with noise of variance $R = 0.1$ (Särkkä &
# Svensson, *Bayesian Filtering and Smoothing*, 2nd ed., 2023, example 5.1 and the
# particle filters of chapter 11). The state is $x = (\theta, \omega)$ and, with Euler
# steps,
#
# $$x_k = f(x_{k-1}) + q_{k-1}, \quad
#   f(\theta, \omega) = (\theta + \Delta t\, \omega,\ \omega - g \sin\theta\, \Delta t),
#   \quad q_{k-1} \sim N(0, Q), \qquad
#   y_k = \sin\theta_k + r_k, \quad r_k \sim N(0, R),  \qquad \text{(eq. 1)}$$
#
# $g = 9.81$ and $Q = 0.01 \begin{bmatrix} \Delta t^3/3 & \Delta t^2/2 \\
# \Delta t^2/2 & \Delta t \end{bmatrix}$. A particle filter carries $N$ samples
# ("particles") $x^i_k$ of the state. The bootstrap filter, with resampling at every
# step, does at each sample $k$:
#
# * **propagate** (eq. 2): $x^i_k = f(x^i_{k-1}) + q^i$, with $q^i \sim N(0, Q)$ drawn
#   for each particle;
# * **weigh** by the measurement: the log-likelihood (eq. 3)
#   $\ell^i = -(y_k - \sin\theta^i_k)^2 / (2R)$ (constants dropped: they cancel), then the
#   normalised weights (eq. 4) $W^i = e^{\ell^i - \ell^*} / \sum_j e^{\ell^j - \ell^*}$
#   with $\ell^* = \max_j \ell^j$. Subtracting $\ell^*$ changes nothing mathematically,
#   but without it $e^{\ell^i}$ underflows to 0 for every particle when the measurement
#   is far from all of them, and $0/0$ is NaN;
# * **estimate** (eq. 5): $\hat x_k = \sum_i W^i x^i_k$;
# * **resample** (eq. 6), systematically: with the cumulative weights
#   $C_i = W^1 + \dots + W^i$ and one uniform draw $u \in [0, 1)$, the $N$ points
#   $u_j = (j + u)/N$, $j = 0, \dots, N-1$; the new particle $j$ is a copy of the
#   particle $i$ with $C_{i-1} \le u_j < C_i$. A particle of weight $W^i$ is copied about
#   $N W^i$ times, and one of weight zero never.
#
# You write these with numpy. estim gives the model, the book's record and the reference
# filter the grader compares yours with.

# %%
import numpy as np

from estim.plotting import plot_particles

dt, g = 0.01, 9.81
Q = 0.01 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
LQ = np.linalg.cholesky(Q)  # q = LQ @ (standard normal) has covariance Q
R = 0.1
m0, P0 = np.array([1.6, 0.0]), 0.1 * np.eye(2)  # the prior, one step before y[0]


def f(X):
    """The Euler step of eq. (1) for every particle: X (N, 2) -> (N, 2)."""
    theta, omega = X[:, 0], X[:, 1]
    return np.column_stack([theta + dt * omega, omega - g * np.sin(theta) * dt])


data = np.load("book_pendulum_pf.npz")
Y, X = data["Y"], data["X"]  # (500,) measurements, (500, 2) true states
Y.shape, X.shape

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (2 points).** Write `systematic_resample(W, u)`: from the normalised weights
# `W` `(N,)` and the uniform draw `u`, the indices `(N,)` of the particles to copy
# (eq. 6). `np.cumsum` gives the $C_i$ (set the last to exactly 1: rounding may leave it
# just below) and `np.searchsorted(C, points, side="right")` finds, for each point, the
# $i$ with $C_{i-1} \le u_j < C_i$.

# %% [raw]
# # BEGIN SOLUTION

# %%
def systematic_resample(W, u):
    # BEGIN SOLUTION
    N = len(W)
    C = np.cumsum(W)
    C[-1] = 1.0
    indices = np.searchsorted(C, (np.arange(N) + u) / N, side="right")
    # END SOLUTION
    return indices

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: systematic_resample must return N indices, all 3 if particle 3 has all the weight
""" # END TEST CONFIG
W_ = np.zeros(8)
W_[3] = 1.0
i_ = systematic_resample(W_, 0.5)
assert np.shape(i_) == (8,) and np.all(np.asarray(i_) == 3), i_

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: the resampled indices are not those of systematic resampling
""" # END TEST CONFIG
from types import SimpleNamespace

from estim.grading import check_arrays
from estim.solvers.sampling.resampling import resample

rng_ = np.random.default_rng(5)
for N_, u_ in [(10, 0.0), (10, 0.999), (500, 0.37), (1000, 0.5), (1000, 0.0)]:
    W_ = rng_.dirichlet(np.full(N_, 0.3))
    W_[::7] = 0.0  # particle 0 among others of weight zero: never copied
    W_ /= W_.sum()
    uniform_ = SimpleNamespace(random=lambda *args, u=u_, **kwargs: u)  # draws u
    _ = check_arrays(systematic_resample(W_, u_), resample(W_, "systematic", uniform_),
                     quantity=f"the array of indices (N = {N_}, u = {u_})",
                     equation="eq. (6): the point j = 0..N-1 is u_j = (j + u)/N and picks "
                              "the i with C[i-1] <= u_j < C[i] (searchsorted, side='right')",
                     index="point")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (3 points).** Write `weigh(X, y, R)`: the normalised weights `(N,)` of the
# particles `X` `(N, 2)` given the measurement `y` (a number), by eqs. (3)–(4), in log
# space.

# %% [raw]
# # BEGIN SOLUTION

# %%
def weigh(X, y, R):
    # BEGIN SOLUTION
    logw = -0.5 * (y - np.sin(X[:, 0])) ** 2 / R
    w = np.exp(logw - logw.max())
    W = w / w.sum()
    # END SOLUTION
    return W

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: weigh must return N weights that sum to one
""" # END TEST CONFIG
X_ = m0 + np.random.default_rng(1).standard_normal((100, 2)) @ np.linalg.cholesky(P0).T
W_ = weigh(X_, Y[0], R)
assert np.shape(W_) == (100,) and abs(np.sum(W_) - 1) < 1e-12, (np.shape(W_), np.sum(W_))

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your weights are not estim's particle filter's
""" # END TEST CONFIG
import estim
from estim.grading import check_arrays

model_ = estim.models.sine_pendulum(dt=dt, integrator="euler")
pf_ = estim.ParticleFilter(model_, Q=Q, R=R, x0=m0, P0=P0, n_particles=500,
                           ess_threshold=1e-9)  # (no resampling: the weights are kept)
_ = pf_.step([Y[0]])  # its prior's particles, weighed by the first measurement
X_, W_ = pf_.particles
_ = check_arrays(weigh(X_, Y[0], R), W_, quantity="the vector of weights",
                 equation="eq. (3): the log-likelihood -(y - sin θ)² / (2R), normalised "
                          "by eq. (4)", atol=1e-12, index="particle")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your weights fail on an outlier, a measurement far from every particle
""" # END TEST CONFIG
from estim.grading import check_arrays

X_ = m0 + np.random.default_rng(2).standard_normal((500, 2)) @ np.linalg.cholesky(P0).T
with np.errstate(all="ignore"):
    W_ = np.asarray(weigh(X_, 3.0, 1e-3), dtype=float)  # y = 3 with R = 0.001
assert np.isfinite(W_).all(), ("the weights of the measurement y = 3 with R = 0.001 are "
                               "not finite (every e^ℓ underflows to 0): subtract the "
                               "largest ℓ before exponentiating, eq. (4)")
ell_ = -(3.0 - np.sin(X_[:, 0])) ** 2 / (2 * 1e-3)
ref_ = np.exp(ell_ - ell_.max()) / np.exp(ell_ - ell_.max()).sum()
_ = check_arrays(W_, ref_, quantity="the vector of weights for an outlier (y = 3, R = 0.001)",
                 equation="eqs. (3)-(4)", atol=1e-12, index="particle")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (3 points).** Write `pf_step(X, y, rng)`: one step of the filter from the
# equally weighted particles `X` `(N, 2)` of the previous sample: propagate (eq. 2, with
# `rng.standard_normal` and `LQ`), weigh (your `weigh`), estimate (eq. 5) and resample
# (your `systematic_resample` with `u = rng.random()`). Return the estimate `(2,)` and
# the resampled particles `(N, 2)`. Then `particle_filter(Y, N, rng)`: draw $N$ particles
# from the prior $N(m_0, P_0)$, one step *before* the first measurement, and run
# `pf_step` at every sample; return the estimates `(T, 2)` and the resampled particles
# `(T, N, 2)` of every sample.
#
# The grader tests your filter in two ways, both by chance (a particle filter is
# random):
#
# * The book's one run of its bootstrap filter with 1000 particles has an angle RMSE of
#   **0.0799** on this record; 20 runs of yours (seeds 0 to 19) must put it within 3
#   standard deviations of their mean RMSE. A correct filter fails this for about 0.1 %
#   of sets of 20 seeds (the book's run is in the lower tail of the RMSE's spread: about
#   the 4th percentile).
# * Paired over 20 simulated records of 100 measurements (released from 0.5 rad, the
#   prior $(0.6, 0)$, 1000 particles), your filter's RMSE against estim's bootstrap
#   filter with systematic resampling: it must be shown equivalent within 15 % of the
#   reference's median RMSE (two one-sided Wilcoxon tests at confidence 0.95: a filter
#   15 % worse passes with probability at most 5 %). A correct filter fails it for
#   about 0.5 % of sets of seeds (with stratified resampling: about 1 %).

# %% [raw]
# # BEGIN SOLUTION

# %%
def pf_step(X, y, rng):
    # BEGIN SOLUTION
    X = f(X) + rng.standard_normal(X.shape) @ LQ.T
    W = weigh(X, y, R)
    x_hat = W @ X
    X_new = X[systematic_resample(W, rng.random())]
    # END SOLUTION
    return x_hat, X_new


def particle_filter(Y, N, rng):
    # BEGIN SOLUTION
    X = m0 + rng.standard_normal((N, 2)) @ np.linalg.cholesky(P0).T
    means, clouds = [], []
    for y in Y:
        x_hat, X = pf_step(X, y, rng)
        means.append(x_hat)
        clouds.append(X)
    # END SOLUTION
    return np.array(means), np.array(clouds)


means, clouds = particle_filter(Y, 1000, np.random.default_rng(0))
rmse = np.sqrt(np.mean((means[:, 0] - X[:, 0]) ** 2))
rmse

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the book's RMSE 0.0799 is not within 3 sd of the mean RMSE of 20 runs of yours
""" # END TEST CONFIG
rmses_ = []
for seed_ in range(20):
    means_, _ = particle_filter(Y, 1000, np.random.default_rng(seed_))
    rmses_.append(np.sqrt(np.mean((np.asarray(means_)[:, 0] - X[:, 0]) ** 2)))
mean_, sd_ = np.mean(rmses_), np.std(rmses_, ddof=1)
assert abs(0.07992204807089615 - mean_) < 3 * sd_, (
    f"the book's 0.0799 against your 20 runs' mean RMSE {mean_:.4g}, sd {sd_:.3g}")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 2
failure_message: your filter is less accurate than estim's bootstrap filter (check eqs. 2-6)
""" # END TEST CONFIG
import estim
from estim.adapters import from_function
from estim.grading import check_over_seeds

prior_ = np.array([0.6, 0.0])
tuning_ = {"Q": Q, "R": R, "x0": prior_, "P0": P0}
scenario_ = estim.scenarios.book_pendulum(n_steps=101).replace(
    x0=np.array([0.5, 0.0]), tuning=tuning_,
    sampling={"sin_theta": (1, 1)})  # sample 0 unmeasured: the prior one step before y[0]
N_ = 1000
seeds_ = {"yours": iter(range(10**6, 2 * 10**6)), "estim": iter(range(2 * 10**6, 3 * 10**6))}
held_ = {}
_ = pf_step(prior_ + np.zeros((N_, 2)), 0.5, np.random.default_rng(0))  # it runs
def reset_yours_():
    rng = np.random.default_rng(next(seeds_["yours"]))  # a new seed for every run
    held_.update(rng=rng, X=prior_ + rng.standard_normal((N_, 2)) @ np.linalg.cholesky(P0).T)
def step_yours_(y, u):
    if np.isnan(y).all():  # sample 0: the prior
        return held_["X"].mean(axis=0)
    x_hat, held_["X"] = pf_step(held_["X"], float(y[0]), held_["rng"])
    return np.asarray(x_hat, dtype=float)
pf_ = estim.ParticleFilter(scenario_.model, **tuning_, n_particles=N_,
                           resampling="systematic", ess_threshold=1.0)
def reset_estim_():
    pf_.seed = next(seeds_["estim"])  # estim's filter too: new random numbers every run
    pf_.reset()
yours_ = from_function(step_yours_, scenario_.model, name="your filter", reset=reset_yours_)
reference_ = from_function(lambda y, u: pf_.step(y, u), scenario_.model,
                           name="estim's filter", reset=reset_estim_)
_ = check_over_seeds(yours_, reference_, scenario_, seeds=range(20), tolerance=0.15,
                     confidence=0.95)

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# The particles of your filter's run over time, drawn by estim: the angle's cloud (a
# random 200 of the 1000 particles at each sample), its mean and the truth. At the start
# the cloud is as wide as the prior; near $\theta = \pm\pi/2$ the sine is flat and the
# measurements say little, so the cloud widens there again.

# %%
plot_particles(clouds, t=data["T"], truth=X, state=0, name="θ");
