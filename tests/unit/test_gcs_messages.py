"""Messages pymavlink builds without the current spec's fields, and STATUSTEXT chunking."""
from __future__ import annotations

from pymavlink.dialects.v20 import common as M

from aeroperception.services.gcs.link import Parser, make_mav
from aeroperception.services.gcs.messages import statustext


def test_statustext_chunks_long_texts():
    assert len(statustext(M.MAV_SEVERITY_INFO, "short")) == 1
    chunks = statustext(M.MAV_SEVERITY_CRITICAL, "x" * 120, 9)
    assert [(c.id, c.chunk_seq, len(c.text)) for c in chunks] == [(9, 0, 50), (9, 1, 50), (9, 2, 20)]
    chunks = statustext(M.MAV_SEVERITY_CRITICAL, "y" * 100, 0)   # a multiple of 50: an empty last chunk
    assert [(c.id, c.chunk_seq, len(c.text)) for c in chunks] == [(1, 0, 50), (1, 1, 50), (1, 2, 0)]
    mav = make_mav(1, 1)
    assert [Parser().feed(c.pack(mav))[0].chunk_seq for c in chunks] == [0, 1, 2]
