"""State estimation: the UKF fusing 500 Hz IMU and 100 Hz MoCap. Pure numerics, no I/O.

``Ukf(EstimatorConfig())`` is the object the 500 Hz loop calls: ``predict`` with every IMU sample,
``update_pose`` with every MoCap frame (fused at its capture time), ``estimate`` every tick.
"""

from .config import EstimatorConfig
from .types import EstimatorHealth, HealthFlag, StateEstimate
from .ukf import PoseVerdict, ResetInfo, Ukf

__all__ = ["EstimatorConfig", "EstimatorHealth", "HealthFlag", "PoseVerdict", "ResetInfo",
           "StateEstimate", "Ukf"]
