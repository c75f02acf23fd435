"""Scoring an observer: how close its estimates come to a truth, and the bound they are compared with.

- :mod:`.run`: :func:`observe_run` (a run folder's log checked, filtered and scored, with the summary a result file
  records), :func:`metrics` (RMS and max errors against a truth), the whole-log NIS test.
- :mod:`.bound`: the posterior Cramer-Rao bound, the Kalman covariance recursion of the observer's model
  linearised along the truth or the plan (:func:`estimation_bound`, :func:`bound_track`), its frozen steady state
  (:func:`steady_bound`) and observability (:class:`UnobservableError`).
- :mod:`.stats`: NEES/NIS consistency statistics, error statistics, FFT peaks.
- :mod:`.output`: the outcome on disk (``estimates.csv``, ``result.json``); :mod:`.design`: gauge stations ranked
  by the bound.
"""

from .bound import (UnobservableError, bound_rms, bound_track, estimation_bound, linearise, steady_bound,
                    steady_state_covariance)
from .run import Outcome, metrics, observe_run

__all__ = [
    "Outcome",
    "UnobservableError",
    "bound_rms",
    "bound_track",
    "estimation_bound",
    "linearise",
    "metrics",
    "observe_run",
    "steady_bound",
    "steady_state_covariance",
]
