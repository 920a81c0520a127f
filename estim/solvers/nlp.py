r"""The windowed least-squares estimation NLP shared by MHE and full-information estimation.

Decision variables are the states of ``N`` slots, :math:`X = (x_0, \dots, x_{N-1})`.
The residual vector is

.. math::
    r(X) = \begin{bmatrix}
      a_j W_0 (x_j - \bar x), \; j = 0..N-1 \\
      \omega_j W_Q (x_{j+1} - F(x_j, u_j)) + (1 - \omega_j)(x_{j+1} - x_j),
          \; j = 0..N-2 \\
      W_{y,j} (y_j - h(x_j, u^-_j)), \; j = 0..N-1
    \end{bmatrix}

and the cost :math:`\|r\|^2`. Only the last ``n`` slots hold data
(:math:`s_0 = N - n`): for them :math:`\omega_j = 1`; the unused slots before
them are chained to :math:`x_{s_0}` at no cost (:math:`\omega_j = 0`), so the
optimum of the full-length problem is exactly that of the ``n``-slot problem.
The arrival weight acts on :math:`x_{s_0}` (selected by the one-hot
parameter :math:`a`, one residual block per slot so the Hessian stays
banded); measurement weights :math:`W_{y,j}` carry zero rows for missing
outputs. One NLP thus serves every window length, built once.
"""

from __future__ import annotations

import re
import time
from collections.abc import Mapping
from dataclasses import dataclass
from statistics import NormalDist

import casadi as ca
import numpy as np

from estim._fast import FastFunction
from estim._validate import as_bool, as_choice, as_float, as_int, unknown_keywords_message
from estim.consistency import SUSPECT_TAIL, chi2_limit, consistency_status
from estim.model import Model
from estim.solvers.gauss_newton import StructuredGaussNewton, full_record_constants
from estim.solvers.robust import RobustLoss

SOLVERS = ("gauss-newton", "ipopt", "sqp", "fatrop")
#: What the estimators' ``solver=`` accepts: a solver by name, or ``"auto"``.
SOLVER_CHOICES = ("auto", *SOLVERS)

#: A robust fit's reweighted solves stop when no weight moves by more than
#: ``IRLS_WTOL`` between two of them, or after ``IRLS_MAX`` solves.
IRLS_WTOL = 1e-6
IRLS_MAX = 100
#: A whitened measurement component beyond this many standard deviations is an
#: outlier for a robust loss: a Gaussian one goes beyond it with the probability
#: ``SUSPECT_TAIL`` of the consistency test (6.1 at 1e-9): the square root of the
#: chi-square(1) quantile, which is the normal one.
OUTLIER_SIGMA = -NormalDist().inv_cdf(SUSPECT_TAIL / 2)

_IPOPT_DEFAULTS = {
    "ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False,
    "ipopt.tol": 1e-10, "ipopt.acceptable_tol": 1e-7, "ipopt.max_iter": 200,
    "ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-4,
    "ipopt.warm_start_bound_push": 1e-9, "ipopt.warm_start_mult_bound_push": 1e-9,
    "show_eval_warnings": False,
}
_SQP_DEFAULTS = {
    "qpsol": "qrqp",
    "qpsol_options": {"print_iter": False, "print_header": False, "print_info": False,
                      "error_on_fail": False},
    "print_header": False, "print_iteration": False, "print_status": False,
    "print_time": False, "max_iter": 100, "tol_pr": 1e-9, "tol_du": 1e-9,
    "min_step_size": 1e-12, "error_on_fail": False, "show_eval_warnings": False,
}
_FATROP_DEFAULTS = {
    "print_time": False, "structure_detection": "auto", "expand": True,
    "fatrop.print_level": 0, "fatrop.tol": 1e-10, "fatrop.max_iter": 200,
    "error_on_fail": False, "show_eval_warnings": False,
}


#: The options of the Gauss-Newton solver and their checks.
_GN_OPTIONS = {
    "max_iter": lambda v, n: as_int(v, n, minimum=1),
    "xtol": lambda v, n: as_float(v, n, positive=True),
    "newton": as_bool,
    "jit": as_bool,
    "mode": lambda v, n: as_choice(v, ("auto", "unrolled", "mapped"), n),
}
_PLUGINS = {"ipopt": "ipopt", "sqp": "sqpmethod", "fatrop": "fatrop"}
_CASADI_TYPES = {"double": "a number", "int": "an integer", "string": "a string",
                 "bool": "a bool", "dict": "a dict"}


def _casadi_reason(exc: Exception) -> str:
    """The useful part of a CasADi error message (source locations and banners removed)."""
    lines = []
    for line in str(exc).splitlines():
        line = re.sub(r"^\S*\.(?:cpp|hpp):\d+:\s*", "", line.strip())
        if not line or line.startswith(("Error calling", "Error in Function::call", ">",
                                        "Did you mean", "Use print_options")):
            continue
        lines.append(line)
    text = " ".join(lines[:2]) or str(exc).strip()
    text = re.sub(r'Assertion "is_(\w+)\(\)" failed:\s*type mismatch',
                  lambda m: f"type mismatch (expected {_CASADI_TYPES.get(m[1], m[1])})", text)
    return re.sub(r'Assertion "[^"]*" failed:\s*', "", text)


def _dry_run(solver: str, options: dict) -> None:
    """Build (and for fatrop, which reads its options late, solve) a one-variable problem
    with ``options`` merged over the defaults; CasADi's exceptions pass through."""
    x, w, z = ca.SX.sym("x"), ca.SX.sym("w"), ca.SX.sym("z")
    if solver == "fatrop":
        opts = _merge(_FATROP_DEFAULTS, options)
        opts.setdefault("equality", [True])
        opts["fatrop.print_level"] = 0
        nlp = {"x": ca.vertcat(x, w, z), "f": x**2 + w**2 + z**2, "g": z - x - w}
        ca.nlpsol("options_check", "fatrop", nlp, opts)(x0=0, lbg=0, ubg=0)
        return
    defaults = _IPOPT_DEFAULTS if solver == "ipopt" else _SQP_DEFAULTS
    ca.nlpsol("options_check", _PLUGINS[solver], {"x": x, "f": x**2},
              _merge(defaults, options))


def resolve_solver(solver, options) -> str:
    """The solver ``solver=`` names; ``"auto"`` is the fastest one for the problem.

    Moving horizon and full-information estimation pose nonlinear least-squares
    problems with box bounds, which the structured Gauss-Newton solver
    (:mod:`estim.solvers.gauss_newton`) solves to the same optimum as Ipopt
    in a fraction of the time (van der Pol MHE, N = 15: 0.26 against 2.3 ms per
    step), so ``"auto"`` is ``"gauss-newton"``. Options of another solver with
    ``"auto"`` are an error that says which solver to name.
    """
    solver = as_choice(solver, SOLVER_CHOICES, "solver")
    if solver != "auto":
        return solver
    if isinstance(options, Mapping):
        foreign = sorted(k for k in options if isinstance(k, str) and k not in _GN_OPTIONS)
        if foreign:
            raise ValueError(f"solver='auto' is the Gauss-Newton solver, and solver_options "
                             f"{foreign} are not its options: name the solver they belong "
                             f"to, e.g. solver='ipopt'")
    return "gauss-newton"


def check_solver_options(solver: str, options) -> dict:
    """Check ``solver_options`` for ``solver`` before anything is built; return a copy.

    Gauss-Newton's options are checked by name and type; the CasADi solvers'
    (``"ipopt"``, ``"sqp"``, ``"fatrop"``) by CasADi itself on a one-variable
    problem, its refusal turned into a ``ValueError`` naming the option.
    """
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise TypeError(f"solver_options must be a dict, got {type(options).__name__}")
    options = dict(options)
    for key in options:
        if not isinstance(key, str):
            raise TypeError(f"solver_options keys must be strings, got {key!r}")
    if solver == "gauss-newton":
        unknown = [k for k in options if k not in _GN_OPTIONS]
        if unknown:
            raise ValueError(unknown_keywords_message(
                "solver_options for solver 'gauss-newton'", unknown, list(_GN_OPTIONS)))
        return {k: _GN_OPTIONS[k](v, f"solver_options[{k!r}]") for k, v in options.items()}
    only_gn = sorted(set(options) & {"xtol", "newton", "mode"})
    if only_gn:
        raise ValueError(f"solver_options {only_gn} apply to solver='gauss-newton' only "
                         f"(solver is {solver!r})")
    if not options:
        return options
    try:
        _dry_run(solver, options)
    except (RuntimeError, NotImplementedError) as exc:
        # name the option: the first one CasADi refuses on its own
        for key, value in options.items():
            try:
                _dry_run(solver, {key: value})
            except (RuntimeError, NotImplementedError) as one:
                reason = _casadi_reason(one)
                if solver in ("ipopt", "fatrop") and reason.startswith("Unknown option") \
                        and not key.startswith(solver + "."):
                    reason += (f" ({solver}'s own options are given as '{solver}.<name>', "
                               f"e.g. '{solver}.max_iter')")
                raise ValueError(f"solver_options for solver {solver!r} were refused by "
                                 f"CasADi: solver_options[{key!r}]: {reason}") from None
        raise ValueError(f"solver_options for solver {solver!r} were refused by CasADi: "
                         f"{_casadi_reason(exc)}") from None
    return options


def _nlpsol(name: str, solver: str, nlp: dict, opts: dict, user: dict):
    """``ca.nlpsol`` with CasADi's refusal of the user's options as a ``ValueError``."""
    try:
        return ca.nlpsol(name, _PLUGINS[solver], nlp, opts)
    except (RuntimeError, NotImplementedError) as exc:
        if not user:
            raise
        raise ValueError(f"solver_options for solver {solver!r} were refused by CasADi: "
                         f"{_casadi_reason(exc)}") from None


def is_diagonal(M: np.ndarray) -> bool:
    return bool(np.array_equal(M, np.diag(np.diag(M))))


def weight_factor(cov: np.ndarray) -> np.ndarray:
    """``W`` with ``W^T W = cov^{-1}``, so ``||W r||^2 = r^T cov^{-1} r``."""
    L = np.linalg.cholesky(np.linalg.inv(cov))
    return L.T


def measurement_weights(mask: np.ndarray, R: np.ndarray, WR: np.ndarray) -> np.ndarray:
    """``(T, ny, ny)``: the weight factor of each sample's measured outputs (``mask``
    (T, ny)): ``WR`` where every output is measured, the factor of the marginal of
    ``R`` over the measured rows (zero elsewhere) where some are, zero where none."""
    wy = np.zeros((len(mask), len(R), len(R)))
    full = mask.all(axis=1)
    wy[full] = WR
    for j in np.flatnonzero(~full & mask.any(axis=1)):
        rows = np.flatnonzero(mask[j])
        wy[j][np.ix_(rows, rows)] = weight_factor(R[np.ix_(rows, rows)])
    return wy


@dataclass
class Solution:
    """One solve: trajectory ``X (N, nx)``, status and statistics.

    ``success``: converged. ``usable``: ``X`` and ``cost`` are finite and the cost is
    not above that of the (projected) initial guess, so ``X`` may serve as an
    estimate even where the solver stopped early (``max_iter``, a failed line search).
    """

    X: np.ndarray
    success: bool
    status: str
    iterations: int
    cost: float
    solve_time: float
    usable: bool = False
    build_time: float = 0.0
    outliers: int = 0  # robust loss: measurement components beyond OUTLIER_SIGMA
    outlier_cost: float = 0.0  # and their share of the cost

    def __post_init__(self):
        self.usable = self.usable or self.success

    def consistency(self, dof: int, measured: int) -> str:
        """:func:`~estim.consistency.consistency_status` of the cost with ``dof``
        degrees of freedom, ``measured`` of them measurements. With a robust loss
        the outliers are left out of the test (their number is reported
        elsewhere), unless they are half the measurements or more: then the
        estimate, not the data, is the likelier culprit (the breakdown point of a
        robust fit)."""
        if not self.outliers:
            return consistency_status(self.cost, dof, "cost")
        if 2 * self.outliers >= measured:
            return (f"suspect: {self.outliers} of {measured} measured values beyond "
                    f"{OUTLIER_SIGMA:.1f} standard deviations")
        return consistency_status(self.cost - self.outlier_cost, dof - self.outliers,
                                  "cost without the outliers")


def _merge(defaults: dict, user: dict) -> dict:
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in defaults.items()}
    for k, v in user.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k].update(v)
        else:
            out[k] = v
    return out


class LeastSquaresNLP:
    """Build-once, solve-many windowed estimation problem (see module docstring).

    Parameters
    ----------
    model : Model
    N : int
        Number of slots (window length).
    lower, upper : (nx,) arrays
        State bounds.
    solver : {"ipopt", "sqp", "fatrop"}
    options : dict
        Solver options merged over the defaults.
    diagonal_Q, diagonal_R : bool
        The process and measurement weights are diagonal (cheaper stage
        functions). The weights :math:`W_Q` (:math:`W_Q^\\top W_Q = Q^{-1}`),
        :math:`W_R`, the arrival weight and mean are parameters of every graph,
        given to each :meth:`solve`: the tuning is data.
    full : bool
        Solved only with every slot holding data (``n == N``); the
        Gauss-Newton graph then treats the window bookkeeping as constants.
    loss : RobustLoss, optional
        A robust measurement cost, minimised by reweighted solves (see
        :mod:`estim.solvers.robust`); least squares if omitted.
    """

    def __init__(self, model: Model, N: int, lower: np.ndarray, upper: np.ndarray,
                 solver: str, options: dict, diagonal_Q: bool = False,
                 diagonal_R: bool = False, full: bool = False, loss: RobustLoss | None = None):
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
        self.model, self.N, self.solver_name = model, N, solver
        nx, nu, ny = model.nx, model.nu, model.ny
        self.lbx = np.tile(lower, N)
        self.ubx = np.tile(upper, N)
        self.bounded = bool(np.isfinite(self.lbx).any() or np.isfinite(self.ubx).any())
        # parameter layout
        sizes = {"y": N * ny, "wy": N * ny * ny, "u": N * model.nw, "up": N * nu,
                 "omega": max(N - 1, 0), "a": N, "xbar": nx, "w0": nx * nx, "wq": nx * nx,
                 "wr": ny * ny}
        self._slices, start = {}, 0
        for key, size in sizes.items():
            self._slices[key] = slice(start, start + size)
            start += size
        self.np = start
        self._p = np.zeros(self.np)
        p = ca.SX.sym("p", self.np)
        part = {k: p[s] for k, s in self._slices.items()}
        Y = ca.reshape(part["y"], ny, N)
        U = ca.reshape(part["u"], model.nw, N)  # transitions' inputs
        Up = ca.reshape(part["up"], nu, N)
        a = part["a"]
        xbar = part["xbar"]
        W0 = ca.reshape(part["w0"], nx, nx)
        WQd = ca.diag(part["wq"][[i * nx + i for i in range(nx)]]) if diagonal_Q else \
            ca.reshape(part["wq"], nx, nx)
        pm = ca.DM(model.p)
        # (the estimators check the options by check_solver_options first)
        gn_opts = options if solver == "gauss-newton" else {}
        self.full = bool(full)
        self.gn = StructuredGaussNewton(model, N, self.lbx, self.ubx, self._slices, self.np,
                                        diagonal_Q=diagonal_Q, diagonal_R=diagonal_R,
                                        full=full, **gn_opts)
        self._wy_complete = None  # (W_R, its weights tiled over the slots)
        self.loss = loss
        self._whitened = None  # the measurement residuals, built on first use
        #: (N, ny): the robust loss's weights of the last solve's measurements
        self.weights: np.ndarray | None = None
        self._complete = False  # the last parameters: every slot holds every output
        if solver == "gauss-newton":
            self.reset()
            return
        if self.full:  # every slot active, arrival on the first: constants, not parameters
            a, part["omega"] = full_record_constants(N)
        if solver == "fatrop":
            self._build_fatrop(p, Y, U, Up, part, a, xbar, W0, WQd, pm, options)
            return
        X = ca.SX.sym("X", nx, N)
        # arrival on the first active slot, one residual block per slot (a_j in {0, 1}):
        # a single W0 (X a - xbar) would couple every slot and make the Hessian dense
        res = [a[j] * (W0 @ (X[:, j] - xbar)) for j in range(N)]
        for j in range(N - 1):
            om = part["omega"][j]
            xn = model.F(X[:, j], U[:, j], pm)
            res.append(om * (WQd @ (X[:, j + 1] - xn)) + (1 - om) * (X[:, j + 1] - X[:, j]))
        for j in range(N):
            Wy = ca.reshape(part["wy"][j * ny * ny:(j + 1) * ny * ny], ny, ny)
            res.append(Wy @ (Y[:, j] - model.H(X[:, j], Up[:, j], pm)))
        r = ca.vertcat(*res)
        x = ca.vec(X)
        f = ca.dot(r, r)
        nlp = {"x": x, "p": p, "f": f}
        if solver == "ipopt":
            self._solver = _nlpsol("mhe_ipopt", "ipopt", nlp, _merge(_IPOPT_DEFAULTS, options),
                                   options)
        else:
            J = ca.jacobian(r, x)
            lam_f, lam_g = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", 0)
            # Gauss-Newton Hessian with a tiny damping: the stationary points are unchanged,
            # the QP stays well posed when the window alone does not determine every state
            H = lam_f * (2 * (J.T @ J) + 1e-10 * ca.DM.eye(x.numel()))
            hess = ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [H],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
            opts = _merge(_SQP_DEFAULTS, options)
            opts["hess_lag"] = hess
            self._solver = _nlpsol("mhe_sqp", "sqp", nlp, opts, options)
        self.reset()

    # ----------------------------------------------------------- stage-wise form
    def _build_fatrop(self, p, Y, U, Up, part, a, xbar, W0, WQd, pm, options) -> None:
        """Multiple-shooting form with process noise as controls, for fatrop.

        Stage k has variables ``(x_k, w_k)``; the gap constraint is
        ``x_{k+1} = omega_k F(x_k, u_k) + (1 - omega_k) x_k + w_k`` and the
        stage cost ``omega_k ||W_Q w_k||^2 + (1 - omega_k) ||w_k||^2``: the same
        optimum as the eliminated form.
        """
        m, N = self.model, self.N
        nx, ny = m.nx, m.ny
        xs = [ca.SX.sym(f"x{k}", nx) for k in range(N)]
        ws = [ca.SX.sym(f"w{k}", nx) for k in range(N - 1)]
        variables, g, lbg, ubg = [], [], [], []
        cost = sum(a[k] * ca.sumsqr(W0 @ (xs[k] - xbar)) for k in range(N))
        for k in range(N):
            variables.append(xs[k])
            Wy = ca.reshape(part["wy"][k * ny * ny:(k + 1) * ny * ny], ny, ny)
            cost += ca.sumsqr(Wy @ (Y[:, k] - m.H(xs[k], Up[:, k], pm)))
            if k < N - 1:
                variables.append(ws[k])
                om = part["omega"][k]
                cost += om * ca.sumsqr(WQd @ ws[k]) + (1 - om) * ca.sumsqr(ws[k])
                g.append(xs[k + 1] - (om * m.F(xs[k], U[:, k], pm) + (1 - om) * xs[k]
                                      + ws[k]))
                lbg.append(np.zeros(nx))
                ubg.append(np.zeros(nx))
        x = ca.vertcat(*variables)
        nlp = {"x": x, "p": p, "f": cost, "g": ca.vertcat(*g)}
        opts = _merge(_FATROP_DEFAULTS, options)
        opts.setdefault("equality", [True] * (nx * (N - 1)))
        self._solver = _nlpsol("mhe_fatrop", "fatrop", nlp, opts, options)
        self._lbg = np.concatenate(lbg) if lbg else np.zeros(0)
        self._ubg = np.concatenate(ubg) if ubg else np.zeros(0)
        inf = np.full(nx, np.inf)
        lb, ub = [], []
        for k in range(N):
            lb.append(self.lbx[k * nx:(k + 1) * nx])
            ub.append(self.ubx[k * nx:(k + 1) * nx])
            if k < N - 1:
                lb.append(-inf)
                ub.append(inf)
        self._lbz, self._ubz = np.concatenate(lb), np.concatenate(ub)
        self._xsel = np.concatenate([np.arange(k * 2 * nx, k * 2 * nx + nx) for k in range(N)])
        self.reset()

    def reset(self) -> None:
        """Forget the warm-start multipliers and the solver's adaptive state."""
        self._lam_x = None
        self._lam_g = None
        self.gn.reset()

    # ------------------------------------------------------------------ solve
    def parameters(self, Y, U, Uprev, n, xbar, W0, WQ, WR, R) -> np.ndarray:
        """Fill the parameter vector for a window with ``n`` measured slots: data,
        arrival mean ``xbar`` and weight ``W0`` (None: no arrival term), the process
        and measurement weight factors ``WQ``, ``WR`` and ``R`` (for the weights of
        partly measured samples)."""
        m, N = self.model, self.N
        nx = m.nx
        p, s = self._p, self._slices
        p[s["wq"]] = WQ.ravel(order="F")
        p[s["wr"]] = WR.ravel(order="F")
        mask = np.isfinite(Y)
        s0 = N - n
        self._complete = False
        if s0 == 0 and mask.all():  # complete data in a full window: the common case
            self._complete = True
            p[s["y"]] = Y.ravel()
            if self._wy_complete is None or not np.array_equal(self._wy_complete[0], WR):
                self._wy_complete = (WR.copy(), np.tile(WR.ravel(order="F"), N))
            p[s["wy"]] = self._wy_complete[1]
            p[s["u"]] = U.ravel()
            p[s["up"]] = Uprev.ravel()
            p[s["omega"]] = 1.0
            p[s["a"]] = 0.0
            p[s["a"].start] = 1.0
            p[s["xbar"]] = xbar
            p[s["w0"]] = 0.0 if W0 is None else W0.ravel(order="F")
            return p
        p[s["y"]] = np.where(mask, Y, 0.0).ravel()          # column-major (ny, N)
        used = mask.copy()
        used[:s0] = False  # the unused slots weigh nothing
        wy = measurement_weights(used, R, WR)
        p[s["wy"]] = wy.transpose(0, 2, 1).ravel()            # each block column-major
        if s0:  # the unused slots evaluate the model at the inputs of the first used one
            U, Uprev = U.copy(), Uprev.copy()  # (stale ones may make it non-finite, and
            U[:s0] = U[s0] if n > 1 else 0.0  # the zero weights of these slots cannot
            Uprev[:s0] = Uprev[s0]             # undo that: 0 * NaN is NaN)
        p[s["u"]] = U.ravel()
        p[s["up"]] = Uprev.ravel()
        omega = np.zeros(max(N - 1, 0))
        omega[s0:] = 1.0
        p[s["omega"]] = omega
        a = np.zeros(N)
        a[s0] = 1.0
        p[s["a"]] = a
        p[s["xbar"]] = xbar
        p[s["w0"]] = (np.zeros((nx, nx)) if W0 is None else W0).ravel(order="F")
        return p

    def solve(self, X0, Y, U, Uprev, n, xbar, W0, WQ, WR, R, robust: bool = False
              ) -> Solution:
        """Solve from the initial guess ``X0 (N, nx)``; never raises on solver failure.

        ``robust``: with the structured Gauss-Newton solver whatever the solver chosen
        (a descent method from any finite start: the estimators' recovery solves).
        With a robust ``loss``, the weighted problems of
        :mod:`estim.solvers.robust` are solved until the weights settle; the
        solution's ``weights`` are the final ones.
        """
        if self.full and n != self.N:
            raise ValueError(f"this problem is built for full records (n = {self.N}), got n = {n}")
        p = self.parameters(Y, U, Uprev, n, xbar, W0, WQ, WR, R)
        if self.loss is None:
            return self._solve(X0, p, Y, n, W0 is not None, robust)
        return self._solve_reweighted(X0, p, Y, n, W0 is not None, robust)

    def _residuals(self, X: np.ndarray, p: np.ndarray, wy: np.ndarray) -> np.ndarray:
        """Whitened measurement residuals :math:`W_{y,j}(y_j - h(x_j))`, (N, ny), for
        the data in ``p`` and the weights ``wy`` (laid out as ``p``'s; zero rows where
        not measured)."""
        if self._whitened is None:
            m, s = self.model, self._slices
            x, y = ca.SX.sym("x", m.nx), ca.SX.sym("y", m.ny)
            w, up = ca.SX.sym("wy", m.ny * m.ny), ca.SX.sym("up", m.nu)
            e = y - m.H(x, up, ca.DM(m.p))
            one = ca.Function("whitened", [x, y, w, up], [ca.reshape(w, m.ny, m.ny) @ e])
            fun = FastFunction(one.map(self.N))
            self._whitened = (fun, s["y"], s["up"])
        fun, sy, sup = self._whitened
        with np.errstate(invalid="ignore", over="ignore"):
            r = fun(np.asarray(X, float).ravel(), p[sy], wy, p[sup])[0]
        return r.reshape(self.N, self.model.ny)

    def _solve_reweighted(self, X0, p, Y, n, arrival, robust) -> Solution:
        """Iteratively reweighted least squares for the robust loss (see
        :mod:`estim.solvers.robust`), from weights at ``X0``.

        Gauss-Newton (and every ``robust`` solve): new weights at every accepted
        iterate, inside the solver. The NLP solvers: a weighted solve, new weights at
        its solution, until no weight moves by more than ``IRLS_WTOL`` (at most
        ``IRLS_MAX`` solves)."""
        loss, s, ny = self.loss, self._slices, self.model.ny
        self._complete = False  # the weights differ between slots
        base = p[s["wy"]].copy()

        def weights(x):
            r = self._residuals(x, p, base)
            w = loss.weight(r)
            return np.where(np.isfinite(w), w, 1.0)  # a non-finite residual stays so

        def scaled(w):
            return base * np.repeat(np.sqrt(w), ny, axis=0).ravel()

        if self.solver_name == "gauss-newton" or robust:
            used = []

            def reweight(x):
                used[:] = [weights(x)]
                self.gn._pbuf[s["wy"]] = scaled(used[0])

            sol = self._solve_gn(X0, p, reweight)
            p[s["wy"]] = self.gn._pbuf[s["wy"]]  # the final weights (covariance)
            return self._robust_summary(sol, p, base, used[0])
        X = np.clip(np.asarray(X0, float).reshape(self.N, -1), self.lbx.reshape(self.N, -1),
                    self.ubx.reshape(self.N, -1))
        w = weights(X)
        iters, elapsed, build, status = 0, 0.0, 0.0, None
        for solves in range(1, IRLS_MAX + 1):
            p[s["wy"]] = scaled(w)
            sol = self._solve(X, p, Y, n, arrival, robust, same_window=solves > 1)
            iters, elapsed = iters + sol.iterations, elapsed + sol.solve_time
            build += sol.build_time
            if not sol.usable:
                return Solution(sol.X, False, sol.status, iters, sol.cost, elapsed, False,
                                build)
            X, w_used, w = sol.X, w, weights(sol.X)
            if not sol.success:
                status = sol.status
                break
            if np.max(np.abs(w - w_used), initial=0.0) <= IRLS_WTOL:
                break
        else:
            status = f"robust weights not settled after {IRLS_MAX} reweighted solves"
        sol = Solution(X, status is None, status or "ok", iters, sol.cost, elapsed, True, build)
        return self._robust_summary(sol, p, base, w_used)

    def _robust_summary(self, sol: Solution, p, base, w_used) -> Solution:
        """The robust cost of a reweighted solve (its weighted cost, computed with the
        weights ``w_used``, with the measurement part replaced by the loss), and its
        outliers: the components beyond ``OUTLIER_SIGMA`` standard deviations."""
        r = self._residuals(sol.X, p, base)
        rho = self.loss.rho(r)
        sol.cost = float(sol.cost - np.sum(w_used * r * r) + np.sum(rho))
        far = np.abs(r) > OUTLIER_SIGMA
        sol.outliers, sol.outlier_cost = int(far.sum()), float(rho[far].sum())
        self.weights = self.loss.weight(r)
        return sol

    def _solve(self, X0, p, Y, n, arrival: bool, robust: bool, same_window: bool = False
               ) -> Solution:
        """One solve for the parameters ``p`` (``same_window``: a re-solve of the
        window of the previous solve: its multipliers are not shifted)."""
        if self.solver_name != "gauss-newton" and not robust:
            x0 = np.clip(np.asarray(X0, float).ravel(), self.lbx, self.ubx)
        if self.solver_name == "fatrop" and not robust:
            # fatrop can stall and never return where the data contradict the start (an
            # outlier in the window, a start in an overflowing region of the model):
            # such windows, whose cost is beyond the chi-square limit of the suspect
            # test, go to the Gauss-Newton solver
            robust = not self.gn.cost(x0, p, self._complete) <= chi2_limit(
                self.degrees_of_freedom(Y, n, arrival))
        if self.solver_name == "gauss-newton" or robust:
            return self._solve_gn(X0, p)
        t0 = time.perf_counter()
        # not started where the model is not finite (the solvers would spend their
        # iterations on it, or crash)
        start = self.gn.cost(x0, p, self._complete)
        if not np.isfinite(start):
            return Solution(np.asarray(X0, float), False,
                            "non-finite cost at the initial guess", 0, start,
                            time.perf_counter() - t0)
        try:
            if self.solver_name == "fatrop":
                sol = self._solve_fatrop(X0, p)
            else:
                args = {"x0": x0, "p": p, "lbx": self.lbx, "ubx": self.ubx}
                if self._lam_x is not None and self.bounded:
                    args["lam_x0"] = self._lam_x if same_window else self._shifted(self._lam_x)
                sol = self._solver(**args)
            stats = self._solver.stats()
        except RuntimeError as exc:  # solver crashed on NaN or similar
            return Solution(np.asarray(X0, float), False,
                            f"error: {str(exc).strip().splitlines()[-1]}"[:200], 0, np.nan,
                            time.perf_counter() - t0)
        elapsed = time.perf_counter() - t0
        status = str(stats.get("return_status", "unknown"))
        iters = int(stats.get("iter_count", 0))
        z = np.asarray(sol["x"]).ravel()
        X = (z[self._xsel] if self.solver_name == "fatrop" else z).reshape(self.N, -1)
        cost = float(sol["f"])
        # sqpmethod stops on a step below min_step_size when Gauss-Newton's linear
        # convergence has reached the stationary point to rounding: a converged solve
        ok = bool(stats.get("success", False)) or status in (
            "Solved_To_Acceptable_Level", "Search_Direction_Becomes_Too_Small")
        ok = ok and np.isfinite(X).all() and np.isfinite(cost)
        usable = ok
        if ok:
            if self.solver_name != "fatrop":
                self._lam_x = np.asarray(sol["lam_x"]).ravel()
            status = "ok"
        elif np.isfinite(X).all():  # an early stop: usable if no worse than the start
            cost = self.gn.cost(X.ravel(), p, self._complete)
            usable = bool(np.isfinite(cost) and not cost > start)
        return Solution(X, ok, status, iters, cost, elapsed, usable)

    def _solve_gn(self, X0, p, reweight=None) -> Solution:
        """The structured Gauss-Newton solve (see :meth:`StructuredGaussNewton.solve`)."""
        x, ok, status, iters, cost, elapsed = self.gn.solve(X0, p, self._complete, reweight)
        # the iterations only ever decrease the cost: a finite end point is usable
        usable = bool(np.isfinite(cost) and np.isfinite(x).all())
        return Solution(x.reshape(self.N, -1), ok, "ok" if ok else status, iters, cost,
                        elapsed, usable, self.gn.last_build)

    def measured(self, Y: np.ndarray, n: int) -> int:
        """The number of measured values in the last ``n`` slots of ``Y``."""
        return n * self.model.ny if self._complete else int(np.isfinite(Y[self.N - n:]).sum())

    def degrees_of_freedom(self, Y: np.ndarray, n: int, arrival: bool) -> int:
        """Chi-square degrees of freedom of the cost of a window of ``n`` measured slots
        (its measured outputs, and ``nx`` for an arrival term), for the consistency test
        of :func:`~estim.consistency.consistency_status`."""
        return self.measured(Y, n) + (self.model.nx if arrival else 0)

    def covariance(self, X: np.ndarray) -> np.ndarray | None:
        """Laplace covariance of the last state, ``[(J^T J)^{-1}]_{N-1,N-1}``, at the
        solution ``X`` for the parameters of the last solve (None if singular)."""
        P = self.gn.covariance(np.asarray(X, float).ravel(), self._p, self._complete)
        return P if np.isfinite(P).all() else None

    def _solve_fatrop(self, X0, p):
        nx, N = self.model.nx, self.N
        z0 = np.zeros(self._lbz.size)
        X0 = np.clip(np.asarray(X0, float), self.lbx.reshape(N, nx), self.ubx.reshape(N, nx))
        z0[self._xsel] = X0.ravel()
        return self._solver(x0=z0, p=p, lbx=self._lbz, ubx=self._ubz, lbg=self._lbg,
                            ubg=self._ubg)

    def _shifted(self, lam: np.ndarray) -> np.ndarray:
        """Bound multipliers moved one slot earlier (the window moved one sample)."""
        nx = self.model.nx
        out = np.empty_like(lam)
        out[:-nx] = lam[nx:]
        out[-nx:] = lam[-nx:]
        return out
