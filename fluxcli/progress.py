"""Progress that moves: fractions reported from inside long tasks, in this process or in
``--jobs`` worker processes, shown as one bar with an ETA.

:func:`run_tasks` runs ``fn(*args, progress=callback)`` for each argument tuple, serially
or in a process pool, and advances one bar by the fraction each task reports (e.g.
:func:`fluxcli.optics.transfer.build_transfer` reports after every batch of rays).
Workers send their fractions through a manager queue; the parent drains it a few times
a second, so the bar and its ETA move smoothly however many workers run.
"""

from __future__ import annotations

import contextlib
import queue as _queue
import sys
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from functools import partial
from typing import Callable, Iterator, Sequence

SCALE = 1000  # bar units per task


def _put(q, task: int, fraction: float) -> None:
    q.put((task, float(fraction)))


@contextlib.contextmanager
def _bar(label: str, n_tasks: int, quiet: bool) -> Iterator[Callable[[float], None]]:
    """Yields ``show(units, tasks_finished)``; nothing is drawn when quiet or when there is nothing to do."""
    if quiet or n_tasks == 0:
        yield lambda units, finished: None
        return
    from rich.console import Console
    from rich.progress import (BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    bar = Progress(TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(),
                   TextColumn("{task.fields[tasks]}"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                   console=Console(file=sys.stderr), transient=False, refresh_per_second=8)
    with bar:
        t = bar.add_task(label, total=n_tasks * SCALE, tasks=f"0/{n_tasks}")
        yield lambda units, finished: bar.update(t, completed=units, tasks=f"{finished}/{n_tasks}")


def run_tasks(fn: Callable, arglists: Sequence[tuple], *, label: str, jobs: int = 1, quiet: bool = False,
              pool: Callable[[int], contextlib.AbstractContextManager] | None = None, poll_s: float = 0.2,
              remote: bool = False) -> list:
    """Run ``fn(*args, progress=cb)`` for every ``args``; results in the order given.

    Parameters
    ----------
    fn : picklable callable taking ``progress`` (called with the fraction 0..1 done).
    arglists : the positional arguments of each task.
    jobs : worker processes (1: run here).
    pool : ``pool(n_workers)`` -> context manager yielding an executor (default ProcessPoolExecutor);
        local workers send their fractions through a manager queue.
    remote : ``pool`` is a cluster (:mod:`fluxcli.cluster`): every task goes to it even with one
        job or one task, and its executor's ``progress_queue()`` carries the fractions.
    """
    n = len(arglists)
    frac = [0.0] * n
    out: list = [None] * n
    with _bar(label, n, quiet) as show:
        def note(task: int, f: float) -> None:
            frac[task] = max(frac[task], min(max(f, 0.0), 1.0))
            show(sum(frac) * SCALE, sum(x >= 1.0 for x in frac))

        if n == 0 or (not remote and (jobs <= 1 or n <= 1)):
            for i, args in enumerate(arglists):
                out[i] = fn(*args, progress=partial(note, i))
                note(i, 1.0)
            return out
        make_pool = pool or (lambda k: ProcessPoolExecutor(max_workers=k))
        with contextlib.ExitStack() as stack:
            if remote:  # a cluster carries the fractions itself
                ex = stack.enter_context(make_pool(n))
                q = stack.enter_context(ex.progress_queue())
            else:  # the manager outlives the pool: on Ctrl-C the workers are killed first
                q = stack.enter_context(_manager_queue())
                ex = stack.enter_context(make_pool(min(jobs, n)))
            futs = {ex.submit(fn, *args, progress=q.sender(i)): i for i, args in enumerate(arglists)}
            pending = set(futs)
            while pending:
                finished, pending = wait(pending, timeout=poll_s, return_when=FIRST_COMPLETED)
                for task, f in q.drain():
                    note(task, f)
                for fut in finished:
                    out[futs[fut]] = fut.result()
                    note(futs[fut], 1.0)
    return out


class _ManagerQueue:
    """Fractions from local worker processes through a multiprocessing manager queue."""

    def __init__(self, q):
        self.q = q

    def sender(self, task: int) -> Callable[[float], None]:
        return partial(_put, self.q, task)

    def drain(self) -> Iterator[tuple[int, float]]:
        with contextlib.suppress(_queue.Empty):
            while True:
                yield self.q.get_nowait()


@contextlib.contextmanager
def _manager_queue() -> Iterator[_ManagerQueue]:
    """A queue served by a manager process that dies with this one, like the workers."""
    import os
    from multiprocessing.managers import SyncManager

    from .workers import _init_worker

    manager = SyncManager()
    manager.start(_init_worker, (os.getpid(),))
    with manager:
        yield _ManagerQueue(manager.Queue())
