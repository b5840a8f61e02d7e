"""The `aero` codec for the PyPI `zenoh-cli` (`zenoh subscribe --decoder aero`, `zenoh put --encoder aero`).

zenoh-cli is the generic tool Zenoh users already know; this plugin lets it read and write our
msgpack messages. It is registered through zenoh-cli's entry-point groups
`zenoh_cli.codecs.decoders` / `zenoh_cli.codecs.encoders` (pyproject.toml), whose API is
`decoder(key, payload: bytes) -> str` and `encoder(key, value: str) -> bytes`.

zenoh-cli hands a codec the key and the payload only, never the sample's encoding, so the
schema comes from what the services' contracts declare for the key (the table of
docs/reference/keys.md; a `<vehicle>/` prefix is recognised). A key no contract declares is shown as schema-less
msgpack. Service keys work with `zenoh get` (reply decoded, `-v` encoded as the request).
What a user types for `put` is a command: it is decoded strictly (unknown fields and
wrong types refused, with the error on stderr), exactly like `aero topic pub`.
"""
from __future__ import annotations

import functools
import json

import msgpack

from aeroperception.schemas import SchemaError, decode, encode, get_schema, to_builtins

from . import contracts
from .common import CliError, summarize


@functools.lru_cache(maxsize=1)
def _contracts() -> list[contracts.Contract]:
    return contracts.load_contracts()


@functools.lru_cache(maxsize=512)
def schemas_for_key(key: str, replies: bool = True) -> tuple[str, ...]:
    """Schema names the contracts declare for `key`: topics (writers first), then for a service
    key its reply (`replies`, what `zenoh get` prints) or its request (what `zenoh get -v` sends).
    Tries the key without its first chunk too, for a `<vehicle>/` prefix."""
    key = key.strip("/").split("?", 1)[0]
    candidates = [key]
    if "/" in key:
        candidates.append(key.split("/", 1)[1])
    for k in candidates:
        found = [s for s, _svc, _role in contracts.declared_schemas(k, _contracts())]
        found += [pair[1 if replies else 0] for c in _contracts() for pattern, pair in c.services.items()
                  if contracts.key_matches(pattern, k) and isinstance(pair[1 if replies else 0], str)]
        if found:
            return tuple(dict.fromkeys(found))
    return ()


def decode_payload(key: str, payload: bytes) -> str:
    """One JSON line: {"schema": name, "data": fields}; arrays shown as a one-line summary."""
    key = str(key)
    for name in schemas_for_key(key):
        try:
            cls = get_schema(name)
            msg = decode(payload, cls)
        except SchemaError:
            continue
        return json.dumps({"schema": name, "data": summarize(to_builtins(msg))}, default=str)
    data = msgpack.unpackb(payload, raw=False)  # not one of ours: plain msgpack, or the error says why
    return json.dumps({"schema": None, "data": summarize(data)}, default=str)


def encode_value(key: str, value: str) -> bytes:
    """A typed message from what the user typed: `{yaml/json fields}` with the schema the key is
    declared with, or `SchemaName {fields}` to name it (needed for undeclared keys)."""
    from aeroperception.tools.cli.topic import build_message  # the one place `aero topic pub` builds a message too

    text = value.strip()
    head, _, rest = text.partition(" ")
    if head and head[0].isalpha() and not head.endswith(":"):
        type_name, text = head, rest.strip() or "{}"
    else:
        declared = schemas_for_key(str(key), replies=False)
        if not declared:
            _refuse(f"no service declares {key}: name the schema, e.g. -v 'VehicleState {{...}}'")
        type_name = declared[0]
    try:
        return encode(build_message(type_name, text))
    except CliError as e:
        _refuse(str(e))


def _refuse(why: str):
    """Nothing is sent: one line on stderr and exit 2 (zenoh-cli would print a traceback)."""
    raise SystemExit(f"aero codec: {why}")
