"""Declared parameters: one table per service with defaults, units and limits (like PX4 module.yaml).

Values come from the declaration, then a YAML file, then --param overrides, then live updates
on config/<service>/**. Every new value is validated against its declaration; a bad value is
rejected with a message that says what is allowed, and the old value stays.

A live update (`ParamSet.apply`) is never accepted and ignored: a parameter declared
`start_only` (read once when the service starts) is refused naming that, and a service's apply
callback (`on_change`) may refuse a valid value by raising ParamError (a model that does not
load, a polygon that does not parse): the old value is restored, so what a parameter list shows
is what runs, and the reason goes back in the reply.
"""
from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import yaml


class ParamError(ValueError):
    """A parameter value or file that does not match the declaration."""


@dataclass(frozen=True)
class Param:
    """One parameter: name, default (its type is the parameter's type), unit and limits."""

    name: str
    default: Any
    unit: str = ""
    min: float | None = None
    max: float | None = None
    choices: tuple[Any, ...] | None = None
    description: str = ""
    start_only: bool = False      # read once at start: a live set is refused, saying so

    @property
    def type(self) -> type:
        return type(self.default)

    def validate(self, value: Any) -> Any:
        """Coerce `value` (possibly a string from the CLI) to the declared type and check limits."""
        t = self.type
        v = value
        if isinstance(v, str) and t is not str:
            try:
                v = yaml.safe_load(v)
            except yaml.YAMLError:
                pass
            if isinstance(v, str) and t in (int, float):
                try:  # YAML 1.1 reads "1e9" (no dot) as a string
                    v = float(v)
                except ValueError:
                    pass
        if t is bool:
            if not isinstance(v, bool):
                raise ParamError(f"{self.name}: expected true/false, got {value!r}")
        elif t is int:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or (isinstance(v, float) and not v.is_integer()):
                raise ParamError(f"{self.name}: expected an integer, got {value!r}")
            v = int(v)
        elif t is float:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ParamError(f"{self.name}: expected a finite number, got {value!r}")
            v = float(v)
        elif t is str:
            if not isinstance(v, str):
                raise ParamError(f"{self.name}: expected a string, got {value!r}")
        if self.min is not None and v < self.min:
            raise ParamError(f"{self.name}: {v} is below the minimum {self.min} {self.unit}".rstrip())
        if self.max is not None and v > self.max:
            raise ParamError(f"{self.name}: {v} is above the maximum {self.max} {self.unit}".rstrip())
        if self.choices is not None and v not in self.choices:
            raise ParamError(f"{self.name}: {v!r} is not one of {list(self.choices)}")
        return v


@dataclass
class ParamSet:
    """Current values of a service's declared parameters; thread-safe; notifies on change.

    Read a value as `ps.NAME` or `ps["NAME"]`. Each value is also kept as a plain instance
    attribute, rewritten by every set, apply and rollback (`_store`), so `ps.NAME` is an ordinary
    attribute read (~40 ns) rather than a failed lookup plus __getattr__ (~430 ns): services read
    parameters in their hot loops (the sim's physics a dozen a step at 400 Hz). A name that is
    also one of ParamSet's own attributes (`values`, `set`, ...) is only reachable as ps["NAME"]."""

    declared: dict[str, Param]
    values: dict[str, Any] = field(default_factory=dict)
    _listeners: list[Callable[[str, Any], None]] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        for name, v in self.values.items():
            self._store(name, v)

    def _store(self, name: str, v: Any) -> None:
        """The one place a value is written: the dict and its attribute mirror (callers hold the lock
        once the set is shared)."""
        self.values[name] = v
        if name not in _OWN_NAMES:
            self.__dict__[name] = v

    @classmethod
    def from_declarations(cls, params: Iterable[Param]) -> "ParamSet":
        declared = {p.name: p for p in params}
        return cls(declared=declared, values={n: p.default for n, p in declared.items()})

    def __getitem__(self, name: str) -> Any:
        return self.values[name]

    def __getattr__(self, name: str) -> Any:   # only names that are no parameter get here
        raise AttributeError(name)

    def _declared(self, name: str) -> Param:
        p = self.declared.get(name)
        if p is None:
            raise ParamError(f"unknown parameter {name!r}; declared: {', '.join(sorted(self.declared))}")
        return p

    def set(self, name: str, value: Any) -> Any:
        """Validate and store (start-up values, a service's own corrections); raises ParamError
        (old value kept) when invalid or unknown. Listeners are told; none may refuse here."""
        v = self._declared(name).validate(value)
        with self._lock:
            self._store(name, v)
        for cb in list(self._listeners):
            cb(name, v)
        return v

    def apply(self, name: str, value: Any) -> Any:
        """A live update: refused (ParamError, old value kept) when unknown, invalid, start-only,
        or when an apply callback refuses it by raising ParamError (or fails: that exception is
        re-raised). Then the callbacks that had already taken the new value get the old one back."""
        p = self._declared(name)
        if p.start_only:
            raise ParamError(f"{name} is read at start only (restart the service with --param {name}=...); "
                             f"still {self.values[name]!r}")
        v = p.validate(value)
        with self._lock:
            old = self.values[name]
            self._store(name, v)
        done: list[Callable[[str, Any], None]] = []
        try:
            for cb in list(self._listeners):
                cb(name, v)
                done.append(cb)
        except Exception:   # a refusal (ParamError) or a callback that failed: either way not applied
            with self._lock:
                self._store(name, old)
            for cb in done:
                cb(name, old)
            raise
        return v

    def update(self, mapping: dict[str, Any]) -> None:
        """Apply several values atomically: all valid or none applied."""
        checked = {}
        for k, v in mapping.items():
            if k not in self.declared:
                raise ParamError(f"unknown parameter {k!r}; declared: {', '.join(sorted(self.declared))}")
            checked[k] = self.declared[k].validate(v)
        for k, v in checked.items():
            self.set(k, v)

    def on_change(self, cb: Callable[[str, Any], None]) -> None:
        self._listeners.append(cb)

    def load_file(self, path: str | Path, service: str) -> None:
        """YAML file: either {service: {name: value}} for a whole stack or a flat {name: value}."""
        p = Path(path)
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except OSError as e:
            raise ParamError(f"{p}: cannot read parameter file: {e.strerror}") from None
        except yaml.YAMLError as e:
            raise ParamError(f"{p}: not valid YAML: {e}") from None
        if not isinstance(data, dict):
            raise ParamError(f"{p}: expected a mapping of parameter names to values")
        if service in data and isinstance(data[service], dict):
            data = data[service]
        elif any(isinstance(v, dict) for v in data.values()):
            return  # a stack-wide file without a section for this service
        try:
            self.update(data)
        except ParamError as e:
            raise ParamError(f"{p}: {e}") from None


_OWN_NAMES = frozenset(dir(ParamSet)) | {f.name for f in dataclasses.fields(ParamSet)}


def start_only_but(params: Iterable[Param], live: Iterable[str] = ()) -> list[Param]:
    """For a service that builds itself from its parameters at start (sockets, tables, a pipeline):
    every parameter but those named in `live` declared start_only."""
    live = set(live)
    return [p if p.name in live else dataclasses.replace(p, start_only=True) for p in params]


def parse_overrides(items: Iterable[str]) -> dict[str, str]:
    """`--param k=v` strings to a dict; the value is validated later against the declaration."""
    out = {}
    for item in items:
        k, sep, v = item.partition("=")
        if not sep or not k:
            raise ParamError(f"--param {item!r}: expected NAME=VALUE, e.g. --param max_velocity_mps=1.5")
        out[k.strip()] = v.strip()
    return out
