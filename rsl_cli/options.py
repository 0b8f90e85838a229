"""typer commands generated from a stage's Config dataclass (nerfstudio-style).

Each field of the Config becomes a parameter of the command: the fields the stage lists in
``arguments`` (stages/registry.py) are positional arguments, every other field an option
``--field-name`` (or the names in the stage's ``flags``).  The field's type gives the option type
(``Literal[...]`` → choices, checked by click and shown in --help; ``X | None`` → default None;
``bool`` → ``--x/--no-x``), the dataclass default the default, and the docstring under the field
the help text.  A field without a default is a required option (``workspace`` is ``-w/--workspace``).

`rsl`'s group (:class:`RslGroup`) lists each stage from the registry alone (name and summary) and builds
its command, importing the stage module, only when that command is run, asked for --help or documented.
"""
from __future__ import annotations

import dataclasses
import inspect
import types
import typing
from typing import Any, Callable, Optional

import typer
from typer.core import TyperCommand, TyperGroup

from rsl_cli.console import RichReporter
from stages.config import field_default, field_docs
from stages.registry import STAGES, stage


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
                                                                          if hint in (bool, Optional[bool])
                                                                          else ""),))
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


def build_stage_command(name: str):
    """The click command of the stage ``name`` of stages/registry.py (imports the stage module): its Config's
    fields as arguments and options, its summary as help; running it runs ``stage.run(config, reporter)``."""
    s = stage(name)
    mod = s.load()

    def action(config: Any) -> None:
        mod.run(config, RichReporter())

    sub = typer.Typer(add_completion=False, pretty_exceptions_enable=False, rich_markup_mode="rich")
    sub.command(s.name, help=s.summary)(config_command(s.config_cls(mod), action, s.arguments, dict(s.flags)))
    cmd = typer.main.get_command(sub)  # one command: typer gives the command itself
    cmd.name = s.name
    return cmd


class LazyStageCommand(TyperCommand):
    """A stage's command in `rsl`'s list before its module is imported: name and help from the registry;
    parsing, running and its own --help build the real command (and import the stage) on first use.
    So `rsl --help` imports no stage module, and a stage that fails to import breaks only its command."""

    def __init__(self, name: str, summary: str):
        super().__init__(name, help=summary)
        self._real = None

    def real(self):
        if self._real is None:
            self._real = build_stage_command(self.name)
        return self._real

    @property
    def params(self):  # click sets self.params in __init__; read through to the real command after that
        return self.real().params if "_real" in self.__dict__ else []

    @params.setter
    def params(self, value) -> None:
        pass

    def make_context(self, info_name, args, parent=None, **extra):
        return self.real().make_context(info_name, args, parent=parent, **extra)

    def invoke(self, ctx):
        return self.real().invoke(ctx)

    def main(self, *args: Any, **kwargs: Any):
        return self.real().main(*args, **kwargs)

    def get_help(self, ctx) -> str:
        return self.real().get_help(ctx)


class RslGroup(TyperGroup):
    """`rsl`'s command group: the hand-written commands typer registered, plus one :class:`LazyStageCommand`
    per stage declared with :func:`stage_command`, listed in the order of ``orders`` (ORDER of a command
    module; the registry's order for stages)."""

    lazy: dict[str, str] = {}  # stage name -> summary, filled by stage_command(...)(app)
    orders: dict[str, float] = {}  # command name -> position in `rsl --help`

    def __init__(self, **kw: Any):
        super().__init__(**kw)
        for name, summary in self.lazy.items():
            self.commands[name] = LazyStageCommand(name, summary)
        order = sorted(self.commands, key=lambda n: self.orders.get(n, 100))
        self.commands = {n: self.commands[n] for n in order}


def stage_command(name: str) -> Callable[[typer.Typer], None]:
    """``register(app)`` declaring the command of the stage ``name`` of stages/registry.py; the command is built
    from the stage's Config (:func:`build_stage_command`) only when it is run, asked for help, or documented."""
    s = stage(name)

    def register(app: typer.Typer) -> None:
        RslGroup.lazy[s.name] = s.summary
        RslGroup.orders[s.name] = register.order  # type: ignore[attr-defined]

    register.order = 5 + 7 * STAGES.index(s)  # type: ignore[attr-defined]  # `rsl --help` lists the registry's order
    return register
