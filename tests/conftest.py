"""Shared pytest fixtures: real Zenoh routers, real runtime Nodes, and a real `aero up` stack.
Plain helpers live in aerotest.py (`from aerotest import wait_until, ...`; tests/ is on the
pytest pythonpath).

Fixtures:
    zenoh_router    an in-process Zenoh router on tcp/127.0.0.1:<free port>; yields the endpoint
    make_node       factory: make_node(name, **Node kwargs) -> a connected runtime Node on that
                    router; all closed at teardown
    stack           factory: stack(services=["diagnostics"], extra_args=[], profile="sim",
                    timeout_s=20) starts `aero up --profile P --only ... --listen
                    tcp/127.0.0.1:<free> --log-dir <tmp>`, waits for every service's liveliness
                    token aero/alive/default/<name>, and returns an aerotest.Stack:
                      .endpoint .session (client) .log_dir .proc (the `aero up` Popen) .services
                      .service_log(name) .up_output() .pids() .alive(name) .aero(*args) .stop()
                    A start-up failure raises StackStartError carrying aero up's output and
                    every service log. Teardown: SIGINT to `aero up`, bounded wait, then kill.
    stack_module    the same factory, module-scoped (one stack shared by a test module)
    px4_build       a PX4 SITL build dir (bin/px4 + etc/): $AERO_PX4_DIR or the bundle
                    ../shared/px4/px4-sitl-sih.tar.gz extracted once per session; skips without
                    either (fails under CI=true)
    lan             factory: lan(["vehicle", "ground"]) -> netns.Lan, hosts as network namespaces
                    on one switch (10.77.0.0/24 inside them only); skips when namespaces cannot
                    be made (not root). Teardown stops their processes and deletes them.
"""
from __future__ import annotations

import os
import tarfile
from pathlib import Path
from typing import Any

import pytest

# Re-exported for convenience; import them from aerotest in test modules.
from aerotest import (  # noqa: F401
    Stack, StackFactory, StackStartError, aero, free_port, wait_for_message, wait_until, zenoh_client,
)
from aeroperception.tools.cli.router import open_router


# ---------------------------------------------------------------- order


# Unit tests first (no timing-sensitive flights: .ci/run prepares Docker beside them), then the
# integration tests (CLI and detector modules before the first flight), the fault rows, and the
# compose flight test last (it waits for that preparation). Whole modules move, so module-scoped
# stacks stay contiguous; the order within each group is kept.
_ORDER = ("tests/unit/", "tests/integration/", "tests/faults/")
_LAST = "tests/integration/test_compose.py"


def pytest_collection_modifyitems(config, items):
    def rank(item) -> int:
        path = item.nodeid
        if path.startswith(_LAST):
            return len(_ORDER)
        return next((i for i, prefix in enumerate(_ORDER) if path.startswith(prefix)), len(_ORDER) - 1)
    items.sort(key=rank)                      # stable


# ---------------------------------------------------------------- router / nodes


@pytest.fixture
def zenoh_router():
    """An in-process Zenoh router on a free loopback port; yields "tcp/127.0.0.1:<port>"."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(None, [endpoint])
    try:
        yield endpoint
    finally:
        router.close()


@pytest.fixture
def make_node(zenoh_router):
    """Factory of connected runtime Nodes on `zenoh_router`; all closed at teardown."""
    from aeroperception.services.runtime import Node

    nodes: list[Node] = []

    def make(name: str, **kw: Any) -> Node:
        kw.setdefault("connect", zenoh_router)
        node = Node(name, **kw)
        nodes.append(node)
        assert node.connect(max_wait_s=5.0), f"node {name} could not connect to {zenoh_router}"
        return node

    yield make
    for n in reversed(nodes):
        n.close()


# ---------------------------------------------------------------- several machines


@pytest.fixture
def lan():
    """Factory: `lan(["vehicle", "ground"])` -> a netns.Lan (see tests/netns.py); every Lan made
    is closed at teardown (processes stopped, namespaces deleted), also after a failure."""
    from netns import Lan, netns_unavailable

    why = netns_unavailable()
    if why:
        pytest.skip(why)
    made: list[Lan] = []

    def make(names):
        made.append(Lan(names))
        return made[-1]

    try:
        yield make
    finally:
        for n in reversed(made):
            n.close()


# ---------------------------------------------------------------- PX4 SITL


PX4_BUNDLE = Path(__file__).resolve().parents[1].parent / "shared" / "px4" / "px4-sitl-sih.tar.gz"


@pytest.fixture(scope="session")
def px4_build(tmp_path_factory) -> Path:
    """A PX4 SITL build (bin/px4 + etc/): $AERO_PX4_DIR, else the bundle ../shared/px4 beside the
    repository, extracted once per session. Neither: skip saying what to point AERO_PX4_DIR at; but
    under CI=true (the bundle must be there) fail."""
    return _sitl_bundle(tmp_path_factory, "AERO_PX4_DIR", PX4_BUNDLE, "px4-build", ".", (
        f"no PX4 build: set AERO_PX4_DIR to one (the directory holding bin/px4 and etc/, e.g. "
        f"PX4-Autopilot/build/px4_sitl_default) or put px4-sitl-sih.tar.gz at {PX4_BUNDLE}"))


def _sitl_bundle(tmp_path_factory, env: str, bundle: Path, name: str, inside: str, why: str) -> Path:
    """$env, else `bundle` extracted into a session temp dir (its `inside` folder); neither: skip with
    `why`, but fail under CI=true (the bundle must be there)."""
    own = os.environ.get(env)
    if own:
        return Path(own)
    if not bundle.is_file():
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(why)
        pytest.skip(why)
    out = tmp_path_factory.mktemp(name)
    with tarfile.open(bundle) as tar:
        tar.extractall(out, filter="tar")
    return out / inside


ARDUPILOT_BUNDLE = Path(__file__).resolve().parents[1].parent / "shared" / "ardupilot" / "ardupilot-sitl-copter.tar.gz"


@pytest.fixture(scope="session")
def ardupilot_dir(tmp_path_factory) -> Path:
    """ArduCopter SITL (bin/arducopter + default_params/): $AERO_ARDUPILOT_DIR, else the bundle
    ../shared/ardupilot beside the repository, extracted once per session. Neither: skip saying what to
    point AERO_ARDUPILOT_DIR at; but under CI=true (the bundle must be there) fail."""
    return _sitl_bundle(tmp_path_factory, "AERO_ARDUPILOT_DIR", ARDUPILOT_BUNDLE, "ardupilot", "ardupilot-sitl-copter", (
        f"no ArduCopter SITL: set AERO_ARDUPILOT_DIR to one (ardupilot-sitl-copter/ or its .tar.gz, or an "
        f"ArduPilot checkout after ./waf copter) or put ardupilot-sitl-copter.tar.gz at {ARDUPILOT_BUNDLE}"))


# ---------------------------------------------------------------- aero up


@pytest.fixture
def stack(tmp_path):
    """Factory: `stack(services=["diagnostics"], extra_args=[...], profile="sim")` starts
    `aero up --profile P --only ... --listen tcp/127.0.0.1:<free> --log-dir <tmp>` and returns a
    Stack once every service's liveliness token exists. Stopped (SIGINT, bounded) at teardown."""
    factory = StackFactory(lambda: tmp_path)
    try:
        yield factory
    finally:
        factory.close()


@pytest.fixture(scope="module")
def stack_module(tmp_path_factory):
    """Like `stack`, but the stacks live for the whole test module."""
    base = tmp_path_factory.mktemp("stack")
    factory = StackFactory(lambda: base)
    try:
        yield factory
    finally:
        factory.close()
