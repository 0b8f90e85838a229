"""Progress reporting passed into stages; the library never prints by itself.

A stage receives a :class:`Reporter`; the CLI hands in a rich one, tests and
library users get :class:`SilentReporter` by default.
"""
from __future__ import annotations

import contextlib
from typing import Iterator, Protocol


class Task(Protocol):
    def advance(self, n: float = 1, **fields: object) -> None:
        """Advance by ``n`` steps; ``fields`` are shown beside the bar (e.g. loss=0.1)."""


class Reporter(Protocol):
    def task(self, description: str, total: float | None) -> contextlib.AbstractContextManager[Task]:
        """A progress bar (rate, ETA) for ``total`` steps; None = spinner."""

    def info(self, message: str) -> None:
        """A line of information (hidden with --quiet)."""

    def warn(self, message: str) -> None:
        """A warning (always shown)."""

    def summary(self, message: str) -> None:
        """The one summary line at the end of a stage (always shown)."""


class _SilentTask:
    def advance(self, n: float = 1, **fields: object) -> None:
        pass


class SilentReporter:
    """Reports nothing; records warnings and summaries for inspection."""

    def __init__(self) -> None:
        self.messages: list[str] = []

    @contextlib.contextmanager
    def task(self, description: str, total: float | None) -> Iterator[Task]:
        yield _SilentTask()

    def info(self, message: str) -> None:
        self.messages.append(message)

    def warn(self, message: str) -> None:
        self.messages.append("warning: " + message)

    def summary(self, message: str) -> None:
        self.messages.append(message)
