"""Issue 15: no file pcfbench reads may execute code. Every call that can run code from a file
(unpickling, yaml.load, eval/exec, np.load with pickles, torch.load without weights_only) is
refused in the source tree; docs/trust.md lists every reader and why it is safe."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: the folders of the installed package (pyproject.toml: bench -> pcfbench, methods, datasets)
SOURCES = ("bench", "methods", "datasets")

#: module.function calls that run code from what they read, whatever their arguments
FORBIDDEN = {
    ("pickle", "load"), ("pickle", "loads"), ("pickle", "Unpickler"),
    ("cloudpickle", "load"), ("cloudpickle", "loads"), ("dill", "load"), ("dill", "loads"),
    ("marshal", "load"), ("marshal", "loads"), ("shelve", "open"), ("joblib", "load"),
    ("yaml", "load"), ("yaml", "load_all"), ("yaml", "unsafe_load"), ("yaml", "full_load"),
    ("pd", "read_pickle"), ("pandas", "read_pickle"), ("runpy", "run_path"), ("runpy", "run_module"),
}
#: builtins that run code (``__import__`` only of a name that is not a literal)
FORBIDDEN_BUILTINS = {"eval", "exec", "compile", "__import__"}
#: calls that are safe only with this keyword set to this constant
REQUIRED_KEYWORD = {("np", "load"): ("allow_pickle", False), ("numpy", "load"): ("allow_pickle", False),
                    ("torch", "load"): ("weights_only", True)}


def _dotted(node: ast.AST) -> tuple[str, str] | None:
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
        return node.value.id, node.attr
    return None


def violations(source: str, filename: str = "<source>") -> list[str]:
    """Every code-running call in ``source``: ``file:line: what``."""
    out = []
    tree = ast.parse(source, filename)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module in {m for m, _ in FORBIDDEN}:
            for alias in node.names:
                if (node.module, alias.name) in FORBIDDEN:
                    out.append(f"{filename}:{node.lineno}: from {node.module} import {alias.name}")
        if not isinstance(node, ast.Call):
            continue
        if isinstance(node.func, ast.Name) and node.func.id in FORBIDDEN_BUILTINS and not (
                node.func.id == "__import__" and node.args and isinstance(node.args[0], ast.Constant)):
            out.append(f"{filename}:{node.lineno}: {node.func.id}()")
        name = _dotted(node.func)
        if name in FORBIDDEN:
            out.append(f"{filename}:{node.lineno}: {'.'.join(name)}()")
        if name in REQUIRED_KEYWORD:
            key, value = REQUIRED_KEYWORD[name]
            given = {k.arg: k.value for k in node.keywords}
            if not (isinstance(given.get(key), ast.Constant) and given[key].value is value):
                out.append(f"{filename}:{node.lineno}: {'.'.join(name)}() without {key}={value}")
    return out


def test_the_scanner_finds_each_kind_of_code_running_call():
    bad = """
import pickle, yaml, numpy as np, torch
from pickle import loads
pickle.load(open("x", "rb"))
yaml.load(text)
eval("1 + 1")
exec("x = 1")
np.load("a.npy")
np.load("a.npy", allow_pickle=True)
torch.load("w.pt")
torch.load("w.pt", weights_only=flag)
__import__(name)
"""
    found = violations(bad)
    assert [v.split(": ", 1)[1] for v in found] == [
        "from pickle import loads", "pickle.load()", "yaml.load()", "eval()", "exec()",
        "np.load() without allow_pickle=False", "np.load() without allow_pickle=False",
        "torch.load() without weights_only=True", "torch.load() without weights_only=True", "__import__()",
    ]
    safe = """
np.load("a.npz", allow_pickle=False)
torch.load(buf, map_location="cpu", weights_only=True)
model.eval()
json.loads(text)
tomllib.loads(text)
pickle.dumps(obj)
__import__("pcfbench")
"""
    assert violations(safe) == []


def test_no_source_file_runs_code_from_what_it_reads():
    files = sorted(p for folder in SOURCES for p in (REPO / folder).rglob("*.py"))
    assert len(files) > 40  # the whole package, not an empty glob
    found = [v for p in files for v in violations(p.read_text(encoding="utf-8"), str(p.relative_to(REPO)))]
    assert not found, "code-running calls (see docs/trust.md, 'Files pcfbench reads'):\n" + "\n".join(found)


def test_the_docs_list_the_readers():
    text = (REPO / "docs" / "trust.md").read_text(encoding="utf-8")
    for reader in ("cell.json", "Parquet", "checkpoint", "experiment", "protocol.toml", "config.toml", "KITTI",
                   "nuScenes", "Argoverse 2", "MCAP", ".npz"):
        assert reader in text, reader
