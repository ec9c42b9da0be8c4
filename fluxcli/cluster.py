"""Sweeps on a Dask distributed cluster: ``--scheduler ADDRESS`` (or ``FLUXMAP_SCHEDULER``).

The independent work of a run — one T per pose (build-T, simulate's forward T, the T
reconstruct needs), or, when the poses are fewer than the workers' threads, blocks of one
pose's T (:func:`fluxcli.transfer_cache.build_on_cluster`), and the cells of a reconstruction
sweep — goes to the workers of a running ``dask scheduler`` instead of local processes;
without an address nothing here is used and ``--jobs`` runs local processes as before.

What a task carries and does:

- meshes and numbers, never an Embree scene: each worker builds its own scene from the
  surface and occluder arrays (once per pose and worker process for a pose's blocks);
  what many tasks share travels as a path in the shared cache, never inside the task graph
  (a pose's scene, pickled beside its partial files; a sweep cell's T, its cache file),
  so that nothing is lost with a worker and no graph carries large arrays;
- it writes its file itself, atomically (:mod:`fluxcli.artefacts.atomic`), to the absolute
  path this process chose — so the T cache (``transfer.cache_dir``) and the workdir must be
  a folder every worker sees under the same path (one machine, or a shared file system);
- it is pure given its arguments, so the scheduler may retry it (a lost worker): a retried
  task rewrites the same bytes. ``SOURCE_DATE_EPOCH`` of this process travels with every
  task, so a reproducible run stays byte-identical whichever worker writes;
- it reports its fraction done as a Dask event (``Worker.log_event``) that this process
  subscribes to, so the progress bar moves as it does locally.

Ctrl-C cancels every task not yet finished; a task already running on a worker finishes
(Dask cannot interrupt a running thread) and its complete file lands in the cache, where
the next run finds it.
"""

from __future__ import annotations

import collections
import contextlib
import os
import time
import uuid
from functools import partial
from typing import Callable, Iterator

from .errors import UserError

CONNECT_TIMEOUT_S = 10.0  # how long to try to reach the scheduler before giving up (exit 2)
RETRIES = 2  # a task whose worker died is run again this many times
_ENV = ("SOURCE_DATE_EPOCH",)  # what a task must see as this process does (reproducible bytes)


def connect(address: str):
    """A ``distributed.Client`` connected to the scheduler at ``address``
    (``tcp://host:8786``, ``host:8786``); an unreachable address is a UserError naming it."""
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - a main dependency
        raise UserError("--scheduler needs dask.distributed (pip install 'dask[distributed]').") from None
    import logging

    logging.getLogger("distributed").setLevel(logging.CRITICAL)  # its own retries are not the user's business
    try:
        return Client(address, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=False)
    except (OSError, TimeoutError, ValueError) as e:
        raise UserError(f"--scheduler {address}: no Dask scheduler answers there within {CONNECT_TIMEOUT_S:g} s "
                        f"({type(e).__name__}: {e}). Start one ('dask scheduler' prints its address, "
                        "'dask worker ADDRESS' on each machine) or leave --scheduler out to run locally.") from None


def worker_threads(client) -> int:
    """How many tasks the cluster runs at once (its workers' threads; at least 1)."""
    return max(1, sum(client.nthreads().values()))


def _call(env: dict, fn: Callable, *args, **kwargs):
    """Run ``fn`` on a worker with this run's reproducibility settings."""
    for k in _ENV:
        if env.get(k) is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = env[k]
    return fn(*args, **kwargs)


class _EventProgress:
    """A task's ``progress`` callback on a worker: its fraction done as a Dask event
    (at most ~5 per second per task)."""

    def __init__(self, topic: str, task: int):
        self.topic, self.task, self._last = topic, task, 0.0

    def __call__(self, fraction: float) -> None:
        now = time.monotonic()
        if fraction < 1.0 and now - self._last < 0.2:
            return
        self._last = now
        with contextlib.suppress(Exception):  # outside a worker (a test calling it directly): no bar
            from distributed import get_worker

            get_worker().log_event(self.topic, [self.task, float(fraction)])


class _EventQueue:
    """This process's side: events from the workers, drained by :func:`fluxcli.progress.run_tasks`."""

    def __init__(self, client):
        self.client, self.topic = client, f"fluxmap-progress-{uuid.uuid4().hex}"
        self._events: collections.deque = collections.deque()
        client.subscribe_topic(self.topic, lambda event: self._events.append(tuple(event[1])))

    def sender(self, task: int) -> Callable[[float], None]:
        return _EventProgress(self.topic, task)

    def drain(self) -> Iterator[tuple[int, float]]:
        while self._events:
            yield self._events.popleft()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.client.unsubscribe_topic(self.topic)


class DaskExecutor:
    """A ``concurrent.futures``-style executor over a Dask client (submit, map, shutdown),
    plus :meth:`progress_queue` for :func:`fluxcli.progress.run_tasks`."""

    def __init__(self, client):
        self.client = client
        self._ex = client.get_executor(pure=False, retries=RETRIES)
        self._env = {k: os.environ.get(k) for k in _ENV}

    def submit(self, fn, *args, **kwargs):
        return self._ex.submit(_call, self._env, fn, *args, **kwargs)

    def map(self, fn, *iterables):
        return self._ex.map(partial(_call, self._env, fn), *iterables)

    @contextlib.contextmanager
    def progress_queue(self):
        q = _EventQueue(self.client)
        try:
            yield q
        finally:
            q.close()

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        self._ex.shutdown(wait=wait and not cancel_futures)


@contextlib.contextmanager
def dask_pool(client) -> Iterator[DaskExecutor]:
    """Tasks on the cluster; on any exception (Ctrl-C, SIGTERM, an error) every task not
    finished is cancelled before the exception goes on."""
    ex = DaskExecutor(client)
    try:
        yield ex
    except BaseException:
        ex.shutdown(wait=False, cancel_futures=True)
        raise
    ex.shutdown(wait=True)

