"""`rsl status -w WS`: which artefacts exist and which are stale against their inputs."""
from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from rsl_cli.options import workspace_option
from stages.errors import RslError

ORDER = 91

_STYLE = {"up to date": "green", "stale": "yellow", "missing": "dim", "invalid": "red"}


def register(app: typer.Typer) -> None:
    @app.command("status", help="Which artefacts of a workspace exist, and which are stale (an input file "
                                "changed or is gone).")
    def _cmd(workspace: Path = workspace_option()) -> None:
        from stages.pipeline import STAGES
        from stages.workspace import STALE, artefact_state

        if not workspace.is_dir():
            raise RslError(f"{workspace}: workspace folder not found.")
        hashes: dict[str, str] = {}
        states = {s.produces: artefact_state(workspace, s.produces, hashes) for s in STAGES}
        table = Table(title=f"workspace {workspace}", title_justify="left")
        for col in ("stage", "artefact", "state", "created", "why"):
            table.add_column(col)
        for s in STAGES:
            st = states[s.produces]
            state, why = st.state, "; ".join(st.reasons)
            if state == "up to date":
                bad = [k for k in s.reads if states[k].state == STALE]
                if bad:
                    state, why = STALE, f"reads {states[bad[0]].path.name}, which is stale"
            table.add_row(s.name, st.path.name, f"[{_STYLE[state]}]{state}[/]", (st.created or "")[:19], why)
        _print(table)


def _print(table: Table) -> None:
    """To stdout: the terminal's width, or 160 columns in a pipe or a log."""
    from rich.console import Console

    c = Console(highlight=False)
    (c if c.is_terminal else Console(highlight=False, width=160)).print(table)
