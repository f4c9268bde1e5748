"""Shared input checks: finite floats, strict integers and booleans, files without duplicate keys.

Every config and scene model uses ``MODEL_CONFIG`` (or ``FROZEN_MODEL_CONFIG``): unknown keys and
NaN or infinite floats are refused with the field's dotted path. Integer and boolean fields are
``Int`` and ``Bool``: ``steps: true`` or ``steps: 2.5`` are refused instead of becoming 1 or 2
(numpy integers and booleans, which code passes, are accepted as the Python values they stand for).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from types import UnionType
from typing import Annotated, Any, Union, get_args, get_origin

import numpy as np
import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, Strict, ValidationError

MODEL_CONFIG = ConfigDict(extra="forbid", allow_inf_nan=False)
FROZEN_MODEL_CONFIG = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


def _from_numpy(v: Any) -> Any:
    return v.item() if isinstance(v, np.integer | np.bool_) else v


Int = Annotated[int, BeforeValidator(_from_numpy), Strict()]
"""An integer field: a bool, a float or a string is refused, not converted."""
Bool = Annotated[bool, BeforeValidator(_from_numpy), Strict()]
"""A boolean field: only true or false (not 1, "yes" or "on")."""


def error_lines(e: ValidationError, prefix: str = "", most: int = 5) -> str:
    """A pydantic error as one line: ``field a.b: message; field c: message (+N more)``."""
    lines = []
    for err in e.errors()[:most]:
        loc = ".".join(str(x) for x in err["loc"])
        if not loc and not prefix:  # a check across fields: its message names them
            lines.append(str(err["msg"]).removeprefix("Value error, "))
            continue
        lines.append(f"field {prefix}{loc or '<root>'}: {err['msg']}")
    more = f" (+{e.error_count() - most} more)" if e.error_count() > most else ""
    return "; ".join(lines) + more


# ------------------------------------------------------------------------------ non-finite values
def non_finite(value: Any, path: str = "") -> Iterator[str]:
    """Dotted paths of the NaN or infinite floats in a nested value (models, mappings, sequences)."""
    if isinstance(value, BaseModel):
        value = {k: getattr(value, k) for k in type(value).model_fields}
    if isinstance(value, float | np.floating):
        if not math.isfinite(value):
            yield path or "<root>"
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from non_finite(v, f"{path}.{k}" if path else str(k))
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            yield from non_finite(v, f"{path}.{i}" if path else str(i))


def loose_scalar(value: Any, annotation: Any) -> str | None:
    """Why ``value`` may not fill a field annotated ``int`` or ``bool`` (or optional): pydantic's lax mode
    would turn ``true`` into 1 and ``1`` or ``"yes"`` into True. None when it may (or the field is another type)."""
    union = get_origin(annotation) in (Union, UnionType)
    types = set(get_args(annotation)) - {type(None)} if union else {annotation}
    if value is None or types not in ({int}, {bool}):
        return None
    if types == {int} and (isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer)):
        return f"Input should be a valid integer, not {value!r}"
    if types == {bool} and not isinstance(value, bool | np.bool_):
        return f"Input should be true or false, not {value!r}"
    return None


# ------------------------------------------------------------------------------ YAML and JSON
class DuplicateKeyError(yaml.YAMLError):
    """A YAML mapping holds the same key twice; the message (one line) names the key and both lines."""


class UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a mapping with the same key twice (PyYAML keeps the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            line = key_node.start_mark.line + 1
            if key in seen:
                raise DuplicateKeyError(f"duplicate key {key!r} at line {line} (first at line {seen[key]})")
            seen[key] = line
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str) -> Any:
    """YAML as ``yaml.safe_load`` reads it, but a duplicate key is a ``yaml.YAMLError`` naming key and line."""
    return yaml.load(text, Loader=UniqueKeyLoader)


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"duplicate key {k!r}")
        out[k] = v
    return out


def load_json(text: str) -> Any:
    """JSON as ``json.loads`` reads it, but a duplicate key in an object is a ``ValueError``."""
    return json.loads(text, object_pairs_hook=_unique_pairs)
