"""A job's TOML table -> the command line click would accept, checked by click itself.

The command schemas are the CLI's own click commands, passed in by the caller
(``load_jobs(path, commands)``): the farm never imports the CLI, and a job accepts exactly
the arguments and long options its command does, by name (``points_cache`` or
``points-cache`` for ``--points-cache``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import click

from ..errors import InputError

_BATCH_OWNS = frozenset({"quiet", "verbose", "as_json"})  # the batch decides what its jobs print


def _long(option: click.Parameter) -> str:
    return next((o for o in option.opts if o.startswith("--")), option.opts[0])


def _key_of(param: click.Parameter) -> str:
    return _long(param).lstrip("-").replace("-", "_") if isinstance(param, click.Option) else str(param.name)


def schema(command: click.Command) -> dict[str, click.Parameter]:
    """TOML key -> click parameter: arguments by name, options by long name."""
    return {_key_of(p): p for p in command.params if p.name not in _BATCH_OWNS}


def _scalar(kind: click.ParamType, value: Any, where: str, key: str) -> str:
    if isinstance(kind, click.types.IntParamType):
        ok, want = isinstance(value, int) and not isinstance(value, bool), "an integer"
    elif isinstance(kind, click.types.FloatParamType):
        ok, want = isinstance(value, int | float) and not isinstance(value, bool), "a number"
    elif isinstance(kind, click.types.BoolParamType):
        ok, want = isinstance(value, bool), "true or false"
    else:
        ok, want = isinstance(value, str), "a string"
    if not ok:
        raise InputError(f"{where}: {key} must be {want}, got {value!r}")
    return repr(value) if isinstance(value, float) else str(value).lower() if isinstance(value, bool) else str(value)


def values(param: click.Parameter, value: Any, where: str, key: str) -> list[str]:
    """A TOML value as the strings click will parse (one per value, nargs/multiple flattened)."""
    many = getattr(param, "multiple", False) or param.nargs == -1
    if param.nargs > 1:
        if not isinstance(value, list) or len(value) != param.nargs:
            raise InputError(f"{where}: {key} must be a list of {param.nargs} values, got {value!r}")
        kinds = param.type.types  # type: ignore[attr-defined]  # a click.Tuple when nargs > 1
        return [_scalar(kind, v, where, key) for kind, v in zip(kinds, value, strict=True)]
    if many:
        items = value if isinstance(value, list) else [value]
        return [_scalar(param.type, v, where, key) for v in items]
    return [_scalar(param.type, value, where, key)]


def arguments(command: click.Command, table: Mapping[str, Any], where: str) -> list[str]:
    """The command line of one job (after the command name), checked by click itself."""
    keys = schema(command)
    for key, param in keys.items():
        if param.required and key not in table:
            raise InputError(f"{where}: missing required key {key!r}")
    positional: list[str] = []
    options: list[str] = []
    for key, param in keys.items():
        if key not in table:
            continue
        value = table[key]
        if isinstance(param, click.Argument):
            positional += values(param, value, where, key)
        elif isinstance(param, click.Option) and param.is_flag and not param.count:
            if not isinstance(value, bool):
                raise InputError(f"{where}: {key} must be true or false, got {value!r}")
            options += [_long(param)] if value else param.secondary_opts[:1]
        elif param.nargs > 1:
            options += [_long(param), *values(param, value, where, key)]
        else:
            options += [f"{_long(param)}={v}" for v in values(param, value, where, key)]
    if any(p.startswith("-") for p in positional):
        args = [*options, "--", *positional]
    else:
        args = [*positional, *options]
    try:
        command.make_context(str(command.name), list(args))
    except click.ClickException as exc:
        raise InputError(f"{where}: {exc.format_message()}") from None
    return args
