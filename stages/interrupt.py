"""Ctrl-C (SIGINT) for a loop whose finished steps must be saved however it ends.

Python turns SIGINT into a KeyboardInterrupt at whatever bytecode the main thread is running.  Inside compiled
code that calls back into Python that exception can come out as another one (seen in `rsl adapt`: numba's
``_numba_unpickle``, called back from an njit kernel, returned with it set, a SystemError) or be dropped.
:class:`CtrlC` keeps Python's behaviour (a KeyboardInterrupt at once) and records every SIGINT, so that

- :meth:`CtrlC.check`, called where a step is complete, raises the KeyboardInterrupt a lost one should have
  been (the loop ends at the next step boundary at the latest);
- :attr:`CtrlC.pressed` tells an ``except`` clause that an error after a Ctrl-C is the Ctrl-C's doing;
- :attr:`CtrlC.defer` holds SIGINT back (recorded, no exception) while the result is written, so a
  second (or late) Ctrl-C cannot abort the write half-way.

Where it installs no handler (see :meth:`CtrlC.install`) it changes nothing.
"""
from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

from stages.progress import Reporter


class CtrlC:
    """Between :meth:`install` and :meth:`restore`: SIGINT raises KeyboardInterrupt (as by default) and is
    counted; while :attr:`defer` is true it is only counted."""

    def __init__(self) -> None:
        self.pressed = 0  # SIGINTs received since install()
        self.defer = False  # a plain attribute: setting it is one bytecode, no KeyboardInterrupt can split it
        self._previous = None

    def _handler(self, signum, frame) -> None:
        self.pressed += 1
        if not self.defer:
            raise KeyboardInterrupt

    def install(self) -> "CtrlC":
        """Replace Python's default SIGINT handler; a caller's own handler, SIG_IGN (a background job) or a
        non-main thread is left alone."""
        if (self._previous is None and threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
            self._previous = signal.signal(signal.SIGINT, self._handler)
        return self

    def restore(self) -> None:
        """The SIGINT handler from before :meth:`install`."""
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None

    def check(self) -> None:
        """Raise KeyboardInterrupt if a Ctrl-C came and its exception was lost on the way."""
        if self.pressed and not self.defer:
            raise KeyboardInterrupt


class _CheckedTask:
    def __init__(self, task, ctrl_c: CtrlC):
        self._task, self._ctrl_c = task, ctrl_c

    def advance(self, n: float = 1, **fields: object) -> None:
        self._task.advance(n, **fields)
        self._ctrl_c.check()  # a step is reported once it is recorded: a safe place to stop


class CheckedReporter:
    """A Reporter whose tasks' ``advance`` (called once a step is done and recorded) ends the loop with a
    KeyboardInterrupt when a Ctrl-C came whose exception was lost."""

    def __init__(self, reporter: Reporter, ctrl_c: CtrlC):
        self._reporter, self._ctrl_c = reporter, ctrl_c

    @contextlib.contextmanager
    def task(self, description: str, total: float | None) -> Iterator[_CheckedTask]:
        with self._reporter.task(description, total) as task:
            yield _CheckedTask(task, self._ctrl_c)

    def __getattr__(self, name: str):  # info, warn, summary, ...
        return getattr(self._reporter, name)
