"""Independent runs of a benchmark sweep, here, in a local process pool, or as Ray tasks on a cluster.

    from _parallel import add_parallel_args, map_tasks
    add_parallel_args(parser)                      # --workers N, --ray ADDRESS
    results = map_tasks(run_one, [(a, b), ...], workers=args.workers, ray=args.ray)

``run_one`` must be a module-level function (the pool and Ray send it to other processes); results come
back in the order of the argument list, whichever process ran them.  Sweeps whose *timings* are the
result must not use this: runs sharing a machine disturb each other's clocks.
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Callable, Sequence

_ENV = {"JAX_ENABLE_X64": "1", "JAX_PLATFORMS": "cpu"}  # as stages.steps.generate_data.RAY_ENV


def add_parallel_args(parser: argparse.ArgumentParser) -> None:
    """--workers and --ray options of a sweep script."""
    parser.add_argument("--workers", type=int, default=1, help="Local worker processes for the sweep's runs.")
    parser.add_argument("--ray", default="", metavar="ADDRESS",
                        help="Run the sweep's runs as Ray tasks on the cluster at ADDRESS ('auto', 'HOST:PORT' or "
                             "'ray://HOST:10001'); see docs/cluster.md.")


def _worker_init() -> None:
    for k, v in _ENV.items():
        os.environ.setdefault(k, v)


def _call(fn: Callable, args: tuple) -> Any:
    _worker_init()
    return fn(*args)


def map_tasks(fn: Callable, arg_list: Sequence[tuple], workers: int = 1, ray: str = "") -> list:
    """[fn(*args) for args in arg_list], run in this process (workers 1), a 'spawn' pool of ``workers``
    processes, or as Ray tasks on the cluster at ``ray`` (then ``workers`` is ignored)."""
    arg_list = [tuple(a) for a in arg_list]
    if ray:
        return _map_ray(fn, arg_list, ray)
    if workers <= 1 or len(arg_list) <= 1:
        return [fn(*a) for a in arg_list]
    ctx = multiprocessing.get_context("spawn")  # JAX does not fork safely
    with ProcessPoolExecutor(max_workers=min(workers, len(arg_list)), mp_context=ctx,
                             initializer=_worker_init) as pool:
        return list(pool.map(_call, [fn] * len(arg_list), arg_list))


def _map_ray(fn: Callable, arg_list: list[tuple], address: str) -> list:
    from stages.errors import RslError
    from stages.steps.generate_data import connect_ray  # one way to reach a cluster, shared with rsl generate-data

    try:
        ray, started_here = connect_ray(address)
    except RslError as e:
        raise SystemExit(str(e)) from None
    # Send this module and the sweep's own module by value: on a cluster's nodes only rsl is installed
    # (stages.*), not the bench scripts.
    for name in {__name__, fn.__module__}:
        mod = sys.modules.get(name)
        if mod is not None and name != "__main__" and not name.startswith(("stages", "rsl_cli")):
            ray.cloudpickle.register_pickle_by_value(mod)
    try:
        remote = ray.remote(_call)
        return ray.get([remote.remote(fn, a) for a in arg_list])
    finally:
        if started_here:
            ray.shutdown()
