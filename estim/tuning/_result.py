r"""The result of a noise-covariance estimate and its innovation diagnostics.

Both :func:`estim.tuning.als` and :func:`estim.tuning.maximum_likelihood` return a
:class:`TuningResult`: the estimated ``Q`` and ``R`` (and model parameters, for
maximum likelihood), their standard errors, and a check of the innovations of the
filter run with the estimates. With the right covariances the innovations of a
Kalman filter are a white sequence with covariance :math:`S_k`
(Kailath 1968; Mehra 1970): the whitened innovations
:math:`\varepsilon_k = L_k^{-1} e_k` (:math:`L_k L_k^\top = S_k`) have zero
autocorrelation at every lag and the normalised innovation squared
:math:`e_k^\top S_k^{-1} e_k` averages :math:`n_y`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Lags of the whiteness test and the autocorrelation plot (default).
DEFAULT_LAGS = 20


@dataclass
class InnovationCheck:
    r"""Whiteness and consistency of a filter's innovations.

    Attributes
    ----------
    autocorrelation : (L+1, ny, ny) array
        Sample autocorrelation of the whitened innovations at lags
        :math:`0..L` (the identity at lag 0 for white innovations).
    band : float
        The 95 % band :math:`\pm 1.96/\sqrt{T}` of one autocorrelation of a white
        sequence.
    statistic, p_value : float
        Ljung-Box portmanteau statistic over lags 1..L of all output pairs,
        :math:`Q = T(T+2) \sum_{l=1}^{L} \lVert \hat\rho_l \rVert_F^2/(T-l)`, and its
        :math:`\chi^2_{L n_y^2}` tail probability (Ljung & Box 1978; the
        multivariate form of Hosking 1980). A small p-value rejects whiteness.
    nis_mean : float
        Time average of :math:`e_k^\top S_k^{-1} e_k`; about :math:`n_y` when the
        covariances are right.
    nis_bounds : (float, float)
        Its two-sided 95 % interval for independent samples
        (:func:`estim.chi2_bounds`).
    """

    autocorrelation: np.ndarray
    band: float
    statistic: float
    p_value: float
    nis_mean: float
    nis_bounds: tuple[float, float]

    @property
    def white(self) -> bool:
        """Whiteness not rejected at the 5 % level."""
        return bool(self.p_value >= 0.05)


def innovation_check(whitened: np.ndarray, lags: int = DEFAULT_LAGS) -> InnovationCheck:
    r"""The :class:`InnovationCheck` of whitened innovations ``(T, ny)`` (NaN rows: missing
    outputs, left out of the sums).

    ``whitened[k] = L_k^{-1} e_k`` with :math:`L_k L_k^\top = S_k`.
    """
    from estim.metrics import chi2_bounds

    eps = np.asarray(whitened, dtype=float)
    if eps.ndim == 1:
        eps = eps[:, None]
    ok = np.isfinite(eps).all(axis=1)
    E = np.where(ok[:, None], eps, 0.0)
    T, ny = E.shape
    n = int(ok.sum())
    lags = int(min(lags, max(n - 1, 1)))
    c0 = E.T @ E / max(n, 1)
    scale = np.sqrt(np.maximum(np.diag(c0), 1e-300))
    rho = np.empty((lags + 1, ny, ny))
    q = 0.0
    for lag in range(lags + 1):
        both = ok[lag:] & ok[:T - lag]
        C = (E[lag:][both].T @ E[:T - lag][both]) / max(n, 1)
        rho[lag] = C / np.outer(scale, scale)
        if lag:
            q += float(np.sum(rho[lag] ** 2)) / max(n - lag, 1)
    q *= n * (n + 2)
    from scipy import stats

    dof = lags * ny * ny
    nis = np.sum(E**2, axis=1)[ok]
    return InnovationCheck(autocorrelation=rho, band=1.96 / np.sqrt(max(n, 1)),
                           statistic=q, p_value=float(stats.chi2.sf(q, dof)),
                           nis_mean=float(nis.mean()) if n else float("nan"),
                           nis_bounds=chi2_bounds(ny, max(n, 1)))


@dataclass
class TuningResult:
    """Noise covariances (and parameters) estimated from data.

    Attributes
    ----------
    method : str
        ``"als"`` or ``"maximum likelihood"``.
    Q : (nx, nx) array
        Process-noise covariance (with ``continuous=True`` the spectral density
        :math:`Q_c`, ``(nq, nq)`` for a noise input of ``nq`` columns).
    R : (ny, ny) array
        Measurement-noise covariance.
    params : dict of str -> float
        Model parameters estimated along (maximum likelihood with ``params=``);
        empty otherwise.
    stderr : dict
        Standard errors: ``stderr["Q"]`` and ``stderr["R"]`` arrays shaped like
        ``Q`` and ``R`` (NaN for entries held fixed by the structure), and
        ``stderr["params"]`` a dict like ``params``.
    check : InnovationCheck
        The innovations of the filter run with the estimates.
    objective : float
        The minimised objective: the ALS least-squares cost, or the negative
        log-likelihood.
    success : bool
        The optimiser converged.
    status : str
        ``"ok"`` or what went wrong.
    details : dict
        Method-specific data (the ALS lags and weighting, the starts of maximum
        likelihood and their objectives, ...).
    """

    method: str
    Q: np.ndarray
    R: np.ndarray
    params: dict = field(default_factory=dict)
    stderr: dict = field(default_factory=dict)
    check: InnovationCheck | None = None
    objective: float = float("nan")
    success: bool = True
    status: str = "ok"
    details: dict = field(default_factory=dict)

    def summary(self) -> str:
        """A plain-text table of the estimates with standard errors and the diagnostics."""
        lines = [f"{self.method}: {self.status}, objective {self.objective:.6g}"]

        def block(name: str, M: np.ndarray) -> None:
            se = self.stderr.get(name)
            for i in range(M.shape[0]):
                for j in range(i, M.shape[1]):
                    if i != j and M[i, j] == 0 and (se is None or not se[i, j] > 0):
                        continue
                    s = f" ± {se[i, j]:.3g}" if se is not None and np.isfinite(se[i, j]) else ""
                    lines.append(f"  {name}[{i},{j}] = {M[i, j]:.6g}{s}")

        block("Q", np.atleast_2d(self.Q))
        block("R", np.atleast_2d(self.R))
        for k, v in self.params.items():
            se = self.stderr.get("params", {}).get(k, float("nan"))
            lines.append(f"  {k} = {v:.6g}" + (f" ± {se:.3g}" if np.isfinite(se) else ""))
        if self.check is not None:
            c = self.check
            lo, hi = c.nis_bounds
            lines.append(f"  innovations: Ljung-Box p = {c.p_value:.3g} "
                         f"({'white' if c.white else 'not white'} at 5 %), "
                         f"NIS mean {c.nis_mean:.3g} (95 % interval {lo:.3g}..{hi:.3g})")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.summary()

    def plot(self, path=None):
        """Autocorrelation of the whitened innovations per output pair, with the 95 % band
        of a white sequence; returns the matplotlib Figure."""
        from estim.plotting import _finish, _pyplot

        if self.check is None:
            raise ValueError("this result has no innovation check to plot")
        plt = _pyplot()
        rho = self.check.autocorrelation
        ny = rho.shape[1]
        fig, axes = plt.subplots(ny, ny, figsize=(3.2 * ny + 1, 2.4 * ny + 0.6),
                                 squeeze=False, sharex=True, constrained_layout=True)
        lags = np.arange(rho.shape[0])
        for i in range(ny):
            for j in range(ny):
                ax = axes[i, j]
                ax.vlines(lags[1:], 0, rho[1:, i, j], color="C0")
                ax.plot(lags[1:], rho[1:, i, j], "o", ms=3, color="C0")
                ax.axhspan(-self.check.band, self.check.band, color="0.85", lw=0)
                ax.axhline(0, color="0.4", lw=0.6)
                ax.set_title(f"output {i} vs {j}", fontsize="small")
                if i == ny - 1:
                    ax.set_xlabel("lag (samples)")
        fig.suptitle(f"{self.method}: innovation autocorrelation (Ljung-Box p = "
                     f"{self.check.p_value:.3g})", fontsize="medium")
        return _finish(fig, path)
