"""The recorder's logic, without Zenoh: which keys, a bounded buffer, and the MCAP file sink.

The sink writes our msgpack payloads unchanged (message encoding `msgpack`), one channel per
(key, encoding), the schema record named "<name>@<version>" (as in the Zenoh encoding) holding a
JSON Schema generated from the msgspec type. Chunks are closed and written at least every
`flush_interval_s`, so what is on disk after a kill -9 is every message but the last interval's
(`aero mcap recover` indexes it). A disk error (full, file-size limit, unwritable) ends the
recording with the reason, and the file is cut back to its last complete chunk so it stays
readable; it never raises into the caller.
"""
from __future__ import annotations

import json
import os
import re
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterable

import msgspec
from mcap.writer import CompressionType, Writer

from aeroperception.schemas import REGISTRY
from aeroperception.services.runtime import param, section

from . import contract

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
PROFILE = "aeroperception"
MSGPACK_MIME = "application/msgpack"


def default_output_dir() -> Path:
    return Path(os.environ.get("AERO_RECORD_DIR") or Path.home() / ".aero" / "recordings")


def output_path(text: str) -> Path:
    """The output_dir parameter: a path (~ expanded), '' = default_output_dir()."""
    return Path(text).expanduser() if text else default_output_dir()


def select_keys(preset: str, keys: Iterable[str] = (), record_images: bool = False) -> list[str]:
    """The key expressions to subscribe to (without vehicle prefix), duplicates removed."""
    if preset not in contract.PRESETS:
        raise ValueError(f"unknown preset {preset!r}; presets: {', '.join(contract.PRESETS)}")
    out: list[str] = []
    for k in (*contract.PRESETS[preset], *(k.strip().strip("/") for k in keys),
              *(contract.IMAGE_KEYS if record_images else ())):
        if k and k not in out:
            out.append(k)
    return out


def is_image_key(key: str) -> bool:
    """A raw camera image (left out of wildcard presets unless record_images)."""
    return key.endswith("/image")


def schema_of_encoding(encoding: str) -> str:
    """"<name>@<version>" from a Zenoh encoding "application/msgpack;<name>@<version>" ("" if none)."""
    return encoding.split(";", 1)[1] if ";" in encoding else ""


def json_schema(schema_id: str) -> bytes:
    """A JSON Schema for a registered schema (msgspec's; arrays' bytes are msgpack bin on the
    wire, which JSON Schema can only call a base64 string). `{}` for an unknown schema."""
    cls = REGISTRY.get(schema_id.partition("@")[0])
    if cls is None:
        return b"{}"
    doc = msgspec.json.schema(cls)
    doc["$comment"] = (f"aeroperception schema {schema_id}; payloads are MessagePack maps "
                       "(bytes fields are msgpack bin, shown here as base64 strings)")
    return json.dumps(doc).encode()


@dataclass
class Sample:
    key: str
    encoding: str
    payload: bytes
    log_time_ns: int


class BoundedBuffer:
    """Samples waiting for the writer, at most `max_bytes` of payload: when full, the new sample
    is dropped and counted (per key) — the callback never blocks and memory never grows."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self.bytes = 0
        self.dropped: Counter[str] = Counter()
        self._q: deque[Sample] = deque()
        self._cond = threading.Condition()

    def put(self, s: Sample) -> bool:
        with self._cond:
            if self.bytes + len(s.payload) > self.max_bytes:
                self.dropped[s.key] += 1
                return False
            self._q.append(s)
            self.bytes += len(s.payload)
            self._cond.notify()
            return True

    def take_all(self, wait_s: float) -> list[Sample]:
        with self._cond:
            if not self._q:
                self._cond.wait(wait_s)
            out = list(self._q)
            self._q.clear()
            self.bytes = 0
            return out

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()


@dataclass(frozen=True)
class SinkConfig:
    """Where and how the files are written (defaults, units and ranges: contract.PARAMS)."""

    output_dir: Path = param("output_dir", output_path)
    prefix: str = param("prefix")
    max_bag_size: int = param("max_bag_size")
    chunk_size: int = param("chunk_size")
    compression: str = param("compression")
    flush_interval_s: float = param("flush_interval_s")
    max_total_size: int = param("max_total_size")    # disk budget of <prefix>_*.mcap in output_dir (0: none), see McapSink._rotate

    def check(self) -> None:
        """A budget must hold a finished split besides the one being written (at most
        max_bag_size + chunk_size), or every new split would delete the one before it."""
        least = 2 * self.max_bag_size + self.chunk_size
        if self.max_total_size and self.max_total_size < least:
            raise ValueError(f"max_total_size {self.max_total_size} B keeps less than one finished file: "
                             f"give at least 2 x max_bag_size + chunk_size = {least} B, or lower max_bag_size")


@dataclass(frozen=True)
class RecorderConfig:
    """Every parameter of contract.PARAMS, referenced once (all read when the recording starts)."""

    sink: SinkConfig = section(SinkConfig)
    preset: str = param("preset")
    keys: str = param("keys")
    record_images: bool = param("record_images")
    max_buffer_mb: float = param("max_buffer_mb")
    params_timeout_s: float = param("params_timeout_s")

    def key_exprs(self) -> list[str]:
        """The key expressions to record (select_keys)."""
        return select_keys(self.preset, [k for k in self.keys.split(",") if k.strip()], self.record_images)


_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


@dataclass
class SinkStats:
    messages: int = 0
    bytes: int = 0
    files: list[str] = field(default_factory=list)
    per_key: Counter = field(default_factory=Counter)
    deleted: list[str] = field(default_factory=list)   # split files removed to stay within max_total_size
    deleted_bytes: int = 0
    delete_errors: int = 0


def split_files(output_dir: Path, prefix: str) -> list[Path]:
    """The recorder's own files in `output_dir` (<prefix>_<UTC start>_<split>.mcap), oldest first:
    by start time, then split number (not by name: split 10 sorts before 2). Other files are
    never listed, so rotation cannot delete what the recorder did not write."""
    pattern = re.compile(rf"^{re.escape(prefix)}_(\d{{8}}T\d{{6}}Z)_(\d+)\.mcap$")
    found = []
    for path in output_dir.glob(f"{prefix}_*.mcap") if output_dir.is_dir() else ():
        m = pattern.match(path.name)
        if m:
            found.append(((m.group(1), int(m.group(2))), path))
    return [path for _, path in sorted(found)]


LIVE_S = 10.0       # an unfinished split file touched this recently may be another recorder's
_MCAP_MAGIC = b"\x89MCAP0\r\n"


def _finished(path: Path) -> bool:
    """Whether the MCAP file ends with its closing magic (its writer finished it)."""
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        if f.tell() < 2 * len(_MCAP_MAGIC):
            return False
        f.seek(-len(_MCAP_MAGIC), os.SEEK_END)
        return f.read() == _MCAP_MAGIC


def rotation_victims(sizes: list[tuple[Path, int]], max_total_size: int, reserve: int) -> list[Path]:
    """The oldest files to delete (`sizes`: (path, bytes) oldest first) so that what is left plus
    `reserve` (bytes that stay: the split about to be written, files in use) fits in
    `max_total_size`; all of them if it cannot fit."""
    total = sum(size for _, size in sizes) + reserve
    victims = []
    for path, size in sizes:
        if total <= max_total_size:
            break
        victims.append(path)
        total -= size
    return victims


class McapSink:
    """MCAP files: open lazily, one channel per (key, encoding), split past max_bag_size.

    `metadata` (name -> {str: str}) is written into every split so each file stands alone.
    After an OSError the sink is `failed` (reason in `error`) and drops everything it is given.
    """

    def __init__(self, cfg: SinkConfig, metadata: dict[str, dict[str, str]] | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.cfg = cfg
        self.metadata: dict[str, dict[str, str]] = dict(metadata or {})
        self.clock = clock
        self.stats = SinkStats()
        self.error = ""
        self.lost_after_error = 0
        self._writer: Writer | None = None
        self._stream = None
        self._path: Path | None = None
        self._channels: dict[tuple[str, str], int] = {}
        self._schemas: dict[str, int] = {}
        self._good_offset = 0
        self._last_flush = clock()
        self._split = 0
        self._stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")

    @property
    def failed(self) -> bool:
        return bool(self.error)

    @property
    def path(self) -> Path | None:
        return self._path

    # ---------------------------------------------------------- writing

    def write(self, samples: Iterable[Sample]) -> None:
        for s in samples:
            if self.failed:
                self.lost_after_error += 1
                continue
            self._guard(self._write_one, s)
        if not self.failed and self.clock() - self._last_flush >= self.cfg.flush_interval_s:
            self.flush()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Metadata for this and every later split (written at once if a file is open)."""
        self.metadata[name] = data
        if self._writer is not None and not self.failed:
            self._guard(self._writer.add_metadata, name, data)

    def flush(self) -> None:
        """Close the chunk in progress and push it to the OS (survives a kill -9 of this process)."""
        self._last_flush = self.clock()
        if self._writer is None or self.failed:
            return
        if self._guard(self._writer.flush):
            self._good_offset = self._stream.tell()

    def close(self) -> None:
        """Finish the file (summary + index); after a failure only cut back to the last good chunk."""
        if self._writer is not None and not self.failed:
            self._close_file()
        self._release()

    def _write_one(self, s: Sample) -> None:
        if self._writer is None:
            self._open()
        ch = self._channels.get((s.key, s.encoding))
        if ch is None:
            ch = self._channel(s.key, s.encoding)
        self._good_offset = self._stream.tell()     # a record boundary: a failed write is cut back to it
        self._writer.add_message(ch, log_time=s.log_time_ns, data=s.payload, publish_time=s.log_time_ns)
        self.stats.messages += 1
        self.stats.bytes += len(s.payload)
        self.stats.per_key[s.key] += 1
        # Split before the chunk being built (at most chunk_size) could take the file past the limit.
        if self._stream.tell() + self.cfg.chunk_size >= self.cfg.max_bag_size:
            self._close_file()

    def _channel(self, key: str, encoding: str) -> int:
        sid = schema_of_encoding(encoding)
        schema = 0
        if sid:
            schema = self._schemas.get(sid) or 0
            if not schema:
                schema = self._schemas[sid] = self._writer.register_schema(sid, SCHEMA_ENCODING, json_schema(sid))
        is_msgpack = encoding.split(";", 1)[0] == MSGPACK_MIME
        ch = self._writer.register_channel(key, MESSAGE_ENCODING if is_msgpack else encoding.split(";", 1)[0],
                                           schema, {"zenoh_encoding": encoding, "schema": sid})
        self._channels[(key, encoding)] = ch
        return ch

    def _rotate(self) -> None:
        """Before a new split: delete the oldest split files (this flight's or earlier ones) until
        they plus a full new split fit in max_total_size. A file being written by another
        recorder (unfinished, touched in the last LIVE_S) is counted, never deleted. A file that
        cannot be deleted is counted and the recording goes on (over budget, not stopped)."""
        now = time.time()
        candidates, live_bytes = [], 0
        for path in split_files(self.cfg.output_dir, self.cfg.prefix):
            try:
                st = path.stat()
                live = now - st.st_mtime < LIVE_S and not _finished(path)
            except OSError:     # deleted meanwhile
                continue
            if live:
                live_bytes += st.st_size
            else:
                candidates.append((path, st.st_size))
        size_of = dict(candidates)
        reserve = live_bytes + self.cfg.max_bag_size + self.cfg.chunk_size   # the new split's worst case
        for path in rotation_victims(candidates, self.cfg.max_total_size, reserve):
            try:
                path.unlink()
            except FileNotFoundError:
                continue
            except OSError:
                self.stats.delete_errors += 1
                continue
            self.stats.deleted.append(str(path))
            self.stats.deleted_bytes += size_of[path]

    def _open(self) -> None:
        self.cfg.output_dir.mkdir(parents=True, exist_ok=True)
        if self.cfg.max_total_size:
            self._rotate()
        self._path = self.cfg.output_dir / f"{self.cfg.prefix}_{self._stamp}_{self._split}.mcap"
        self._split += 1
        self._stream = _FileStream(self._path)
        self.stats.files.append(str(self._path))
        self._writer = Writer(self._stream, chunk_size=self.cfg.chunk_size,
                              compression=_COMPRESSION[self.cfg.compression])
        self._writer.start(profile=PROFILE, library="aeroperception recorder")
        self._channels.clear()
        self._schemas.clear()
        for name, data in self.metadata.items():
            self._writer.add_metadata(name, data)
        self._writer.flush()
        self._good_offset = self._stream.tell()

    def _close_file(self) -> None:
        if self._guard(self._writer.finish):
            self._stream.close()
            self._writer = self._stream = None

    def _guard(self, fn, *args) -> bool:
        try:
            fn(*args)
            return True
        except OSError as e:
            where = self._path or self.cfg.output_dir
            self.error = f"{where}: {e.strerror or e}"
            self._cut_back()
            return False

    def _cut_back(self) -> None:
        """After a failed write: drop the partial chunk so the file is header + whole chunks."""
        if self._stream is None:
            return
        try:
            os.ftruncate(self._stream.fileno(), self._good_offset)
        except OSError:
            pass
        self._release()

    def _release(self) -> None:
        if self._stream is not None:
            self._stream.close()
        self._writer = self._stream = None


class _FileStream:
    """An unbuffered file for the MCAP writer: every write goes to the OS at once (the writer
    batches records itself), so a failed write is seen where it happens and nothing buffered
    is written later, past the cut."""

    def __init__(self, path: Path):
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._pos = 0

    def write(self, data) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            self._pos += n
            view = view[n:]
        return len(data)

    def tell(self) -> int:
        return self._pos

    def fileno(self) -> int:
        return self._fd

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._fd >= 0:
            try:
                os.close(self._fd)
            except OSError:
                pass
            self._fd = -1


class KeyFilter:
    """Which subscription records a sample: the first expression that includes its key (so a key
    under two expressions is recorded once), and images only when asked for, even under `**`."""

    def __init__(self, exprs: list[str], record_images: bool):
        import zenoh

        self._exprs = [zenoh.KeyExpr(e) for e in exprs]
        self._explicit_images = [i for i, e in enumerate(exprs) if e.endswith("/image")]
        self.record_images = record_images
        self._owner: dict[str, int] = {}

    def accept(self, index: int, key: str) -> bool:
        owner = self._owner.get(key)
        if owner is None:
            owner = next((i for i, e in enumerate(self._exprs) if e.includes(key)), index)
            self._owner[key] = owner
        if owner != index:
            return False
        return self.record_images or not is_image_key(key) or index in self._explicit_images


class Recording:
    """The buffer and the sink with the one thread that writes: `offer()` from any thread, never
    blocking; the writer drains, writes and flushes at least every flush interval; `close()`
    writes what is left and finishes the file."""

    def __init__(self, sink: McapSink, max_buffer_bytes: int):
        self.sink = sink
        self.buffer = BoundedBuffer(max_buffer_bytes)
        self._pending_meta: list[tuple[str, dict[str, str]]] = []
        self.before_clock = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="recorder-writer", daemon=True)

    def start(self) -> "Recording":
        self._thread.start()
        return self

    def offer(self, key: str, encoding: str, payload: bytes, log_time_ns: int) -> bool:
        if log_time_ns <= 0:
            # On sim time before the first sim/clock (the node's clock reads 0): the sample has no
            # place on the time line, and a 0 would make the file start in 1970 (replay would
            # wait decades for the next message). Counted, not recorded.
            self.before_clock += 1
            return False
        if self.sink.failed:
            self.buffer.dropped[key] += 1
            return False
        return self.buffer.put(Sample(key, encoding, payload, log_time_ns))

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Written by the writer thread (the sink is single-threaded)."""
        self._pending_meta.append((name, data))
        self.buffer.wake()

    @property
    def dropped(self) -> int:
        return sum(self.buffer.dropped.values())

    def _run(self) -> None:
        interval = self.sink.cfg.flush_interval_s
        while not self._stop.is_set():
            self._step(self.buffer.take_all(interval / 2))

    def _step(self, samples: list[Sample]) -> None:
        while self._pending_meta:
            self.sink.add_metadata(*self._pending_meta.pop(0))
        self.sink.write(samples)

    def close(self, timeout_s: float = 1.5) -> None:
        self._stop.set()
        self.buffer.wake()
        self._thread.join(timeout_s)
        self._step(self.buffer.take_all(0))
        self.sink.close()
