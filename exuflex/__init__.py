"""exuflex: planar flexible multibody dynamics (ERLS) and reduced-order state estimation.

exuflex's matrices are small (tens of rows); multithreaded BLAS only adds synchronisation overhead to
them (measured: a 22x22 LU solve 4 ms with OpenBLAS threads on a busy 2-core machine, 10 us without).
Unless the user has chosen otherwise, BLAS runs single-threaded: set before NumPy loads its BLAS when
exuflex is imported first (the CLI), else through threadpoolctl if it is installed.
"""

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
