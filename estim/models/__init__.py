"""The benchmark systems, as :class:`estim.Model` factories.

Every factory takes the model's parameters as keywords, so
``estim.models.batch_reactor(k1=0.6)`` is the same reactor with another
rate constant.
"""

from estim.models.batch_reactor import batch_reactor
from estim.models.lorenz import lorenz
from estim.models.runaway import runaway
from estim.models.satellite import PDAttitudeController, reference_attitude, satellite
from estim.models.van_der_pol import van_der_pol

__all__ = ["batch_reactor", "lorenz", "runaway", "satellite", "van_der_pol",
           "PDAttitudeController", "reference_attitude"]
