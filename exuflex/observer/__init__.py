"""State estimation on flexible-multibody models (paper eqs. 8-15).

- :mod:`.base`: what a model supplies to the filter (:class:`Prediction`, :class:`Measurement`), a linear model.
- :mod:`.ekf`: :class:`MultirateEKF`, one driver over the model's predict and measure steps (online ``step``,
  offline ``run``), :class:`EstimationResult`; the Kalman algebra compiled in :mod:`.kalman`.
- :mod:`.reduced`: the reduced ERLS model as the filter's model (cached step or the exact RK4 reference), with
  the second-order expansion about held configurations in :mod:`.expansion`; :mod:`.full`: the full-order model.
- :mod:`.session`: the observer as users run it (:func:`make_observer`, :func:`estimate`); scored against a
  truth and its bound in :mod:`exuflex.scoring`.
- :mod:`.stats`: the filter's quantiles.
- Beyond the paper: :mod:`.augmented` (:class:`AugmentedModel`: the payload scale and motor torque disturbances as
  states), :mod:`.smoother` (:func:`rts_smooth`), :mod:`.ukf` (:class:`UnscentedKF`), :mod:`.imm` (:class:`IMMFilter`:
  interacting multiple models, the payload estimator with a nominal mode).

One sample from the log to the estimate (``exuflex observe``): :func:`exuflex.scoring.run.observe_run` reads the
log's columns a block of rows at a time (:class:`exuflex.runs.LogColumns`, the torques held where not sampled) and
hands them to :func:`.session.estimate_chunks`, which runs the filter over each block
(:meth:`.ekf.BeliefFilter.run`, the one driver) and maps its estimates to the physical quantities
(:meth:`.session.Observer.physical`). The driver hands the samples the model's compiled step can take to the one
compiled sample loop (:func:`.loop.samples`): per sample the model's interval (:func:`.expansion.cached_interval`),
the covariance's prediction (:func:`.kalman.predict_cov`), the model's measurement
(:func:`.expansion.cached_rows`), the update (:func:`.kalman.condition_on`) and the monitors (:func:`.loop.screen`'s
tests), until a sample needs the model's Python side (new held arrays: the loop resumes after) or its own step
(:meth:`.ekf.BeliefFilter.step`: the model's :meth:`~.base.DiscreteModel.predict` and
:meth:`~.base.DiscreteModel.measure`, the same sample in the same compiled code, :func:`.loop.given`). The UKF
and the IMM take every sample through ``step`` (their own prediction and update in Python, the monitors compiled).
"""

from .augmented import AugmentedModel
from .base import DiscreteModel, FilterDivergedError, LinearDiscreteModel, Measurement, Prediction
from .ekf import EstimationResult, MultirateEKF, NISMonitor
from .imm import IMMFilter
from .reduced import ReducedObserverModel
from .smoother import SmoothedResult, rts_smooth
from .ukf import UnscentedKF
from .session import Observer, ObserverConfig, estimate, make_observer

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
    "estimate",
    "make_observer",
]
