"""deploy/constraints.txt is the lock CI tests: every dependency pyproject.toml declares for the
extras CI installs is pinned there, within pyproject's range, and (unless AERO_DEPS=newest asked for
today's releases) this very environment runs exactly those pins — so a green CI means a fresh machine
installing the lock gets what was tested."""
from __future__ import annotations

import os
import re
import tomllib
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pytest
from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

REPO = Path(__file__).resolve().parents[2]


def ci_extras() -> list[str]:
    m = re.search(r"^CI_EXTRAS=(\S+)$", (REPO / ".ci/run").read_text(), re.M)
    return m.group(1).split(",")


def lock_extras() -> list[str]:
    m = re.search(r"^LOCK_EXTRAS=\(([^)]*)\)", (REPO / "deploy/lock.sh").read_text(), re.M)
    return m.group(1).split()


def declared() -> list[Requirement]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in ci_extras():
        reqs += project["optional-dependencies"][extra]
    return [Requirement(r) for r in reqs]


def pins() -> dict[str, str]:
    """{canonical name: version} of the lock's rows whose marker holds on this interpreter."""
    env, out = default_environment(), {}
    for line in (REPO / "deploy/constraints.txt").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        r = Requirement(line)
        if r.marker is None or r.marker.evaluate(env):
            (spec,) = r.specifier
            assert spec.operator == "==", f"not an exact pin: {line}"
            out[canonicalize_name(r.name)] = spec.version
    return out


def test_the_lock_covers_the_extras_ci_installs():
    assert lock_extras() == ci_extras(), "deploy/lock.sh LOCK_EXTRAS and .ci/run's extras differ"


def test_every_declared_dependency_is_pinned_within_its_range():
    locked = pins()
    missing = [str(r) for r in declared() if canonicalize_name(r.name) not in locked]
    assert not missing, f"not in deploy/constraints.txt (run deploy/lock.sh --keep): {missing}"
    outside = [f"{r} (pinned {locked[canonicalize_name(r.name)]})" for r in declared()
               if locked[canonicalize_name(r.name)] not in r.specifier]
    assert not outside, f"pins outside pyproject.toml's range (run deploy/lock.sh --keep): {outside}"


@pytest.mark.skipif(os.environ.get("AERO_DEPS") == "newest", reason="AERO_DEPS=newest: today's releases, not the lock")
def test_this_environment_runs_the_pinned_versions():
    locked, wrong = pins(), []
    for r in declared():
        name = canonicalize_name(r.name)
        try:
            have = version(name)
        except PackageNotFoundError:
            wrong.append(f"{name}: not installed (pinned {locked[name]})")
            continue
        if have != locked[name]:
            wrong.append(f"{name}: {have} installed, {locked[name]} pinned")
    assert not wrong, ("the suite is not running the lock (install with deploy/install.sh, or refresh the "
                       f"lock with deploy/lock.sh): {wrong}")
