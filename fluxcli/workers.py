"""Worker processes that die with their parent.

``--jobs N`` runs work in a process pool.  Its workers must not outlive the fluxmap that
started them (a SIGKILLed parent would otherwise leave them computing and holding the
pipes of a shell pipeline open): each worker asks Linux to SIGKILL it when its parent
dies (``prctl(PR_SET_PDEATHSIG)``), and also watches ``os.getppid()`` (other systems).
Workers ignore Ctrl-C; the parent cancels what is queued and kills what runs, so Ctrl-C
stops within a second or two instead of waiting for the poses in flight.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Iterator

_PR_SET_PDEATHSIG = 1


def _watch_parent(parent: int) -> None:
    while True:
        if os.getppid() != parent:
            os._exit(1)
        time.sleep(0.25)


_SPAWN_BLOCKED = {signal.SIGINT, signal.SIGTERM}


def _init_worker(parent: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    # the parent forked us with these blocked (see worker_pool): a Ctrl-C that reached the process
    # group between the fork and here is now pending and ignored, never a KeyboardInterrupt traceback
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _SPAWN_BLOCKED)
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:  # the parent died before we got here
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()


def kill_pool(ex: ProcessPoolExecutor) -> None:
    """Cancel queued work and kill the running workers now."""
    procs = list(getattr(ex, "_processes", {}).values())
    manager = getattr(ex, "_executor_manager_thread", None)  # shutdown() forgets it
    ex.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        with contextlib.suppress(Exception):
            p.kill()
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(timeout=2)
    # Let the pool's manager thread see its dead workers and close its wake-up pipe now: left
    # running, it can close the pipe while the interpreter's exit hook writes to it, which
    # prints "OSError: Bad file descriptor" under the user's clean "terminated".
    if manager is not None:
        with contextlib.suppress(Exception):
            manager.join(timeout=2)


@contextlib.contextmanager
def worker_pool(jobs: int, temp_dirs: tuple = ()) -> Iterator[ProcessPoolExecutor]:
    """A process pool whose workers die with this process; on any exception (Ctrl-C,
    SIGTERM, an error) queued work is cancelled, running workers are killed, and the
    temporary files they were writing in ``temp_dirs`` are removed."""
    ex = ProcessPoolExecutor(max_workers=jobs, initializer=_init_worker, initargs=(os.getpid(),))
    # Start the workers now with SIGINT/SIGTERM blocked: they inherit the mask and unblock only once
    # they ignore Ctrl-C.  Here a signal is merely delayed until the mask is restored below.
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _SPAWN_BLOCKED)
    try:
        ex.submit(int)  # a no-op; with the fork start method this forks every worker
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
    try:
        yield ex
        ex.shutdown(wait=True)  # inside the try: a signal that lands while the pool winds down is handled too
    except BaseException:
        kill_pool(ex)
        from .artefacts.atomic import clean_stale_temps

        for d in temp_dirs:
            clean_stale_temps(d)
        raise


def pool_for(client=None, temp_dirs: tuple = ()):
    """``pool(n_workers)`` -> executor context: local worker processes (:func:`worker_pool`),
    or the Dask cluster behind ``client`` (``--scheduler``; :mod:`fluxcli.cluster`)."""
    if client is not None:
        from .cluster import dask_pool

        return lambda n: dask_pool(client)
    return lambda n: worker_pool(n, temp_dirs=temp_dirs)


@contextlib.contextmanager
def blas_threads(n: int = 1) -> Iterator[None]:
    """Run the body with at most ``n`` BLAS/LAPACK threads.

    The reconstruction's dense solves (eigendecompositions and Cholesky factors of ~10³ x 10³
    normal matrices) are too small for OpenBLAS's threads to pay off, and on a shared
    machine its spinning threads fight other processes: measured on the 2-core machine under
    load (paper-3d, 1600 elements), one thread took 1.7 s of CPU for the default method where
    two took 15 s, and a 1600 x 1600 Cholesky 0.23 s of wall time where two threads took 6.9 s.
    Parallelism comes from ``--jobs`` / ``--scheduler`` over independent solves instead."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=n, user_api="blas"):
        yield
