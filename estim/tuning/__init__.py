r"""Noise covariances from data: autocovariance least squares and maximum likelihood.

Every estimator takes ``Q`` and ``R``; on measured data nobody knows them. This
module estimates them from a record, with standard errors and a check of the
resulting filter's innovations (:class:`TuningResult`):

* :func:`als`: autocovariance least squares (Odelson, Rajamani & Rawlings 2006;
  Rajamani & Rawlings 2009) from the innovations of a filter run with any
  stable gain;
* :func:`maximum_likelihood`: the prediction-error likelihood of the EKF or UKF,
  maximised over ``Q``, ``R`` and optionally model parameters.
"""

from __future__ import annotations

from estim.tuning._result import InnovationCheck, TuningResult, innovation_check
from estim.tuning.autocovariance import als
from estim.tuning.likelihood import log_likelihood, maximum_likelihood

__all__ = ["InnovationCheck", "TuningResult", "als", "innovation_check", "log_likelihood",
           "maximum_likelihood"]
