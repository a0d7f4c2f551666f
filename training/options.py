"""A command's options declared once, as dataclass fields: its parser, its defaults and its record.

A field made by `option` carries its help and any argparse keyword (metavar, nargs, choices), a
`parse` of the parsed value, its `flag` where that is not `--name-with-dashes` (`--no-name` for a
switch on by default), `cli=False` where it is not on the command line, and `recorded=False` where
the command that repeats a run leaves it out. From the fields follow the parser (`add_arguments`,
each default shown in its help), the options built back by name (`from_args`), the command that
repeats them (`command_line`) and their JSON (`dataclasses.asdict`), as `training.config` does for
`fcemu train`. A `None` default means what the field's help says it means.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import typing
from collections.abc import Callable
from typing import Any

from fcemu.sim_bridge.env_config import scalar

REQUIRED: Any = dataclasses.MISSING  # the default of an option the command line must give
JSON_HELP = "print the summary as one JSON object on stdout"
_OWN = ("help", "flag", "cli", "recorded", "parse")  # metadata that is not an argparse keyword


def option(default: Any, help: str, *, flag: str | None = None, cli: bool = True, recorded: bool = True,
           parse: Callable[[Any], Any] | None = None, **argparse_kwargs: Any) -> Any:
    """A dataclass field with its command-line description (see the module doc)."""
    meta = {"help": help, "cli": cli, "recorded": recorded, **argparse_kwargs}
    meta |= {} if flag is None else {"flag": flag}
    meta |= {} if parse is None else {"parse": parse}
    return dataclasses.field(default=default, metadata=meta)


def flag_of(f: dataclasses.Field) -> str:
    if "flag" in f.metadata:
        return f.metadata["flag"]
    return ("--no-" if f.default is True else "--") + f.name.replace("_", "-")


def shown(value: Any) -> str:
    """A value as a command line writes it: floats short (540, not 540.0), sequences spaced."""
    if isinstance(value, tuple | list):
        return " ".join(shown(v) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return shlex.quote(value) if isinstance(value, str) else str(value)


def _command_fields(cls: type) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.metadata.get("cli", True)]


def add_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup, *classes: type) -> None:
    """One flag per command-line field of each class, in field order, its default in its help: a
    switch is off unless given (`--name` sets a field that defaults to False, `--no-name` clears one
    that defaults to True)."""
    for cls in classes:
        hints = typing.get_type_hints(cls)
        for f in _command_fields(cls):
            kwargs = {k: v for k, v in f.metadata.items() if k not in _OWN}
            text = f.metadata["help"]
            if hints[f.name] is bool:
                action = "store_false" if f.default else "store_true"
                parser.add_argument(flag_of(f), dest=f.name, action=action, help=f"{text} (default: off)")
                continue
            if f.default is REQUIRED:
                kwargs["required"], text = True, f"{text} (required)"
            elif f.default is not None:
                text = f"{text} (default: {shown(f.default)})"
            parser.add_argument(flag_of(f), dest=f.name, type=scalar(hints[f.name])[0],
                                default=None if f.default is REQUIRED else f.default, help=text, **kwargs)


def from_args(cls: type, args: argparse.Namespace, **overrides: Any) -> Any:
    """`cls` built by name from the command-line fields a parser of `add_arguments` produced, each
    through its `parse`; `overrides` (by field) win."""
    values = {}
    for f in _command_fields(cls):
        if f.name in overrides or not hasattr(args, f.name):
            continue
        value, parse = getattr(args, f.name), f.metadata.get("parse")
        values[f.name] = parse(value) if parse is not None and value is not None else value
    return cls(**values, **overrides)


def command_line(prog: str, opts: Any) -> str:
    """The command that repeats `opts`: every recorded command-line field that is not None, in field
    order, and each switch that is not at its default."""
    words = [prog]
    for f in _command_fields(type(opts)):
        value = getattr(opts, f.name)
        if not f.metadata.get("recorded", True) or value is None:
            continue
        if isinstance(value, bool):
            words += [flag_of(f)] if value != f.default else []
        else:
            words += [flag_of(f), shown(value)]
    return " ".join(words)
