"""Load heavy packages (jax, torch, numba kernels) on first use, so that `rsl --help`
and commands that do not need them start in well under a second."""
from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any


class LazyModule(ModuleType):
    """A stand-in for ``import NAME as alias`` that imports NAME on first attribute access."""

    def __init__(self, name: str):
        super().__init__(name)
        self.__dict__["_lazy_name"] = name
        self.__dict__["_lazy_module"] = None

    def _load(self) -> ModuleType:
        mod = self.__dict__["_lazy_module"]
        if mod is None:
            mod = importlib.import_module(self.__dict__["_lazy_name"])
            self.__dict__["_lazy_module"] = mod
        return mod

    def __getattr__(self, attr: str) -> Any:
        return getattr(self._load(), attr)


def lazy_module(name: str) -> Any:
    """``st = lazy_module("stages.sim.stress")`` behaves like ``from stages.sim import stress as st``."""
    return LazyModule(name)
