"""Read a saved .rrd back with Rerun's own reader: which entities hold data, how many rows, over
which span of the shared timeline. Used by the tests (and handy at a Python prompt)."""
from __future__ import annotations

from dataclasses import dataclass

import pyarrow as pa
from rerun.chunk import RrdReader

from .adapters import TIMELINE


@dataclass
class EntitySpan:
    rows: int = 0
    first_ns: int | None = None     # None: static data only
    last_ns: int | None = None


def entity_spans(path: str) -> dict[str, EntitySpan]:
    """{entity path: rows and stamp span} of the first recording in the file (streamed, so a
    file whose footer was never written, e.g. after kill -9, reads too)."""
    out: dict[str, EntitySpan] = {}
    for chunk in RrdReader(path).stream():
        span = out.setdefault(chunk.entity_path, EntitySpan())
        span.rows += chunk.num_rows
        if TIMELINE not in chunk.timeline_names:
            continue
        stamps = chunk.to_record_batch().column(TIMELINE).cast(pa.int64()).to_numpy(zero_copy_only=False)
        if len(stamps):
            lo, hi = int(stamps.min()), int(stamps.max())
            span.first_ns = lo if span.first_ns is None else min(span.first_ns, lo)
            span.last_ns = hi if span.last_ns is None else max(span.last_ns, hi)
    return out
