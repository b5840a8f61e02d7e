"""Small validation helpers shared by the schema modules (not part of the public API).

Each raises ValueError with the field named; msgspec turns that into a ValidationError during
decode (adding the path), and `decode` turns that into SchemaError.
"""
from __future__ import annotations

import math
from typing import Any, Iterable

from ._base import NDArray


def check_dtype(field: str, arr: NDArray | None, allowed: Iterable[str]) -> None:
    """Reject an array whose dtype is not one of `allowed` (None passes: optional field)."""
    if arr is None:
        return
    allowed = tuple(allowed)
    if arr.dtype not in allowed:
        raise ValueError(f"field `{field}` must have dtype {' or '.join(allowed)}, got {arr.dtype}")


def check_finite(field: str, value: float) -> None:
    if not math.isfinite(value):
        raise ValueError(f"field `{field}` must be a finite number, got {value!r}")


def check_positive(field: str, value: float) -> None:
    check_finite(field, value)
    if value <= 0:
        raise ValueError(f"field `{field}` must be > 0, got {value!r}")


def check_choice(field: str, value: Any, choices: Iterable[Any]) -> None:
    choices = tuple(choices)
    if value not in choices:
        raise ValueError(f"field `{field}` must be one of {', '.join(map(str, choices))}; got {value!r}")


def enum_names(cls: type, prefix: str = "") -> dict[int, str]:
    """{value: NAME} of the int class constants of `cls` starting with `prefix` (for logs/UIs)."""
    out: dict[int, str] = {}
    for klass in reversed(cls.__mro__):
        for name, value in vars(klass).items():
            if name.isupper() and name.startswith(prefix) and type(value) is int:
                out[value] = name[len(prefix):]
    return out
