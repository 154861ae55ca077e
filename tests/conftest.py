"""Suite-wide set-up: the threads each test process may use.

`make test` runs the suite in pytest-xdist workers, one per core. Each worker's numerical
libraries (OpenBLAS under numpy, MKL's PARDISO, numba's parallel loops) would otherwise start
one thread per core of the machine, so every core would carry several spinning threads and
each solve would wait on the others. A worker is given its share of the cores instead. A run
without xdist (one test, or `pytest` alone) keeps the libraries' defaults.
"""
import os

_workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
if _workers:
    _cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    _threads = str(max(1, (_cores or 1) // int(_workers)))
    # read when the libraries start their thread pools (numba and MKL are first used by the
    # tests, after this file is imported); dask workers started by the tests inherit them
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ.setdefault(_var, _threads)
    # numpy's OpenBLAS may already be loaded (by a plugin): limit its running pool too
    from threadpoolctl import threadpool_limits

    threadpool_limits(int(_threads))
