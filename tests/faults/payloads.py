"""Hypothesis strategies for hostile payloads, shared by the schema fuzz unit tests and the stack
fuzz test: random msgpack values, schema-shaped maps with random values, and mutations of valid
messages (bytes flipped, cut, extended; a field replaced; an unknown field added).

    from faults.payloads import msgpack_values, schema_maps, valid_example, mutated, collect
"""
from __future__ import annotations

from typing import Any

import msgpack
import msgspec
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from aeroperception.schemas import (
    REGISTRY, ArmRequest, CancelRequest, GoToPositionGoal, Message, MissionCommand, ResultRequest,
    SetTrajectoryGoal, TakeoffGoal, Trajectory, Vector3, encode,
)
from aeroperception.schemas.mission import Mission, Waypoint

scalars = st.one_of(
    st.none(), st.booleans(),
    st.integers(min_value=-(2 ** 63), max_value=2 ** 64 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20), st.binary(max_size=40),
)

# Any value msgpack can carry (maps with str or int keys), a few levels deep.
msgpack_values = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=5),
                            st.dictionaries(st.one_of(st.text(max_size=12), st.integers(-5, 5)), inner, max_size=5)),
    max_leaves=20,
)

# Messages that need a value (no default-constructible instance).
_REQUIRED: dict[type, Message] = {
    Mission: Mission(waypoints=[Waypoint(x=0.0, y=0.0, z=5.0)]),
    MissionCommand: MissionCommand(command="HOLD"),
    ArmRequest: ArmRequest(arm=False),
    TakeoffGoal: TakeoffGoal(target_altitude_m=3.0),
    SetTrajectoryGoal: SetTrajectoryGoal(trajectory=Trajectory()),
    GoToPositionGoal: GoToPositionGoal(position_m=Vector3(x=1.0, y=0.0, z=3.0)),
    CancelRequest: CancelRequest(goal_id="g"),
    ResultRequest: ResultRequest(goal_id="g"),
}


def valid_example(cls: type[Message]) -> Message:
    """A valid instance of every registered schema."""
    return _REQUIRED[cls] if cls in _REQUIRED else cls()


def field_names(cls: type) -> list[str]:
    return [f.encode_name for f in msgspec.structs.fields(cls)]


def schema_maps(cls: type[Message]):
    """Maps whose keys are mostly the schema's own field names, with random values."""
    names = field_names(cls)
    keys = st.one_of(st.sampled_from(names), st.text(max_size=10)) if names else st.text(max_size=10)
    return st.dictionaries(keys, msgpack_values, max_size=max(1, len(names) + 2))


def _as_plain(cls: type[Message]) -> dict[str, Any]:
    return msgpack.unpackb(encode(valid_example(cls)), raw=False, strict_map_key=False)


def field_replaced(cls: type[Message]):
    """A valid message's map with one field's value replaced by a random value."""
    base = _as_plain(cls)
    if not base:
        return st.just(base)
    return st.tuples(st.sampled_from(sorted(base)), msgpack_values).map(lambda kv: {**base, kv[0]: kv[1]})


def byte_mutations(data: bytes):
    """`data` with bytes flipped, cut short, or extended with junk."""
    n = len(data)
    flips = st.lists(st.tuples(st.integers(0, max(n - 1, 0)), st.integers(0, 255)), min_size=1, max_size=4).map(
        lambda fl: bytes(_flip(bytearray(data), fl)))
    cut = st.integers(0, max(n - 1, 0)).map(lambda k: data[:k])
    grow = st.binary(min_size=1, max_size=16).map(lambda tail: data + tail)
    return st.one_of(flips, cut, grow) if n else st.binary(max_size=16)


def _flip(buf: bytearray, flips) -> bytearray:
    for i, v in flips:
        buf[i] = v
    return buf


def mutated(cls: type[Message]):
    """Encoded hostile variants of a valid `cls` message (bytes)."""
    valid = encode(valid_example(cls))
    pack = lambda obj: msgpack.packb(obj, use_bin_type=True)  # noqa: E731
    return st.one_of(byte_mutations(valid), field_replaced(cls).map(pack), schema_maps(cls).map(pack))


def garbage():
    """Bytes that are anything: random, or a random msgpack value."""
    return st.one_of(st.binary(max_size=64), msgpack_values.map(lambda v: msgpack.packb(v, use_bin_type=True)))


def collect(strategy, n: int) -> list:
    """n examples of `strategy`, deterministic across runs (for feeding a live stack)."""
    out: list = []

    @settings(max_examples=n, database=None, derandomize=True, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck), deadline=None)
    @given(strategy)
    def take(x) -> None:
        out.append(x)

    take()
    return out


ALL_SCHEMAS = sorted(REGISTRY)
