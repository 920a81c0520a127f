"""The benchmark systems, as :class:`estim.Model` factories.

Every factory takes the model's parameters as keywords, so
``estim.models.batch_reactor(k1=0.6)`` is the same reactor with another
rate constant.
"""

from estim.models.batch_reactor import batch_reactor
from estim.models.constant_velocity import constant_velocity
from estim.models.localization import (
    martinelli_simple,
    odometry_circular,
    odometry_noncircular,
    quadrotor_ko2019,
)
from estim.models.lorenz import lorenz
from estim.models.pendulum import pendulum
from estim.models.runaway import runaway
from estim.models.satellite import (
    PDAttitudeController,
    nadir_in_body,
    reference_attitude,
    satellite,
    satellite_rates,
)
from estim.models.sine_pendulum import sine_pendulum
from estim.models.van_der_pol import van_der_pol
from estim.models.vertical_channel import vertical_channel

__all__ = ["batch_reactor", "constant_velocity", "lorenz", "martinelli_simple", "odometry_circular",
           "odometry_noncircular", "pendulum", "quadrotor_ko2019", "runaway", "satellite",
           "satellite_rates", "sine_pendulum", "van_der_pol", "vertical_channel",
           "PDAttitudeController", "nadir_in_body", "reference_attitude"]
