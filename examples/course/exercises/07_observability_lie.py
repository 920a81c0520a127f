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
# # Exercise 7: observability by Lie derivatives
#
# Before estimating a state, ask whether the measurements can tell it apart from its
# neighbours at all. For a continuous model $\dot x = f(x)$, $y = h(x)$ the output's time
# derivatives are functions of the state alone, the **Lie derivatives** of $h$ along $f$:
#
# $$L_f \varphi(x) = \frac{\partial \varphi}{\partial x}(x)\, f(x), \tag{eq. 1}$$
#
# $$L_f^0 h = h, \qquad L_f^k h = L_f\big(L_f^{k-1} h\big), \qquad
#   y^{(k)}(t) = L_f^k h(x(t)). \tag{eq. 2}$$
#
# If two nearby states gave the same output over a short time, they would give the same
# $y, \dot y, \ddot y, \dots$; so the state is *locally weakly observable* where the
# **observability matrix**
#
# $$\mathcal O(x) = \frac{\partial}{\partial x}
#   \begin{bmatrix} h \\ L_f h \\ \vdots \\ L_f^K h \end{bmatrix}(x) \tag{eq. 3}$$
#
# has full rank $n_x$ (the rank condition of Hermann & Krener, IEEE TAC 1977). The rank is
# decided in floating point: each nonzero row is scaled to unit length (rows of norm at most
# $10^{-12}$ times the largest are dropped), and the rank is the number of singular values
# $s_i$ of the result with
#
# $$s_i > r_{tol}\, s_1, \qquad r_{tol} = 10^{-9}. \tag{eq. 4}$$
#
# Where the rank is lower, the null space of $\mathcal O$ holds the directions in which
# the state can move without changing the output: the continuous **symmetries**
# (Martinelli, INRIA RR-7049, 2010). With an orthonormal basis $N$ of the null space
# (one symmetry a row), a state $x_i$ is
#
# * **observable** when every symmetry has a zero component on it:
#   $\max_j |N_{ji}| < 10^{-6}$;
# * **unobservable** when it can move alone, its unit vector in the null space:
#   $\|N_{:,i}\| > 1 - 10^{-6}$;
# * **jointly observable** otherwise: it moves with other states along a symmetry, so
#   some combinations of them are observable but not the state itself. (eq. 5)
#
# First system: the pendulum of Särkkä & Svensson, *Bayesian Filtering and Smoothing*,
# 2nd ed., 2023, whose angle is measured through its sine (exercise 6's pendulum, in
# continuous time):
#
# $$\dot\theta = \omega, \quad \dot\omega = -\frac{g}{\ell} \sin\theta, \qquad
#   y = \sin\theta, \qquad g/\ell = 9.81.$$
#
# You compute the Lie derivatives with sympy and the rank and classification with numpy;
# the grader compares them with `estim.observability`, which differentiates the same
# models with CasADi.

# %%
import numpy as np
import sympy as sp

import estim
import estim.observability

model = estim.models.sine_pendulum()  # theta' = omega, omega' = -(g/l) sin(theta), y = sin(theta)
theta, omega = sp.symbols("theta omega")
x = sp.Matrix([theta, omega])
f = sp.Matrix([omega, -9.81 * sp.sin(theta)])
h = sp.sin(theta)
x, f, h

# %% [raw]
# # BEGIN QUESTION
# name: q1

# %% [markdown]
# **Part 1 (2 points): Lie derivatives.** Write `lie_derivative(phi, f, x)`, the sympy
# expression $L_f \varphi$ of eq. (1) for a scalar expression `phi`, a vector field `f`
# and the state symbols `x` (sympy column matrices), and `lie_derivatives(h, f, x, K)`,
# the list $[h, L_f h, \dots, L_f^K h]$ of eq. (2).

# %% [raw]
# # BEGIN SOLUTION

# %%
def lie_derivative(phi, f, x):
    # BEGIN SOLUTION
    Lf = sum(sp.diff(phi, xi) * fi for xi, fi in zip(x, f, strict=True))
    # END SOLUTION
    return Lf


def lie_derivatives(h, f, x, K):
    # BEGIN SOLUTION
    lies = [h]
    for _ in range(K):
        lies.append(lie_derivative(lies[-1], f, x))
    # END SOLUTION
    return lies


lies = lie_derivatives(h, f, x, 2)
[sp.simplify(L) for L in lies]

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: the pendulum's first Lie derivative is ω cos θ (eq. 1), and
  lie_derivatives(h, f, x, 2) is a list of three expressions (eq. 2)
""" # END TEST CONFIG
assert sp.simplify(lie_derivative(h, f, x) - omega * sp.cos(theta)) == 0, lie_derivative(h, f, x)
assert len(lie_derivatives(h, f, x, 2)) == 3, lie_derivatives(h, f, x, 2)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your Lie derivatives differ from estim's (CasADi's derivatives of the same models)
""" # END TEST CONFIG
import casadi as ca

from estim.grading import check_arrays


def estim_lies_(mdl, K, output):
    """[h, L_f h, ..., L_f^K h] of output `output` of mdl, differentiated by CasADi."""
    xs_ = ca.SX.sym("x", mdl.nx)
    p_, u_ = ca.DM(mdl.p), ca.DM.zeros(mdl.nu)
    fx_ = mdl.f_c(xs_, u_, p_)
    phi_ = mdl.H(xs_, u_, p_)[output]
    out_ = [phi_]
    for _k in range(K):
        phi_ = ca.jtimes(phi_, xs_, fx_)
        out_.append(phi_)
    return ca.Function("lies", [xs_], [ca.vertcat(*out_)])


def your_values_(exprs, symbols, points):
    if exprs is None or exprs is Ellipsis:
        raise AssertionError(f"lie_derivatives: not answered yet (got {exprs!r})")
    fun = sp.lambdify(list(symbols), list(exprs), "numpy")
    return np.array([np.asarray(fun(*pt), dtype=float) for pt in points])


rng_ = np.random.default_rng(11)
x1_, x2_, x3_ = sp.symbols("x1 x2 x3")
lorenz_ = (estim.models.lorenz(), sp.Matrix([x1_, x2_, x3_]),
           sp.Matrix([10 * (x2_ - x1_), x1_ * (28 - x3_) - x2_,
                      x1_ * x2_ - sp.Rational(8, 3) * x3_]),
           x3_**2 / 10 - x1_, 2)  # the third output of estim's Lorenz model
for mdl_, xs_, fs_, hs_, output_ in ((model, x, f, h, 0), lorenz_):
    pts_ = rng_.normal(scale=1.5, size=(6, mdl_.nx))
    ref_ = np.array([estim_lies_(mdl_, 2, output_)(pt).full().ravel() for pt in pts_])
    got_ = your_values_(lie_derivatives(hs_, fs_, xs_, 2), xs_, pts_)
    assert got_.shape == ref_.shape, (f"lie_derivatives(h, f, x, 2) of {mdl_.name} has "
                                      f"{got_.shape[1:]} values per point, expected 3")
    for k_ in range(3):
        _ = check_arrays(got_[:, k_], ref_[:, k_], index="random point",
                         quantity=f"L_f^{k_} h of the {mdl_.name} model",
                         equation="eq. (1): (∂φ/∂x) f, applied k times (eq. 2)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [raw]
# # BEGIN QUESTION
# name: q2

# %% [markdown]
# **Part 2 (3 points): the observability matrix and its rank.** Write
# `observability_matrix(lies, x)`, the sympy matrix of eq. (3) (one row per Lie
# derivative), and `numeric_rank(obs, rtol=1e-9)`, the rank of a numeric matrix by eq. (4)
# (rows scaled to unit length first). Then evaluate the pendulum's $\mathcal O$ (with
# $K = 2$) with `sp.lambdify` and give its rank at a random point, `rank_generic`, and at
# $\theta = \pi/2$, $\omega = 0$ (the top of a swing that reaches the horizontal, where
# $\sin\theta$ is flat), `rank_special`.

# %% [raw]
# # BEGIN SOLUTION

# %%
def observability_matrix(lies, x):
    # BEGIN SOLUTION
    obs = sp.Matrix(lies).jacobian(x)
    # END SOLUTION
    return obs


def numeric_rank(obs, rtol=1e-9):
    # BEGIN SOLUTION
    obs = np.asarray(obs, dtype=float)
    norms = np.linalg.norm(obs, axis=1)
    keep = norms > 1e-12 * norms.max()
    s = np.linalg.svd(obs[keep] / norms[keep, None], compute_uv=False)
    rank = int(np.sum(s > rtol * s[0]))
    # END SOLUTION
    return rank


O_pendulum = observability_matrix(lies, x)
O_at = sp.lambdify((theta, omega), O_pendulum, "numpy")
# BEGIN SOLUTION
rng = np.random.default_rng(0)
rank_generic = numeric_rank(O_at(*rng.normal(size=2)))
rank_special = numeric_rank(O_at(np.pi / 2, 0.0))
# END SOLUTION
O_pendulum, rank_generic, rank_special

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: observability_matrix([θ ω, sin θ], x) must be the 2 x 2 matrix
  [[ω, θ], [cos θ, 0]] (eq. 3), and rank_generic, rank_special integers
""" # END TEST CONFIG
O_ = sp.Matrix(observability_matrix([theta * omega, sp.sin(theta)], x))
assert O_.shape == (2, 2), O_.shape
assert sp.simplify(O_ - sp.Matrix([[omega, theta], [sp.cos(theta), 0]])) == sp.zeros(2, 2), O_
assert isinstance(rank_generic, int | np.integer) and isinstance(rank_special, int | np.integer)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your observability matrix differs from estim's
""" # END TEST CONFIG
import casadi as ca  # noqa: F811

from estim.grading import check_arrays
from estim.observability import lie

rows_, variables_ = lie.rows(model, 2, "constant", None)  # what estim.observability.analyze builds
O_ref_ = ca.Function("O", variables_, [ca.densify(ca.vertcat(*rows_))])
rng_ = np.random.default_rng(12)
lies_ = [sp.sin(theta), omega * sp.cos(theta),  # the pendulum's, eq. (2) with K = 2
         -omega**2 * sp.sin(theta) - 9.81 * sp.sin(theta) * sp.cos(theta)]
mine_ = sp.lambdify((theta, omega), sp.Matrix(observability_matrix(lies_, x)), "numpy")
for pt_ in rng_.normal(scale=1.5, size=(5, 2)):
    _ = check_arrays(np.asarray(mine_(*pt_), dtype=float), O_ref_(pt_, []).full(),
                     index="row (derivative order)",
                     quantity=f"the observability matrix at (θ, ω) = {np.round(pt_, 3)}",
                     equation="eq. (3): row k is the gradient ∂(L_f^k h)/∂x")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your ranks are not estim's
""" # END TEST CONFIG
from estim.observability import analyze, lie

rng_ = np.random.default_rng(13)
mats_ = {"a random 3 x 3 matrix": rng_.normal(size=(3, 3)),
         "a rank-2 matrix of 4 x 3": rng_.normal(size=(4, 2)) @ rng_.normal(size=(2, 3)),
         "rows of very different scales": np.array([[1.0, 1.0], [1e-10, 0.0]]),
         "a matrix with a zero row": np.array([[0.0, 0.0], [1.0, 2.0], [2.0, 4.0]])}
for label_, M_ in mats_.items():
    got_, ref_ = numeric_rank(M_), lie.numeric_rank(M_, 1e-9)[0]
    assert got_ == ref_, (f"numeric_rank of {label_} is {got_}, estim's is {ref_}: look at "
                          f"eq. (4) (rows scaled to unit length, zero rows dropped)")
generic_ = analyze(model, order=2).rank
special_ = analyze(model, order=2, at=[np.pi / 2, 0.0], n_points=1).ranks[0]
assert rank_generic == generic_, (f"rank_generic is {rank_generic}; estim.observability."
                                  f"analyze finds rank {generic_} at random points. It is "
                                  f"the rank (eq. 4) of O_pendulum (eq. 3), made from "
                                  f"your Lie derivatives of part 1")
assert rank_special == special_, (f"rank_special is {rank_special}; estim.observability."
                                  f"analyze finds rank {special_} at θ = π/2, ω = 0. It is "
                                  f"the rank (eq. 4) of O_pendulum (eq. 3), made from "
                                  f"your Lie derivatives of part 1")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION

# %% [markdown]
# Where is the pendulum hard to observe? The ratio $s_2 / s_1$ of the singular values of
# $\mathcal O$ (rows normalised: the inverse of its condition number) over the
# $(\theta, \omega)$ plane, drawn by `estim.observability.conditioning`: it vanishes at
# $\theta = \pm\pi/2$, $\omega = 0$, the point of `rank_special`, and is small around
# it, where $\sin\theta$ is flat and the swing almost stopped. The rank test says only
# *whether* the state is determined at a point; how well, the conditioning says.

# %%
grid = {"theta": np.linspace(-np.pi, np.pi, 121), "omega": np.linspace(-4, 4, 81)}
estim.observability.conditioning(estim.models.sine_pendulum(), grid, order=2).plot();

# %% [raw]
# # BEGIN QUESTION
# name: q3

# %% [markdown]
# **Part 3 (3 points): which states are observable?** A robot moves in the plane at speed
# $v$ and turn rate $\omega$ (known inputs) and measures the bearing $\beta$ of a landmark
# (Martinelli 2010; `estim.models.martinelli_simple()`): its distance $D$ to the
# landmark, the landmark's direction $\varphi_R$ and its heading $\theta_R$,
#
# $$\dot D = v \cos(\theta_R - \varphi_R), \quad
#   \dot\varphi_R = \frac{v}{D} \sin(\theta_R - \varphi_R), \quad
#   \dot\theta_R = \omega, \qquad \beta = \pi - \theta_R + \varphi_R.$$
#
# Write `classify(obs, names, tol=1e-6)`: from a numeric observability matrix, the dictionary
# `{state name: "observable" | "jointly observable" | "unobservable"}` of eq. (5), with
# the rank of eq. (4) and the null space from the SVD of the row-scaled matrix. Then
# build the robot's $\mathcal O$ with $K = 2$ and the inputs held constant (symbols, so
# the Lie derivatives of eq. 2 apply unchanged), evaluate it at a random state and
# random inputs, and give `verdict = classify(...)` and `symmetry`, the null-space vector
# scaled so that its entry of largest magnitude is $+1$.

# %% [raw]
# # BEGIN SOLUTION

# %%
def classify(obs, names, tol=1e-6):
    # BEGIN SOLUTION
    obs = np.asarray(obs, dtype=float)
    norms = np.linalg.norm(obs, axis=1)
    A = obs[norms > 1e-12 * norms.max()]
    A = A / np.linalg.norm(A, axis=1, keepdims=True)
    N = np.linalg.svd(A)[2][numeric_rank(obs):]  # an orthonormal basis of the null space
    verdict = {}
    for i, name in enumerate(names):
        if len(N) == 0 or np.max(np.abs(N[:, i])) < tol:
            verdict[name] = "observable"
        elif np.linalg.norm(N[:, i]) > 1 - tol:
            verdict[name] = "unobservable"
        else:
            verdict[name] = "jointly observable"
    # END SOLUTION
    return verdict


D, phi_R, theta_R, v, w = sp.symbols("D phi_R theta_R v w")
x_robot = sp.Matrix([D, phi_R, theta_R])
f_robot = sp.Matrix([v * sp.cos(theta_R - phi_R), v * sp.sin(theta_R - phi_R) / D, w])
h_robot = sp.pi - theta_R + phi_R
# BEGIN SOLUTION
O_robot = observability_matrix(lie_derivatives(h_robot, f_robot, x_robot, 2), x_robot)
rng = np.random.default_rng(1)
values = dict(zip([D, phi_R, theta_R, v, w], [1.5, *rng.normal(size=4)], strict=True))
O_num = np.array(O_robot.subs(values), dtype=float)
verdict = classify(O_num, ["D", "phi_R", "theta_R"])
null = np.linalg.svd(O_num / np.linalg.norm(O_num, axis=1, keepdims=True))[2][-1]
symmetry = null / null[np.argmax(np.abs(null))]
# END SOLUTION
verdict, symmetry

# %% [raw]
# # END SOLUTION

# %% [raw]
# # BEGIN TESTS

# %%
""" # BEGIN TEST CONFIG
points: 1
failure_message: verdict must give each of D, phi_R, theta_R one of "observable",
  "jointly observable", "unobservable" (eq. 5), and symmetry three numbers
""" # END TEST CONFIG
assert isinstance(verdict, dict) and set(verdict) == {"D", "phi_R", "theta_R"}, verdict
assert set(verdict.values()) <= {"observable", "jointly observable", "unobservable"}, verdict
assert np.shape(symmetry) == (3,), np.shape(symmetry)

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: your verdict on the robot is not estim.observability.analyze's
""" # END TEST CONFIG
from estim.grading import check_arrays
from estim.observability import analyze


def status_(report, name):
    """The class of state `name` in an estim.observability.analyze report."""
    if name in report.observable:
        return "observable"
    return "unobservable" if name in report.unobservable else "jointly observable"


robot_ = estim.models.martinelli_simple()
report_ = analyze(robot_)
for name_ in robot_.state_names:
    ref_ = status_(report_, name_)
    assert verdict.get(name_) == ref_, (
        f"the state {name_} is {verdict.get(name_)!r} in your verdict; estim.observability."
        f"analyze finds it {ref_!r} (rank {report_.rank} of {report_.n}, symmetry "
        f"{report_.symmetries.round(3).tolist()} over {robot_.state_names}). Look at eq. (5)")
_ = check_arrays(symmetry, report_.symmetries[0], quantity="the symmetry",
                 equation="the null space of O (eq. 5), scaled so its largest entry is +1")

# %%
""" # BEGIN TEST CONFIG
hidden: true
points: 1
failure_message: classify disagrees with estim.observability.analyze on other models
""" # END TEST CONFIG
import casadi as ca  # noqa: F811

from estim.observability import analyze, lie


def status_(report, name):
    """The class of state `name` in an estim.observability.analyze report."""
    if name in report.observable:
        return "observable"
    return "unobservable" if name in report.unobservable else "jointly observable"


def estim_matrix_(mdl, order, seed):
    """The observability matrix analyze builds: rows stacked over random inputs."""
    rows_, variables_ = lie.rows(mdl, order, "varying", None)
    O_fun_ = ca.Function("O", variables_, [ca.densify(ca.vertcat(*rows_))])
    rng_ = np.random.default_rng(seed)
    pt_ = lie.points(mdl, variables_, 1, None, rng_)[0]
    draws_ = lie.input_samples(pt_, variables_, "varying", None, 2 * mdl.nx, rng_)
    return np.vstack([O_fun_(*q).full() for q in draws_])


bias_ = estim.Model(states=["p", "v", "b"], outputs=["y"], dt=0.1, name="bias_not_measured",
                    ode=lambda x, u, p: ca.vertcat(x[1], -x[0], 0), output=lambda x, u, p: x[0])
for mdl_ in (estim.models.odometry_circular(), model.augment("g", "length"), bias_):
    report_ = analyze(mdl_)
    mine_ = classify(estim_matrix_(mdl_, report_.order, 5), list(mdl_.state_names))
    for name_ in mdl_.state_names:
        ref_ = status_(report_, name_)
        assert isinstance(mine_, dict) and mine_.get(name_) == ref_, (
            f"{mdl_.name}: the state {name_} is "
            f"{mine_.get(name_) if isinstance(mine_, dict) else mine_!r} in classify's "
            f"answer; estim.observability.analyze finds it {ref_!r} (rank {report_.rank} of "
            f"{report_.n}, symmetries {report_.symmetries.round(3).tolist()} over "
            f"{list(mdl_.state_names)}). Look at eq. (5)")

# %% [raw]
# # END TESTS

# %% [raw]
# # END QUESTION
