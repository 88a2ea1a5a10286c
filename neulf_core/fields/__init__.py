"""Field representations: functions from normalised (u, v, s, t) to colour and depth.

Each representation is a module with a config dataclass and an `nn.Module`, registered by
name here; a new representation is a new file plus one `register` call.  Every field maps
(N, 4) coordinates in [-1, 1] to rgb (N, 3) in [0, 1] and depth (N, 1) in [0, 1] (the
slab turns the latter into scene units).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields as dataclass_fields
from typing import Callable

import torch

from ..errors import NeulfError


@dataclass
class FieldEntry:
    config_class: type
    build: Callable[[object], torch.nn.Module]
    summary: str


REGISTRY: dict[str, FieldEntry] = {}


def register(name: str, config_class: type, build: Callable, summary: str) -> None:
    REGISTRY[name] = FieldEntry(config_class, build, summary)


def make_config(name: str, overrides: dict | None = None):
    if name not in REGISTRY:
        raise NeulfError(f"unknown field '{name}'; known: {', '.join(sorted(REGISTRY))}.")
    config_class = REGISTRY[name].config_class
    known = {f.name for f in dataclass_fields(config_class)}
    overrides = dict(overrides or {})
    unknown = set(overrides) - known
    if unknown:
        raise NeulfError(f"field '{name}' has no option(s) {', '.join(sorted(unknown))}; it has {', '.join(sorted(known))}.")
    return config_class(**overrides)


def build_field(name: str, config) -> torch.nn.Module:
    field = REGISTRY[name].build(config)
    field.field_name = name
    field.field_config = asdict(config)
    return field


def depth_unit(field: torch.nn.Module, uvst: torch.Tensor) -> torch.Tensor:
    """The field's depth output (N, 1) alone, as its forward gives it: a field that can leave
    out its colour's work for it (a `depth_unit` method: the disparity field, an ensemble of
    members) does, another runs its whole forward."""
    own = getattr(field, "depth_unit", None)
    return own(uvst) if own is not None else field(uvst)[1]


def count_parameters(field: torch.nn.Module) -> int:
    return sum(p.numel() for p in field.parameters())


from . import disparity, mlp, planes  # noqa: E402,F401  (registration side effects)
