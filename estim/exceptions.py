"""The warnings and errors estim raises, in one module at the bottom of the package.

Every other module imports them from here (they are re-exported where users meet
them: :class:`estim.EstimationWarning`), so that no layer has to reach up to the
estimators or the compile cache for an exception class.
"""

from __future__ import annotations

__all__ = ["CompilerUnavailable", "EstimationWarning"]


class EstimationWarning(UserWarning):
    """Something a user should know about a run or a model: many steps of a run failed
    (the estimates are then mostly predictions or re-anchors), or the model has
    switches that stall a gradient-based estimator.

    Silence it with ``warnings.simplefilter("ignore", estim.EstimationWarning)``, or pass
    ``warn=False`` to :func:`~estim.simulate` / :func:`~estim.replay`.
    """


class CompilerUnavailable(RuntimeError):
    """No C compiler was found (or it failed): the interpreted path is used instead."""
