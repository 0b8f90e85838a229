"""Entry point `rsl`: a typer app whose commands live in rsl_cli/commands/ (one module each)."""
from __future__ import annotations

import importlib
import os
import pkgutil
import sys

# Physics runs in float64 (DESIGN §6); must be set before jax is imported anywhere.
os.environ.setdefault("JAX_ENABLE_X64", "1")
if not os.environ.get("RSL_USE_GPU"):
    os.environ.setdefault("JAX_PLATFORMS", "cpu")

import typer

from rsl_cli import commands
from rsl_cli.console import console, error, state
from rsl_cli.options import RslGroup
from stages.errors import Interrupted, RslError

app = typer.Typer(
    cls=RslGroup,
    name="rsl",
    help="RealSimLoop: keep a soft-body simulation in step with a real object seen by cameras.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)


@app.callback()
def _global(
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars or info lines."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="More detail; tracebacks on errors."),
) -> None:
    state["quiet"], state["verbose"] = quiet, verbose


def _register_commands() -> None:
    mods = []
    for info in pkgutil.iter_modules(commands.__path__):
        mod = importlib.import_module(f"rsl_cli.commands.{info.name}")
        if hasattr(mod, "register"):
            mods.append(mod)
    for mod in sorted(mods, key=lambda m: getattr(m, "ORDER", getattr(m.register, "order", 100))):
        before = len(app.registered_commands)
        mod.register(app)  # a hand-written command registers with typer; a stage declares a lazy one
        for info in app.registered_commands[before:]:
            RslGroup.orders[info.name or ""] = getattr(mod, "ORDER", 100)


_register_commands()


def main() -> None:
    """Run the CLI; an RslError or a bad path ends with one red sentence and exit 1."""
    try:
        rc = app(standalone_mode=False)
        if rc == 130:  # typer turns a Ctrl-C (KeyboardInterrupt) into exit code 130
            error("interrupted.")
            _exit_now(130)
        if isinstance(rc, int) and rc != 0:
            sys.exit(rc)
    except Interrupted as e:  # Ctrl-C, and the stage says what it kept
        error(f"interrupted; {e}")
        _exit_now(130)
    except RslError as e:
        error(str(e))
        sys.exit(1)
    except KeyboardInterrupt:
        error("interrupted.")
        _exit_now(130)
    except SystemExit:
        raise
    except Exception as e:  # click usage errors and unexpected failures
        # click's (or typer's vendored click's) usage errors: their own message with the usage line
        if callable(getattr(e, "show", None)) and isinstance(getattr(e, "exit_code", None), int):
            e.show()
            sys.exit(e.exit_code)
        if type(e).__name__ == "Abort":
            error("aborted.")
            sys.exit(1)
        if state["verbose"]:
            console.print_exception()
        error(f"{type(e).__name__}: {e}")
        sys.exit(1)


def _exit_now(code: int) -> None:
    """Exit after a Ctrl-C without the interpreter's teardown: a native library (XLA's thread pools, a sparse
    solver) interrupted mid-call can crash in its destructors, turning a clean stop into a segfault."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    main()
