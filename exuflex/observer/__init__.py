"""Model-agnostic multirate state estimation (paper eqs. 10-15) for any :class:`DiscreteModel`.

- :mod:`.base`: the model protocol, a linear reference model, the divergence error.
- :mod:`.ekf`: :class:`MultirateEKF` (online ``step`` and offline ``run``), :class:`EstimationResult`.
- :mod:`.bound`: steady-state Kalman covariance (the best achievable error), linearisation.
- :mod:`.stats`: NEES/NIS, Monte-Carlo chi-square consistency, error metrics, FFT peaks.
- :mod:`.tuning`: process-noise construction and NIS-based scaling.
"""

from .base import DiscreteModel, FilterDivergedError, LinearDiscreteModel
from .bound import bound_rms, linearise, steady_state_covariance
from .ekf import EstimationResult, MultirateEKF, NISMonitor

__all__ = [
    "DiscreteModel",
    "EstimationResult",
    "FilterDivergedError",
    "LinearDiscreteModel",
    "MultirateEKF",
    "NISMonitor",
    "bound_rms",
    "linearise",
    "steady_state_covariance",
]
