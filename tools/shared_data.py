"""Where the project's real test recordings are: `../shared/data` beside the checkout (CI's
layout), found by walking up from the repository, or AERO_SHARED_DATA. Never copied in."""
from __future__ import annotations

import os
from pathlib import Path


def shared_data_dir() -> Path | None:
    env = os.environ.get("AERO_SHARED_DATA")
    if env:
        return Path(env) if Path(env).is_dir() else None
    for up in Path(__file__).resolve().parents[1:5]:
        cand = up / "shared" / "data"
        if cand.is_dir():
            return cand
    return None


def kitti_scans() -> list[Path]:
    """The real KITTI .bin scans, sorted; empty when the data is not there."""
    root = shared_data_dir()
    return sorted((root / "kitti" / "seq00").glob("*.bin")) if root else []
