"""What a cell asks of a method working elsewhere: its samples, and what an answer must echo.

An answer file (a submission) echoes ``Questions.answers``: the exchange format's version, the
protocol's identity (version, ROI, minimum range, setting parameters, sample policy, ego box),
the dataset (name, version, root options, files' fingerprint by content), split, setting,
policy and the hash of the sample ids. A submission whose echo differs in any of them answers
other questions and is refused, naming each difference (:func:`differences`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pcfbench import config
from pcfbench.dataset import options_identity
from pcfbench.plugins import Plugins, get_plugins, get_setting
from pcfbench.protocol import SampleBuilder, check_compatible, ids_hash, sample_id

#: The version of the query and submission files' layout (docs/bring-your-own-method.md); a
#: file of another version is refused.
EXCHANGE_VERSION = 1


@dataclass
class Questions:
    """One dataset x split x setting x policy: its sample builder, sample keys and ids."""

    dataset: str
    dataset_root: str | None
    split: str
    setting: str
    policy: str
    builder: SampleBuilder
    keys: list[tuple[str, int]]

    @property
    def ids(self) -> list[str]:
        return [sample_id(s, i) for s, i in self.keys]

    def answers(self) -> dict[str, Any]:
        """What every answer to these questions echoes (JSON-ready; the data fingerprint is
        computed by content, so this reads every file of the split once, then from its cache)."""
        adapter = self.builder.adapter
        return {
            "exchange_version": EXCHANGE_VERSION,
            **self.builder.identity(),
            "dataset": self.dataset,
            "dataset_version": adapter.version,
            "dataset_options": options_identity(adapter, config.split_root_options(self.dataset_root)[1]),
            "data_fingerprint": adapter.fingerprint(self.split).digest,
            "split": self.split,
            "setting": self.setting,
            "policy": self.policy,
            "sample_ids_hash": ids_hash(self.ids),
        }


def open_questions(dataset: str, root: str | None, split: str, setting: str, policy: str,
                   plugins: Plugins | None = None) -> Questions:
    """The samples of ``dataset`` (opened on ``root``, ``PATH?key=value`` options included, as
    a cell opens it) under ``setting`` and ``policy``; no samples is the runner's one error."""
    from pcfbench.running.runner import Resolved, sample_keys
    from pcfbench.store.cells import CellSpec

    plugins = plugins or get_plugins()
    adapter_cls = plugins.datasets.get(dataset)
    path, raw = config.split_root_options(root)
    adapter = adapter_cls(path, **raw)
    s = get_setting(setting, plugins)
    check_compatible(s, adapter)
    builder = SampleBuilder(adapter, s, policy)
    spec = CellSpec("", {}, "", dataset, root, split, setting, builder.policy)
    keys = sample_keys(Resolved(builder, None, []), spec, plugins)  # type: ignore[arg-type]
    return Questions(dataset, root, split, setting, builder.policy, builder, keys)


def differences(given: Any, expected: dict[str, Any]) -> list[str]:
    """Each field on which an answer's echo ``given`` differs from ``expected``, as
    ``field: file X, benchmark Y`` (a missing field reads as ``missing``)."""
    if not isinstance(given, dict):
        return [f"the echo is {type(given).__name__}, not an object of the query file's answers"]
    out = []
    for key, want in expected.items():
        got = given.get(key, "missing")
        if got != want:
            out.append(f"{key}: the file's {got!r}, this benchmark's {want!r}")
    out += [f"{key}: the file has it, the benchmark's questions do not" for key in sorted(set(given) - set(expected))]
    return out
