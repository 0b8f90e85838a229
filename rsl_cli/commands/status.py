"""`rsl status -w WS`: which artefacts exist and which are stale against their inputs."""
from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from rsl_cli.console import out
from rsl_cli.options import workspace_option
from stages.errors import RslError

ORDER = 91

_STYLE = {"up to date": "green", "stale": "yellow", "missing": "dim", "invalid": "red"}


def register(app: typer.Typer) -> None:
    @app.command("status", help="Which artefacts of a workspace exist, and which are stale (an input file "
                                "changed or is gone).")
    def _cmd(workspace: Path = workspace_option()) -> None:
        from stages.pipeline import STAGES  # loaded on use: `rsl --help` imports every command module
        from stages.workspace import STALE, artefact_state

        if not workspace.is_dir():
            raise RslError(f"{workspace}: workspace folder not found.")
        hashes: dict[str, str] = {}
        states = {s.produces: artefact_state(workspace, s.produces, hashes) for s in STAGES}
        table = Table(title=f"workspace {escape(str(workspace))}", title_justify="left")
        for col in ("stage", "artefact", "state", "created", "why"):
            table.add_column(col)
        effective: dict[str, str] = {}
        for s in STAGES:
            st = states[s.produces]
            state, why = st.state, "; ".join(st.reasons)
            if state == "up to date":  # stale as soon as an artefact it reads is stale (transitively)
                bad = [k for k in s.reads if effective.get(k, states[k].state) in (STALE, "invalid")]
                if bad:
                    state, why = STALE, f"reads {states[bad[0]].path.name}, which is {effective.get(bad[0])}"
            effective[s.produces] = state
            table.add_row(s.name, escape(st.path.name), f"[{_STYLE[state]}]{state}[/]", (st.created or "")[:19],
                          escape(why))
        _print(table)
        partial = workspace / "adapt.partial.h5"
        if partial.is_file():
            out(f"{partial}: the frames of an unfinished `rsl adapt` (kept apart; adapt.h5 is never replaced "
                f"by an unfinished run).", markup=False)


def _print(table: Table) -> None:
    """To stdout: the terminal's width, or 160 columns in a pipe or a log."""
    c = Console(highlight=False)
    (c if c.is_terminal else Console(highlight=False, width=160)).print(table)
