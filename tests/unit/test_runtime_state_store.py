"""The state store (services/runtime/state_store.py): atomic writes, read back, a corrupt file refused."""
from __future__ import annotations

import pytest

from mission_rig import snapshot_mid_survey


def test_store_writes_atomically_and_reads_back(tmp_path):
    from aeroperception.services.runtime.state_store import StateStore
    store = StateStore(tmp_path / "v1", "mission.json")
    assert store.load() is None
    store.save(snapshot_mid_survey())
    store.save(snapshot_mid_survey(wp_index=3))
    assert store.load()["wp_index"] == 3
    assert [p.name for p in store.path.parent.iterdir()] == ["mission.json"]  # no temp files left
    store.path.write_text("{not json")
    with pytest.raises(ValueError, match="mission.json"):
        store.load()
