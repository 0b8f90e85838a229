"""The one rich console of the program and the Reporter the stages talk to."""
from __future__ import annotations

import contextlib
from typing import Iterator

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, SpinnerColumn,
                           TextColumn, TimeElapsedColumn, TimeRemainingColumn)
from rich.markup import escape
from rich.text import Text

console = Console(stderr=True, highlight=False)
state = {"quiet": False, "verbose": False}


class RateColumn(ProgressColumn):
    """Steps per second (or seconds per step when slower than one a second)."""

    def render(self, task) -> Text:
        speed = task.finished_speed or task.speed
        if not speed:
            return Text("-- it/s", style="dim")
        return Text(f"{speed:.2f} it/s" if speed >= 1 else f"{1 / speed:.2f} s/it", style="cyan")


class _RichTask:
    def __init__(self, progress: Progress, task_id: int):
        self.progress, self.task_id = progress, task_id

    def advance(self, n: float = 1, **fields: object) -> None:
        text = "  ".join(f"{k}={_fmt(v)}" for k, v in fields.items())
        self.progress.update(self.task_id, advance=n, fields=text)


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


class _NullTask:
    def advance(self, n: float = 1, **fields: object) -> None:
        pass


class _LineTask:
    """Not a terminal but --verbose: one plain line per step, so a log (or a script) sees each one finish."""

    def __init__(self, description: str, total: float | None):
        self.description, self.total, self.done = description, total, 0.0

    def advance(self, n: float = 1, **fields: object) -> None:
        self.done += n
        of = f"/{self.total:g}" if self.total is not None else ""
        text = "  ".join(f"{k}={_fmt(v)}" for k, v in fields.items())
        console.print(escape(f"{self.description}: {self.done:g}{of}  {text}"), soft_wrap=True)


class RichReporter:
    """Progress bars with rate and ETA on stderr; --quiet keeps only warnings and summaries."""

    @contextlib.contextmanager
    def task(self, description: str, total: float | None) -> Iterator[object]:
        if state["quiet"] or not console.is_terminal:
            # Not a terminal (a log, CI): no bar redraws; one line at start (and one per step with --verbose).
            if not state["quiet"]:
                console.print(f"[dim]{escape(description)} …[/]")
            yield _LineTask(description, total) if state["verbose"] and not state["quiet"] else _NullTask()
            return
        columns = [SpinnerColumn(), TextColumn("[bold]{task.description}"), BarColumn(),
                   MofNCompleteColumn(), RateColumn(), TimeElapsedColumn(), TextColumn("eta"),
                   TimeRemainingColumn(), TextColumn("{task.fields[fields]}")]
        with Progress(*columns, console=console, transient=False) as progress:
            tid = progress.add_task(description, total=total, fields="")
            yield _RichTask(progress, tid)

    def info(self, message: str) -> None:
        if not state["quiet"]:
            console.print(escape(str(message)))

    def warn(self, message: str) -> None:
        console.print(f"[yellow]warning:[/] {escape(str(message))}")

    def summary(self, message: str) -> None:
        console.print(f"[green]✓[/] {escape(str(message))}")


def error(message: str) -> None:
    """One red sentence; the message is user text (paths, values) and is printed escaped, never as markup."""
    console.print(f"[bold red]error:[/] {escape(str(message))}", soft_wrap=True)


def out(message: str, markup: bool = True) -> None:
    """Results meant for stdout (e.g. `rsl info`); user text inside ``message`` must be escaped
    (rich.markup.escape) by the caller, or the whole line printed with ``markup=False``."""
    Console(highlight=False, soft_wrap=True).print(message, markup=markup)
