"""Where things live: dataset roots, the results store, the reports folder, the cache.

Dataset roots come from ``--dataset NAME=ROOT``, then ``PCFBENCH_DATASET_<NAME>`` (name upper-
cased, ``-`` as ``_``), then the ``[datasets]`` table of the config file
(``$PCFBENCH_CONFIG`` or ``~/.config/pcfbench/config.toml``); never the working directory.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

from pcfbench.errors import PcfbenchError


def config_path() -> Path:
    env = os.environ.get("PCFBENCH_CONFIG")
    if env:
        return Path(env).expanduser()
    base = Path(os.environ.get("XDG_CONFIG_HOME", Path.home() / ".config"))
    return base / "pcfbench" / "config.toml"


def load_config() -> dict:
    path = config_path()
    if not path.is_file():
        if os.environ.get("PCFBENCH_CONFIG"):
            raise PcfbenchError(f"config file {path} (from PCFBENCH_CONFIG) does not exist")
        return {}
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise PcfbenchError(f"config file {path} is not valid TOML: {exc}") from None


def env_var_for(dataset: str) -> str:
    return "PCFBENCH_DATASET_" + dataset.upper().replace("-", "_")


def dataset_root(name: str, cli: dict[str, str]) -> str | None:
    """The root for dataset ``name``, or None when none is configured anywhere."""
    if name in cli:
        return cli[name]
    if os.environ.get(env_var_for(name)):
        return os.environ[env_var_for(name)]
    roots = load_config().get("datasets", {})
    if name in roots:
        return str(Path(roots[name]).expanduser())
    return None


def parse_dataset_args(values: tuple[str, ...]) -> tuple[list[str], dict[str, str]]:
    """``NAME`` or ``NAME=ROOT`` items into the ordered names and the roots given."""
    names, roots = [], {}
    for v in values:
        name, sep, root = v.partition("=")
        if sep and not root:
            raise PcfbenchError(f"--dataset {v!r}: empty root (use NAME=ROOT)")
        names.append(name)
        if sep:
            path, _, query = root.partition("?")
            roots[name] = str(Path(path).expanduser()) + (f"?{query}" if query else "")
    return names, roots


def resolve_root(name: str, adapter_cls: type, cli_roots: dict[str, str], progress: bool = True) -> str:
    """The root of dataset ``name``: configured (CLI, environment, config file), else the
    adapter's default root (an embedded dataset generates its data there on first use)."""
    root = dataset_root(name, cli_roots)
    if root is None:
        return str(adapter_cls.default_root(progress=progress))
    if not Path(split_root_options(root)[0]).exists():
        raise PcfbenchError(f"dataset {name!r}: root {root} does not exist")
    root_options(name, adapter_cls, root)  # an unknown or unreadable option fails now, before any work
    return root


def root_options(name: str, adapter_cls: type, root: str | None) -> object:
    """The typed ``Options`` of dataset ``name``'s adapter from the query of ``root``
    (``PATH?key=value&...``), read by the parser of method options (``pcfbench.options``)."""
    from pcfbench.options import parse_options

    path, raw = split_root_options(root)
    return parse_options(adapter_cls.Options, raw, f"dataset {name} root {path}")


def open_adapter(name: str, adapter_cls: type, root: str | None) -> object:
    """``adapter_cls`` opened on ``root`` (``PATH?key=value&...``) with its typed options."""
    return adapter_cls(split_root_options(root)[0], root_options(name, adapter_cls, root))


def split_root_options(root: str | None) -> tuple[str | None, dict[str, str]]:
    """``PATH?key=value&key=value`` into the path and the adapter's options as strings
    (``root_options`` types them by the adapter's ``Options``).

    Lets ``--dataset mcap=rec.mcap?topic=/points&rate_hz=10`` reach the adapter's options.
    """
    if root is None or "?" not in root:
        return root, {}
    path, _, query = root.partition("?")
    options = {}
    for item in filter(None, query.split("&")):
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise PcfbenchError(f"dataset root {root!r}: option {item!r} must look like key=value")
        if key in options:
            raise PcfbenchError(f"dataset root {root!r}: option {key!r} is given twice")
        options[key] = value
    return path, options


def cache_dir() -> Path:
    """Generated data and checkpoints: ``$PCFBENCH_CACHE`` or ``~/.cache/pcfbench``."""
    env = os.environ.get("PCFBENCH_CACHE")
    base = Path(env).expanduser() if env else Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "pcfbench"
    return base


def reports_dir(cli: str | None = None) -> Path:
    """Where tables are written: ``--reports``, ``$PCFBENCH_REPORTS``, else ./reports; an
    existing file there is one error (before any work)."""
    path = Path(cli or os.environ.get("PCFBENCH_REPORTS") or "reports")
    if path.exists() and not path.is_dir():
        where = "--reports" if cli else "$PCFBENCH_REPORTS" if os.environ.get("PCFBENCH_REPORTS") else "the default"
        raise PcfbenchError(f"the reports folder {path} ({where}) is a file, not a folder: give a folder")
    return path


#: the sub-folder of the reports folder where a partial run writes, in the same layout
PARTIAL_DIR = "partial"


def partial_reports_dir(reports: Path) -> Path:
    """Where a partial run writes its tables and figures (``run --limit``; a sweep with a
    limited or incomplete cell): ``<reports>/partial``, so it never replaces a complete table."""
    return Path(reports) / PARTIAL_DIR


def store_dir(cli: str | None = None, reports: Path | None = None) -> Path:
    """The results store: ``--store``, ``$PCFBENCH_STORE``, else <reports>/store."""
    if cli:
        return Path(cli)
    if os.environ.get("PCFBENCH_STORE"):
        return Path(os.environ["PCFBENCH_STORE"])
    return (reports or reports_dir()) / "store"
