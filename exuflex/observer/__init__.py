"""Model-agnostic multirate state estimation (paper eqs. 10-15) for any :class:`DiscreteModel`.

- :mod:`.base`: the model protocol, a linear reference model, the divergence error.
- :mod:`.ekf`: :class:`MultirateEKF` (online ``step`` and offline ``run``), :class:`EstimationResult`.
- :mod:`.bound`: steady-state Kalman covariance (the best achievable error), linearisation.
- :mod:`.stats`: NEES/NIS, Monte-Carlo chi-square consistency, error metrics, FFT peaks.
- :mod:`.tuning`: process-noise construction and NIS-based scaling.
- :mod:`.session`: the observer as users run it on a mechanism and a log (``make_observer``, ``ObserverConfig``,
  ``estimate``, ``observe_run``, ``estimation_bound``), importable from here.
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
    # the session layer (lazy: it builds on the reduction)
    "ObserverConfig",
    "Observer",
    "make_observer",
    "estimate",
    "observe_run",
    "estimation_bound",
]

_SESSION = ("ObserverConfig", "Observer", "make_observer", "estimate", "observe_run", "estimation_bound")


def __getattr__(name: str):
    if name in _SESSION:
        from . import session

        return getattr(session, name)
    raise AttributeError(f"module 'exuflex.observer' has no attribute {name!r}")
