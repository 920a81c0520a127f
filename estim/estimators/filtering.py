"""The result of a whole record filtered in one call (:meth:`EKF.filter <estim.EKF.filter>`,
:meth:`UKF.filter <estim.UKF.filter>`, :meth:`EnKF.filter <estim.EnKF.filter>`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FilterResult:
    """A record filtered by :meth:`EKF.filter <estim.EKF.filter>`,
    :meth:`UKF.filter <estim.UKF.filter>` or :meth:`EnKF.filter <estim.EnKF.filter>`:
    what :func:`~estim.replay` (``step`` at every sample) gives, sample by sample (for
    the EnKF: ensemble means and covariances).

    Attributes
    ----------
    x : (T, nx) array
        The estimates :math:`\\hat x_{k|k}`.
    P : (T, nx, nx) array
        Their covariances.
    innovation : (T, ny) array
        The innovations :math:`y_k - h(\\bar x_k)` (for the UKF, :math:`y_k` less the
        sigma-point mean of :math:`h`; 0 where an output is missing, NaN at a failed step).
    nis : (T,) array
        Normalised innovations squared (NaN without any output measured, or at a
        failed step).
    status : tuple of str
        The status of every sample (``"ok"``, ``"suspect: ..."``, ``"rejected: ..."``,
        ``"failed: ..."``).
    success : bool
        Every step succeeded.
    """

    x: np.ndarray
    P: np.ndarray
    innovation: np.ndarray
    nis: np.ndarray
    status: tuple[str, ...]
    success: bool
