"""typer options built from a stage Config: one set of defaults, help from field docstrings."""
from __future__ import annotations

from typing import Any

import typer

from stages.config import field_default, field_docs


def opt(config_cls: type, name: str, *flags: str, **kw: Any) -> Any:
    """``typer.Option`` whose default and help come from ``config_cls.name``."""
    default = kw.pop("default", field_default(config_cls, name))
    help_text = kw.pop("help", field_docs(config_cls).get(name, ""))
    flags = flags or ("--" + name.replace("_", "-"),)
    return typer.Option(default, *flags, help=help_text, show_default=True, **kw)


def workspace_option() -> Any:
    return typer.Option(..., "-w", "--workspace", help="Workspace folder holding the artefacts.",
                        file_okay=False)
