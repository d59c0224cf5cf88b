"""Settings as frozen dataclasses with a help string per field; the command line made from them.

One declaration per setting (as CleanRL's `Args`): `setting(default, help)`
gives the field its default and its help; `add_arguments` turns a settings
class into argparse options (``--eval-every`` for ``eval_every``; booleans as
``--quiet`` / ``--no-quiet``); `parse_text` types a ``key=value`` string by the
field's annotation. Nothing here knows about training: `zeus_ros.learning_tools.train` and
`zeus_ros.core.config` declare the fields.
"""

from __future__ import annotations

import argparse
from dataclasses import Field, field, fields, MISSING
import types
import typing
from typing import Callable, Container


# `default` is any value a field may hold (MISSING: none).
def setting(default: object = MISSING, help_text: str = '', **cli) -> Field:
    """Return a dataclass field with its help string; `cli` goes to argparse (choices, ...)."""
    return field(default=default, metadata={'help': help_text, 'cli': cli})


def field_types(cls: type) -> dict[str, type]:
    """Return each field's value type (`int | None` -> int, `tuple[str, ...]` -> tuple)."""
    hints = typing.get_type_hints(cls)
    return {f.name: plain_type(hints[f.name]) for f in fields(cls)}


# `kind` is a type hint as get_type_hints returns it: a class, a union, a generic alias.
def plain_type(kind: object) -> type:
    """Return the type a value is parsed as: the non-None member of an optional, the origin."""
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        kind = next(a for a in typing.get_args(kind) if a is not type(None))
    return typing.get_origin(kind) or kind


def parse_bool(text: str) -> bool:
    """Read a boolean the way a shell user writes one (true/false, 1/0, yes/no, on/off)."""
    if text.lower() in ('1', 'true', 'yes', 'on'):
        return True
    if text.lower() in ('0', 'false', 'no', 'off'):
        return False
    raise ValueError(f'{text!r} is not a boolean (true/false)')


def parse_text(kind: type, text: str) -> bool | int | float | str:
    """Return `text` as a value of `kind` (bool, int, float or str); ValueError otherwise."""
    if kind is bool:
        return parse_bool(text)
    if kind in (int, float, str):
        return kind(text)
    raise ValueError(f'cannot read a {kind.__name__} from text')  # pragma: no cover


def describe_default(f: Field) -> str:
    """Return the field's default as the help shows it ('required' when it has none)."""
    if f.default is MISSING:
        return '(none)'
    if isinstance(f.default, tuple):
        return ' '.join(str(v) for v in f.default) or '(none)'
    return repr(f.default)


def add_arguments(parser: argparse._ActionsContainer, cls: type, *, skip: Container[str] = (),
                  only: Container[str] | None = None,
                  note: Callable[[str], str] | None = None,
                  keep_defaults: bool = True) -> None:
    """Add one option per field of `cls` to `parser` (a parser or an argument group).

    `keep_defaults`: the option's default is the field's; otherwise None, so a
    caller can tell a value the user gave from one a preset will choose. `note`
    maps a field name to text appended to its help (the presets that change it).
    """
    kinds = field_types(cls)
    for f in fields(cls):
        if f.name in skip or (only is not None and f.name not in only) \
                or f.metadata.get('cli') is None:
            continue
        extra = f' {note(f.name)}' if note and note(f.name) else ''
        default_text = 'required' if f.default is MISSING else f'default: {describe_default(f)}'
        help_text = f"{f.metadata['help']} ({default_text}){extra}"
        options = dict(f.metadata['cli'])
        default = f.default if keep_defaults and f.default is not MISSING else None
        _add_option(parser, f.name, kinds[f.name], default, help_text.replace('%', '%%'),
                    options)


def _add_option(parser: argparse._ActionsContainer, name: str, kind: type, default: object,
                help_text: str, options: dict) -> None:
    flag = '--' + name.replace('_', '-')
    if kind is bool:
        parser.add_argument(flag, dest=name, action=argparse.BooleanOptionalAction,
                            default=default, help=help_text)
    elif kind is tuple:
        parser.add_argument(flag, dest=name, nargs='*', default=default, help=help_text,
                            **options)
    else:
        if 'choices' not in options:   # argparse shows the choices themselves
            options.setdefault('metavar', kind.__name__.upper())
        parser.add_argument(flag, dest=name, type=kind, default=default, help=help_text,
                            **options)
