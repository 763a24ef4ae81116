"""What produced a result, beyond its inputs: the code's git commit, the environment, and
the identity of a plugin's code (its distribution and a hash of its source files).

A leaf of the import graph: the runner records them in a cell, training in a checkpoint's
manifest.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import os
import platform
import subprocess
import sys
import weakref
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["code_identity", "code_unit", "environment", "git_commit", "source_files_sha256"]


def git_commit() -> str | None:
    """The commit of the git checkout this package's files lie in (editable, or a wheel in a
    virtual environment inside the checkout), else None."""
    here = Path(__file__).resolve().parent  # git looks upwards from any folder of a work tree
    try:
        out = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def environment() -> dict[str, Any]:
    """The versions and the host a result was computed with: Python, the platform, the CPU
    (its model: the generated datasets' bytes and the learned methods' arithmetic depend on it),
    numpy, pandas, pyarrow, and each of torch (with the instruction set its kernels use), numba,
    Open3D and scipy that the process has imported."""
    import pandas
    import pyarrow

    env = {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "cpu_simd": None if cpu_simd() is None else list(cpu_simd()),
        "numpy": np.__version__,
        "pandas": pandas.__version__,
        "pyarrow": pyarrow.__version__,
        "cpus": os.cpu_count(),
    }
    for name in ("torch", "numba", "open3d", "scipy"):
        if name in sys.modules:
            env[name] = getattr(sys.modules[name], "__version__", None)
    if "torch" in sys.modules:
        env["torch_cpu_capability"] = sys.modules["torch"].backends.cpu.get_cpu_capability()
    return env


#: the vector instruction sets that choose the ray casts' and the kernels' code paths
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_bf16", "avx512_fp16", "amx_tile")


def _cpuinfo(key: str) -> str | None:
    """The first ``key`` line's value of ``/proc/cpuinfo``, None where there is none."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.split(":", 1)[0].strip() == key:
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


@functools.lru_cache(maxsize=1)
def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` where there is one, else what ``platform``
    says; "" when neither knows)."""
    return _cpuinfo("model name") or platform.processor() or ""


@functools.lru_cache(maxsize=1)
def cpu_simd() -> tuple[str, ...] | None:
    """Which of :data:`SIMD_FLAGS` the CPU has (``/proc/cpuinfo``'s flags), None where it
    cannot be read."""
    flags = _cpuinfo("flags")
    return None if flags is None else tuple(f for f in SIMD_FLAGS if f in flags.split())


def code_unit(module_name: str) -> str:
    """The importable package whose source is hashed for code defined in ``module_name``:
    its top-level package (or module), and for pcfbench's own built-ins the sub-package
    under ``pcfbench`` (``pcfbench.methods``): the built-in methods' code, not the harness's,
    whose rows are versioned by the protocol and metric versions."""
    parts = module_name.split(".")
    return ".".join(parts[:2]) if parts[0] == "pcfbench" and len(parts) > 1 else parts[0]


def source_files_sha256(path: Path) -> tuple[str, dict[str, str]]:
    """The hash of a module file, or of a package folder's Python sources (``*.py`` of the
    folder and of each sub-folder that is a package, i.e. has an ``__init__.py``), and each
    file's sha256 (16 hex digits) by its path relative to the folder. Only relative paths and
    contents count, so an installed wheel and an editable checkout of the same sources agree."""
    path = Path(path)
    if path.is_file():
        files = {path.name: path}
    else:
        files = {}
        stack = [path]
        while stack:
            d = stack.pop()
            for child in d.iterdir():
                if child.is_dir() and (child / "__init__.py").is_file():
                    stack.append(child)
                elif child.is_file() and child.suffix == ".py":
                    files[child.relative_to(path).as_posix()] = child
    per_file = {rel: hashlib.sha256(files[rel].read_bytes()).hexdigest()[:16] for rel in sorted(files)}
    h = hashlib.sha256()
    for rel, sha in per_file.items():
        h.update(f"{rel}\0{sha}\n".encode("utf-8", "surrogateescape"))
    return h.hexdigest()[:16], per_file


@functools.cache
def _distributions() -> dict[str, list[str]]:
    return importlib.metadata.packages_distributions()


def code_identity(unit: str) -> dict[str, Any]:
    """What a cell records of the code of package ``unit`` (:func:`code_unit`): ``sha256``
    and ``files`` (:func:`source_files_sha256`; None and {} for code with no source file, a
    class made at run time), its ``distribution`` and that distribution's ``version`` (None
    when no installed distribution provides it). Computed once per imported module: the code
    a process runs is the code it imported (a module imported again is hashed again)."""
    module = sys.modules.get(unit)
    found = _CODE.get(module) if module is not None else None
    if found is None:
        found = _code_identity(unit, getattr(module, "__file__", None))
        if module is not None:
            _CODE[module] = found
    return {**found, "files": dict(found["files"])}


_CODE: "weakref.WeakKeyDictionary[Any, dict[str, Any]]" = weakref.WeakKeyDictionary()


def _code_identity(unit: str, file: str | None) -> dict[str, Any]:
    sha, files = None, {}
    if file:
        source = Path(file).parent if Path(file).name == "__init__.py" else Path(file)
        try:
            sha, files = source_files_sha256(source)
        except OSError:
            sha, files = None, {}
    dists = _distributions().get(unit.split(".")[0]) or []
    dist = dists[0] if len(dists) == 1 else None
    version = None
    if dist is not None:
        try:
            version = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            version = None
    return {"unit": unit, "sha256": sha, "files": files, "distribution": dist, "version": version}
