"""Whether a saved configuration's values are of the types its dataclass declares.

A checkpoint keeps the TrainConfig it trained with as a plain dict; resuming builds the
config again from it.  A value edited or damaged to another type ("preset": 5, "scale":
"half") had reached the option's own check and ended in that option's message ("unknown
preset '5'"), which names an option the user never gave rather than the damaged file."""
from __future__ import annotations

import numbers
import types
import typing
from dataclasses import fields

import numpy as np


# Fields whose type changed between versions, with what an older checkpoint's value means now:
# pixel_jitter was a switch (on: anywhere in the pixel) before it took a width in pixels.
UPGRADES = {"pixel_jitter": (bool, float)}


def upgraded(values: dict) -> dict:
    """`values` with each field an older version saved as another type turned into today's."""
    out = dict(values)
    for name, (old, new) in UPGRADES.items():
        if isinstance(out.get(name), old):
            out[name] = new(out[name])
    return out


def type_problem(values: dict, config_class: type) -> str | None:
    """The first value in `values` whose type `config_class` does not declare for its field, in
    words; None if all fit.  Names that are not fields are left alone (the caller drops them:
    a checkpoint of another version)."""
    hints = typing.get_type_hints(config_class)
    for field in fields(config_class):
        if field.name in values and not _fits(values[field.name], hints[field.name]):
            value = values[field.name]
            return (f"its train_config's {field.name!r} is {_a(type(value).__name__)} ({value!r:.40}), "
                    f"not {_said(hints[field.name])}")
    return None


def _alternatives(hint) -> tuple:
    return typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)


def _fits(value, hint) -> bool:
    return any(_fits_one(value, kind) for kind in _alternatives(hint))


def _fits_one(value, kind) -> bool:
    origin = typing.get_origin(kind) or kind
    if kind is type(None):
        return value is None
    if kind is typing.Any:
        return True
    if origin is bool:
        return isinstance(value, (bool, np.bool_))
    if isinstance(value, (bool, np.bool_)):
        return False  # (a bool is an int to Python, not a count or a scale)
    if origin is int:
        return isinstance(value, numbers.Integral)
    if origin is float:
        return isinstance(value, numbers.Real)
    if origin is list:
        (item,) = typing.get_args(kind) or (typing.Any,)
        return isinstance(value, (list, tuple)) and all(_fits_one(entry, item) for entry in value)
    return isinstance(value, origin)


def _said(hint) -> str:
    names = [getattr(typing.get_origin(kind) or kind, "__name__", str(kind)) for kind in _alternatives(hint)]
    words = {"NoneType": "None", "int": "a whole number", "float": "a number", "bool": "true or false", "str": "a text",
             "list": "a list", "dict": "a dict"}
    return " or ".join(words.get(name, name) for name in names)


def _a(name: str) -> str:
    return ("an " if name[:1] in "aeiou" else "a ") + name
