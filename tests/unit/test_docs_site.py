"""The documentation site (mkdocs.yml, docs/) builds with `mkdocs build --strict`: a broken link or
anchor between pages, or a page left out of the nav, fails. mkdocs and mkdocs-material are in the
`test` extra, so a missing mkdocs is a failure here, never a skip. The README lives outside docs/
(GitHub shows it), so its links into docs/ are checked against the built site here as well."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL,
                       env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert r.returncode == 0, f"mkdocs build --strict failed (pip install -e .[docs]):\n{r.stdout}\n{r.stderr}"
    return out


def test_the_site_builds_strictly(site):
    assert (site / "index.html").is_file()
    assert (site / "limitations" / "index.html").is_file()


def test_every_docs_page_is_in_the_nav():
    nav = (ROOT / "mkdocs.yml").read_text()
    pages = sorted(str(p.relative_to(ROOT / "docs")) for p in (ROOT / "docs").rglob("*.md"))
    missing = [p for p in pages if p not in nav]
    assert not missing, f"docs pages the nav of mkdocs.yml does not list: {missing}"


def test_readme_links_into_docs_resolve(site):
    """README links are plain relative paths (docs/x.md#anchor) so they work on GitHub; each file
    exists and each anchor is a heading id of the built page."""
    links = re.findall(r"\]\((docs/[^)#\s]+)(?:#([^)\s]+))?\)", (ROOT / "README.md").read_text())
    assert links, "the README links no docs page"
    bad = []
    for path, anchor in links:
        if not (ROOT / path).exists():
            bad.append(path)
            continue
        if anchor:
            page = path.removeprefix("docs/").removesuffix(".md")
            html = site / ("" if page == "index" else page) / "index.html"
            if f'id="{anchor}"' not in html.read_text():
                bad.append(f"{path}#{anchor}")
    assert not bad, f"README links that do not resolve: {bad}"
