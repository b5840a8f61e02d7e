"""The layers, checked: a service imports only the library (services/lib), the runtime, schemas
and itself, never another service; the MAVLink boundary library (services/mavlink, NED/FRD) only
fmu, gcs and sim import; the library, the runtime and the schemas import no service; nothing under
services/ or schemas/ imports tools/ (tools may import anything).

Every import counts, wherever it is (inside functions, try blocks, `importlib.import_module`
with a literal name): the statements are read with tools/service_imports.py, the walker `aero up`
and `aero doctor` use, so what "an import" is has one definition. A failure names the file, the
line and the service imported.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

import aeroperception.services as services_pkg
from aeroperception.tools import service_imports as si

ROOT = si.ROOT_PACKAGE
SERVICES = f"{ROOT}.services"
# Packages under services/ that are libraries, not services (no contract, no process).
LIBRARIES = services_pkg.LIBRARIES
# The only services that speak MAVLink and so may see NED/FRD (services/mavlink/frames.py).
MAVLINK_BOUNDARIES = ("fmu", "gcs", "sim")
# What each library may import of ours besides itself and schemas (lowest layer first).
LIBRARY_MAY_IMPORT = {"runtime": (), "mavlink": ("runtime", "lib"), "lib": ("runtime",)}


@dataclass(frozen=True)
class Violation:
    path: str
    line: int
    imported: str
    why: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line} imports {self.imported}: {self.why}"


def _layer(module: str) -> tuple[str, str]:
    """("schemas" | "tools" | "service" | "library" | "", name) of an aeroperception module."""
    parts = module.split(".")
    if parts[0] != ROOT or len(parts) < 2:
        return "", ""
    if parts[1] in ("schemas", "tools"):
        return parts[1], parts[1]
    if parts[1] != "services" or len(parts) < 3:
        return "", ""                     # aeroperception / aeroperception.services: the packages themselves
    return ("library" if parts[2] in LIBRARIES else "service"), parts[2]


def violations(imports: list[tuple[int, str]], module: str, path: str) -> list[Violation]:
    """What of `imports` ((line, module) pairs of module `module`, in file `path`) breaks the layers."""
    kind, name = _layer(module)
    out = []
    for line, imported in imports:
        to_kind, to_name = _layer(imported)
        if not to_kind or (to_kind, to_name) == (kind, name) or to_kind == "schemas":
            continue
        why = ""
        if to_kind == "tools":
            why = "tools/ is never imported by services or schemas" if kind != "tools" else ""
        elif kind == "schemas":
            why = "schemas import nothing of the services"
        elif kind == "service" and to_kind == "service":
            why = f"service {name} imports service {to_name}: move what both need into services/lib"
        elif kind == "service" and to_name == "mavlink" and name not in MAVLINK_BOUNDARIES:
            why = (f"only the MAVLink boundaries ({', '.join(MAVLINK_BOUNDARIES)}) import services.mavlink; "
                   f"{name} is ENU/FLU only")
        elif kind == "library" and to_kind == "service":
            why = f"library {name} imports service {to_name}: a library never imports a service"
        elif kind == "library" and to_name not in LIBRARY_MAY_IMPORT[name]:
            why = f"library {name} imports library {to_name} (it may import: schemas, {name}" + "".join(
                f", {n}" for n in LIBRARY_MAY_IMPORT[name]) + ")"
        if why:
            out.append(Violation(path, line, imported, why))
    return out


def tree_violations() -> tuple[int, list[Violation]]:
    """(files read, violations) over every module of services/ and schemas/."""
    dirs = si.package_dirs()
    read, found = 0, []
    for top in ("services", "schemas"):
        folder = dirs[f"{ROOT}.{top}"]
        for path in sorted(folder.rglob("*.py")):
            rel = f"{top}/{path.relative_to(folder).as_posix()}"
            module = ".".join([ROOT, top, *path.relative_to(folder).with_suffix("").parts])
            is_package = path.name == "__init__.py"
            module = module.removesuffix(".__init__")
            found += violations(si.source_imports(path.read_bytes(), module, is_package, rel), module, rel)
            read += 1
    return read, found


def test_no_service_imports_another_and_no_library_imports_a_service():
    read, found = tree_violations()
    assert read > 200, f"only {read} files read: is the package found? ({si.package_dirs()})"
    assert not found, "layer rule broken:\n" + "\n".join(map(str, found))


def check_source(source: str, module: str) -> list[str]:
    path = module.removeprefix(ROOT + ".").replace(".", "/") + ".py"
    return [str(v) for v in violations(si.source_imports(source.encode(), module), module, path)]


SYNTHETIC = '''\
import math
from aeroperception.schemas import Trajectory
from aeroperception.services.lib.geofence import Geofence
from aeroperception.services.runtime import Param
from . import contract
from .fsm import State


def later():
    from aeroperception.services.planner.avoidance import BLOCKED
    return BLOCKED


try:
    from ..safety import rules
except ImportError:
    rules = None
plugins = importlib.import_module("aeroperception.services.planner.plugins")
from aeroperception.services.mavlink import frames
from aeroperception.tools import common
'''


def test_a_synthetic_violation_is_found_with_its_file_line_and_service():
    found = check_source(SYNTHETIC, f"{SERVICES}.mission.limits")
    assert found == [
        "services/mission/limits.py:10 imports aeroperception.services.planner.avoidance: "
        "service mission imports service planner: move what both need into services/lib",
        "services/mission/limits.py:10 imports aeroperception.services.planner.avoidance.BLOCKED: "
        "service mission imports service planner: move what both need into services/lib",
        "services/mission/limits.py:15 imports aeroperception.services.safety: "
        "service mission imports service safety: move what both need into services/lib",
        "services/mission/limits.py:15 imports aeroperception.services.safety.rules: "
        "service mission imports service safety: move what both need into services/lib",
        "services/mission/limits.py:18 imports aeroperception.services.planner.plugins: "
        "service mission imports service planner: move what both need into services/lib",
        "services/mission/limits.py:19 imports aeroperception.services.mavlink: only the MAVLink boundaries "
        "(fmu, gcs, sim) import services.mavlink; mission is ENU/FLU only",
        "services/mission/limits.py:19 imports aeroperception.services.mavlink.frames: only the MAVLink "
        "boundaries (fmu, gcs, sim) import services.mavlink; mission is ENU/FLU only",
        "services/mission/limits.py:20 imports aeroperception.tools: tools/ is never imported by services or schemas",
        "services/mission/limits.py:20 imports aeroperception.tools.common: tools/ is never imported by services or "
        "schemas",
    ]


@pytest.mark.parametrize("module, source, expect", [
    (f"{SERVICES}.lib.geofence", "from aeroperception.services.safety import contract\n",
     "library lib imports service safety"),
    (f"{SERVICES}.runtime.node", "def f():\n    import aeroperception.services.mission.fsm\n",
     "library runtime imports service mission"),
    (f"{SERVICES}.runtime.node", "from aeroperception.services.lib import geofence\n",
     "library runtime imports library lib"),
    (f"{SERVICES}.lib.geo", "from aeroperception.services.mavlink import frames\n",
     "library lib imports library mavlink"),
    (f"{ROOT}.schemas.planning", "from aeroperception.services.runtime import Param\n",
     "schemas import nothing of the services"),
])
def test_libraries_and_schemas_importing_upwards_are_found(module, source, expect):
    found = check_source(source, module)
    assert found and all(expect in f for f in found), found


@pytest.mark.parametrize("module, source", [
    (f"{SERVICES}.fmu.truth", "from aeroperception.services.mavlink import frames\n"),
    (f"{SERVICES}.sim.vehicle.model", "from aeroperception.services.mavlink.frames import ned_to_enu\n"),
    (f"{SERVICES}.mavlink.frames", "from aeroperception.services.runtime.rotations import quat_to_rotmat\n"),
    (f"{SERVICES}.objects.logic", "from aeroperception.services.lib.pose_history import PoseHistory\n"
                                  "from ..objects.tracker import Tracker\nimport aeroperception.services\n"),
    (f"{SERVICES}.runtime.service", "import importlib\ncontract = importlib.import_module(f'{package}.contract')\n"),
])
def test_what_the_layers_allow_passes(module, source):
    assert check_source(source, module) == []


def test_the_rule_knows_every_library_folder():
    folder = Path(si.package_dirs()[SERVICES])
    for name in LIBRARIES:
        assert (folder / name / "__init__.py").is_file(), f"services/{name}: listed in LIBRARIES but not a package"
        assert not (folder / name / "contract.py").exists(), f"services/{name} has a contract: it is a service"
