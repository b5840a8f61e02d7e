"""The services' declared keys, read from their source: services/*/contract.py, written in the
vocabulary of services/runtime/contract.py (Topics of Topic, Queries of Query, ACTIONS,
ACTION_CALLS, LIVELINESS).

One home for "who publishes what": `aero topic echo` suggests keys from it, `aero topic pub`
checks a type against it, and `aero docs reference` generates docs/reference/keys.md from
it. The files are parsed (ast), never imported: importing a contract imports its package (vio's
pulls in GTSAM, the detector's ONNX Runtime), and a new service folder is picked up with no
registration.
"""
from __future__ import annotations

import ast
import difflib
from dataclasses import dataclass, field
from importlib import resources


@dataclass
class Contract:
    """What one service declares; schema names are the class names used in the file
    (None: no payload schema)."""

    service: str
    source: str
    inputs: dict[str, str | None] = field(default_factory=dict)
    outputs: dict[str, str | None] = field(default_factory=dict)
    services: dict[str, tuple[str | None, str | None]] = field(default_factory=dict)
    calls: dict[str, tuple[str | None, str | None]] = field(default_factory=dict)
    actions: list[str] = field(default_factory=list)        # served action base keys
    action_calls: list[str] = field(default_factory=list)   # another service's actions used
    liveliness: list[str] = field(default_factory=list)     # services whose token is watched ("*": all)
    rates_hz: dict[str, float] = field(default_factory=dict)   # key -> rate_hz (those that have one)
    notes: dict[str, str] = field(default_factory=dict)        # key -> note

    def rate(self, key: str) -> str:
        """The declared rate of `key` ("50 Hz"), else ""."""
        hz = self.rates_hz.get(key)
        return f"{hz:g} Hz" if hz is not None else ""


def _value(node: ast.AST, consts: dict[str, object]):
    """A literal, a class name (as its name), or a module-level constant's value."""
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.Name):
        return consts.get(node.id, node.id)
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, (ast.Tuple, ast.List)):
        return tuple(_value(e, consts) for e in node.elts)
    return None


def _declarations(node: ast.AST, kind: str, fields: tuple[str, ...], consts: dict[str, object]) -> list[dict]:
    """The `kind(...)` calls inside a Topics(...) / Queries(...) call, as {field: value}."""
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)):
        return []
    out = []
    for arg in node.args:
        if isinstance(arg, ast.Call) and isinstance(arg.func, ast.Name) and arg.func.id == kind:
            d = dict(zip(fields, (_value(a, consts) for a in arg.args)))
            d.update({kw.arg: _value(kw.value, consts) for kw in arg.keywords if kw.arg})
            out.append(d)
    return out


def _assignments(tree: ast.Module):
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign) and len(stmt.targets) == 1 and isinstance(stmt.targets[0], ast.Name):
            yield stmt.targets[0].id, stmt.value
        elif isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name) and stmt.value is not None:
            yield stmt.target.id, stmt.value


def parse_contract(text: str, service: str, source: str = "") -> Contract:
    """Read NAME, INPUTS, OUTPUTS, SERVICES, CALLS, ACTIONS, ACTION_CALLS and LIVELINESS."""
    c = Contract(service=service, source=source)
    tree = ast.parse(text)
    consts = {name: node.value for name, node in _assignments(tree)
              if isinstance(node, ast.Constant) and isinstance(node.value, (int, float, str))}
    for name, node in _assignments(tree):
        if name == "NAME" and isinstance(node, ast.Constant):
            c.service = str(node.value)
        elif name in ("INPUTS", "OUTPUTS"):
            target = getattr(c, name.lower())
            for d in _declarations(node, "Topic", ("key", "schema", "rate_hz", "note"), consts):
                target[d["key"]] = d.get("schema")
                if d.get("rate_hz") is not None:
                    c.rates_hz[d["key"]] = float(d["rate_hz"])
                if d.get("note") and (name == "OUTPUTS" or d["key"] not in c.outputs):
                    c.notes[d["key"]] = d["note"]     # what the service publishes says what the key is
        elif name in ("SERVICES", "CALLS"):
            target = getattr(c, name.lower())
            for d in _declarations(node, "Query", ("key", "request", "reply", "note"), consts):
                target[d["key"]] = (d.get("request"), d.get("reply"))
                if d.get("note"):
                    c.notes.setdefault(d["key"], d["note"])
        elif name in ("ACTIONS", "ACTION_CALLS", "LIVELINESS") and isinstance(node, (ast.List, ast.Tuple)):
            setattr(c, name.lower(), [str(_value(e, consts)) for e in node.elts])
    return c


def load_contracts() -> list[Contract]:
    """Every service folder's contract, sorted by service name."""
    root = resources.files("aeroperception.services")
    out = []
    for folder in sorted(root.iterdir(), key=lambda p: p.name):
        f = folder.joinpath("contract.py")
        if folder.is_dir() and not folder.name.startswith(("_", ".")) and f.is_file():
            out.append(parse_contract(f.read_text(), folder.name, f"services/{folder.name}/contract.py"))
    return out


# ---------------------------------------------------------------- key expressions


def key_matches(pattern: str, key: str) -> bool:
    """Whether zenoh key expression `pattern` (`*` one chunk, `**` any, `<x>` one chunk) matches `key`."""
    pat = [("*" if p.startswith("<") and p.endswith(">") else p) for p in pattern.strip("/").split("/")]
    return _match(pat, key.strip("/").split("/"))


def _match(pat: list[str], parts: list[str]) -> bool:
    if not pat:
        return not parts
    head = pat[0]
    if head == "**":
        return any(_match(pat[1:], parts[i:]) for i in range(len(parts) + 1))
    if not parts:
        return False
    return (head == "*" or head == parts[0]) and _match(pat[1:], parts[1:])


def declared_keys(contracts: list[Contract]) -> set[str]:
    """Every key a service declares it reads or writes (placeholders and wildcards kept)."""
    keys: set[str] = set()
    for c in contracts:
        keys |= set(c.inputs) | set(c.outputs)
    return keys


def declared_schemas(key: str, contracts: list[Contract]) -> list[tuple[str, str, str]]:
    """(schema, service, "writes"/"reads") for every typed declaration that matches `key`,
    the writers first."""
    out = []
    for role, attr in (("writes", "outputs"), ("reads", "inputs")):
        for c in contracts:
            for pattern, schema in getattr(c, attr).items():
                if isinstance(schema, str) and key_matches(pattern, key):
                    out.append((schema, c.service, role))
    return out


def close_keys(key: str, candidates, n: int = 5) -> list[str]:
    """Keys that look like `key` (a typo, a missing or extra chunk)."""
    cands = sorted({c for c in candidates if c and c != key})
    near = difflib.get_close_matches(key, cands, n=n, cutoff=0.6)
    last = key.rstrip("/").rsplit("/", 1)[-1]
    near += [c for c in cands if c not in near and (c.endswith("/" + last) or key in c)]
    return near[:n]
