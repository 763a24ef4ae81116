"""The training data of a trained method: which dataset, split and content a checkpoint was
trained on (:class:`TrainOn`), and the data handed to ``fit`` (:class:`TrainSource`)."""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from pcfbench.errors import PcfbenchError

if TYPE_CHECKING:  # pragma: no cover
    from pcfbench.plugins import Plugins

#: the split a method trains on unless told otherwise
DEFAULT_SPLIT = "train"


@dataclass(frozen=True)
class TrainOn:
    """The training data of a checkpoint: dataset name, split, the split's file fingerprint
    (``adapter.fingerprint(split).digest``), the adapter's root options and the root used."""

    dataset: str
    split: str
    fingerprint: str
    dataset_options: Mapping[str, Any] = field(default_factory=dict)
    root: str | None = None
    #: the split's data files (``adapter.data_files(split)``), for :meth:`content_sha256`;
    #: not part of the identity (the fingerprint is)
    files: tuple[str, ...] = field(default=(), compare=False, repr=False)
    #: sha256 of the split's recipe (:func:`recipe_sha256`) when the dataset makes its own data
    #: and no root is configured for it, else None; recorded by :func:`ship`, not part of the
    #: identity
    recipe: str | None = field(default=None, compare=False, repr=False)

    def content_sha256(self) -> str:
        """sha256 over the split's files (relative path and sha256 of the bytes of each, in
        sorted order): the same data anywhere, whatever its modification times. Computed on
        demand (it reads every file); a shipped checkpoint matches local data by it."""
        base = Path(self.root) if self.root else None
        if base is not None and base.is_file():
            base = base.parent
        entries = []
        for f in sorted(self.files):
            p = Path(f)
            h = hashlib.sha256()
            with open(p, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 22), b""):
                    h.update(chunk)
            rel = p.as_posix() if base is None else Path(os.path.relpath(p, base)).as_posix()
            entries.append([rel, h.hexdigest()])
        return hashlib.sha256(json.dumps(entries).encode()).hexdigest()

    @property
    def label(self) -> str:
        return f"{self.dataset}:{self.split}"

    @property
    def key(self) -> str:
        """What names the checkpoint folder: the root path itself is left out (the same files
        elsewhere are the same data), its fingerprint and options are in."""
        blob = json.dumps([self.dataset, self.split, self.fingerprint, dict(self.dataset_options)], sort_keys=True,
                          default=str)
        return f"{self.dataset}.{self.split}.{hashlib.sha256(blob.encode()).hexdigest()[:12]}"

    def to_meta(self) -> dict[str, Any]:
        return {"dataset": self.dataset, "split": self.split, "fingerprint": self.fingerprint,
                "dataset_options": json.loads(json.dumps(dict(self.dataset_options), default=str)), "root": self.root}


@dataclass
class TrainSource:
    """What ``fit`` trains on: an opened dataset adapter and the split (``train_on`` names both)."""

    adapter: Any
    split: str
    train_on: TrainOn


def open_training_data(dataset: str, split: str = DEFAULT_SPLIT, plugins: Plugins | None = None,
                       progress: bool = True, split_option: str = "--split {}") -> TrainSource:
    """``NAME`` or ``NAME=ROOT`` (root options ``ROOT?key=value`` allowed) opened for training:
    the root from the argument, the config, or the adapter's default (embedded datasets are
    generated). An unknown name or a split without sequences is one clear error; for a split
    whose sequences are elsewhere it names their split and ``split_option`` (``{}``: the split)."""
    from pcfbench import config
    from pcfbench.dataset import options_identity
    from pcfbench.plugins import get_plugins

    plugins = plugins or get_plugins()
    names, roots = config.parse_dataset_args((dataset,))
    if len(names) != 1:
        raise PcfbenchError(f"--dataset {dataset!r}: expected one NAME[=ROOT]")
    name = names[0]
    cls = plugins.datasets.get(name)
    root = config.resolve_root(name, cls, roots, progress)
    adapter = config.open_adapter(name, cls, root)
    if split not in adapter.splits():
        from pcfbench.errors import unknown_name

        raise unknown_name(f"split of dataset {name}", split, adapter.splits())
    if not adapter.sequence_names(split):
        from pcfbench.protocol.nosamples import Options, no_sequences

        raise PcfbenchError(no_sequences(adapter, split, f"dataset {name!r} has no sequences in split {split!r}",
                                         Options(split=split_option)).message)
    fp = adapter.fingerprint(split).digest
    opts = options_identity(adapter, config.split_root_options(root)[1])
    files = tuple(str(f) for f in adapter.data_files(split))
    recipe = data_recipe_sha256(dataset, split, plugins)
    return TrainSource(adapter, split, TrainOn(name, split, fp, opts, None if root is None else str(root), files, recipe))


def recipe_sha256(recipe: Mapping[str, Any]) -> str:
    """sha256 of a dataset's recipe (``DatasetAdapter.recipe``) as sorted JSON."""
    return hashlib.sha256(json.dumps(recipe, sort_keys=True).encode()).hexdigest()


def data_recipe_sha256(dataset: str, split: str = DEFAULT_SPLIT, plugins: Plugins | None = None) -> str | None:
    """The sha256 of the recipe that makes ``split`` of ``dataset`` (``NAME``), without making
    or reading any data; None for recorded data, for a root given or configured (its bytes
    may come from anywhere: ``NAME=ROOT``, the environment, the config file) and for a split
    the dataset does not have."""
    from pcfbench import config
    from pcfbench.plugins import get_plugins

    names, roots = config.parse_dataset_args((dataset,))
    if len(names) != 1 or roots or config.dataset_root(names[0], {}) is not None:
        return None
    recipe = (plugins or get_plugins()).datasets.get(names[0]).recipe(split)
    return None if recipe is None else recipe_sha256(recipe)


