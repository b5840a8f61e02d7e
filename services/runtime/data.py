"""Where the project's real recordings are (EuRoC, KITTI): $AERO_DATA_DIR, else the first
`shared/data` found walking up from this checkout (in CI the layout is <clone>/ next to
<clone>/../shared). Tests and eval tools read them by path; they are never copied in."""
from __future__ import annotations

import os
from pathlib import Path


def shared_data_dir() -> Path | None:
    env = os.environ.get("AERO_DATA_DIR")
    if env:
        return Path(env) if Path(env).is_dir() else None
    for parent in Path(__file__).resolve().parents:
        cand = parent / "shared" / "data"
        if cand.is_dir():
            return cand
    return None


def kitti_scans() -> list[Path]:
    """The real KITTI .bin scans, sorted; empty when the data is not there."""
    root = shared_data_dir()
    return sorted((root / "kitti" / "seq00").glob("*.bin")) if root else []
