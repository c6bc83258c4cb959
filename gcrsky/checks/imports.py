"""The package's own import graph: layers, floors and circles, parsed from the source with ``ast``.

Every ``import`` / ``from ... import`` anywhere in a module counts (also those inside
functions: a lazy import is still a dependency).  Importing ``gcrsky.a.b`` from
outside ``gcrsky.a`` also runs the subpackage's ``__init__``, so it counts as an edge
to ``gcrsky.a`` too (from inside, the ``__init__`` is already running); the top-level ``gcrsky/__init__.py`` (the facade, which every import runs) is
left out of the graph and checked on its own.

Layers, lowest first (:data:`LAYERS`); a module may import only from its own layer
or lower ones.  The *core* (:data:`CORE`) is what ``import gcrsky`` and a library
user need; the *applications* (:data:`APPS`) sit on top, and the core never
imports them.  The facade may import the core and ``sim`` (for
:func:`gcrsky.standard_case`).

``python -m gcrsky.checks.imports [PACKAGE_DIR]`` prints the layer table, the floors
(the longest chain of imports below each module) and any circles or violations.
"""

from __future__ import annotations

import ast
import sys
from collections import defaultdict
from pathlib import Path
from typing import NamedTuple

__all__ = [
    "APPS",
    "CORE",
    "LAYERS",
    "Violation",
    "find_cycles",
    "floors",
    "import_graph",
    "layer_of",
    "layer_violations",
    "modules_only",
    "private_imports",
    "report",
]

#: Subpackages (and top-level modules) from the bottom of the data flow to the top.
LAYERS = ("base", "sphere", "io", "instrument", "model", "solvers", "inference", "parallel", "ingest", "run",
          "sim", "checks", "paper", "cli")
#: The library core: never imports an application layer.
CORE = LAYERS[: LAYERS.index("run") + 1]
#: The applications built on the core.
APPS = LAYERS[LAYERS.index("run") + 1 :]
#: What the facade ``gcrsky/__init__.py`` may import.
FACADE_ALLOWED = CORE + ("sim",)


def _modules(root: Path, package: str) -> dict[str, Path]:
    out = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).with_suffix("")
        parts = [package, *rel.parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _resolve(module: str, is_pkg: bool, level: int, target: str | None) -> str:
    base = module.split(".") if is_pkg else module.split(".")[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def import_graph(root: Path | str | None = None, package: str = "gcrsky") -> dict[str, set[str]]:
    """``{module: {internal modules it imports}}`` for every module of the package at ``root``.

    Args:
        root: the package directory (default: this installed gcrsky).
        package: the package's import name.
    """
    root = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    mods = _modules(root, package)
    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = _resolve(mod, is_pkg, node.level, node.module)
                else:
                    base = node.module or ""
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            for t in targets:
                if not (t == package or t.startswith(package + ".")):
                    continue
                while t not in mods and "." in t:
                    t = t.rsplit(".", 1)[0]
                parts = t.split(".")
                for k in range(2, len(parts) + 1):  # the subpackage __init__s run first ...
                    anc = ".".join(parts[:k])
                    if k == len(parts) or not (mod == anc or mod.startswith(anc + ".")):  # ... unless ours
                        deps.add(anc)
        deps.discard(mod)
        deps.discard(package)
        graph[mod] = deps
    return graph


def layer_of(module: str, package: str = "gcrsky") -> str:
    """The layer of a module: its subpackage (``gcrsky.model.system`` -> ``"model"``,
    ``gcrsky.cli.parser`` -> ``"cli"``), ``"cli"`` for ``gcrsky.__main__``, ``"facade"`` for ``gcrsky``."""
    parts = module.split(".")
    if parts == [package]:
        return "facade"
    name = parts[1]
    if name == "__main__":
        return "cli"
    return name


class Violation(NamedTuple):
    """An import that breaks the layering: ``importer`` -> ``imported``, and why."""

    importer: str
    imported: str
    why: str


def layer_violations(graph: dict[str, set[str]], package: str = "gcrsky") -> list[Violation]:
    """Imports from a higher layer, core modules importing applications, unknown layers."""
    out = []
    rank = {name: i for i, name in enumerate(LAYERS)}
    for mod, deps in sorted(graph.items()):
        src = layer_of(mod, package)
        for dep in sorted(deps):
            dst = layer_of(dep, package)
            if src == "facade":
                if dst not in FACADE_ALLOWED:
                    out.append(Violation(mod, dep, f"the facade may import only {FACADE_ALLOWED}, not {dst!r}"))
                continue
            if src not in rank or dst not in rank:
                out.append(Violation(mod, dep, f"layer {src if src not in rank else dst!r} is not in LAYERS"))
            elif src in CORE and dst in APPS:
                out.append(Violation(mod, dep, f"core layer {src!r} imports application layer {dst!r}"))
            elif rank[dst] > rank[src]:
                out.append(Violation(mod, dep, f"layer {src!r} imports the higher layer {dst!r}"))
    return out


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Import circles: the strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(graph) + 100))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return sorted(out)


def modules_only(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The graph without the subpackages' ``__init__`` nodes: module -> module imports only."""
    pkgs = {m for m in graph if any(o.startswith(m + ".") for o in graph)}
    return {m: {d for d in deps if d not in pkgs} for m, deps in graph.items() if m not in pkgs}


def floors(graph: dict[str, set[str]]) -> dict[str, int]:
    """The floor of each module: 0 if it imports nothing internal, else 1 + its highest import's.

    Modules in a circle share a floor (computed on the graph of circles).  Apply to
    :func:`modules_only` for the depth of the module chain alone.
    """
    comp_of = {}
    for i, comp in enumerate(find_cycles(graph)):
        for m in comp:
            comp_of[m] = f"<cycle {i}>"
    node = lambda m: comp_of.get(m, m)  # noqa: E731
    cgraph: dict[str, set[str]] = defaultdict(set)
    for m, deps in graph.items():
        cgraph[node(m)] |= {node(d) for d in deps if node(d) != node(m)}
    memo: dict[str, int] = {}

    def fl(v: str) -> int:
        if v not in memo:
            memo[v] = 0
            memo[v] = 1 + max((fl(w) for w in cgraph.get(v, ())), default=-1)
        return memo[v]

    return {m: fl(node(m)) for m in graph}


class PrivateImport(NamedTuple):
    """A module using another module's private name: ``importer`` line ``line`` uses ``owner.name``."""

    importer: str
    line: int
    owner: str
    name: str


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_imports(root: Path | str | None = None, package: str = "gcrsky") -> list[PrivateImport]:
    """Every use of another module's private name (``_name``, not a dunder) inside the package.

    Counted: ``from .mod import _name`` (any level, also inside functions) and ``mod._name``
    where ``mod`` is an internal module bound by ``import`` / ``from . import mod``.  A module's
    private names are its own: a helper two modules share is made public where it belongs, or moved.
    """
    root = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    mods = _modules(root, package)
    out = []
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        tree = ast.parse(path.read_text(), str(path))
        aliases: dict[str, str] = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                base = _resolve(mod, is_pkg, node.level, node.module) if node.level else (node.module or "")
                if not (base == package or base.startswith(package + ".")):
                    continue
                for a in node.names:
                    full = f"{base}.{a.name}"
                    if full in mods:
                        aliases[a.asname or a.name] = full
                    elif _is_private(a.name) and base != mod:
                        out.append(PrivateImport(mod, node.lineno, base, a.name))
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name in mods and a.asname:
                        aliases[a.asname] = a.name
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and _is_private(node.attr) and aliases[node.value.id] != mod):
                out.append(PrivateImport(mod, node.lineno, aliases[node.value.id], node.attr))
    return sorted(out)


def report(root: Path | str | None = None, package: str = "gcrsky") -> str:
    """A Markdown report: modules per layer with their floors (module -> module imports), circles
    (package ``__init__``s included) and layer violations."""
    graph = import_graph(root, package)
    fl = floors(modules_only(graph))
    by_layer: dict[str, list[str]] = defaultdict(list)
    for m in graph:
        by_layer[layer_of(m, package)].append(m)
    lines = ["| layer | kind | modules (floor) |", "|---|---|---|"]
    for layer in LAYERS + tuple(sorted(set(by_layer) - set(LAYERS))):
        if layer not in by_layer:
            continue
        kind = "core" if layer in CORE else "app" if layer in APPS else "?"
        mods = ", ".join(f"`{m}` ({fl[m]})" if m in fl else f"`{m}`" for m in sorted(by_layer[layer]))
        lines.append(f"| {layer} | {kind} | {mods} |")
    cyc = find_cycles(graph)
    vio = layer_violations(graph, package)
    lines += ["", f"modules: {len(graph)} ({len(fl)} without package __init__s); module floors: "
              f"{max(fl.values()) + 1} (0..{max(fl.values())}); "
              f"circles: {len(cyc)}; layer violations: {len(vio)}"]
    lines += [f"- circle: {' <-> '.join(c)}" for c in cyc]
    lines += [f"- {v.importer} -> {v.imported}: {v.why}" for v in vio]
    priv = private_imports(root, package)
    lines += ["", f"private names used across modules: {len(priv)}"]
    lines += [f"- {p.importer}:{p.line} uses {p.owner}.{p.name}" for p in priv]
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover - a command-line report
    print(report(sys.argv[1] if len(sys.argv) > 1 else None))
