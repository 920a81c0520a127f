"""The outcome of one solve of the windowed least-squares problem."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estim.consistency import consistency_status
from estim.solvers.least_squares.robust import OUTLIER_SIGMA

__all__ = ["Solution"]


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
    messages: str = ""  # what the solver wrote to stderr (CasADi's warnings), captured

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

