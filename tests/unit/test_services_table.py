"""The services table lives in one place, the docs home page (docs/index.md § Services): every
service folder (one with a __main__.py) has exactly one row there, and neither the README nor
docs/ARCHITECTURE.md keeps a second copy that drifts: they link to it."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "index.md"


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


def test_docs_home_lists_every_service_folder_once():
    folders = sorted(p.parent.name for p in (ROOT / "services").glob("*/__main__.py"))
    rows = table_services(PAGE.read_text())
    assert sorted(rows) == folders, f"docs/index.md § Services rows {sorted(rows)} != service folders {folders}"


def test_no_second_copy_of_the_services_table():
    copies = [str(p.relative_to(ROOT)) for p in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
              if p != PAGE and "| service | does |" in p.read_text()]
    assert not copies, f"a second services table (link docs/index.md#services instead): {copies}"


def test_architecture_and_readme_link_to_the_table():
    assert "index.md#services" in (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    assert "docs/index.md#services" in (ROOT / "README.md").read_text()
