"""Command-line flags made from the config dataclasses, as nerfstudio makes its command line from its configs.

Each `ConfigFlag` sets one field of a config (`TrainConfig`, `PackConfig`, `PlayConfig`, `ServeConfig` and
the settings inside them, a dotted path for a nested one: `download.retries`). Its help is the field's
docstring, its default the config's (the flag's value is None until it is given, so whatever the config or a
budget says stands), its type the field's annotation unless the flag names a parser. A flag is the field's
name with dashes unless it says otherwise, and each flag is declared once: the parser, the config values and
the flag named in an error message (`flag_of`, for a FieldError) all come from the same declaration.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import re
import textwrap
import types
import typing
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

_FLAG_OF: dict[str, str] = {}
"""Field (dotted path) -> its flag, for every ConfigFlag added to a parser in this process."""


@dataclass(frozen=True)
class ConfigFlag:
    """How the command line sets one config field."""

    field: str
    """The field, a dotted path into nested settings (`download.retries`)."""
    flag: str | None = None
    """The option (default: --field-name of the last part)."""
    type: Callable[[str], Any] | None = None
    """Parser of the text (default: from the field's annotation: int, float, str or Path)."""
    choices: Sequence[Any] | None = None
    metavar: str | None = None
    off: bool = False
    """A switch that turns the field off: `--no-...` sets it to `off_value`."""
    off_value: Any = False
    on: bool = False
    """A switch that turns a False field on."""
    repeat: bool = False
    """Repeatable: each use adds one value to a tuple."""
    default_note: str | None = None
    """Said instead of the config's default (e.g. where a budget sets it)."""

    @property
    def option(self) -> str:
        return self.flag or "--" + self.field.rsplit(".", 1)[-1].replace("_", "-")


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """A dataclass's field docstrings (the string literal under each field, as nerfstudio writes them), its
    bases' included, whitespace folded."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        node = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0]
        assert isinstance(node, ast.ClassDef)
        for here, after in zip(node.body, node.body[1:], strict=False):
            if (isinstance(here, ast.AnnAssign) and isinstance(here.target, ast.Name) and isinstance(after, ast.Expr)
                    and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
                docs[here.target.id] = " ".join(after.value.value.split())
    return docs


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """typing.get_type_hints of a config class, resolved once (it evaluates every annotation of the class)."""
    return typing.get_type_hints(cls)


def _field(cls: type, path: str) -> tuple[type, dataclasses.Field, Any]:
    """(the dataclass holding it, the field, its type hint) of a dotted path from `cls`."""
    holder = cls
    *outer, last = path.split(".")
    for name in outer:
        holder = _hints(holder)[name]
    fields = {f.name: f for f in dataclasses.fields(holder)}
    if last not in fields:
        raise KeyError(f"{cls.__name__} has no field {path!r}")
    return holder, fields[last], _hints(holder)[last]


def _plain(hint: Any) -> Any:
    """The type a hint stands for once None is taken out of a union (int | None -> int)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        rest = [a for a in typing.get_args(hint) if a is not type(None)]
        return rest[0] if len(rest) == 1 else hint
    return hint


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _show(value: Any) -> str:
    if isinstance(value, tuple | list):
        return ",".join(str(v) for v in value) or "none"
    if value is None:
        return "none"
    return str(value)


def help_text(cls: type, spec: ConfigFlag, others: Iterable[ConfigFlag] = ()) -> str:
    """The field's docstring, its default and, in place of the names of fields the same parser sets, their
    flags; escaped for argparse."""
    holder, f, _ = _field(cls, spec.field)
    text = field_docs(holder).get(f.name, "")
    for other in others:
        last = other.field.rsplit(".", 1)[-1]
        if "_" in last:  # a one-word name is a word of the prose as well
            text = re.sub(rf"(?<![\w.]){re.escape(last)}(?!\w)", other.option, text)
    if spec.off:
        text = f"Turns this off: {text}"
    if spec.default_note is not None:
        text += f" (default: {spec.default_note})"
    elif not (spec.off or spec.on):
        default = _default(f)
        if default is not None:
            text += f" (default: {_show(default)})"
    return text.replace("%", "%%")


def add_config_flags(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls: type,
                     specs: Sequence[ConfigFlag], among: Sequence[ConfigFlag] = ()) -> None:
    """One option per spec, setting `cls`'s field (read back with config_values); `among`: the command's other
    flags, whose fields' names the help texts speak of by their flags."""
    for spec in specs:
        hint = _field(cls, spec.field)[2]
        _FLAG_OF[spec.field] = spec.option
        kwargs: dict[str, Any] = {"dest": spec.field, "default": None, "help": help_text(cls, spec, [*specs, *among])}
        if spec.off:
            kwargs |= {"action": "store_const", "const": spec.off_value}
        elif spec.on:
            kwargs |= {"action": "store_const", "const": True}
        else:
            kind = _plain(hint)
            if spec.repeat and typing.get_origin(kind) is tuple:
                kind = typing.get_args(kind)[0]
            parse = spec.type or (kind if kind in (int, float, str, Path) else None)
            if parse is None:
                raise TypeError(f"{cls.__name__}.{spec.field}: say how to parse a {hint}")
            metavar = spec.metavar or (None if spec.choices else spec.option.lstrip("-").replace("-", "_").upper())
            kwargs |= {"type": parse, "choices": spec.choices, "metavar": metavar}
            if spec.repeat:
                kwargs |= {"action": "append"}
        parser.add_argument(spec.option, **{k: v for k, v in kwargs.items() if v is not None or k == "default"})


def config_values(args: argparse.Namespace, specs: Sequence[ConfigFlag]) -> dict[str, Any]:
    """The fields the command line set (dotted paths), by the specs' fields."""
    out = {}
    for spec in specs:
        value = getattr(args, spec.field)
        if value is not None:
            out[spec.field] = tuple(value) if spec.repeat else value
    return out


def build_config(cls: type, values: dict[str, Any], **fixed: Any) -> Any:
    """`cls(**fixed)` with `values` (dotted paths into nested settings) set."""
    top = {k: v for k, v in values.items() if "." not in k}
    nested: dict[str, dict[str, Any]] = {}
    for key, value in values.items():
        if "." in key:
            head, rest = key.split(".", 1)
            nested.setdefault(head, {})[rest] = value
    hints = _hints(cls)
    for head, inner in nested.items():
        top[head] = build_config(hints[head], inner)
    return cls(**fixed, **top)


def flag_of(field: str) -> str:
    """The flag that sets `field` (a FieldError's field: its last name, or a dotted path): the one declared for
    it, else its name with dashes (the commands whose options are not a config's spell theirs so)."""
    if field in _FLAG_OF:
        return _FLAG_OF[field]
    matches = {flag for path, flag in _FLAG_OF.items() if path.rsplit(".", 1)[-1] == field}
    return matches.pop() if len(matches) == 1 else "--" + field.rsplit(".", 1)[-1].replace("_", "-")
