"""Shared test setup: float64 JAX on the CPU, paths to sample and shared data."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_DATA = ROOT / "sample_data"
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} not present")
    return SHARED_DATA


@pytest.fixture(scope="session")
def sample_data() -> Path:
    return SAMPLE_DATA


def run_rsl(*args: str, cwd: Path | None = None, check: bool = False) -> subprocess.CompletedProcess:
    """Run the real CLI in a subprocess; returns the CompletedProcess (text mode)."""
    env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu", COLUMNS="200")
    proc = subprocess.run([sys.executable, "-m", "rsl_cli.app", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"rsl {' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr}")
    return proc


@pytest.fixture
def rsl():
    """The CLI as a function: rsl("tetrahedralize", capture, "-w", ws)."""
    return run_rsl
