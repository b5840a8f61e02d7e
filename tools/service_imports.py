"""Which third-party modules each service's code imports, found by reading it (never importing it),
and which of them this machine lacks.

Why: a service whose module is missing is found out only when it starts and crash-loops
(`ModuleNotFoundError: No module named 'gtsam'`), on exactly the machines nobody tests: every
development and CI machine has every extra installed. Reading the source finds what a service
needs without having it installed; `importlib.util.find_spec` on a top-level name then says
whether it is there without running it (no heavy import). `aero up` refuses a profile whose
modules are missing (check_installed), `aero doctor` reports them, and a unit test proves that
the pip extras each profile declares (profiles.yaml `install:`) cover them.

What counts as an import: every `import` / `from ... import` statement anywhere in a module
(inside functions and try blocks too: a lazy import is still needed when its path runs) and
`importlib.import_module("literal...")`. aeroperception.* imports are followed to their files,
transitively; everything else that is not in the standard library is a third-party module.
"""
from __future__ import annotations

import ast
import importlib.util
import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

ROOT_PACKAGE = "aeroperception"
# The source folder of each aeroperception.<top> package (setup.py maps the repo's top-level folders).
TOP_PACKAGES = ("schemas", "services", "tools")

# Imports a service works without, {(service, module): why}: not required of any install, not
# checked by `aero up` (`aero doctor` warns when one is missing). Keep it short: everything else a
# service imports is required.
OPTIONAL_IMPORTS: dict[tuple[str, str], str] = {
    ("viz", "cv2"): "only to JPEG-compress camera images for the viewer (adapters.py, inside "
                    "try/except ImportError); without OpenCV viz logs raw pixels",
}


def optional_modules(service: str) -> dict[str, str]:
    """{module: why} of the imports `service` works without (OPTIONAL_IMPORTS)."""
    return {m: why for (s, m), why in OPTIONAL_IMPORTS.items() if s == service}


@lru_cache(maxsize=None)
def package_dirs() -> dict[str, Path]:
    """{"aeroperception.services": its folder, ...}, found without importing any of them."""
    out = {}
    for top in TOP_PACKAGES:
        name = f"{ROOT_PACKAGE}.{top}"
        mod = sys.modules.get(name)
        paths = list(mod.__path__) if mod is not None else []
        if not paths:
            spec = importlib.util.find_spec(name)   # imports only the namespace package `aeroperception`
            paths = list(spec.submodule_search_locations or []) if spec else []
        if paths:
            out[name] = Path(paths[0])
    return out


@lru_cache(maxsize=None)
def module_file(name: str) -> Path | None:
    """The source file of aeroperception module `name` (a package's __init__.py), None if there is none."""
    for pkg, folder in package_dirs().items():
        if name == pkg or name.startswith(pkg + "."):
            base = folder.joinpath(*name[len(pkg):].lstrip(".").split(".")) if name != pkg else folder
            for candidate in (base / "__init__.py", base.with_suffix(".py")):
                if candidate.is_file():
                    return candidate
    return None


def _module_name(path: Path) -> str:
    for pkg, folder in package_dirs().items():
        try:
            rel = path.relative_to(folder)
        except ValueError:
            continue
        parts = list(rel.with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        return ".".join([pkg, *parts])
    raise ValueError(f"{path} is not in an aeroperception package")


def _dynamic_import(node: ast.Call) -> str | None:
    """The literal module prefix of `importlib.import_module("x.y")` / `import_module(f"x.{n}")`."""
    func = node.func
    name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
    if name not in ("import_module", "__import__") or not node.args:
        return None
    arg = node.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        literal = str(arg.values[0].value)     # f"pkg.{name}_pb2": "pkg." is whole, what follows is not
        return literal.rsplit(".", 1)[0] if "." in literal else None
    return None


def _statements(nodes):
    """Every statement, nested ones too (function, class, if/try/with/loop/match bodies): where an
    import statement can be; far fewer nodes than ast.walk (`aero up` runs this on every start)."""
    for node in nodes:
        yield node
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            sub = getattr(node, field, None)
            if isinstance(sub, list):
                yield from _statements(sub)


@lru_cache(maxsize=None)
def imports_of(path: Path) -> tuple[str, ...]:
    """Every module name `path` imports, absolute (relative imports resolved), including the
    `from X import name` candidates X.name (a submodule or an attribute: module_file tells)."""
    return tuple(name for _, name in import_lines(path))


def import_lines(path: Path) -> list[tuple[int, str]]:
    """imports_of with the line of each import: [(line, module name), ...], in file order."""
    return source_imports(path.read_bytes(), _module_name(path), path.name == "__init__.py", str(path))


def source_imports(source: bytes, module: str, is_package: bool = False,
                   filename: str = "<source>") -> list[tuple[int, str]]:
    """[(line, module name)] of every import in `source`, the text of module `module` (a package's
    __init__ when `is_package`): what relative imports are resolved against."""
    package = module if is_package else module.rpartition(".")[0]
    names: list[tuple[int, str]] = []
    tree = ast.parse(source, filename)
    # import_module(...) is an expression, anywhere: the whole tree only where the source has one
    dynamic = b"import_module(" in source or b"__import__(" in source
    for node in ast.walk(tree) if dynamic else _statements(tree.body):
        if isinstance(node, ast.Import):
            names += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module or ""
            names.append((node.lineno, src))
            names += [(node.lineno, f"{src}.{a.name}") for a in node.names if a.name != "*"]
        elif isinstance(node, ast.Call):
            literal = _dynamic_import(node)
            if literal and not literal.startswith("."):
                names.append((node.lineno, literal))
    return sorted(names, key=lambda n: n[0])


def _parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts) + 1)]


def walk(start: list[Path]) -> tuple[set[Path], set[str]]:
    """(aeroperception files reached from `start`, third-party top-level modules they import).
    Importing a submodule runs its packages' __init__ too: those are walked as well."""
    seen: set[Path] = set()
    third: set[str] = set()
    todo = list(start)
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        for name in imports_of(path):
            top = name.partition(".")[0]
            if top == ROOT_PACKAGE:
                for part in _parents(name)[1:]:
                    f = module_file(part)
                    if f is not None and f not in seen:
                        todo.append(f)
            elif top and top not in sys.stdlib_module_names and top != "__future__":
                third.add(top)
    return seen, third


def service_dir(service: str) -> Path | None:
    f = module_file(f"{ROOT_PACKAGE}.services.{service}")
    return f.parent if f is not None and f.name == "__init__.py" else None


@lru_cache(maxsize=None)
def service_modules(service: str) -> frozenset[str]:
    """Third-party top-level modules service `service` imports (every file of its folder, and what
    they import of aeroperception), the optional ones (OPTIONAL_IMPORTS) left out. Empty for a
    name that is not a service folder (px4: PX4 itself, no Python of ours)."""
    return frozenset(all_service_modules(service) - set(optional_modules(service)))


@lru_cache(maxsize=None)
def all_service_modules(service: str) -> frozenset[str]:
    """service_modules with the optional ones."""
    folder = service_dir(service)
    if folder is None:
        return frozenset()
    return frozenset(walk(sorted(folder.rglob("*.py")))[1])


def missing_modules(modules) -> list[str]:
    """Those of `modules` (top-level names) this interpreter cannot find; nothing is imported."""
    out = []
    for m in sorted(set(modules)):
        try:
            found = importlib.util.find_spec(m) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            out.append(m)
    return out


@dataclass(frozen=True)
class Shortfall:
    """What a profile's services need that is not installed: {module: [services]}."""

    needed_by: dict[str, list[str]]

    @property
    def modules(self) -> list[str]:
        return sorted(self.needed_by)


def shortfall(services: list[str]) -> Shortfall:
    """The modules `services` import that are missing here, with the services that import each."""
    needed: dict[str, list[str]] = {}
    for s in services:
        for m in missing_modules(service_modules(s)):
            needed.setdefault(m, []).append(s)
    return Shortfall(needed)


def repo_root() -> Path | None:
    """The source checkout this package runs from (an editable install), None for an installed wheel."""
    tools = package_dirs().get(f"{ROOT_PACKAGE}.tools")
    root = tools.parent if tools else None
    return root if root is not None and (root / "deploy" / "install.sh").is_file() else None


def install_command(extras: list[str]) -> str:
    """The one command that installs `extras`: deploy/install.sh in a checkout, else pip."""
    joined = ",".join(extras)
    root = repo_root()
    if root is None:
        return f"pip install 'aeroperception[{joined}]'"
    script = root / "deploy" / "install.sh"
    try:
        script = script.relative_to(Path.cwd())
    except ValueError:
        pass
    return f"{script} {joined}"
