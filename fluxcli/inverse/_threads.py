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
import pickle
import signal
import sys
import threading
import traceback

WAIT_S = 0.05  # the main thread's longest wait between two chances to run a signal handler
WORKERS = max(1, min(2, os.cpu_count() or 1))  # the solves' threads (the issue's bar: 2 cores)

_busy: list[threading.Thread] = []  # workers left running by an interrupted wait
_children: set[int] = set()  # child processes solving (in_child)
_exit_status = [None]


def _exit_now() -> None:
    """atexit: after an interrupted wait, end here (no finalisation under a worker inside C)."""
    if _exit_status[0] is not None:  # set only where a worker was still busy
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

    done = [threading.Event() for _ in range(n)]

    def work(k):
        _local.parallel = parallel
        try:
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
        finally:
            done[k].set()

    threads = [threading.Thread(target=work, args=(k,), daemon=True, name=f"fluxmap-solve-{k}") for k in range(n)]
    for t in threads:
        t.start()
    try:
        # an Event, not Thread.join: a join interrupted by a signal handler's exception marks a
        # thread that is still running as stopped (Python 3.11, bpo-45274's fix)
        for ev in done:
            while not ev.wait(WAIT_S):
                pass
    except BaseException as e:
        # Ctrl-C / SIGTERM (or anything else) while the workers are busy: let it unwind now
        with lock:
            errors.append(e)  # the workers take no further task
        for pid in list(_children):  # a dense solve in a child process: it has nothing to leave behind
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        _busy.extend(t for t, ev in zip(threads, done) if not ev.is_set())
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


def in_child(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` in a forked child process, its result (pickled) sent back.

    For calls into C that keep the GIL: scipy's LAPACK wrappers (``eigh``, ``cholesky``,
    ``solve_triangular``, ``cho_solve``) hold it for their whole run (measured: 1.3 s of a
    generalised ``eigh`` at 1 500 unknowns under load, the main thread frozen throughout), so a
    worker thread cannot leave the main thread free; a child process can.  An interrupted wait
    kills the child (SIGKILL: it writes no file); the child dies with its parent (Linux).
    The child computes exactly what the call would have here (same code, a copy of the same
    memory), so results are unchanged.  Where there is no ``fork``, the call runs here."""
    if not hasattr(os, "fork"):
        return fn(*args, **kwargs)
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: compute, send, leave without running the parent's exit handlers
        status = 0
        try:
            os.close(r)
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            try:
                import ctypes

                ctypes.CDLL("libc.so.6").prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
            except (OSError, AttributeError):
                pass
            try:
                out = (True, fn(*args, **kwargs))
            except BaseException as e:  # noqa: BLE001 - re-raised in the parent
                out = (False, e, traceback.format_exc())
            try:
                data = pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL)
            except Exception as e:  # noqa: BLE001
                data = pickle.dumps((False, RuntimeError(f"the solve's result could not be sent back: {e}"), ""))
            with os.fdopen(w, "wb") as f:
                f.write(data)
        except BaseException:  # noqa: BLE001
            status = 1
        finally:
            os._exit(status)
    os.close(w)
    _children.add(pid)
    try:
        with os.fdopen(r, "rb") as f:
            data = f.read()
    finally:
        try:
            os.waitpid(pid, 0)
        except ChildProcessError:
            pass
        _children.discard(pid)
    if not data:
        raise RuntimeError("the solve's child process ended without a result (killed: out of memory?)")
    out = pickle.loads(data)
    if out[0]:
        return out[1]
    err = out[1]
    if out[2] and hasattr(err, "add_note") and not isinstance(err, ValueError):
        err.add_note("in the solve's child process:\n" + out[2])
    raise err


# ------------------------------------------------------------------ objects made and freed on one thread


class _Owner:
    """A thread that makes objects, keeps them, and frees them when their handle goes."""

    def __init__(self, k: int):
        import itertools
        import queue

        self.jobs: queue.SimpleQueue = queue.SimpleQueue()
        self.objs: dict = {}
        self.ids = itertools.count()
        threading.Thread(target=self._run, daemon=True, name=f"fluxmap-factor-{k}").start()

    def _run(self):
        while True:
            job = self.jobs.get()
            if job is None:
                return
            job()

    def close(self, timeout: float) -> None:
        """Free what it holds, on its thread, and end it (before the interpreter finalises)."""
        done = threading.Event()
        self.jobs.put(lambda: (self.objs.clear(), done.set()))
        self.jobs.put(None)
        done.wait(timeout)


class Owned:
    """A handle on an object that lives on its owner's thread: attributes (``.solve``) are the
    object's; when the handle goes, the owner drops the object, on its own thread."""

    __slots__ = ("_owner", "_id")

    def __init__(self, owner: _Owner, i: int):
        self._owner, self._id = owner, i

    def __getattr__(self, name):
        return getattr(self._owner.objs[self._id], name)

    def __del__(self):
        if _closed:
            return
        try:
            self._owner.jobs.put(lambda o=self._owner, i=self._id: o.objs.pop(i, None))
        except Exception:  # noqa: BLE001 - interpreter shutting down
            pass


_owners_lock = threading.Lock()
_idle = None  # queue of owners free to make the next object
_all_owners: list = []
_closed: list = []


def _close_owners() -> None:
    """atexit: the owners free their objects on their own threads while the interpreter is
    whole (a SuperLU object freed during finalisation left exit status 120).  Not after an
    interrupted wait: an owner may be inside C; :func:`_exit_now` ends the process then."""
    if _exit_status[0] is not None:
        return
    _closed.append(True)
    for o in _all_owners:
        o.close(timeout=5.0)


def _wait(ev: threading.Event) -> None:
    """Wait for ``ev``; in slices on the main thread (signals), marking the exit if interrupted."""
    if threading.current_thread() is not threading.main_thread():
        ev.wait()
        return
    try:
        while not ev.wait(WAIT_S):
            pass
    except BaseException as e:
        _exit_status[0] = (130 if isinstance(e, KeyboardInterrupt) else 143 if type(e).__name__ == "Terminated" else 1)
        raise


def owned(fn, *args, **kwargs) -> Owned:
    """``fn(*args, **kwargs)`` made on an owner thread (one of :data:`WORKERS`, so two can be
    made at once), a handle on it returned.  For scipy's SuperLU: it frees a factorisation's
    memory only on the thread that made it (its allocations are tracked per thread), so a
    factorisation made on a passing worker thread and dropped elsewhere was never freed
    (0.7 GB per factorisation at 45 568 unknowns: 7-8 GB after a λ search)."""
    global _idle
    import queue

    with _owners_lock:
        if _idle is None:
            _idle = queue.Queue()
            for k in range(WORKERS):
                _all_owners.append(_Owner(k))
                _idle.put(_all_owners[-1])
            atexit.register(_close_owners)  # runs before _exit_now (registered first)
    main = threading.current_thread() is threading.main_thread()
    while True:
        try:
            owner = _idle.get(timeout=WAIT_S if main else None)
            break
        except queue.Empty:
            continue
    done, box = threading.Event(), {}

    def job():
        try:
            i = next(owner.ids)
            owner.objs[i] = fn(*args, **kwargs)
            box["id"] = i
        except BaseException as e:  # noqa: BLE001 - raised where it was asked for
            box["err"] = e
        finally:
            done.set()

    owner.jobs.put(job)
    try:
        _wait(done)
    finally:
        _idle.put(owner)  # an interrupted job still runs: later jobs queue behind it
    if "err" in box:
        raise box["err"]
    return Owned(owner, box["id"])
