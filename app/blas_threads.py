"""One BLAS thread per process: the linear algebra of a calibration (normal equations of a few hundred
unknowns, OpenCV's LAPACK calls inside stereoCalibrate and calibrateCamera) is too small to gain from
threads, and OpenBLAS's threads wait for work by spinning. On a machine whose cores are already busy
(the station's preview and detection threads, a second process) a spinning BLAS thread holds a core
that the thread it waits for needs: one stereoCalibrate that takes a third of a second on idle cores
then takes tens of seconds. NumPy, SciPy and OpenCV each ship their own OpenBLAS, so the limit is set
for every copy.

    limit_blas_threads()   # at a process's start: the copies loaded now, and (by the environment)
                           # those loaded later and every child process

A user who set OPENBLAS_NUM_THREADS (or OMP_NUM_THREADS) keeps their own setting.
"""

from __future__ import annotations

import os

#: the environment variables OpenBLAS reads when it loads; a user's own value is left alone
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")


def limit_blas_threads() -> bool:
    """Limit every OpenBLAS in this process, and in the processes it starts, to one thread unless the
    user chose a number. Returns whether the limit was set."""
    if any(v in os.environ for v in BLAS_THREAD_VARIABLES):
        return False
    # read by each OpenBLAS as it loads: copies not loaded yet, and child processes (which inherit it)
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    from threadpoolctl import threadpool_limits

    # the copies already loaded read no environment any more: set their thread count directly
    threadpool_limits(limits=1, user_api="blas")
    return True
