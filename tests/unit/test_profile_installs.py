"""What is installed is what runs: for every profile of tools/profiles.yaml, the pip extras it
declares (`install:`) cover every third-party import of every service it starts.

Found on a fresh machine: deploy/install.sh installed the extras sim,tools while the sim profile
starts vio (gtsam) and detector (onnxruntime); vio crash-looped. No development or CI machine saw
it: they all have every extra. So this test does not ask the machine; it reads the services'
source (tools/service_imports.py: every import statement, lazy ones too, following
aeroperception.* transitively), maps each third-party module to the distributions that provide
it on this machine (importlib.metadata.packages_distributions) and checks one of them is a core
dependency of pyproject.toml or in one of the profile's extras.
"""
from __future__ import annotations

import importlib.metadata
import re
import textwrap
import tomllib
from pathlib import Path

import pytest

from aeroperception.tools import service_imports as si
from aeroperception.tools.cli import up as cmd_up
from aeroperception.tools.common import CliError

REPO = Path(__file__).resolve().parents[2]
PROFILES = cmd_up.load_profiles()


def normalise(dist: str) -> str:
    """PEP 503: case, and runs of -_. are one '-'."""
    return re.sub(r"[-_.]+", "-", dist).lower()


def requirement_name(req: str) -> str:
    return normalise(re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req).group(1))


def pyproject() -> tuple[set[str], dict[str, set[str]]]:
    """(core dependencies, {extra: distributions}) of pyproject.toml, names normalised."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    return ({requirement_name(r) for r in project["dependencies"]},
            {extra: {requirement_name(r) for r in reqs} for extra, reqs in project["optional-dependencies"].items()})


def uncovered(profile: dict, core: set[str], extras: dict[str, set[str]],
              provides: dict[str, list[str]]) -> dict[str, str]:
    """{"service: module": why} for each import of the profile's services that neither the core
    dependencies nor the profile's extras install (an empty dict: the install covers the profile)."""
    unknown = [e for e in profile["install"] if e not in extras]
    if unknown:
        return {f"install: {e}": "no such extra in pyproject.toml" for e in unknown}
    allowed = core.union(*(extras[e] for e in profile["install"]))
    out = {}
    for service in profile["services"]:
        for module in sorted(si.service_modules(service)):
            dists = {normalise(d) for d in provides.get(module, ())}
            if not dists:
                out[f"{service}: {module}"] = "no installed distribution provides it (install every extra to run this test)"
            elif not dists & allowed:
                out[f"{service}: {module}"] = (f"from {', '.join(sorted(dists))}, which is not in the core dependencies "
                                               f"nor in the extras {profile['install']}")
    return out


@pytest.fixture(scope="module")
def provides() -> dict[str, list[str]]:
    return importlib.metadata.packages_distributions()


@pytest.mark.parametrize("name", sorted(PROFILES))
def test_the_install_a_profile_declares_covers_every_service_it_starts(name, provides):
    core, extras = pyproject()
    assert PROFILES[name]["install"], f"profile {name} declares no install: (its pip extras)"
    assert uncovered(PROFILES[name], core, extras, provides) == {}


def test_the_check_fails_on_the_bug_found_on_a_fresh_machine(provides):
    """The sim profile installed without perception: vio's gtsam and detector's onnxruntime are named."""
    core, extras = pyproject()
    short = dict(PROFILES["sim"], install=[e for e in PROFILES["sim"]["install"] if e != "perception"])
    found = uncovered(short, core, extras, provides)
    assert "vio: gtsam" in found and "detector: onnxruntime" in found, found
    assert uncovered(dict(short, install=["nonsense"]), core, extras, provides) == {
        "install: nonsense": "no such extra in pyproject.toml"}


def test_install_sh_installs_what_the_default_profile_declares():
    """README command 1 (`deploy/install.sh && aero up`) installs what the default profile starts."""
    script = (REPO / "deploy" / "install.sh").read_text()
    default = re.search(r"^EXTRAS=\$\{1:-([^}]*)\}", script, re.M).group(1)
    up_default = next(a.default for a in _up_parser()._actions if a.dest == "profile")
    assert default.split(",") == PROFILES[up_default]["install"], (default, up_default)


def _up_parser():
    import argparse

    sub = argparse.ArgumentParser().add_subparsers()
    cmd_up.register(sub)
    return sub.choices["up"]


def test_extends_adds_the_base_profiles_extras():
    assert PROFILES["viz"]["install"] == PROFILES["sim"]["install"]
    assert PROFILES["ros2"]["install"] == [*PROFILES["sim"]["install"], "ros2"]
    assert set(PROFILES["vehicle"]["install"]) <= set(PROFILES["px4"]["install"])


def test_optional_imports_each_say_why_and_are_imported():
    """The allowlist stays short and true: each entry has its reason, and its service still imports
    the module (a stale entry would hide a new required import of it)."""
    assert len(si.OPTIONAL_IMPORTS) <= 3
    for (service, module), why in si.OPTIONAL_IMPORTS.items():
        assert len(why) > 40, (service, module)
        assert module in si.all_service_modules(service), f"{service} no longer imports {module}: drop the entry"


# ---------------------------------------------------------------- the source walk itself


def test_lazy_imports_are_found(tmp_path, monkeypatch):
    """Inside functions, try blocks, relative, `from pkg import sub` and import_module(f"pkg.{x}")."""
    pkg = tmp_path / "demo"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "helper.py").write_text("import yaml_like_dep\n")
    (pkg / "main.py").write_text(textwrap.dedent("""
        import os, json
        from . import helper
        from .helper import something
        def f():
            import lazy_dep.sub
            try:
                import fast_dep
            except ImportError:
                fast_dep = None
            return importlib.import_module(f"dynamic_dep.{os.name}_pb2")
        from aeroperception.services import demo as again
    """))
    monkeypatch.setattr(si, "package_dirs", lambda: {"aeroperception.services": tmp_path})
    si.module_file.cache_clear()        # resolved against the real folders by earlier tests
    try:
        files, third = si.walk([pkg / "main.py"])
    finally:
        si.module_file.cache_clear()
    assert third == {"yaml_like_dep", "lazy_dep", "fast_dep", "dynamic_dep"}
    assert files == {pkg / "main.py", pkg / "helper.py", pkg / "__init__.py"}


def test_real_services_lazy_and_transitive_imports_are_seen():
    assert "cv2" in si.service_modules("planner")                       # inside CostmapView.__init__
    assert "foxglove_schemas_protobuf" in si.service_modules("recorder")  # importlib.import_module(f"...")
    assert "gtsam" in si.service_modules("vio") and "onnxruntime" in si.service_modules("detector")
    assert si.service_modules("px4") == frozenset()                     # PX4 itself, not a service folder


# ---------------------------------------------------------------- aero up refuses before anything starts


def hide(monkeypatch, *modules: str) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda m, *a: None if m in modules else real(m, *a))


def test_aero_up_names_the_missing_modules_and_the_install_command(monkeypatch):
    hide(monkeypatch, "gtsam", "onnxruntime")
    with pytest.raises(CliError) as e:
        cmd_up.check_installed("sim", PROFILES["sim"]["services"])
    msg = str(e.value)
    assert "\n" not in msg
    assert "gtsam (vio)" in msg and "onnxruntime (detector)" in msg, msg
    assert msg.count("install.sh sim,perception,tools") == 1, msg
    cmd_up.check_installed("sim", ["fmu", "planner"])          # what they import is here


def test_the_statement_walk_finds_every_import_statement_ast_walk_finds():
    """imports_of visits statements only (fast enough for every `aero up`): it must miss none."""
    import ast

    for path in sorted(si.package_dirs()["aeroperception.services"].rglob("*.py")):
        tree = ast.parse(path.read_bytes())
        every = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
        fast = [n for n in si._statements(tree.body) if isinstance(n, (ast.Import, ast.ImportFrom))]
        assert len(fast) == len(every), path
