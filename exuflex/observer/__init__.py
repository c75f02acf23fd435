"""State estimation on flexible-multibody models (paper eqs. 8-15).

- :mod:`.base`: what a model supplies to the filter (:class:`Prediction`, :class:`Measurement`), a linear model.
- :mod:`.ekf`: :class:`MultirateEKF`, one driver over the model's predict and measure steps (online ``step``,
  offline ``run``), :class:`EstimationResult`; the Kalman algebra compiled in :mod:`.kalman`.
- :mod:`.reduced`: the reduced ERLS model as the filter's model (cached step or the exact RK4 reference), with
  the second-order expansion about held configurations in :mod:`.expansion`; :mod:`.full`: the full-order model.
- :mod:`.session`: the observer as users run it (:func:`make_observer`, :func:`estimate`, :func:`metrics`,
  :func:`estimation_bound`, the posterior Cramer-Rao bound along the truth or the plan).
- :mod:`.bound`, :mod:`.observability`, :mod:`.stats`, :mod:`.tuning`: the bound's Riccati recursion (along a
  trajectory, and its frozen steady state as a quick estimate), observability,
  NEES/NIS statistics, process-noise construction.
- Beyond the paper: :mod:`.augmented` (:class:`AugmentedModel`: the payload scale and motor torque disturbances as
  states), :mod:`.smoother` (:func:`rts_smooth`), :mod:`.ukf` (:class:`UnscentedKF`), :mod:`.design` (gauge
  stations ranked by the bound), :mod:`.imm` (:class:`IMMFilter`: interacting multiple models, the payload
  estimator with a nominal mode).
"""

from .augmented import AugmentedModel
from .base import DiscreteModel, FilterDivergedError, LinearDiscreteModel, Measurement, Prediction
from .bound import bound_rms, linearise, steady_state_covariance
from .ekf import EstimationResult, MultirateEKF, NISMonitor
from .imm import IMMFilter
from .reduced import ReducedObserverModel
from .smoother import SmoothedResult, rts_smooth
from .ukf import UnscentedKF
from .session import Observer, ObserverConfig, estimate, estimation_bound, make_observer, metrics, observe_run

__all__ = [
    "AugmentedModel",
    "SmoothedResult",
    "UnscentedKF",
    "rts_smooth",
    "DiscreteModel",
    "EstimationResult",
    "FilterDivergedError",
    "IMMFilter",
    "LinearDiscreteModel",
    "Measurement",
    "MultirateEKF",
    "NISMonitor",
    "Observer",
    "ObserverConfig",
    "Prediction",
    "ReducedObserverModel",
    "bound_rms",
    "estimate",
    "estimation_bound",
    "linearise",
    "make_observer",
    "metrics",
    "observe_run",
    "steady_state_covariance",
]
