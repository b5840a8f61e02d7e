"""The services table lives in one place, README § Services: every service folder (one with a
__main__.py) has exactly one row there, and docs/ARCHITECTURE.md links to it instead of keeping a
second copy that drifts."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def table_services(text: str) -> list[str]:
    """The service names of the `| service | does |` table(s) in a markdown text."""
    names, inside = [], False
    for line in text.splitlines():
        if line.startswith("| service | does |"):
            inside = True
        elif inside and line.startswith("| `"):
            names.append(re.match(r"\| `([^`]+)`", line).group(1))
        elif inside and not line.startswith("|"):
            inside = False
    return names


def test_readme_lists_every_service_folder_once():
    folders = sorted(p.parent.name for p in (ROOT / "services").glob("*/__main__.py"))
    rows = table_services((ROOT / "README.md").read_text())
    assert sorted(rows) == folders, f"README § Services rows {sorted(rows)} != service folders {folders}"


def test_architecture_links_to_the_readme_table_instead_of_copying_it():
    doc = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    assert "| service | does |" not in doc, "docs/ARCHITECTURE.md holds a second services table: link README"
    assert "../README.md#services" in doc
