"""Code cites requirements by the stable ids of docs/requirements.md (`requirement MIS-1`), not
sections of documents the repository does not contain: every id cited must be defined there."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ID = re.compile(r"\b(?:FC|VIO|DET|PERC|MIS|PLAN|SIM|LOG|GCS|IF|LID)-\d+\b")
CITING = ("services", "schemas", "tools", "tests", "deploy")


def defined_ids() -> set[str]:
    text = (ROOT / "docs" / "requirements.md").read_text()
    return set(re.findall(r"^- \*\*([A-Z]+-\d+) ", text, flags=re.M))


def test_every_cited_requirement_id_is_defined():
    defined = defined_ids()
    assert defined, "docs/requirements.md defines no ids"
    missing = []
    for top in CITING:
        for path in sorted((ROOT / top).rglob("*")):
            if path.suffix not in (".py", ".yaml", ".json5", ".md") or not path.is_file():
                continue
            for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                missing += [f"{path.relative_to(ROOT)}:{n}: {i}" for i in ID.findall(line) if i not in defined]
    assert not missing, "requirement ids cited but not in docs/requirements.md:\n" + "\n".join(missing)


def test_requirement_ids_are_unique():
    text = (ROOT / "docs" / "requirements.md").read_text()
    ids = re.findall(r"^- \*\*([A-Z]+-\d+) ", text, flags=re.M)
    assert len(ids) == len(set(ids))
