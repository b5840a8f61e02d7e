"""A service's memory across restarts, one JSON file per concern in the vehicle's state directory,
written atomically (temp file in the same directory, fsync, os.replace): the mission's loaded
mission and progress, so a restarted mission service over a flying vehicle knows what it was
flying (ARCHITECTURE §8); the planner's selected parts, so a restart does not change what flies.
A reader sees the old or the new file, never half of one; an unreadable file is reported and
ignored, never fatal.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

VERSION = 1


def default_state_dir(vehicle: str) -> Path:
    """$AERO_STATE_DIR/<vehicle>/, else ~/.aero/state/<vehicle>/ (vehicle "" -> "default", as in
    the liveliness keys). Tests give each stack its own AERO_STATE_DIR so no run restores another's."""
    root = os.environ.get("AERO_STATE_DIR")
    return (Path(root) if root else Path.home() / ".aero" / "state") / (vehicle or "default")


class StateStore:
    """One JSON snapshot, `file_name` in `directory`."""

    def __init__(self, directory: str | Path, file_name: str):
        self.path = Path(directory).expanduser() / file_name

    def save(self, snapshot: dict[str, Any]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        data = json.dumps({"version": VERSION, **snapshot}).encode()
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.stem}-", suffix=".tmp", dir=self.path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise

    def load(self) -> dict[str, Any] | None:
        """The last snapshot, None when there is none; ValueError naming the file when it is
        unreadable (the caller reports it and starts without one)."""
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return None
        except OSError as e:
            raise ValueError(f"{self.path}: cannot read: {e.strerror}") from None
        try:
            data = json.loads(text)
        except ValueError as e:
            raise ValueError(f"{self.path}: not valid JSON: {e}") from None
        if not isinstance(data, dict) or data.get("version") != VERSION:
            raise ValueError(f"{self.path}: not a version {VERSION} snapshot")
        return data
