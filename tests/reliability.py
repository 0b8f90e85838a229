"""Helpers of the reliability tests (tests/test_reliability_*.py): run `rsl` command lines through the real CLI
in a child process and check that a failure is one clear sentence.

Every command runs `rsl_cli.app.main()`, the `rsl` entry point, in a child process.  To pay the CLI's start-up
(which imports every stage) once rather than per case, :func:`batch` runs several command lines one after
another in a single child process; ``prelude`` is Python run in that child first (a fault injected into h5py,
say).  :func:`rsl_proc` runs one command exactly as a shell would.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data"

_DRIVER = r"""
import contextlib, io, json, sys
argv_file, results_file = sys.argv[1], sys.argv[2]
exec(open(sys.argv[3]).read())  # the prelude
from rsl_cli import app
results = []
for argv in json.load(open(argv_file)):
    err, out = io.StringIO(), io.StringIO()
    sys.argv = ["rsl", *argv]
    code = 0
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            app.main()
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    results.append({"returncode": code, "stderr": err.getvalue(), "stdout": out.getvalue()})
json.dump(results, open(results_file, "w"))
"""


def env() -> dict:
    return dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu", COLUMNS="200")


def batch(commands: list[list], folder: Path, prelude: str = "") -> list[subprocess.CompletedProcess]:
    """Run several `rsl ...` command lines in one child process; a CompletedProcess for each."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "argv.json").write_text(json.dumps([[str(a) for a in c] for c in commands]))
    (folder / "prelude.py").write_text(prelude)
    proc = subprocess.run([sys.executable, "-c", _DRIVER, folder / "argv.json", folder / "results.json",
                           folder / "prelude.py"], capture_output=True, text=True, env=env(), cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    return [subprocess.CompletedProcess(c, r["returncode"], r["stdout"], r["stderr"])
            for c, r in zip(commands, json.loads((folder / "results.json").read_text()))]


def rsl_proc(*args, **kw) -> subprocess.Popen:
    """`python -m rsl_cli.app ARGS` started (not waited for), stderr piped as text; SIGINT at its default, as a
    terminal's Ctrl-C finds it (a background pytest inherits SIGINT ignored)."""
    kw.setdefault("preexec_fn", lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    return subprocess.Popen([sys.executable, "-m", "rsl_cli.app", *map(str, args)], stderr=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, env=env(), cwd=ROOT, **kw)


def flat(text: str) -> str:
    """Undo rich's line wrapping."""
    return " ".join(text.split())


def assert_one_sentence(proc: subprocess.CompletedProcess, *needles: str) -> str:
    """Exit ≠ 0, one `error:` line holding every needle, no traceback; returns the flattened message."""
    err = flat(proc.stderr)
    assert proc.returncode != 0, (proc.args, proc.stderr)
    assert "Traceback" not in proc.stderr + proc.stdout, proc.stderr
    assert err.count("error:") == 1, err
    msg = err[err.index("error:"):]
    for n in needles:
        assert flat(n) in msg, f"{n!r} not in {msg!r}"
    return msg


def copy_capture(dst: Path, src: Path = SAMPLE / "bar_synth") -> Path:
    """A private copy of a sample capture."""
    shutil.copytree(src, dst)
    return dst


def edit(path: Path, old: str, new: str) -> None:
    """Replace ``old`` by ``new`` in a text file (``old`` must be there)."""
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new, 1))


def tree_bytes(folder: Path) -> dict[str, bytes]:
    """Every artefact file of a folder with its bytes (to show that nothing changed)."""
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.h5"))}
