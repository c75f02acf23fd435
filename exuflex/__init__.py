"""exuflex: planar flexible multibody dynamics (ERLS) and reduced-order state estimation.

The public API in one place (each name is imported from its stage when first used, so ``import exuflex``
stays light)::

    import exuflex as xf

    mech = xf.load_mechanism("models/sixbar.toml")           # a model file -> Mechanism (frozen data)
    run = xf.read_run("runs/nominal")                         # a run folder, or a lab's CSV log:
    run = xf.read_lab_run("lab.csv", mech, {"T1": "motor1_Nm", "q1": "enc1_rad"}, time_column="Time_ms",
                          time_scale=1e-3)                    # your column names, time in ms
    obs = xf.make_observer(mech, xf.ObserverConfig())         # reduced model + multirate EKF
    out = xf.observe_run(mech, run, observer=obs)             # filter, check the log, score, bound for this log
    out.metrics, out.bound                                    # RMS errors per quantity, the bound for this log

    # online: one sample at a time
    obs.ekf.reset()
    x_hat = obs.ekf.step(t, u, y)                             # torques u (n_motors,), channels y (m,) or NaN
    P = obs.ekf.P                                             # its covariance

Stages: :mod:`exuflex.mechanism` (model files) -> :mod:`exuflex.erls` (full-order model) ->
:mod:`exuflex.reduction` (Craig-Bampton) -> :mod:`exuflex.observer` (EKF, bound); :mod:`exuflex.runs` (logs),
:mod:`exuflex.validate` (checks), :mod:`exuflex.groundtruth` (Exudyn), :mod:`exuflex.study`.

exuflex's matrices are small (tens of rows); multithreaded BLAS only adds synchronisation overhead to
them (measured: a 22x22 LU solve 4 ms with OpenBLAS threads on a busy 2-core machine, 10 us without).
Unless the user has chosen otherwise, BLAS runs single-threaded: set before NumPy loads its BLAS when
exuflex is imported first (the CLI), else through threadpoolctl if it is installed.
"""

import importlib as _importlib
import os as _os
import sys as _sys

__version__ = "0.1.0"

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
if "numpy" in _sys.modules:  # too late for the environment: limit the loaded BLAS if we can
    try:
        from threadpoolctl import threadpool_limits as _limits

        _limits(1, user_api="blas")
    except Exception:  # noqa: BLE001 - optional
        pass

_API = {
    "Mechanism": "exuflex.mechanism",
    "load_mechanism": "exuflex.mechanism",
    "ModelFileError": "exuflex.mechanism",
    "ErlsModel": "exuflex.erls.model",
    "CraigBampton": "exuflex.reduction",
    "ObserverConfig": "exuflex.observer.session",
    "Observer": "exuflex.observer.session",
    "make_observer": "exuflex.observer.session",
    "estimate": "exuflex.observer.session",
    "observe_run": "exuflex.scoring.run",
    "estimation_bound": "exuflex.scoring.bound",
    "metrics": "exuflex.scoring.run",
    "default_channels": "exuflex.observer.session",
    "MultirateEKF": "exuflex.observer.ekf",
    "Signals": "exuflex.sensors",
    "Run": "exuflex.runs",
    "read_run": "exuflex.runs",
    "write_run": "exuflex.runs",
    "read_csv_log": "exuflex.runs",
    "read_lab_run": "exuflex.runs",
    "check_run": "exuflex.validate",
    "LogFormatError": "exuflex.errors",
    "UsageError": "exuflex.errors",
}

__all__ = sorted(_API) + ["__version__"]


def __getattr__(name: str):
    if name in _API:
        value = getattr(_importlib.import_module(_API[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'exuflex' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))
