"""Property-based fuzzing of every registered schema's decoder (hypothesis).

Whatever the bytes — random, random msgpack, schema-shaped maps with random values, valid
messages with bytes flipped / cut / extended, a field replaced or an unknown field added —
`decode` either returns a valid message of the schema or raises SchemaError: never another
exception, never a crash. Strict decoding accepts a subset of what lenient decoding accepts, and
refuses exactly the unknown fields lenient decoding ignores.
"""
from __future__ import annotations

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from aeroperception.schemas import REGISTRY, SchemaError, decode, encode, get_schema
from faults.payloads import ALL_SCHEMAS, garbage, mutated, schema_maps, valid_example

FUZZ = settings(max_examples=25, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def decode_outcome(data: bytes, cls: type, strict: bool):
    """The decoded message, or the SchemaError; any other exception fails the test."""
    try:
        msg = decode(data, cls, strict=strict)
    except SchemaError as e:
        return e
    assert isinstance(msg, cls)
    encode(msg)  # what decodes must encode again (no half-built message)
    return msg


def check_both(data: bytes, cls: type) -> None:
    lenient = decode_outcome(data, cls, strict=False)
    strict = decode_outcome(data, cls, strict=True)
    if isinstance(lenient, SchemaError):
        assert isinstance(strict, SchemaError), "strict accepted what lenient refused"
    elif not isinstance(strict, SchemaError):
        assert strict == lenient or _has_nan(data), "strict and lenient decoded differently"
    else:
        # The payload had a field the schema does not declare (its key or value may not even decode).
        assert "unknown field" in str(strict), \
            f"strict refused a lenient-valid payload for another reason: {strict}"


def _has_nan(data: bytes) -> bool:
    return b"\xcb\x7f\xf8" in data or b"\xca\x7f\xc0" in data or b"nan" in repr(msgpack.unpackb(data, strict_map_key=False)).encode()


@pytest.mark.parametrize("name", ALL_SCHEMAS)
@FUZZ
@given(data=st.data())
def test_garbage_decodes_or_raises_schema_error(name, data):
    check_both(data.draw(garbage()), REGISTRY[name])


@pytest.mark.parametrize("name", ALL_SCHEMAS)
@FUZZ
@given(data=st.data())
def test_schema_shaped_maps_decode_or_raise_schema_error(name, data):
    cls = REGISTRY[name]
    check_both(msgpack.packb(data.draw(schema_maps(cls)), use_bin_type=True), cls)


@pytest.mark.parametrize("name", ALL_SCHEMAS)
@FUZZ
@given(data=st.data())
def test_mutated_valid_messages_decode_or_raise_schema_error(name, data):
    cls = REGISTRY[name]
    check_both(data.draw(mutated(cls)), cls)


@pytest.mark.parametrize("name", ALL_SCHEMAS)
def test_valid_example_round_trips_in_both_modes(name):
    cls = REGISTRY[name]
    data = encode(valid_example(cls))
    assert decode(data, cls) == decode(data, cls, strict=True) == valid_example(cls)
    assert get_schema(name) is cls


@pytest.mark.parametrize("name", ALL_SCHEMAS)
@FUZZ
@given(extra=st.text(min_size=1, max_size=12), value=st.integers(-(2 ** 63), 2 ** 63 - 1))
def test_unknown_field_lenient_ignores_strict_refuses_naming_it(name, extra, value):
    cls = REGISTRY[name]
    plain = msgpack.unpackb(encode(valid_example(cls)), strict_map_key=False)
    if extra in plain:
        return
    data = msgpack.packb({**plain, extra: value}, use_bin_type=True)
    assert decode(data, cls) == valid_example(cls)
    with pytest.raises(SchemaError) as e:
        decode(data, cls, strict=True)
    assert extra in str(e.value)
