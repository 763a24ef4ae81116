"""The import graph of the package has no circle: a circle makes every module on it load
with the others half-made, and is how a layer starts reading from the layer above it (the
protocol core was one: the ROI found late through a module __getattr__, get_setting
importing the plugins that import the protocol; the protocol is now handed down). Read statically from the sources (every import, at module level or in a
function, outside ``if TYPE_CHECKING:``), so a lazy import does not hide one."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = {"bench": "pcfbench", "methods": "pcfbench.methods", "datasets": "pcfbench.datasets"}

def _modules() -> dict[str, Path]:
    out = {}
    for folder, package in FOLDERS.items():
        for path in (ROOT / folder).rglob("*.py"):
            if "__pycache__" in path.parts:
                continue
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join((package, *parts))] = path
    return out


def _type_checking_blocks(tree: ast.AST) -> set[int]:
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    return skip


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        skip = _type_checking_blocks(tree)
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                targets = [f"{base}.{a.name}" for a in node.names] + [base]
            for t in targets:
                while t and t not in modules:  # the module a name comes from
                    t = t.rpartition(".")[0]
                if t and t != name and t != "pcfbench":  # the package's __init__ re-exports; not a layer
                    graph[name].add(t)
                # importing a.b.c runs a/__init__ and a/b/__init__ first: an edge to each subpackage
                # above the target that is not also above the importer (which is already loading)
                parent = t.rpartition(".")[0]
                while parent and parent != "pcfbench":
                    if parent in modules and not name.startswith(parent + ".") and parent != name:
                        graph[name].add(parent)
                    parent = parent.rpartition(".")[0]
    return graph


def circles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(frozenset(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_circles_finds_a_hand_made_one():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert circles(graph) == [frozenset("abc")]


def test_the_package_has_no_import_circle():
    graph = import_graph()
    # the reading sees lazy imports and the package's own modules (a graph read wrong finds nothing)
    assert "pcfbench.running.runner" in graph["pcfbench.running.backfill"] and "pcfbench.protocol" in graph["pcfbench.plugins"]
    found = [sorted(c) for c in circles(graph)]
    assert not found, f"import circles: {found} (move what both sides need into a module below both)"
