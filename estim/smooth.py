"""The former name of :mod:`estim.soft`, kept working: ``estim.smooth.relu`` is
``estim.soft.relu``, and so on for every helper.

The smooth approximations of a model's switches moved to :mod:`estim.soft`, a name that
cannot be taken for smoothing a record (the Rauch-Tung-Striebel and particle smoothers:
:meth:`EKF.smooth <estim.EKF.smooth>`, :meth:`UKF.smooth <estim.UKF.smooth>`,
:meth:`ParticleFilter.smooth <estim.ParticleFilter.smooth>`). New code imports
``from estim import soft``.
"""

from estim.soft import abs, clip, max, min, relu, sqrt, step  # noqa: A004 - the helpers' names

__all__ = ["abs", "clip", "max", "min", "relu", "sqrt", "step"]
