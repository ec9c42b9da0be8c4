"""Long calls into C off the main thread: Ctrl-C and SIGTERM stop a solve within a fraction of a
second, and the two cores share the work.

Python runs a signal handler in the main thread, between bytecodes: while the main thread sits
in one long call into C (SuperLU's factorisation, LAPACK's ``eigh``) a SIGTERM waits for that
call to return (issue 22: > 5 s inside the dense solve; 45 s at 2 400 unknowns under load).
Here such calls run on worker threads (SuperLU, LAPACK and BLAS release the GIL) while the main
thread waits in slices of :data:`WAIT_S`, so the handler runs at once and its exception
unwinds the stage (temporary files removed, nothing half-written) while the worker is still
busy.  A worker inside C cannot be stopped, and letting the interpreter finalise under it gave
exit status 120 or a segmentation fault (measured in the previous session); so when a wait is
interrupted, the workers are daemon threads and an ``atexit`` hook ends the process with
``os._exit`` once the rest of the exit has run (streams flushed), with the status the CLI gives
the interruption: 130 for Ctrl-C, 143 for SIGTERM (:class:`fluxcli.cli.Terminated`).

Results do not depend on the threads: each task is the same call with the same inputs, and
:func:`run_all` returns results in the order of its tasks.
"""

from __future__ import annotations

import atexit
import os
import sys
import threading

WAIT_S = 0.05  # the main thread's longest wait between two chances to run a signal handler
WORKERS = max(1, min(2, os.cpu_count() or 1))  # the solves' threads (the issue's bar: 2 cores)

_busy: list[threading.Thread] = []  # workers left running by an interrupted wait
_exit_status = [None]


def _exit_now() -> None:
    """atexit: if an interrupted wait left a worker inside C, end here (no finalisation under it)."""
    if _exit_status[0] is not None and any(t.is_alive() for t in _busy):
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - a closed stream: nothing left to flush
                pass
        os._exit(_exit_status[0])


atexit.register(_exit_now)


_local = threading.local()


def in_worker() -> bool:
    """True inside a task that runs beside others (:func:`run_all`): it runs its own tasks
    inline, one after another (no threads within threads: two cores)."""
    return getattr(_local, "parallel", False)


def run_all(tasks, workers: int | None = None, parallel: bool = True) -> list:
    """Call each of ``tasks`` (callables without arguments) on up to ``workers`` threads
    (default :data:`WORKERS`) and return their results in order; the first exception a task
    raised is raised here.  Inline, one after another, inside a task that runs beside others;
    ``parallel=False`` (one task, :func:`call`): the task may run its own tasks side by side."""
    tasks = list(tasks)
    if not tasks:
        return []
    if in_worker():
        return [t() for t in tasks]
    n = max(1, min(int(workers or WORKERS), len(tasks)))
    results: list = [None] * len(tasks)
    errors: list = []
    nxt = iter(range(len(tasks)))
    lock = threading.Lock()

    def work():
        _local.parallel = parallel
        while True:
            with lock:
                if errors:
                    return
                i = next(nxt, None)
            if i is None:
                return
            try:
                results[i] = tasks[i]()
            except BaseException as e:  # noqa: BLE001 - handed to the main thread
                with lock:
                    errors.append(e)
                return

    threads = [threading.Thread(target=work, daemon=True, name=f"fluxmap-solve-{k}") for k in range(n)]
    for t in threads:
        t.start()
    try:
        for t in threads:
            while t.is_alive():
                t.join(WAIT_S)
    except BaseException as e:
        # Ctrl-C / SIGTERM (or anything else) while the workers are busy: let it unwind now
        with lock:
            errors.append(e)  # the workers take no further task
        _busy.extend(t for t in threads if t.is_alive())
        if _busy:
            _exit_status[0] = (130 if isinstance(e, KeyboardInterrupt) else
                               143 if type(e).__name__ == "Terminated" else 1)
        raise
    if errors:
        raise errors[0]
    return results


def call(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` on a worker thread, the main thread free for signals."""
    return run_all([lambda: fn(*args, **kwargs)], workers=1, parallel=False)[0]


def off_main_thread(fn):
    """Decorate: ``fn`` runs on a worker thread when called from the main thread (every long
    call into C inside it, the dense engine's ``eigh`` and Cholesky included, then leaves the
    main thread free to stop the run at once); called from any other thread it runs there."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if threading.current_thread() is threading.main_thread():
            return call(fn, *args, **kwargs)
        return fn(*args, **kwargs)

    return wrapper
