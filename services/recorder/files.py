"""Reading what the recorder wrote: tolerant record streams, `info`, `recover`, ordered messages.

A file cut short (kill -9, power loss, disk full) has no summary or index; its complete chunks
are still there. `scan` reads records until the first damaged one; `recover` writes them into
a new, finished (indexed) file.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from .logic import PROFILE


class RecordingError(Exception):
    """A file that is not MCAP, or cannot be read at all (the message says what to do)."""


@dataclass
class Scan:
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: list[Metadata] = field(default_factory=list)
    truncated: str = ""          # why reading stopped early ("" = the file ended cleanly)


def scan(path: str | Path, on_message: Callable[[Scan, Channel, Message], None] | None = None) -> Scan:
    """Read every record in file order until the end or the first damaged record;
    `on_message(scan so far, channel, message)` for each message."""
    out = Scan()
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False, record_size_limit=1 << 32).records:
                if isinstance(rec, Schema):
                    out.schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    out.channels[rec.id] = rec
                elif isinstance(rec, Metadata):
                    out.metadata.append(rec)
                elif isinstance(rec, Message) and on_message is not None:
                    ch = out.channels.get(rec.channel_id)
                    if ch is not None:
                        on_message(out, ch, rec)
        except McapError as e:
            if "magic" in str(e) and not out.channels and not out.metadata:
                raise RecordingError(f"{path}: not an MCAP file ({e})") from None
            out.truncated = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
        except Exception as e:  # noqa: BLE001 - a cut chunk fails inside zstd/struct: that is the end
            out.truncated = f"{type(e).__name__}: {e}"
    return out


def is_indexed(path: str | Path) -> bool:
    """Whether the file has a summary (finished by its writer)."""
    try:
        with open(path, "rb") as f:
            return make_reader(f).get_summary() is not None
    except Exception:  # noqa: BLE001 - no footer, bad magic, cut file
        return False


@dataclass
class RecoverResult:
    messages: int
    channels: int
    last_time_ns: int
    truncated: str


def recover(src: str | Path, dst: str | Path) -> RecoverResult:
    """Write every readable record of `src` (schemas, channels, metadata, messages) into a new
    finished MCAP file `dst`, with chunk and message indexes."""
    with open(dst, "wb") as out:
        w = Writer(out, compression=CompressionType.ZSTD)
        w.start(profile=PROFILE, library="aero mcap recover")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        n = [0, 0]

        def add_channel(sc: Scan, ch: Channel) -> int:
            """Schemas and channels precede their messages in the file, so `sc` holds them."""
            if ch.schema_id and ch.schema_id not in schema_ids:
                s = sc.schemas[ch.schema_id]
                schema_ids[ch.schema_id] = w.register_schema(s.name, s.encoding, s.data)
            cid = channel_ids[ch.id] = w.register_channel(ch.topic, ch.message_encoding,
                                                          schema_ids.get(ch.schema_id, 0), ch.metadata)
            return cid

        def on_message(sc: Scan, ch: Channel, m: Message) -> None:
            cid = channel_ids.get(ch.id)
            if cid is None:
                cid = add_channel(sc, ch)
            w.add_message(cid, log_time=m.log_time, publish_time=m.publish_time, data=m.data, sequence=m.sequence)
            n[0] += 1
            n[1] = max(n[1], m.log_time)

        result = scan(src, on_message)
        for md in result.metadata:
            w.add_metadata(md.name, md.metadata)
        w.finish()
    return RecoverResult(messages=n[0], channels=len(channel_ids), last_time_ns=n[1], truncated=result.truncated)


@dataclass
class ChannelInfo:
    topic: str
    schema: str
    encoding: str
    count: int = 0
    first_ns: int = 0
    last_ns: int = 0
    bytes: int = 0

    @property
    def rate_hz(self) -> float:
        span = (self.last_ns - self.first_ns) * 1e-9
        return (self.count - 1) / span if self.count > 1 and span > 0 else 0.0


@dataclass
class FileInfo:
    path: str
    indexed: bool
    channels: list[ChannelInfo]
    metadata: dict[str, dict[str, str]]
    truncated: str = ""

    @property
    def messages(self) -> int:
        return sum(c.count for c in self.channels)

    @property
    def start_ns(self) -> int:
        return min((c.first_ns for c in self.channels if c.count), default=0)

    @property
    def end_ns(self) -> int:
        return max((c.last_ns for c in self.channels if c.count), default=0)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9


def info(path: str | Path) -> FileInfo:
    """Channels with counts, first/last log times and rates (reads the whole file: rates per
    channel need each channel's own span, which the summary does not hold)."""
    if not Path(path).is_file():
        raise RecordingError(f"{path}: no such file")
    per: dict[int, ChannelInfo] = {}

    def on_message(_sc: Scan, ch: Channel, m: Message) -> None:
        ci = per.get(ch.id)
        if ci is None:
            schema = ch.metadata.get("schema", "")
            ci = per[ch.id] = ChannelInfo(ch.topic, schema, ch.message_encoding, first_ns=m.log_time)
        ci.count += 1
        ci.first_ns = min(ci.first_ns, m.log_time)
        ci.last_ns = max(ci.last_ns, m.log_time)
        ci.bytes += len(m.data)

    sc = scan(path, on_message)
    for cid, ch in sc.channels.items():
        if cid not in per:
            per[cid] = ChannelInfo(ch.topic, ch.metadata.get("schema", ""), ch.message_encoding)
    return FileInfo(str(path), is_indexed(path), sorted(per.values(), key=lambda c: c.topic),
                    {m.name: dict(m.metadata) for m in sc.metadata}, sc.truncated)


def messages(path: str | Path, topics: list[str] | None = None, start_ns: int | None = None,
             end_ns: int | None = None) -> Iterator[tuple[Channel, Message]]:
    """Messages in log-time order from an indexed file (a cut one: `aero mcap recover` it first)."""
    if not is_indexed(path):
        raise RecordingError(f"{path}: has no index (cut short?): run `aero mcap recover {path}` first")
    with open(path, "rb") as f:
        for _schema, ch, m in make_reader(f).iter_messages(topics=topics, start_time=start_ns, end_time=end_ns,
                                                           log_time_order=True):
            yield ch, m


