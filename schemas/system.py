"""Stack-infrastructure messages: the simulation clock and live parameters.

Parameters are set by putting a ParamSet on `config/<service>/<name>` (fire and forget) or by
querying `config/<service>/@set` (the reply says whether the service accepted it);
`config/<service>/@params` answers with every declared parameter and its current value.
"""
from __future__ import annotations

from typing import Any

import msgspec

from ._base import Header, Message, schema
from .services import Reply


@schema("Clock")
class Clock(Message, kw_only=True):
    """sim/clock: the simulation time services follow in sim (header.stamp_ns is the time)."""

    header: Header = msgspec.field(default_factory=Header)
    speed_factor: float = 1.0


@schema("ParamSet")
class ParamSet(Message, kw_only=True):
    """A new value for one parameter; `name` may be empty when the key names the parameter."""

    header: Header = msgspec.field(default_factory=Header)
    name: str = ""
    value: bool | int | float | str | None = None


@schema("ParamSetReply")
class ParamSetReply(Reply, kw_only=True):
    """Whether the service accepted the value; `value` is the one in force afterwards."""

    name: str = ""
    value: bool | int | float | str | None = None


class ParamDescriptor(msgspec.Struct, kw_only=True):
    """One declared parameter: value, default, unit and limits as the service declares them."""

    name: str
    value: Any = None
    default: Any = None
    type: str = "float"
    unit: str = ""
    min: float | None = None
    max: float | None = None
    choices: list[Any] | None = None
    description: str = ""
    start_only: bool = False      # read once at start: a live set is refused


@schema("ParamList")
class ParamList(Message, kw_only=True):
    header: Header = msgspec.field(default_factory=Header)
    service: str = ""
    params: list[ParamDescriptor] = msgspec.field(default_factory=list)
