"""Schema machinery: typed msgspec Structs that are plain MessagePack maps on the wire.

Why msgspec: typed encode/decode of a 20-field state in ~2 us with validation, and `bytes`
fields decoded as zero-copy memoryviews; the output is an ordinary msgpack map that
`msgpack.unpackb` (or any other language) reads. No extension types, no pickle.

Every message class is registered under a name and a version; publishers put
"<name>@<version>" in the Zenoh encoding's schema suffix and MCAP records it.
Decoding failures of any kind raise one error type, `SchemaError`, naming the field.
"""
from __future__ import annotations

import difflib
import math
import threading
from typing import Any, ClassVar, Iterable, TypeVar

import msgspec
import msgspec.inspect
import numpy as np

__all__ = [
    "Message", "NDArray", "Header", "SchemaError", "schema", "REGISTRY", "get_schema",
    "encode", "decode", "to_builtins", "from_builtins", "check_known_fields", "schema_id", "now_ns",
]

M = TypeVar("M", bound="Message")


class SchemaError(ValueError):
    """A payload does not decode into its schema or fails validation; the message names the field."""


class Message(msgspec.Struct, kw_only=True):
    """Base of every schema. Subclasses are declared with the @schema decorator.

    Fixed-shape arrays are declared in `__shapes__` ({field: shape}) and checked on decode
    and on construction; a dimension of -1 means "any".
    """

    __schema_name__: ClassVar[str] = ""
    __schema_version__: ClassVar[int] = 1
    __shapes__: ClassVar[dict[str, tuple[int, ...]]] = {}

    def __post_init__(self) -> None:
        for field, shape in self.__shapes__.items():
            arr = getattr(self, field)
            if arr is None:
                continue
            if len(arr.shape) != len(shape) or any(
                want not in (-1, got) for want, got in zip(shape, arr.shape)
            ):
                raise ValueError(f"field `{field}` must have shape {list(shape)}, got {list(arr.shape)}")


REGISTRY: dict[str, type[Message]] = {}


def schema(name: str, version: int = 1):
    """Class decorator: give a Message its wire name/version and register it."""

    def wrap(cls: type[M]) -> type[M]:
        if name in REGISTRY and REGISTRY[name] is not cls:
            raise RuntimeError(f"schema name {name!r} registered twice")
        cls.__schema_name__ = name
        cls.__schema_version__ = version
        REGISTRY[name] = cls
        _codec(cls)  # built now, at import (under the import lock), never lazily in a worker thread
        return cls

    return wrap


def schema_id(cls: type[Message]) -> str:
    """The encoding schema suffix: "<name>@<version>"."""
    return f"{cls.__schema_name__}@{cls.__schema_version__}"


def _suggest_schemas(base: str) -> str:
    """"did you mean ..." from spelling (difflib, case-insensitive) and substrings."""
    lower = {n.lower(): n for n in REGISTRY}
    near = [lower[n] for n in difflib.get_close_matches(base.lower(), list(lower), n=4, cutoff=0.6)]
    near += [n for n in sorted(REGISTRY) if base and base.lower() in n.lower() and n not in near]
    if near:
        return f"did you mean {', '.join(near[:5])}?"
    return f"known ones include {', '.join(sorted(REGISTRY)[:8])}"


def get_schema(name: str) -> type[Message]:
    """Look a schema up by "Name" or "Name@version"; SchemaError lists close names if unknown."""
    base, _, ver = name.partition("@")
    cls = REGISTRY.get(base)
    if cls is None:
        raise SchemaError(f"unknown schema {name!r}; {_suggest_schemas(base)} (`aero schema list` shows all)")
    if ver and int(ver) != cls.__schema_version__:
        raise SchemaError(f"schema {base} is version {cls.__schema_version__}, payload says {ver}")
    return cls


# ---------------------------------------------------------------- arrays

_DTYPES = {
    "bool", "uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64",
    "float16", "float32", "float64",
}


class NDArray(msgspec.Struct):
    """An n-d array as {dtype, shape, data}: little-endian, C order, data is raw bytes.

    Decoded `data` is a memoryview into the received buffer, so `to_numpy()` is zero-copy.
    """

    dtype: str
    shape: list[int]
    data: memoryview

    def __post_init__(self) -> None:
        if self.dtype not in _DTYPES:
            raise ValueError(f"array dtype {self.dtype!r} not one of {sorted(_DTYPES)}")
        if any((not isinstance(d, int)) or d < 0 for d in self.shape):
            raise ValueError(f"array shape {self.shape} must be non-negative integers")
        want = math.prod(self.shape) * np.dtype(self.dtype).itemsize
        if len(self.data) != want:
            raise ValueError(
                f"array data is {len(self.data)} bytes but dtype {self.dtype} x shape {self.shape} needs {want}"
            )

    @classmethod
    def from_numpy(cls, arr: Any, dtype: str | None = None) -> "NDArray":
        a = np.asarray(arr, dtype=dtype)
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
        a = np.ascontiguousarray(a)
        # memoryview.cast refuses shapes containing 0 (an empty cloud or grid): use an empty buffer.
        data = memoryview(a).cast("B") if a.size else memoryview(b"")
        return cls(dtype=a.dtype.name, shape=list(a.shape), data=data)

    @classmethod
    def zeros(cls, shape: Iterable[int], dtype: str = "float64") -> "NDArray":
        return cls.from_numpy(np.zeros(tuple(shape), dtype=dtype))

    def to_numpy(self) -> np.ndarray:
        """A read-only numpy array of the data (copy it if you need to write), always aligned
        for its dtype.

        Decoded `data` points into the received payload at whatever offset msgpack put the field,
        so a float32 or float64 view may start at an odd address. Native code that takes arrays
        without copying (Rerun's Arrow import panics and aborts the process, OpenCV and Open3D may
        fault or slow down) requires aligned memory; the view is kept (zero-copy) when it is
        aligned and copied once when it is not.
        """
        a = np.frombuffer(self.data, dtype=self.dtype).reshape(self.shape)
        if a.flags.aligned:
            return a
        a = a.copy()
        a.flags.writeable = False
        return a

    @property
    def nbytes(self) -> int:
        return len(self.data)


# ---------------------------------------------------------------- header


class Header(msgspec.Struct, kw_only=True):
    """Time the data is about (ns, sim or wall clock) and the frame it is expressed in."""

    stamp_ns: int = 0
    frame_id: str = ""


def now_ns() -> int:
    import time

    return time.time_ns()


# ---------------------------------------------------------------- codec
#
# msgspec 0.22 segfaulted when two threads used a freshly created Decoder for the first time
# (seen in gcs at start-up). Every registered schema therefore gets its Decoder and its strict
# field map when it is registered; the few unregistered classes decoded ad hoc are built under a
# lock. Nothing is created lazily on a hot path.

_encoder = msgspec.msgpack.Encoder()
_plain = msgspec.msgpack.Decoder()          # untyped: the strict check reads the raw map once


class _Codec:
    """A class's typed Decoder and, for strict decoding, its field tree."""

    __slots__ = ("decoder", "fields")

    def __init__(self, cls: type) -> None:
        self.decoder = msgspec.msgpack.Decoder(cls)
        self.fields = _field_tree(msgspec.inspect.type_info(cls))


_codecs: dict[type, _Codec] = {}
_codecs_lock = threading.Lock()


def _codec(cls: type) -> _Codec:
    c = _codecs.get(cls)
    if c is None:
        with _codecs_lock:
            c = _codecs.get(cls)
            if c is None:
                c = _codecs[cls] = _Codec(cls)
    return c


def _field_tree(info: Any) -> Any:
    """What strict decoding checks: for a Struct {wire name: subtree}, for containers the
    element's subtree, for unions the tuple of struct alternatives; None where nothing can hold
    unknown fields. Recursive schemas do not occur in this package."""
    ti = msgspec.inspect
    if isinstance(info, ti.StructType):
        return {f.encode_name: _field_tree(f.type) for f in info.fields}
    if isinstance(info, (ti.ListType, ti.VarTupleType, ti.SetType, ti.FrozenSetType)):
        sub = _field_tree(info.item_type)
        return ("items", sub) if sub is not None else None
    if isinstance(info, ti.DictType):
        sub = _field_tree(info.value_type)
        return ("values", sub) if sub is not None else None
    if isinstance(info, ti.UnionType):
        subs = [t for t in (_field_tree(t) for t in info.types) if t is not None]
        return subs[0] if len(subs) == 1 else None
    return None


def _unknown_fields(obj: Any, tree: Any, path: str) -> str | None:
    """The first field of `obj` that `tree` does not declare, as a dotted path, else None."""
    if tree is None:
        return None
    if isinstance(tree, dict):
        if not isinstance(obj, dict):
            return None  # wrong type: the typed decoder reports it
        for k, v in obj.items():
            where = f"{path}.{k}" if path else str(k)
            if k not in tree:
                return where
            bad = _unknown_fields(v, tree[k], where)
            if bad:
                return bad
        return None
    kind, sub = tree
    if kind == "items" and isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            bad = _unknown_fields(v, sub, f"{path}[{i}]")
            if bad:
                return bad
    elif kind == "values" and isinstance(obj, dict):
        for k, v in obj.items():
            bad = _unknown_fields(v, sub, f"{path}[{k!r}]")
            if bad:
                return bad
    return None


def _name(cls: type) -> str:
    return getattr(cls, "__schema_name__", "") or cls.__name__


def encode(msg: Message) -> bytes:
    """Encode a message to plain msgpack bytes."""
    try:
        return _encoder.encode(msg)
    except (TypeError, ValueError, OverflowError) as e:
        raise SchemaError(f"{type(msg).__name__}: cannot encode: {e}") from None


def decode(data: bytes | bytearray | memoryview, cls: type[M], strict: bool = False) -> M:
    """Decode and validate; any failure raises SchemaError naming schema and field.

    Telemetry is decoded leniently (unknown fields ignored: forward compatible). `strict=True`
    is for what commands motion or changes state (requests, goals, setpoints, user files):
    an unknown field anywhere in the message is refused, naming it.
    """
    codec = _codec(cls)
    # A string that is not UTF-8 is a UnicodeDecodeError in some msgspec releases and a
    # DecodeError in others: both are caught. The typed decoder skips unknown keys unread, so
    # a plain decode that fails after the typed one succeeded can only have failed inside an
    # unknown field: strict decoding says so in its own words, not the library's.
    try:
        msg = codec.decoder.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError, UnicodeDecodeError) as e:
        raise SchemaError(f"{_name(cls)}: {e}") from None
    if strict:
        try:
            plain = _plain.decode(data)
        except (msgspec.DecodeError, UnicodeDecodeError) as e:
            raise SchemaError(f"{_name(cls)}: unknown field that does not decode ({e})") from None
        check_known_fields(plain, cls)
    return msg


def check_known_fields(obj: Any, cls: type) -> None:
    """Raise SchemaError if the plain map `obj` has a field `cls` does not declare (at any depth)."""
    bad = _unknown_fields(obj, _codec(cls).fields, "")
    if bad:
        raise SchemaError(f"{_name(cls)}: unknown field `{bad}` (check the spelling; "
                          f"`aero schema show {_name(cls)}` lists the fields)")


def to_builtins(msg: Any) -> Any:
    """Plain Python (dicts/lists) view, arrays kept as NDArray-shaped dicts with bytes data."""
    return msgspec.to_builtins(msg, builtin_types=(bytes, bytearray, memoryview))


def from_builtins(obj: Any, cls: type[M], strict: bool = False) -> M:
    """Validate plain data (e.g. parsed YAML/JSON from the CLI or a user file) into a message;
    `strict=True` refuses unknown fields like `decode(..., strict=True)`."""
    try:
        msg = msgspec.convert(obj, cls, strict=False)
    except msgspec.ValidationError as e:
        raise SchemaError(f"{_name(cls)}: {e}") from None
    if strict:
        check_known_fields(obj, cls)
    return msg
