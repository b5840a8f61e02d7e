"""The library layer and the runtime type-check: mypy with pyproject's [tool.mypy] (services/lib
and services/runtime, bodies of unannotated functions too) finds nothing. What every service is
built on is where a wrong call or a None reaching a use costs the most, and where the types are
written down. The check proves itself on a wrong call, so a configuration that checks nothing
cannot pass."""
from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

pytest.importorskip("mypy", reason="mypy: pip install -e .[test]")

ROOT = Path(__file__).resolve().parents[2]


def mypy(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path / "cache"), *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)


@pytest.mark.timeout(600)
def test_the_library_and_the_runtime_type_check(tmp_path):
    r = mypy(tmp_path)
    assert r.returncode == 0, f"mypy (pyproject [tool.mypy]) found:\n{r.stdout}{r.stderr}"
    assert "Success" in r.stdout and "no issues" in r.stdout, r.stdout


def same_config_without_targets(tmp_path: Path) -> Path:
    """pyproject's [tool.mypy] as an ini file, its `files` left out (mypy takes one kind of target)."""
    table = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]
    lines = ["[mypy]"] + [f"{k} = {', '.join(v) if isinstance(v, list) else str(v).lower() if isinstance(v, bool) else v}"
                          for k, v in table.items() if k != "files"]
    ini = tmp_path / "mypy.ini"
    ini.write_text("\n".join(lines) + "\n")
    return ini


@pytest.mark.timeout(600)
def test_a_wrong_call_into_the_library_is_found(tmp_path):
    wrong = ("from aeroperception.services.lib.geofence import Geofence\n"
             "def f():\n"                                 # unannotated: its body is checked all the same
             "    Geofence.from_params().check_waypoint(1.0, 2.0)\n")
    r = mypy(tmp_path, "--config-file", str(same_config_without_targets(tmp_path)), "-c", wrong)
    assert r.returncode == 1, r.stdout + r.stderr
    assert 'Missing positional argument "z"' in r.stdout, r.stdout
