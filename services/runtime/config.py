"""Configuration from parameters, one home (PX4's ModuleParams + updateParams()).

A service's config is a frozen dataclass whose fields reference its contract's parameters:

    @dataclass(frozen=True)
    class TrackerConfig:
        lag_m: float = param("trajectory_lag_m")

The default, unit and range live only in the contract (`Param`); the class copies none. A field
may hold a nested config (`section(AvoidanceConfig)`). The runtime builds the config from the
parameters at start (`Service.CONFIG`, available as `service.cfg`), rebuilds it on every live
change and calls the service's one `on_config(cfg)`; a ParamError raised there refuses the change
(the old value stays, params.ParamSet.apply). A declared parameter no config field references is
refused at start: a parameter is never accepted and ignored.

Never read a parameter by its string in logic: take it from the config.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Iterable, Mapping, TypeVar, cast

C = TypeVar("C")

PARAM = "aero.param"        # field metadata: the parameter's name
SECTION = "aero.section"    # field metadata: a nested config class


class ConfigError(RuntimeError):
    """A config class and the parameters it is built from disagree."""


def param(name: str, convert: Callable[[Any], Any] | None = None) -> Any:
    """A config field set from the contract parameter `name` (optionally converted, e.g. math.radians)."""
    return dataclasses.field(metadata={PARAM: (name, convert)})


def section(cls: type) -> Any:
    """A config field holding a nested config built from the same parameters."""
    return dataclasses.field(metadata={SECTION: cls})


def referenced(cls: type) -> set[str]:
    """Every parameter name `cls` (and its sections) references."""
    out: set[str] = set()
    for f in dataclasses.fields(cls):
        if PARAM in f.metadata:
            out.add(f.metadata[PARAM][0])
        elif SECTION in f.metadata:
            out |= referenced(f.metadata[SECTION])
    return out


def build(cls: type[C], values: Any, **overrides: Any) -> C:
    """`cls` from parameter values ({name: value}, a ParamSet, or a list of Param declarations for
    their defaults); `overrides` set fields by their field name (a test's variations)."""
    values = _values(values)
    kw: dict[str, Any] = {}
    for f in dataclasses.fields(cast(Any, cls)):
        if f.name in overrides:
            kw[f.name] = overrides.pop(f.name)
        elif PARAM in f.metadata:
            name, convert = f.metadata[PARAM]
            if name not in values:
                raise ConfigError(f"{cls.__name__}.{f.name} references parameter {name!r}, which is not declared")
            kw[f.name] = convert(values[name]) if convert else values[name]
        elif SECTION in f.metadata:
            kw[f.name] = build(f.metadata[SECTION], values)
    if overrides:
        raise ConfigError(f"{cls.__name__} has no field {', '.join(overrides)}")
    return cls(**kw)


def _values(values: Any) -> Mapping[str, Any]:
    if hasattr(values, "values") and isinstance(getattr(values, "values"), dict):   # a ParamSet
        return values.values
    if isinstance(values, Mapping):
        return values
    return {p.name: p.default for p in values}    # Param declarations


def check_covers(cls: type, params: Iterable[Any], service: str = "") -> None:
    """Every declared parameter is referenced by a field of `cls`, and every reference is declared:
    refused at start otherwise."""
    names = [p.name for p in params]
    refs = referenced(cls)
    unused = [n for n in names if n not in refs]
    if unused:
        raise ConfigError(f"{service or cls.__name__}: parameter {unused[0]} is declared but no field of "
                          f"{cls.__name__} references it (a parameter is never accepted and ignored)")
    undeclared = sorted(refs - set(names))
    if undeclared:
        raise ConfigError(f"{service or cls.__name__}: {cls.__name__} references parameter {undeclared[0]}, "
                          "which the contract does not declare")
