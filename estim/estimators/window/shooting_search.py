r"""How the :class:`~estim.ShootingObserver` searches a window's optimum, apart from the
scipy and Ipopt calls themselves: the cost in the coordinates of a search
(:class:`SearchCost`), the subspace of the directions the window determines to the
observer's ``resolution`` (:func:`subspace`, in the magnitudes of :func:`scales`), and
gradient descent with the sensitivity equations' gradient (:func:`gradient_descent`,
report eq. 1.11), and the identifiability of the window's optimum
(:func:`identifiability`).

The weighted output residuals have unit noise, so the Gauss-Newton Hessian :math:`H`
of the cost is the Fisher information of the optimised state: a direction along which
it is small is one the window does not determine.
"""

from __future__ import annotations

import numpy as np

from estim._fast import FastFunction

#: ``(x, cost, iterations, converged, message)`` of a search.
Search = tuple[np.ndarray, float, int, bool, str]


class SearchCost:
    """The shooting cost and gradient at ``start + T z``, evaluated once at the start.

    Parameters
    ----------
    start : (nx,) array
    J : FastFunction
        The cost and its gradient (:attr:`ShootingFunctions.J
        <estim.estimators.window.shooting_problem.ShootingFunctions.J>`).
    args : tuple
        The window's data, ``J``'s inputs after the state.
    """

    def __init__(self, start: np.ndarray, J: FastFunction, args: tuple):
        self.start, self.J, self.args = start, J, args
        J0, g0 = J(start, *args)  # views of J's output buffers: copy what is kept
        self.J0, self.g0 = float(J0[0]), g0.copy()

    def __call__(self, z: np.ndarray, T: np.ndarray) -> tuple[float, np.ndarray]:
        """The cost and its gradient in ``z`` at ``start + T z``."""
        if not z.any():
            return self.J0, T.T @ self.g0
        J, g = self.J(self.start + T @ z, *self.args)
        return float(J[0]), T.T @ g


def scales(H: np.ndarray, start: np.ndarray, g: np.ndarray, P0: np.ndarray | None,
           resolution: float | None) -> np.ndarray:
    r"""The magnitude :math:`D_i` of each component, to which ``resolution`` is relative.

    Where the start (the propagated previous estimate) carries a magnitude, it is that
    one: :math:`D_i = \max(|\xi_{0,i}|,\ 10^{-3} \max_j |\xi_{0,j}|,\ \sqrt{P_{0,ii}})`
    -- the start, floored at 1e-3 of its largest component (a tiny state next to large
    ones is not asked for a relative precision it cannot have), and the prior's
    standard deviation where ``P0`` is given (the user's own scale of the component).

    A start carries no magnitude when it lies within its own standard error of zero,
    :math:`D_i^2 H_{ii} < 2` (a guess of 0, or a value the window cannot tell from 0):
    a relative precision of it would be meaningless, and the old scale (the 1e-3
    floor, or 0) dropped such a component whatever the window held. Its magnitude is
    then the one the window itself gives it, :math:`|\xi^{GN}_i|` with
    :math:`\xi^{GN} = \xi_0 - H^{+} g` the window's Gauss-Newton estimate (the
    Jacobi-scaled pseudo-inverse of the Gauss-Newton Hessian :math:`H` applied to the
    gradient :math:`g` at the start), provided the window determines it to the
    resolution there: :math:`\sigma_i \le` ``resolution`` :math:`|\xi^{GN}_i|`, with
    :math:`\sigma_i = \sqrt{2 (H^{+})_{ii}}` its marginal standard error. The
    component is then judged as it would be from a start at that value; one the window
    does not determine (its estimate is noise, :math:`|\xi^{GN}_i| \sim \sigma_i`)
    keeps the small scale, and so its start. Other absolute scales were rejected:
    :math:`1/\sqrt{H_{ii}}` makes every relative error about 1 whatever the window
    holds, and bounds give a range, not a magnitude. With a non-finite ``g`` the
    start's scale is returned.

    Parameters
    ----------
    H : (nx, nx) array
        The Gauss-Newton Hessian at ``start``.
    start : (nx,) array
    g : (nx,) array
        The cost's gradient at ``start``.
    P0 : (nx, nx) array or None
        The observer's prior covariance.
    resolution : float or None
        The observer's ``resolution`` (None: every component the window resolves).
    """
    D = np.abs(start)
    D = np.maximum(D, 1e-3 * float(D.max()))
    if P0 is not None:
        D = np.maximum(D, np.sqrt(np.diag(P0)))
    if not np.isfinite(g).all():
        return D
    h = np.maximum(np.diag(H), 0.0)
    tiny = D * D * h < 2.0  # the start is within its own standard error of 0
    seen = h > 0
    if not (tiny & seen).any():
        return D
    s = np.sqrt(h[seen])
    Hs_inv = np.linalg.pinv(H[np.ix_(seen, seen)] / np.outer(s, s), rcond=1e-12,
                            hermitian=True)
    step, sigma = np.zeros_like(start), np.full_like(start, np.inf)
    step[seen] = -(Hs_inv @ (g[seen] / s)) / s
    sigma[seen] = np.sqrt(2.0 * np.maximum(np.diag(Hs_inv), 0.0)) / s
    target = np.abs(start + step)
    use = tiny & np.isfinite(target)
    if resolution is not None:
        use &= sigma <= resolution * target
    D[use] = np.maximum(D[use], target[use])
    return D


def subspace(H: np.ndarray | None, start: np.ndarray, g: np.ndarray,
             P0: np.ndarray | None, resolution: float | None) -> np.ndarray:
    r"""Coordinates ``xi = start + T z`` spanning the directions this window determines.

    In relative coordinates (``xi_i = start_i + D_i e_i``, with the magnitudes
    :math:`D_i` of :func:`scales`) the Gauss-Newton Hessian is
    :math:`H_r = D H D = V \Lambda V^\top`; as the weighted residuals have unit
    noise, eigen-direction :math:`i` is determined to the relative standard
    error :math:`\sqrt{2/\lambda_i}`. Directions known better than
    ``resolution`` span the optimisation, with :math:`T = D V_r
    \Lambda_r^{-1/2}` so the Hessian in ``z`` is the identity; the others
    keep the warm start (the propagated previous estimate). With ``resolution=None``
    every direction the Hessian resolves numerically is kept.

    Parameters are those of :func:`scales` (``H`` None: not finite). Returns ``T``, an
    ``(nx, k)`` matrix; ``(nx, 0)`` when the window determines nothing.
    """
    nx = len(start)
    if H is None:
        return np.zeros((nx, 0))
    D = scales(H, start, g, P0, resolution)
    Hr = H * np.outer(D, D)
    lam, V = np.linalg.eigh(0.5 * (Hr + Hr.T))
    if resolution is None:
        keep = lam > nx * np.finfo(float).eps * max(float(lam.max()), 0.0)
    else:
        keep = lam >= 2.0 / resolution**2
    return (D[:, None] * V[:, keep]) / np.sqrt(lam[keep])


def undetermined(resolution: float | None) -> str:
    """Why the subspace methods leave a direction out (for the status)."""
    if resolution is None:
        return "not determined numerically"
    return f"not determined to the resolution {resolution:g}"


def identifiability(sens: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, float]:
    r"""The singular values and condition number of the output sensitivity to relative
    changes of the state, :math:`S\,\mathrm{diag}(|x|)` (columns floored at 1e-3 of the
    largest :math:`|x_i|`: states span many decades).

    Parameters
    ----------
    sens : (w ny, nx) array
        The weighted output sensitivity :math:`S` at ``x``.
    x : (nx,) array

    Returns
    -------
    singular_values : array
        NaN if :math:`S` is not finite.
    condition : float
        Their ratio (inf if the smallest is 0 or :math:`S` is not finite).
    """
    scale = np.maximum(np.abs(x), 1e-3 * max(float(np.abs(x).max()), 1e-300))
    S = sens * scale
    if np.isfinite(S).all():
        sv = np.linalg.svd(S, compute_uv=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    else:
        sv, cond = np.full(min(S.shape), np.nan), float("inf")
    return sv, cond


def gradient_descent(J: FastFunction, grad_sens: FastFunction, grad_other: FastFunction,
                     start: np.ndarray, args: tuple, max_iter: int) -> Search:
    r"""Report eq. 1.11, :math:`\xi_0 \leftarrow \xi_0 - \alpha\, \partial J/\partial
    \xi_0`, with an Armijo backtracking step size.

    The gradient is that of the output term by the forward sensitivity equations
    (``grad_sens``) plus that of the other terms (``grad_other``; see
    :class:`~estim.estimators.window.shooting_problem.ShootingFunctions`). Converged when the
    gradient vanishes or the cost no longer decreases (relative ``1e-12``).
    """
    U, Y = args[0], args[1]
    x = start.copy()
    cost = float(J(x, *args)[0][0])
    alpha = 1.0
    for it in range(1, max_iter + 1):
        g = grad_sens(x, U, Y, args[-1])[0] + grad_other(x, *args)[0]
        if not np.isfinite(g).all():
            return x, cost, it, False, "non-finite gradient"
        gg = float(g @ g)
        if gg <= 1e-30 * max(cost, 1e-300):
            return x, cost, it, True, "gradient vanished"
        while alpha > 1e-30:
            xn = x - alpha * g
            cost_n = float(J(xn, *args)[0][0])
            if np.isfinite(cost_n) and cost_n <= cost - 1e-4 * alpha * gg:
                break
            alpha *= 0.5
        else:
            return x, cost, it, False, "line search stalled (step below 1e-30)"
        converged = abs(cost - cost_n) <= 1e-12 * max(abs(cost), 1e-300)
        x, cost = xn, cost_n
        alpha *= 2.0
        if converged:
            return x, cost, it, True, "converged"
    return x, cost, max_iter, False, f"max_iter ({max_iter}) reached"
