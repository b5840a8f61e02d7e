"""Editors and analysers follow `aeroperception.*` imports by path: src/aeroperception/ holds
relative symlinks to the top-level schemas/, services/ and tools/ ([tool.pyright] extraPaths and
[tool.mypy] mypy_path point there). They must name the very folders the install maps (setup.py),
and Python itself must never import from src/ (one copy of each module per process)."""
from __future__ import annotations

import os
import sys
from pathlib import Path

from aeroperception.tools import service_imports as si

ROOT = Path(__file__).resolve().parents[2]
LINKS = ROOT / "src" / "aeroperception"


def test_each_top_level_folder_has_a_relative_link_for_analysers():
    for top in si.TOP_PACKAGES:
        link = LINKS / top
        assert link.is_symlink(), f"{link} is not a symlink"
        assert not os.path.isabs(os.readlink(link)), f"{link} -> {os.readlink(link)}: keep it relative"
        assert link.resolve() == (ROOT / top).resolve()
    assert sorted(p.name for p in LINKS.iterdir()) == sorted(si.TOP_PACKAGES)


def test_the_links_name_the_folders_python_imports():
    dirs = si.package_dirs()
    for top in si.TOP_PACKAGES:
        assert Path(dirs[f"aeroperception.{top}"]).resolve() == (LINKS / top).resolve()
    assert not any(Path(p or ".").resolve() == (ROOT / "src").resolve() for p in sys.path)
