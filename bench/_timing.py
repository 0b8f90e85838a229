"""Timing shared by the benchmarks (run as `python bench/NAME.py`, so this folder is on sys.path)."""
from __future__ import annotations

import statistics
import time
from typing import Callable


def median_times(fn: Callable[[], object], repeats: int, warmup: bool = False) -> tuple[float, float]:
    """(median wall seconds, median CPU seconds of this process) over ``repeats`` runs,
    after one untimed run when ``warmup``."""
    if warmup:
        fn()
    ts, cs = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    return statistics.median(ts), statistics.median(cs)
