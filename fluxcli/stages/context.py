"""What every stage gets besides its config: flags, and the one place that prints."""

from __future__ import annotations

import contextlib
import sys
from dataclasses import dataclass, field
from typing import Callable, Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table


@dataclass
class RunContext:
    force: bool = False
    jobs: int = 1
    quiet: bool = False
    overrides: tuple[str, ...] = ()
    client: object = None  # --scheduler: a distributed.Client (fluxcli.cluster); None runs locally
    warned: set = field(default_factory=set)  # shared by copies (dataclasses.replace), so a warning shows once
    console: Console = field(default_factory=lambda: Console(highlight=False, soft_wrap=True,
                                                              width=None if sys.stdout.isatty() else 160))

    def say(self, text: str) -> None:
        if not self.quiet:
            self.console.print(text, markup=False)

    def warn(self, text: str) -> None:
        """A warning: printed on stderr even with --quiet, once per run."""
        if text in self.warned:
            return
        self.warned.add(text)
        print(f"fluxmap: warning: {text}", file=sys.stderr, flush=True)

    @contextlib.contextmanager
    def progress(self, label: str, total: int) -> Iterator[Callable[[], None]]:
        """A progress bar on stderr (hidden with --quiet or when there is nothing to do)."""
        if self.quiet or total == 0:
            yield lambda: None
            return
        bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                       TimeElapsedColumn(), TimeRemainingColumn(), console=Console(file=sys.stderr), transient=False)
        with bar:
            task = bar.add_task(label, total=total)
            yield lambda: bar.advance(task)

    @contextlib.contextmanager
    def progress_steps(self, label: str, total: int, completed: int = 0) -> Iterator[Callable[..., None]]:
        """A progress bar that also shows the current step: ``update(step, advance=False)``."""
        if self.quiet or total == 0:
            yield lambda step, advance=False: None
            return
        bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                       TextColumn("{task.fields[step]}"), console=Console(file=sys.stderr), transient=False)
        with bar:
            task = bar.add_task(label, total=total, completed=completed, step="")
            yield lambda step, advance=False: bar.update(task, step=step, advance=1 if advance else 0)

    def table(self, header: list[str], rows: list[list]) -> None:
        if self.quiet:
            return
        t = Table(*header, show_lines=False)
        for r in rows:
            t.add_row(*[_fmt(x) for x in r])
        self.console.print(t)


def _fmt(x) -> str:
    if isinstance(x, float):
        return f"{x:.4g}" if abs(x) >= 1e-3 or x == 0 else f"{x:.3e}"
    return str(x)
