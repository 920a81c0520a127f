r"""Quadrature rules for Gaussian integrals that the sigma-point filters and the particle
filter's unscented proposal share: the points :math:`\xi_i` and weights :math:`W_i` of a
rule for :math:`N(0, I_n)`, so that :math:`E[g(x)] \approx \sum_i W_i\, g(m + L \xi_i)`
for :math:`x \sim N(m, L L^\top)` (Särkkä & Svensson, *Bayesian Filtering and
Smoothing*, 2nd ed., 2023, ch. 8)."""

from __future__ import annotations

from itertools import product

import numpy as np
from numpy.polynomial.hermite_e import hermegauss

__all__ = ["cubature", "cubature5", "gauss_hermite"]


def cubature(n: int) -> tuple[np.ndarray, np.ndarray]:
    r"""The third-degree spherical cubature rule: the :math:`2n` unit points
    :math:`\pm\sqrt n\, e_i`, each of weight :math:`1/(2n)` (Arasaratnam & Haykin 2009)."""
    unit = np.sqrt(n) * np.hstack([np.eye(n), -np.eye(n)])
    return unit, np.full(2 * n, 0.5 / n)


def cubature5(n: int) -> tuple[np.ndarray, np.ndarray]:
    r"""The fifth-degree fully symmetric rule for :math:`N(0, I_n)` (McNamee & Stenger
    1967; Särkkä & Svensson 2023, sec. 8.6): :math:`2n^2 + 1` unit points, the centre
    (weight :math:`2/(n+2)`), :math:`\pm\sqrt{n+2}\,e_i` (weight
    :math:`(4-n)/(2(n+2)^2)`) and :math:`\pm\sqrt{(n+2)/2}\,(e_i \pm e_j)`, :math:`i < j`
    (weight :math:`1/(n+2)^2`). Exact for every polynomial of total degree 5 or less;
    for :math:`n > 4` the axis weights are negative (the square-root UKF downdates by them,
    a failed step where the result is not positive definite; the particle filter's proposal
    refuses them)."""
    eye = np.eye(n)
    cols = [np.zeros(n)]
    W = [2.0 / (n + 2)]
    for i in range(n):
        for sign in (1.0, -1.0):
            cols.append(sign * np.sqrt(n + 2.0) * eye[i])
            W.append((4.0 - n) / (2.0 * (n + 2) ** 2))
    r = np.sqrt((n + 2.0) / 2.0)
    for i in range(n):
        for j in range(i + 1, n):
            for si in (1.0, -1.0):
                for sj in (1.0, -1.0):
                    cols.append(r * (si * eye[i] + sj * eye[j]))
                    W.append(1.0 / (n + 2) ** 2)
    return np.array(cols).T, np.array(W)


def gauss_hermite(n: int, order: int) -> tuple[np.ndarray, np.ndarray]:
    r"""The Gauss-Hermite rule of ``order`` :math:`p` for :math:`N(0, I_n)`: the unit
    points ``(n, p^n)``, the Cartesian product of the :math:`p` roots of the
    probabilists' Hermite polynomial :math:`He_p`, and their weights ``(p^n,)``, the
    products of the one-dimensional weights (normalised to sum to 1). Exact for
    polynomials of degree :math:`2p - 1` in each coordinate (Särkkä & Svensson 2023,
    sec. 8.3; the points of a mean :math:`m` and covariance :math:`P = L L^\top` are
    :math:`m + L \xi_i`)."""
    nodes, weights = hermegauss(order)
    weights = weights / weights.sum()
    unit = np.array(list(product(nodes, repeat=n))).T.reshape(n, -1)
    W = np.array([np.prod(c) for c in product(weights, repeat=n)])
    return unit, W
