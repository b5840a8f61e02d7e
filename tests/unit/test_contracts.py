"""Each service's contract is complete and true: the keys its code subscribes, publishes, serves,
calls and whose liveliness it watches are all declared in services/<name>/contract.py, and every
declared key is used. The code is walked (ast), not run, so a key used on a rare path (a fault
branch, an optional parameter) is checked too.

A service wired from its contract (`CONTRACT = contract`: Node.bind) needs less of this: bind
declares its inputs, outputs and queryables, refuses at start an input without a handler, a
handler no key feeds and a publisher the contract lacks (tests/unit/test_runtime_wiring.py); here
only its handlers are checked without Zenoh and its outputs (`self.io[key]`) are read like any
other use, so an output declared but never published still fails.

A key is read from the call's key argument: a literal, an f-string (`{x}` = one chunk), a module
constant, a local assigned once, a loop over a literal tuple, or a parameter of a function whose
callers pass one of those. Anything else is a key the walker cannot see; DYNAMIC lists each such
place with where its keys come from (a new one fails here until it is listed).
"""
from __future__ import annotations

import ast
import functools
import importlib
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from aeroperception.services.runtime import Queries, Topics
from aeroperception.tools import contracts

ROOT = Path(__file__).resolve().parents[2] / "services"

# Runtime calls -> the contract table they need: Node.subscribe / publisher / serve / call /
# call_async / on_liveliness (key first), ActionServer / ActionClient (key second).
METHOD_ROLES = {"subscribe": "inputs", "publisher": "outputs", "serve": "services", "call": "calls",
                "call_async": "calls", "on_liveliness": "liveliness"}
WIRING = "io"     # a bound service's Wiring: `self.io[key]` publishes an output
CLASS_ROLES = {"ActionServer": "actions", "ActionClient": "action_calls"}
ACTION_VERBS = ("goal", "cancel", "result")

# (service, key expression) the walker cannot resolve -> (why it is complete, contract table whose
# every key it uses, or None when nothing is used through it).
DYNAMIC = {
    ("ros2bridge", "key"): ("the OUTPUTS the `inputs` parameter names (bind_selection binds only those)", "outputs"),
}
# Node.subscribe_raw (full keys, any encoding) is outside the contracts' key space: the recorder's
# presets (any key) and ros2bridge's ROS keys (rmw_zenoh's) use it.


@dataclass
class Use:
    role: str
    key: str            # resolved key pattern ("*" = one chunk), or the expression when dynamic
    where: str          # file:line
    by_hand: bool = True   # False: through a bound service's Wiring (`self.io[key]`)


@dataclass
class Walk:
    uses: list[Use] = field(default_factory=list)
    unresolved: list[Use] = field(default_factory=list)


def _chunks(key: str) -> list[str]:
    return ["*" if c.startswith("<") or c == "*" else c for c in key.strip("/").split("/")]


def keys_overlap(a: str, b: str) -> bool:
    """Whether key patterns a and b (`*` / `<x>` one chunk, `**` any) can name the same key."""
    if "**" in a or "**" in b:
        return contracts.key_matches(a, b) or contracts.key_matches(b, a)
    ca, cb = _chunks(a), _chunks(b)
    return len(ca) == len(cb) and all(x == y or "*" in (x, y) for x, y in zip(ca, cb))


class ServiceWalker:
    """Every runtime call with a key in one service folder's code (contract.py excluded)."""

    def __init__(self, sources: dict[str, str]):
        self.trees = {path: ast.parse(text) for path, text in sources.items()}
        self.consts: dict[str, object] = {}
        self.parents: dict[ast.AST, ast.AST] = {}
        for tree in self.trees.values():
            for stmt in tree.body:
                if isinstance(stmt, ast.Assign) and len(stmt.targets) == 1 and isinstance(stmt.targets[0], ast.Name):
                    value = _literal(stmt.value)
                    if value is not None:
                        self.consts[stmt.targets[0].id] = value
            for node in ast.walk(tree):
                for child in ast.iter_child_nodes(node):
                    self.parents[child] = node

    @classmethod
    def of(cls, service: str) -> "ServiceWalker":
        folder = ROOT / service
        return cls({str(p.relative_to(ROOT)): p.read_text() for p in sorted(folder.rglob("*.py"))
                    if p.name != "contract.py"})

    @property
    def bound(self) -> bool:
        """Whether the service is wired by Node.bind: a class declares CONTRACT, or its code calls bind."""
        return any((isinstance(n, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "CONTRACT" for t in n.targets))
                   or (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "bind"
                       and n.args and ast.unparse(n.args[0]) == "contract")
                   for tree in self.trees.values() for n in ast.walk(tree))

    def walk(self) -> Walk:
        out = Walk()
        for path, tree in self.trees.items():
            for node in ast.walk(tree):
                if isinstance(node, ast.Subscript) and getattr(node.value, "attr", getattr(node.value, "id", "")) == WIRING:
                    keys = self.resolve(node.slice, depth=0)
                    if keys is None:
                        out.unresolved.append(Use("outputs", ast.unparse(node.slice), f"services/{path}:{node.lineno}"))
                    for key in keys or ():
                        out.uses.append(Use("outputs", key, f"services/{path}:{node.lineno}", False))
                if not isinstance(node, ast.Call):
                    continue
                role, arg = self._role(self._unalias(node))
                if role is None or arg is None:
                    continue
                where = f"services/{path}:{node.lineno}"
                keys = self.resolve(arg, depth=0)
                if keys is None:
                    out.unresolved.append(Use(role, ast.unparse(arg), where))
                    continue
                for key in keys:
                    out.uses.append(_as_action_call(Use(role, key, where)))
        return out

    def _unalias(self, call: ast.Call) -> ast.Call:
        """`pub = node.publisher; pub(key, ...)` reads as `node.publisher(key, ...)`."""
        fn = self._enclosing_function(call)
        if not isinstance(call.func, ast.Name) or fn is None:
            return call
        for node in ast.walk(fn):
            if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Attribute)
                    and any(isinstance(t, ast.Name) and t.id == call.func.id for t in node.targets)):
                return ast.Call(func=node.value, args=call.args, keywords=call.keywords)
        return call

    @staticmethod
    def _role(call: ast.Call) -> tuple[str | None, ast.AST | None]:
        f = call.func
        if isinstance(f, ast.Attribute) and f.attr in METHOD_ROLES:
            return METHOD_ROLES[f.attr], call.args[0] if call.args else None
        if isinstance(f, ast.Name) and f.id in CLASS_ROLES:
            return CLASS_ROLES[f.id], call.args[1] if len(call.args) > 1 else None
        return None, None

    def resolve(self, expr: ast.AST, depth: int) -> list[str] | None:
        """The key patterns `expr` can take, or None when the walker cannot tell."""
        if depth > 4:
            return None
        lit = _literal(expr)
        if isinstance(lit, str):
            return [lit]
        if isinstance(expr, ast.JoinedStr):
            return ["".join(v.value if isinstance(v, ast.Constant) else "*" for v in expr.values)]
        if isinstance(expr, ast.Subscript) and isinstance(expr.value, ast.Name):
            seq, idx = self.consts.get(expr.value.id), _literal(expr.slice)
            if isinstance(seq, tuple) and isinstance(idx, int):
                return [seq[idx]]
        if isinstance(expr, ast.Name):
            if isinstance(self.consts.get(expr.id), str):
                return [self.consts[expr.id]]
            return self._resolve_local(expr, depth)
        return None

    def _resolve_local(self, name: ast.Name, depth: int) -> list[str] | None:
        """A local assigned in the enclosing function, a loop variable over a literal tuple, or a
        parameter: then the keys every caller of that function passes."""
        fn = self._enclosing_function(name)
        if fn is None:
            return None
        for node in ast.walk(fn):
            if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name.id for t in node.targets):
                return self.resolve(node.value, depth + 1)
        params = [a.arg for a in fn.args.args]
        if name.id in params:
            index = params.index(name.id) - (1 if params and params[0] in ("self", "cls") else 0)
            return self._passed(fn.name, index, name.id, depth)
        return None

    def _passed(self, fname: str, index: int, pname: str, depth: int) -> list[str] | None:
        keys: list[str] = []
        callers = 0
        for tree in self.trees.values():
            for node in ast.walk(tree):
                if not isinstance(node, ast.Call):
                    continue
                f = node.func
                if (f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)) != fname:
                    continue
                arg = node.args[index] if index < len(node.args) else \
                    next((k.value for k in node.keywords if k.arg == pname), None)
                got = self.resolve(arg, depth + 1) if arg is not None else None
                if got is None:
                    return None
                callers += 1
                keys += got
        return keys if callers else None

    def _enclosing_function(self, node: ast.AST) -> ast.FunctionDef | None:
        while node in self.parents:
            node = self.parents[node]
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                return node
        return None


def _literal(node: ast.AST):
    try:
        return ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError, RecursionError):
        return None


def _as_action_call(use: Use) -> Use:
    """A call of `<base>/goal` (`/cancel`, `/result`) uses the action `<base>`."""
    parts = use.key.rsplit("/", 1)
    if use.role == "calls" and len(parts) == 2 and parts[1] in ACTION_VERBS and "/action/" in parts[0]:
        return Use("action_calls", parts[0], use.where)
    return use


def declared(c: contracts.Contract, role: str) -> list[str]:
    return list(getattr(c, role))


def check(c: contracts.Contract, walk: Walk, bound: bool = False) -> list[str]:
    """Findings: keys used but not declared, declared but not used, unresolved uses not in DYNAMIC.
    `bound`: inputs and queryables are Node.bind's (each has its handler, checked at start)."""
    findings = []
    covered: set[str] = {"inputs", "services"} if bound else set()
    for u in walk.unresolved:
        known = DYNAMIC.get((c.service, u.key))
        if known is None:
            findings.append(f"{u.where}: {u.role} key `{u.key}` cannot be read from the code: "
                            "use a literal or list it in DYNAMIC with where its keys come from")
        elif known[1]:
            covered.add(known[1])
    for u in walk.uses:
        if not any(keys_overlap(u.key, d) for d in declared(c, u.role)):
            findings.append(f"{u.where}: {u.role} `{u.key}` is not declared in services/{c.service}/contract.py")
    for role in ("inputs", "outputs", "services", "calls", "actions", "action_calls", "liveliness"):
        if role in covered:
            continue
        used = [u.key for u in walk.uses if u.role == role]
        for key in declared(c, role):
            if not any(keys_overlap(key, u) for u in used):
                findings.append(f"services/{c.service}/contract.py: {role} `{key}` is declared but never used")
    return findings


CONTRACTS = {c.service: c for c in contracts.load_contracts()}


@functools.cache
def walker_of(service: str) -> ServiceWalker:
    return ServiceWalker.of(service)


@functools.cache
def walk_of(service: str) -> Walk:
    return walker_of(service).walk()


@pytest.mark.parametrize("service", sorted(CONTRACTS))
def test_contract_declares_exactly_the_keys_the_code_uses(service):
    c = CONTRACTS[service]
    findings = check(c, walk_of(service), walker_of(service).bound)
    assert not findings, "\n".join(findings)


BOUND = sorted(s for s in CONTRACTS if walker_of(s).bound)


@pytest.mark.parametrize("service", [s for s in BOUND if "CONTRACT = contract" in (ROOT / s / "main.py").read_text()])
def test_a_bound_service_has_a_handler_for_every_input_and_no_other(service):
    # What Node.bind refuses at start, without Zenoh: each input and queryable has its handler.
    from aeroperception.services.runtime import Service
    from aeroperception.services.runtime.wiring import check_handlers

    main = importlib.import_module(f"aeroperception.services.{service}.main")
    classes = [v for v in vars(main).values()
               if isinstance(v, type) and issubclass(v, Service) and getattr(v, "CONTRACT", None) is not None]
    assert classes, f"services/{service}/main.py: no Service with CONTRACT"
    for cls in classes:
        check_handlers(cls.CONTRACT, cls.handlers(object.__new__(cls)))


@pytest.mark.parametrize("service", [s for s in BOUND if "CONFIG = " in (ROOT / s / "main.py").read_text()])
def test_a_configured_service_builds_its_config_from_every_parameter(service):
    # What Service.wire refuses at start, without Zenoh: a parameter no config field references.
    from aeroperception.services.runtime import Service
    from aeroperception.services.runtime.config import build, check_covers

    main = importlib.import_module(f"aeroperception.services.{service}.main")
    for cls in [v for v in vars(main).values() if isinstance(v, type) and issubclass(v, Service) and v.CONFIG]:
        check_covers(cls.CONFIG, cls.PARAMS, cls.NAME)
        build(cls.CONFIG, cls.PARAMS)


@pytest.mark.parametrize("service", BOUND)
def test_a_bound_service_declares_no_contract_key_by_hand(service):
    hand = [f"{u.where}: {u.role} {u.key}" for u in walk_of(service).uses
            if u.by_hand and u.role in ("inputs", "outputs", "services")]
    assert not hand, "declared by hand, not from the contract (Node.bind):\n" + "\n".join(hand)


def test_every_service_is_wired_from_its_contract():
    # Issue 33: no service declares its subscribers, publishers and queryables by hand any more.
    assert BOUND == sorted(CONTRACTS), sorted(set(CONTRACTS) - set(BOUND))


def test_every_service_folder_has_a_contract():
    folders = {p.name for p in ROOT.iterdir() if p.is_dir() and (p / "main.py").is_file()}
    assert folders <= set(CONTRACTS)


def test_dynamic_keys_listed_still_exist():
    # A DYNAMIC entry whose code is gone would silently excuse a new one with the same text.
    seen = {(s, u.key) for s in CONTRACTS for u in walk_of(s).unresolved}
    assert set(DYNAMIC) <= seen


@pytest.mark.parametrize("service", sorted(CONTRACTS))
def test_parsed_contract_equals_the_imported_one(service):
    # tools/contracts.py parses the file (for the CLI and the docs); the services import it:
    # both must read the same keys, schemas and rates.
    c = CONTRACTS[service]
    mod = importlib.import_module(f"aeroperception.services.{service}.contract")
    name = lambda cls: None if cls is None else cls.__name__  # noqa: E731
    for role in ("INPUTS", "OUTPUTS"):
        topics = getattr(mod, role, Topics())
        assert isinstance(topics, Topics), f"{role}: declare Topics(Topic(key, schema, rate_hz, note), ...)"
        assert {k: name(s) for k, s in topics.items()} == getattr(c, role.lower())
        assert {k: t.rate_hz for k, t in topics.declared.items() if t.rate_hz is not None} == \
            {k: r for k, r in c.rates_hz.items() if k in topics}
    for role in ("SERVICES", "CALLS"):
        assert isinstance(getattr(mod, role, Queries()), Queries), f"{role}: declare Queries(Query(...), ...)"
        assert {k: (name(q), name(r)) for k, (q, r) in getattr(mod, role, {}).items()} == getattr(c, role.lower())
    for role in ("ACTIONS", "ACTION_CALLS", "LIVELINESS"):
        assert list(getattr(mod, role, ())) == getattr(c, role.lower())


def test_walker_reads_every_form_of_key_it_claims():
    src = """
PREFIX = "a/b"
KEYS = ("k/one", "k/two")

class S:
    def start(self, node):
        node.subscribe("lit/key", T, cb)
        node.subscribe(f"cam/{side}/image", T, cb)
        node.publisher(PREFIX, T)
        pub = node.publisher
        pub(KEYS[1], T)
        key = "local/key"
        node.serve(key, None, T, cb)
        self._call("fwd/srv/x", 1)
        node.call_async("m/action/go/goal", g, R, cb)
        ActionServer(node, "m/action/go", G, R)
        node.on_liveliness("fmu", cb)
        node.subscribe(thing.key, T, cb)

    def _call(self, key, req):
        self.node.call_async(key, req, R, cb)
"""
    walk = ServiceWalker({"fake/main.py": src}).walk()
    assert {(u.role, u.key) for u in walk.uses} == {
        ("inputs", "lit/key"), ("inputs", "cam/*/image"), ("outputs", "a/b"), ("outputs", "k/two"),
        ("services", "local/key"), ("calls", "fwd/srv/x"), ("action_calls", "m/action/go"),
        ("actions", "m/action/go"), ("liveliness", "fmu")}
    assert [(u.role, u.key) for u in walk.unresolved] == [("inputs", "thing.key")]


def test_a_key_declared_twice_is_refused():
    from aeroperception.services.runtime import Query, Topic

    with pytest.raises(ValueError, match="declared twice"):
        Topics(Topic("a/b", object), Topic("a/b", object, 1.0))
    with pytest.raises(ValueError, match="declared twice"):
        Queries(Query("a/srv/x", None, object), Query("a/srv/x", None, object))
