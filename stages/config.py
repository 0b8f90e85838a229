"""Stage configs: frozen dataclasses whose field docstrings are the CLI help text.

A field is documented by a string literal right under it::

    @dataclass(frozen=True)
    class TetConfig:
        edge_length: float = 0.05
        \"\"\"Target tet edge length, as a fraction of the bounding-box diagonal.\"\"\"

``field_docs(TetConfig)["edge_length"]`` returns that sentence, so defaults and
help live in one place.
"""
from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import re
import textwrap
from typing import Any


_FIELD = re.compile(r"^    (\w+)\s*:")  # "    name: type = default" at class-body indentation


@functools.lru_cache(maxsize=None)
def _source_lines(filename: str) -> tuple[str, ...]:
    with open(filename, encoding="utf-8") as f:
        return tuple(f.read().splitlines())


def _scan_docs(lines: tuple[str, ...], name: str) -> dict[str, str] | None:
    """Field docstrings of top-level class ``name`` read line by line (no parse of the whole module, which
    costs `rsl --help` ~20 ms per stage); None when the class is not found."""
    start = next((i for i, ln in enumerate(lines) if re.match(rf"class {name}\b", ln)), None)
    if start is None:
        return None
    docs: dict[str, str] = {}
    i = start + 1
    while i < len(lines):
        ln = lines[i]
        if ln.strip() and not ln.startswith(" "):
            break  # the class body ended
        m = _FIELD.match(ln)
        if m and i + 1 < len(lines) and lines[i + 1].lstrip().startswith(('"""', 'r"""')):
            j, text = i + 1, lines[i + 1].strip()
            while text.count('"""') < 2 and j + 1 < len(lines):
                j += 1
                text += "\n" + lines[j].strip()
            docs[m.group(1)] = " ".join(ast.literal_eval(text).split())
            i = j
        i += 1
    return docs


def _ast_docs(klass: type) -> dict[str, str]:
    """Field docstrings of ``klass`` from its parsed source (the slow, obvious twin of :func:`_scan_docs`)."""
    docs: dict[str, str] = {}
    try:
        body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0].body
    except (OSError, TypeError):
        return docs
    for stmt, nxt in zip(body, body[1:] + [None]):
        if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name):
            if isinstance(nxt, ast.Expr) and isinstance(getattr(nxt, "value", None), ast.Constant) \
                    and isinstance(nxt.value.value, str):
                docs[stmt.target.id] = " ".join(nxt.value.value.split())
    return docs


@functools.lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """Map field name -> the docstring written under it in the class body (inherited too)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is object or not dataclasses.is_dataclass(klass):
            continue
        try:
            found = _scan_docs(_source_lines(inspect.getsourcefile(klass) or ""), klass.__name__)
        except (OSError, TypeError, SyntaxError, ValueError):
            found = None
        docs.update(_ast_docs(klass) if found is None else found)
    return docs


def field_default(cls: type, name: str) -> Any:
    """The default of a dataclass field (default_factory called)."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            if f.default is not dataclasses.MISSING:
                return f.default
            if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
                return f.default_factory()  # type: ignore[misc]
            return ...
    raise KeyError(f"{cls.__name__} has no field {name!r}")
