"""The services' declared keys, read from their source: services/*/contract.py (a service without
one, like sim today, declares them at the top of its main.py).

One home for "who publishes what": `aero topic echo` suggests keys from it, `aero topic pub`
checks a type against it, and `aero docs keys` generates docs/ARCHITECTURE.md's key table from
it. The files are parsed (ast), never imported: importing sim's main would load Open3D, and a
new service folder is picked up with no registration.
"""
from __future__ import annotations

import ast
import difflib
import io
import re
import tokenize
from dataclasses import dataclass, field
from importlib import resources

RATE_RE = re.compile(r"\b\d+(?:\.\d+)?(?:\s*-\s*\d+(?:\.\d+)?)?\s*Hz\b")


@dataclass
class Contract:
    """What one service declares; schema names are the class names used in the file
    (None: no payload schema, e.g. a liveliness token)."""

    service: str
    source: str
    inputs: dict[str, str | None] = field(default_factory=dict)
    outputs: dict[str, str | None] = field(default_factory=dict)
    services: dict[str, tuple[str | None, str | None]] = field(default_factory=dict)
    calls: dict[str, tuple[str | None, str | None]] = field(default_factory=dict)
    actions: list[str] = field(default_factory=list)        # served: <service>/action/<name>
    action_calls: list[str] = field(default_factory=list)   # used: another service's actions
    notes: dict[str, str] = field(default_factory=dict)   # key -> the comment beside it

    def rate(self, key: str) -> str:
        """The rate written beside the key ("50 Hz", "on change", "event"), else ""."""
        note = self.notes.get(key, "")
        m = RATE_RE.search(note)
        if m:
            return re.sub(r"\s+", " ", m.group(0))
        for word in ("on change", "event"):
            if word in note:
                return word
        return ""


def _value(node: ast.AST):
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, (ast.Tuple, ast.List)):
        return tuple(_value(e) for e in node.elts)
    return None


def _comments(text: str) -> dict[int, str]:
    out: dict[int, str] = {}
    try:
        for tok in tokenize.generate_tokens(io.StringIO(text).readline):
            if tok.type == tokenize.COMMENT:
                out[tok.start[0]] = tok.string.lstrip("#").strip()
    except (tokenize.TokenError, SyntaxError):
        pass
    return out


def parse_contract(text: str, service: str, source: str = "") -> Contract:
    """Read NAME, INPUTS, OUTPUTS, SERVICES, CALLS and ACTIONS assigned at module level."""
    c = Contract(service=service, source=source)
    comments = _comments(text)
    for stmt in ast.parse(text).body:
        if not (isinstance(stmt, ast.Assign) and len(stmt.targets) == 1 and isinstance(stmt.targets[0], ast.Name)):
            continue
        name, node = stmt.targets[0].id, stmt.value
        if name == "NAME" and isinstance(node, ast.Constant):
            c.service = str(node.value)
        elif name in ("INPUTS", "OUTPUTS", "SERVICES", "CALLS") and isinstance(node, ast.Dict):
            target = getattr(c, name.lower())
            for k, v in zip(node.keys, node.values):
                if not (isinstance(k, ast.Constant) and isinstance(k.value, str)):
                    continue
                target[k.value] = _value(v)
                note = comments.get(v.end_lineno) or comments.get(k.lineno)
                if note:
                    c.notes.setdefault(k.value, note)
        elif name == "ACTIONS" and isinstance(node, (ast.List, ast.Tuple)):
            c.actions = [str(_value(e)) for e in node.elts]
    # Short action names ("takeoff") are the service's own, served as <service>/action/<name>;
    # full keys name another service's actions that this one uses.
    c.actions, c.action_calls = ([f"{c.service}/action/{a}" for a in c.actions if "/" not in a],
                                 [a for a in c.actions if "/" in a])
    return c


def load_contracts() -> list[Contract]:
    """Every service folder's contract, sorted by service name."""
    root = resources.files("aeroperception.services")
    out = []
    for folder in sorted(root.iterdir(), key=lambda p: p.name):
        if not folder.is_dir() or folder.name.startswith(("_", ".")):
            continue
        for fname in ("contract.py", "main.py"):
            f = folder.joinpath(fname)
            if f.is_file():
                c = parse_contract(f.read_text(), folder.name, f"services/{folder.name}/{fname}")
                if c.inputs or c.outputs or c.services or fname == "contract.py":
                    out.append(c)
                    break
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
