"""typer commands generated from a stage's Config dataclass (nerfstudio-style).

Each field of the Config becomes a parameter of the command: the fields the stage lists in
``arguments`` (stages/registry.py) are positional arguments, every other field an option
``--field-name`` (or the names in the stage's ``flags``).  The field's type gives the option type
(``Literal[...]`` → choices, checked by click and shown in --help; ``X | None`` → default None;
``bool`` → ``--x/--no-x``), the dataclass default the default, and the docstring under the field
the help text.  A field without a default is a required option (``workspace`` is ``-w/--workspace``).
"""
from __future__ import annotations

import dataclasses
import inspect
import types
import typing
from typing import Any, Callable, Optional

import typer

from stages.config import field_default, field_docs


def opt(config_cls: type, name: str, *flags: str, **kw: Any) -> Any:
    """``typer.Option`` whose default and help come from ``config_cls.name`` (for hand-written commands)."""
    default = kw.pop("default", field_default(config_cls, name))
    help_text = kw.pop("help", field_docs(config_cls).get(name, ""))
    flags = flags or ("--" + name.replace("_", "-"),)
    return typer.Option(default, *flags, help=help_text, show_default=True, **kw)


def workspace_option() -> Any:
    return typer.Option(..., "-w", "--workspace", help="Workspace folder holding the artefacts.",
                        file_okay=False)


def _option_type(hint: Any) -> Any:
    """The type typer sees: ``X | None`` → ``Optional[X]`` (typer reads both; one spelling here)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return Optional[args[0]]
    return hint


def command_parameters(config_cls: type, arguments: tuple[str, ...] = (),
                       flags: dict[str, tuple[str, ...]] | None = None) -> list[inspect.Parameter]:
    """The typer parameters of a command built from ``config_cls``: positional ``arguments`` first, then
    one option per other field, in field order."""
    flags = flags or {}
    hints = typing.get_type_hints(config_cls)
    docs = field_docs(config_cls)
    fields = {f.name: f for f in dataclasses.fields(config_cls)}
    unknown = [n for n in list(arguments) + list(flags) if n not in fields]
    if unknown:
        raise TypeError(f"{config_cls.__name__} has no field {unknown[0]!r}")
    params = []
    for name in list(arguments) + [n for n in fields if n not in arguments]:
        default = field_default(config_cls, name)
        help_text = docs.get(name, "")
        hint = _option_type(hints[name])
        if name in arguments:
            info = typer.Argument(default, help=help_text, show_default=default is not ...)
        else:
            names = flags.get(name) or (("-w", "--workspace") if name == "workspace" else
                                        ("--" + name.replace("_", "-") + ("/--no-" + name.replace("_", "-")
                                                                          if hint is bool else ""),))
            extra = {"file_okay": False} if name == "workspace" else {}
            info = typer.Option(default, *names, help=help_text, show_default=default is not ..., **extra)
        params.append(inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=info,
                                        annotation=hint))
    return params


def config_command(config_cls: type, action: Callable[[Any], Any], arguments: tuple[str, ...] = (),
                   flags: dict[str, tuple[str, ...]] | None = None) -> Callable[..., None]:
    """A function typer can register whose parameters are ``config_cls``'s fields; calling it builds the
    Config from them and passes it to ``action``."""
    params = command_parameters(config_cls, arguments, flags)

    def command(**kw: Any) -> None:
        action(config_cls(**kw))

    command.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
    command.__annotations__ = {p.name: p.annotation for p in params}
    command.__name__ = config_cls.__name__
    return command


def stage_command(name: str) -> Callable[[typer.Typer], None]:
    """``register(app)`` adding the command of the stage ``name`` of stages/registry.py: its Config's
    fields as arguments and options, its summary as help; running it runs ``stage.run(config, reporter)``."""
    from stages.registry import STAGES, stage

    s = stage(name)

    def register(app: typer.Typer) -> None:
        mod = s.load()

        def action(config: Any) -> None:
            from rsl_cli.console import RichReporter

            mod.run(config, RichReporter())

        cmd = config_command(s.config_cls(mod), action, s.arguments, dict(s.flags))
        app.command(s.name, help=s.summary)(cmd)

    register.order = 5 + 7 * STAGES.index(s)  # type: ignore[attr-defined]  # `rsl --help` lists the registry's order
    return register
