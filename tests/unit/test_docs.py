"""docs/ARCHITECTURE.md's key table is generated from services/*/contract.py: regenerate it and
fail when the committed document drifted (fix: `aero docs keys --write`)."""
from __future__ import annotations

from pathlib import Path

from aeroperception.tools.cli import docs as cmd_docs
from aeroperception.tools import contracts

DOC = Path(__file__).resolve().parents[2] / "docs" / "ARCHITECTURE.md"


def test_key_table_in_architecture_doc_matches_the_contracts():
    doc = DOC.read_text()
    assert doc == cmd_docs.splice(doc, cmd_docs.key_table()), \
        "docs/ARCHITECTURE.md's key table is out of date: run `aero docs keys --write`"


def test_every_service_folder_with_a_contract_is_in_the_table():
    root = Path(__file__).resolve().parents[2] / "services"
    with_contract = {p.parent.name for p in root.glob("*/contract.py")}
    table = cmd_docs.key_table()
    assert with_contract <= {c.service for c in contracts.load_contracts()}
    for name in with_contract:
        assert f"`services/{name}/contract.py`" in table


def test_a_new_service_contract_is_picked_up(tmp_path):
    # A service that does not exist (yet): its keys appear with their producer and consumers.
    text = '''
NAME = "radar"
MAP_RATE_HZ = 5.0
INPUTS = Topics(Topic("sensors/lidar/points", PointCloud))
OUTPUTS = Topics(
    Topic("perception/radar_tracks", PointCloud, 10.0, note="ENU"),
    Topic("perception/radar_map", OccupancyGrid, MAP_RATE_HZ),
)
SERVICES = Queries(Query("radar/srv/reset", Empty, Reply))
ACTIONS = ("radar/action/scan",)
LIVELINESS = ("lidar",)
'''
    c = contracts.parse_contract(text, "radar", "services/radar/contract.py")
    table = cmd_docs.key_table([*contracts.load_contracts(), c])
    assert "| `perception/radar_tracks` | PointCloud | 10 Hz | radar | — | ENU |" in table
    assert "| `perception/radar_map` | OccupancyGrid | 5 Hz | radar | — |  |" in table   # a named constant
    assert "radar" in next(line for line in table.splitlines() if line.startswith("| `sensors/lidar/points`"))
    assert "| `radar/srv/reset` | Empty | Reply | radar | — |" in table
    assert "| `radar/action/scan` | radar | — |" in table
    assert "radar (lidar)" in next(line for line in table.splitlines() if line.startswith("| `aero/alive/"))


def test_key_matching_and_suggestions():
    assert contracts.key_matches("diagnostics/*", "diagnostics/fmu")
    assert not contracts.key_matches("diagnostics/*", "diagnostics/a/b")
    assert contracts.key_matches("sim/truth/**", "sim/truth/state")
    assert contracts.key_matches("config/<service>/@set", "config/fmu/@set")
    keys = contracts.declared_keys(contracts.load_contracts())
    assert contracts.close_keys("state/vehical", keys)[0] == "state/vehicle"
    assert ("MissionCommand", "mission", "reads") in contracts.declared_schemas("mission/command",
                                                                             contracts.load_contracts())


def test_splice_refuses_a_document_without_markers():
    import pytest

    from aeroperception.tools.common import CliError

    with pytest.raises(CliError):
        cmd_docs.splice("no markers here", "table")
