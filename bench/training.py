"""Trained methods: the contract, checkpoints with identity, the one training driver and
(from :mod:`pcfbench.trainloop`) the one training loop.

A method that learns subclasses :class:`TrainedMethod` and implements ``fit`` (train on a
:class:`TrainSource`, saving through the :class:`TrainingRun` it is handed, resuming from
what that run gives back) and ``load`` (take the weights of a verified :class:`Checkpoint`).
``pcfbench train METHOD[:opts] --dataset NAME[=ROOT]`` drives any of them (:func:`train`).
A ``fit`` that trains a torch model by gradient steps hands its model, optimiser, batch sampler
and step function to :func:`~pcfbench.trainloop.fit_loop` (re-exported here), which owns
seeding, resume, the random state, autocast, clipping, the schedule, timing, the saves and
the curve.

A checkpoint is a folder keyed by method, version, options hash and training data (dataset,
split, a hash of the dataset's file fingerprint and root options) under
``<cache>/checkpoints``::

    manifest.json            what it is: method, version, options, train_on, steps, wall and
                             CPU time, device, git commit, the sha256 of each file below
    weights-<step>.pt        the model's tensors (loads with torch.load(weights_only=True))
    state-<step>.pt          optimiser and RNG state to resume from (weights_only too)

The manifest is replaced atomically after both files it names are written, so a run killed
at any moment (SIGKILL included) leaves a consistent checkpoint: the last one saved.
:meth:`Checkpoint.open` refuses a checkpoint whose files do not match their sha256
(truncated, tampered) and :meth:`Checkpoint.check_method` one made by another method,
version or option set: one error naming the file either way.

Shipped checkpoints travel inside a method's package (package data), in
``<package>/checkpoints/<method>/v<version>/<options hash>/<dataset>.<split>/``: the
manifest of the trained checkpoint (weights in float16, no optimiser state) plus a
``shipped`` record (the cache checkpoint's sha256, the training data's content sha256, for
a dataset that makes its own data the sha256 of its recipe, the retrain command).
:func:`checkpoint_for` takes one when the cache holds none trained on that dataset and split:
at once when the dataset, at its default root, is made by the very recipe recorded
(:func:`find_shipped_by_recipe`; the training data is then never made here), else when the
local training data has the same content (:func:`find_checkpoint`). It is verified and loaded
like any checkpoint (float16 tensors cast back to float32). :func:`ship` writes one.
"""

from __future__ import annotations

import fcntl
import hashlib
import io
import json
import os
import time
from abc import abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Mapping

from pcfbench.errors import PcfbenchError
from pcfbench.method import Method, MethodSpec, options_dict, options_hash
from pcfbench.trainloop import (LoopResult, Panel, Randoms, StateError, adamw, autocast, default_device, fit_loop,
                                param_groups, synchronize, warmup_cosine, write_curve)

if TYPE_CHECKING:  # pragma: no cover
    from pcfbench.plugins import Plugins

__all__ = [
    "Checkpoint", "CheckpointError", "TrainOn", "TrainSource", "TrainedMethod", "TrainingInterrupted", "TrainingRun",
    "checkpoint_dir",
    "checkpoint_for", "find_checkpoint", "find_shipped", "find_shipped_by_recipe", "is_trained",
    "missing_checkpoint_message", "open_training_data", "ship", "shipped_dir",
    "train",
    # the one training loop (pcfbench.trainloop)
    "LoopResult", "Panel", "Randoms", "StateError", "adamw", "autocast", "default_device", "fit_loop", "param_groups",
    "synchronize", "warmup_cosine", "write_curve",
]

FORMAT = 1
MANIFEST = "manifest.json"
#: Off a terminal, training progress is a log line this often (seconds), not a bar.
LOG_EVERY_S = 30.0
DEFAULT_SPLIT = "train"


class CheckpointError(PcfbenchError):
    """A checkpoint that is missing, unreadable, altered or made by something else."""


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`train`: where it stopped and what is kept.

    ``step`` of ``total``: the steps trained when it stopped (None: before ``fit`` started the
    loop); ``saved_step``: the step of the checkpoint kept in ``dir`` (its manifest, read from
    the disk: the last save that completed), None when none was saved."""

    def __init__(self, dir: Path, step: int | None, total: int | None, saved_step: int | None) -> None:
        super().__init__(f"training interrupted at step {step}")
        self.dir, self.step, self.total, self.saved_step = Path(dir), step, total, saved_step

    @property
    def manifest_path(self) -> Path:
        return self.dir / MANIFEST


# -- training data ------------------------------------------------------------------------------
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
        from pcfbench.nosamples import Options, no_sequences

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


# -- checkpoints --------------------------------------------------------------------------------
def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def training_options(spec: MethodSpec) -> Any:
    """``spec``'s options with its class's ``inference_options`` at their defaults: the
    options its weights depend on."""
    from dataclasses import MISSING, fields, replace

    names = set(getattr(spec.cls, "inference_options", ()))
    if not names:
        return spec.options
    known = {f.name: f for f in fields(spec.options)}
    unknown = sorted(names - set(known))
    if unknown:
        raise PcfbenchError(f"method {spec.name!r}: inference_options names {', '.join(unknown)}, "
                            f"which its options do not have")
    defaults = {n: known[n].default if known[n].default is not MISSING else known[n].default_factory()
                for n in names}
    return replace(spec.options, **defaults)


def checkpoint_options_hash(spec: MethodSpec) -> str:
    """The options hash that names ``spec``'s checkpoints: that of :func:`training_options`
    (``spec.options_hash`` when the method has no ``inference_options``)."""
    opts = training_options(spec)
    return spec.options_hash if opts == spec.options else options_hash(opts)


def checkpoint_dir(spec: MethodSpec, train_on: TrainOn) -> Path:
    """``<cache>/checkpoints/<method>/v<version>/<options hash>/<dataset>.<split>.<data key>``."""
    return checkpoint_dir_base(spec) / train_on.key


@dataclass
class Checkpoint:
    """A verified checkpoint folder: its manifest, and the sha256 of its weights."""

    dir: Path
    manifest: dict[str, Any]

    @property
    def manifest_path(self) -> Path:
        return self.dir / MANIFEST

    @property
    def weights_path(self) -> Path:
        return self.dir / self.manifest["weights"]

    @property
    def sha256(self) -> str:
        return self.manifest["weights_sha256"]

    @property
    def steps(self) -> int:
        return int(self.manifest["steps"])

    @property
    def train_on(self) -> dict[str, Any]:
        return self.manifest["train_on"]

    @property
    def train_on_label(self) -> str:
        return f"{self.train_on['dataset']}:{self.train_on['split']}"

    @classmethod
    def open(cls, path: str | Path) -> "Checkpoint":
        """The checkpoint at ``path`` (its folder, its manifest.json or its weights file),
        its files checked against the manifest's sha256."""
        path = Path(path)
        folder = path if path.is_dir() else path.parent
        manifest_path = folder / MANIFEST
        if not manifest_path.is_file():
            raise CheckpointError(f"no checkpoint at {path}: {manifest_path} does not exist")
        try:
            manifest = json.loads(manifest_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise CheckpointError(f"checkpoint manifest {manifest_path} is not valid JSON ({exc})") from None
        missing = [k for k in ("format", "method", "method_version", "options_hash", "train_on", "steps", "weights",
                               "weights_sha256") if k not in (manifest if isinstance(manifest, dict) else {})]
        if missing:
            raise CheckpointError(f"checkpoint manifest {manifest_path} lacks {', '.join(missing)}")
        if manifest["format"] != FORMAT:
            raise CheckpointError(f"checkpoint manifest {manifest_path} has format {manifest['format']!r}, "
                                  f"this pcfbench reads format {FORMAT}")
        ck = cls(folder, manifest)
        if path.is_file() and path.name != MANIFEST and path.name != manifest["weights"]:
            raise CheckpointError(f"{path} is not the weights file of the checkpoint in {folder} "
                                  f"(its manifest names {manifest['weights']})")
        ck._read_verified(manifest["weights"], manifest["weights_sha256"])
        return ck

    def _read_verified(self, name: str, sha: str) -> bytes:
        p = self.dir / name
        if not p.is_file():
            raise CheckpointError(f"checkpoint file {p} is missing (named by {self.manifest_path})")
        data = p.read_bytes()
        if _sha256(data) != sha:
            raise CheckpointError(f"checkpoint file {p} does not match the sha256 in {self.manifest_path} "
                                  f"({len(data):,} bytes, sha256 {_sha256(data)[:16]}..., expected {sha[:16]}...): "
                                  "it was truncated or altered; retrain it with --fresh")
        return data

    def check_method(self, spec: MethodSpec) -> None:
        """Refuse a checkpoint of another method, version or option set than ``spec``."""
        m = self.manifest
        want = {"method": spec.name, "method_version": str(spec.cls.version),
                "options_hash": checkpoint_options_hash(spec)}
        have = {"method": m.get("method"), "method_version": str(m.get("method_version")), "options_hash": m.get("options_hash")}
        if want != have:
            diff = ", ".join(f"{k} {have[k]!r} (wanted {want[k]!r})" for k in want if want[k] != have[k])
            opts = ",".join(f"{k}={v}" for k, v in sorted((m.get("options") or {}).items()))
            raise CheckpointError(f"checkpoint {self.manifest_path} was made by another method or configuration: {diff}; "
                                  f"it belongs to {m.get('method')}{':' + opts if opts else ''}")

    @property
    def shipped(self) -> bool:
        """Whether this is a checkpoint shipped inside a package (see :func:`ship`)."""
        return bool(self.manifest.get("shipped"))

    def load_weights(self, map_location: Any = "cpu") -> dict[str, Any]:
        """The weights, read once, checked against their sha256 and unpickled with
        ``torch.load(weights_only=True)`` (tensors and plain containers only). Weights stored
        in float16 (``"weights_dtype": "float16"``, shipped checkpoints) come back float32."""
        weights = self._load(self.manifest["weights"], self.sha256, map_location)
        if self.manifest.get("weights_dtype") == "float16":
            import torch

            weights = {k: v.float() if torch.is_tensor(v) and v.dtype == torch.float16 else v for k, v in weights.items()}
        return weights

    def load_state(self, map_location: Any = "cpu") -> dict[str, Any]:
        """The optimiser and RNG state saved beside the weights (to resume training)."""
        if not self.manifest.get("state"):
            raise CheckpointError(f"checkpoint {self.manifest_path} holds no training state to resume from")
        return self._load(self.manifest["state"], self.manifest["state_sha256"], map_location)

    def _load(self, name: str, sha: str, map_location: Any) -> dict[str, Any]:
        import pickle

        import torch

        data = self._read_verified(name, sha)
        try:
            return torch.load(io.BytesIO(data), map_location=map_location, weights_only=True)
        except (pickle.UnpicklingError, RuntimeError, EOFError) as exc:
            raise CheckpointError(f"checkpoint file {self.dir / name} does not load with weights_only=True: "
                                  f"{str(exc).splitlines()[0]}") from None


def find_checkpoint(spec: MethodSpec, train_on: TrainOn) -> Checkpoint | None:
    """The checkpoint of ``spec`` trained on ``train_on``, verified: the one in the cache,
    else the one shipped with the method's package for the same data (:func:`find_shipped`);
    None when there is none."""
    folder = checkpoint_dir(spec, train_on)
    if not (folder / MANIFEST).is_file():
        return find_shipped(spec, train_on)
    ck = Checkpoint.open(folder)
    ck.check_method(spec)
    return ck


def ready_shipped(spec: MethodSpec, dataset: str, split: str = DEFAULT_SPLIT,
                  plugins: Plugins | None = None) -> Checkpoint | None:
    """The shipped checkpoint :func:`find_shipped_by_recipe` finds, unless the cache holds one
    trained here on that dataset and split (:func:`find_checkpoint` then picks by the data)."""
    from pcfbench import config

    names, _ = config.parse_dataset_args((dataset,))
    if len(names) != 1 or trained_here(spec, names[0], split):
        return None
    return find_shipped_by_recipe(spec, dataset, split, plugins)


def may_have_checkpoint(spec: MethodSpec, dataset: str, split: str = DEFAULT_SPLIT) -> bool:
    """Whether any checkpoint of ``spec`` trained on ``dataset``/``split`` exists (in the cache
    or shipped), without opening the data (so a default run does not prepare training data
    for an untrained method)."""
    if trained_here(spec, dataset, split):
        return True
    shipped = shipped_dir(spec, dataset, split)
    return shipped is not None and (shipped / MANIFEST).is_file()


# -- shipped checkpoints ------------------------------------------------------------------------
#: The most all shipped checkpoints of one package may weigh together (bytes).
SHIPPED_LIMIT_BYTES = 16 * 1024 * 1024


def shipped_root(cls: type) -> Path | None:
    """Where the shipped checkpoints of ``cls`` live: its ``shipped_checkpoints``, else
    ``checkpoints/`` beside its module (package data of the method's package)."""
    import sys

    if getattr(cls, "shipped_checkpoints", None) is not None:
        return Path(cls.shipped_checkpoints)
    module = sys.modules.get(cls.__module__)
    path = getattr(module, "__file__", None)
    return None if path is None else Path(path).resolve().parent / "checkpoints"


def shipped_dir(spec: MethodSpec, dataset: str, split: str = DEFAULT_SPLIT) -> Path | None:
    """``<shipped root>/<method>/v<version>/<options hash>/<dataset>.<split>``. The folder is
    not keyed by the data's fingerprint (file times differ on every machine): the shipped
    manifest holds the data's content sha256, checked by :func:`find_shipped`."""
    root = shipped_root(spec.cls)
    return (None if root is None else
            root / spec.name / f"v{spec.cls.version}" / checkpoint_options_hash(spec) / f"{dataset}.{split}")


def find_shipped(spec: MethodSpec, train_on: TrainOn) -> Checkpoint | None:
    """The checkpoint of ``spec`` shipped for ``train_on``'s data, verified like any other
    (sha256 of its weights, method, version and options); None when none is shipped, or when
    the local data differs from the data it was trained on (other options, other content)."""
    return _shipped_for(spec, train_on)[0]


def shipped_mismatch(spec: MethodSpec, train_on: TrainOn) -> str | None:
    """Why the checkpoint of ``spec`` shipped for ``train_on``'s dataset and split is not for
    this data (other root options, or other bytes), or None when none is shipped or it is."""
    return _shipped_for(spec, train_on)[1]


def _shipped_for(spec: MethodSpec, train_on: TrainOn) -> tuple[Checkpoint | None, str | None]:
    ck = _open_shipped(spec, train_on.dataset, train_on.split)
    if ck is None:
        return None, None
    shipped = ck.manifest["shipped"]
    recorded = ck.manifest["train_on"]
    here = json.loads(json.dumps(dict(train_on.dataset_options), default=str))
    if dict(recorded.get("dataset_options") or {}) != here:
        return None, f"it was trained with the dataset options {recorded.get('dataset_options') or {}}, here {here}"
    if recorded.get("fingerprint") != train_on.fingerprint:
        content = train_on.content_sha256()
        if shipped["data_sha256"] != content:
            return None, (f"it was trained on other bytes of {train_on.label} (content sha256 "
                          f"{shipped['data_sha256'][:12]}, here {content[:12]}; a generated dataset's bytes can "
                          f"differ from one CPU to another)")
    return ck, None


def _open_shipped(spec: MethodSpec, dataset: str, split: str) -> Checkpoint | None:
    """The checkpoint of ``spec`` shipped for ``dataset``/``split``, verified (weights sha256,
    method, version, options), or None when none is shipped."""
    folder = shipped_dir(spec, dataset, split)
    if folder is None or not (folder / MANIFEST).is_file():
        return None
    ck = Checkpoint.open(folder)
    ck.check_method(spec)
    shipped = ck.manifest.get("shipped")
    if not isinstance(shipped, dict) or "data_sha256" not in shipped:
        raise CheckpointError(f"shipped checkpoint manifest {ck.manifest_path} lacks shipped.data_sha256")
    return ck


def find_shipped_by_recipe(spec: MethodSpec, dataset: str, split: str = DEFAULT_SPLIT,
                           plugins: Plugins | None = None) -> Checkpoint | None:
    """The checkpoint of ``spec`` shipped for ``dataset`` (``NAME``) and ``split`` when that
    dataset makes its own data at its default root by the very recipe the checkpoint was
    trained on (``shipped.data_recipe_sha256``), without making or reading the data; else
    None (and :func:`find_shipped` matches the data by content).

    The recipe is what the dataset's cache is keyed by, so it names the data as the cache
    does. Its bytes are not compared: they can differ from one CPU to another in the last
    bits of a ray cast (docs/realism.md), and the data is not needed to run the checkpoint."""
    from pcfbench import config

    names, roots = config.parse_dataset_args((dataset,))
    if len(names) != 1 or roots:
        return None
    ck = _open_shipped(spec, names[0], split)
    if ck is None:
        return None
    wanted = ck.manifest["shipped"].get("data_recipe_sha256")
    if not wanted or ck.manifest["train_on"].get("dataset_options"):
        return None
    return ck if data_recipe_sha256(names[0], split, plugins) == wanted else None


def trained_here(spec: MethodSpec, dataset: str, split: str = DEFAULT_SPLIT) -> bool:
    """Whether the cache holds a checkpoint of ``spec`` trained on ``dataset`` (``NAME``) and
    ``split``, on any data fingerprint: one trained here wins over a shipped one."""
    return any(checkpoint_dir_base(spec).glob(f"{dataset}.{split}.*/{MANIFEST}"))


def list_checkpoints(spec: MethodSpec) -> list[dict[str, Any]]:
    """Every checkpoint of ``spec``'s method and version, any options and any data: those in
    the cache (trained here), then those shipped with its package. From each manifest alone
    (no weights read or hashed, so ``ls`` stays fast): ``where`` ("cache" or "shipped"),
    ``train_on`` (``dataset:split``), ``root`` and ``dataset_options`` of the training data,
    ``options`` (those differing from ``spec``'s), ``steps``, ``complete``, ``manifest`` (its
    path); ``error`` for a manifest that does not read."""
    base = f"{spec.name}/v{spec.cls.version}"
    mine = options_dict(training_options(spec))
    folders = [("cache", checkpoint_dir_base(spec).parent)]
    shipped = shipped_root(spec.cls)
    if shipped is not None:
        folders.append(("shipped", shipped / base))
    out = []
    for where, folder in folders:
        for path in sorted(folder.glob(f"*/*/{MANIFEST}")):
            row: dict[str, Any] = {"where": where, "manifest": str(path)}
            try:
                m = json.loads(path.read_text())
                t = m["train_on"]
                row.update(train_on=f"{t['dataset']}:{t['split']}", root=None if where == "shipped" else t.get("root"),
                           dataset_options=dict(t.get("dataset_options") or {}),
                           options={k: v for k, v in (m.get("options") or {}).items() if mine.get(k, v) != v},
                           steps=int(m["steps"]), complete=bool(m.get("complete")))
            except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
                row["error"] = f"its manifest does not read ({type(exc).__name__}: {exc})"
            out.append(row)
    return out


def retrain_command(spec: MethodSpec, dataset: str, split: str, manifest: Mapping[str, Any]) -> str:
    """The ``pcfbench train`` command that rebuilds a checkpoint with this ``manifest``, for its
    shipped copy: the method with the options it was given, the data, and on the CPU the thread
    count it trained with (the weights' rounding depends on it, so that reproduces the bits)."""
    opts = ",".join(f"{k}={v}" for k, v in sorted(spec.raw.items()))
    threads = manifest.get("threads") if manifest.get("device") == "cpu" else None
    return (f"pcfbench train {spec.name}{':' + opts if opts else ''} --dataset {dataset}"
            f"{'' if split == DEFAULT_SPLIT else ' --split ' + split}{f' --threads {threads}' if threads else ''}"
            " --fresh --ship")


def ship(spec: MethodSpec, checkpoint: Checkpoint, train_on: TrainOn, retrain: str, log=print) -> Checkpoint:
    """Copy a complete ``checkpoint`` of ``spec`` into the method's package
    (:func:`shipped_dir`): weights cast to float16, no optimiser state, a manifest that
    keeps the trained one's record (config, training data and fingerprint, steps, wall and
    CPU time, device, git commit) plus ``weights_dtype`` and ``shipped`` (the cache
    checkpoint's sha256, the data's content sha256, ``retrain``: the command that rebuilds
    it). Refused for an incomplete checkpoint, or when the package's shipped checkpoints
    would weigh more than ``SHIPPED_LIMIT_BYTES``."""
    import torch

    from pcfbench.store import atomic_write_bytes, atomic_write_json

    checkpoint.check_method(spec)
    if not checkpoint.manifest.get("complete"):
        raise CheckpointError(f"checkpoint {checkpoint.manifest_path} is not complete ({checkpoint.steps} steps): "
                              "finish its training before shipping it")
    folder = shipped_dir(spec, train_on.dataset, train_on.split)
    if folder is None:
        raise CheckpointError(f"method {spec.name!r} has no package folder to ship a checkpoint into")
    weights = checkpoint.load_weights()
    half = {k: v.half() if torch.is_tensor(v) and v.dtype == torch.float32 else v for k, v in weights.items()}
    buf = io.BytesIO()
    torch.save(half, buf)
    data = buf.getvalue()
    root = shipped_root(spec.cls)
    others = sum(f.stat().st_size for f in root.rglob("*") if f.is_file() and folder not in f.parents) if root.is_dir() else 0
    if others + len(data) > SHIPPED_LIMIT_BYTES:
        raise CheckpointError(f"shipping {spec.name} ({len(data):,} bytes) into {root} would exceed "
                              f"{SHIPPED_LIMIT_BYTES:,} bytes of shipped checkpoints ({others:,} there already)")
    if folder.is_dir():
        for old in folder.iterdir():
            if old.is_file():
                old.unlink()
    folder.mkdir(parents=True, exist_ok=True)
    name = f"weights-{checkpoint.steps:08d}.fp16.pt"
    atomic_write_bytes(folder / name, data)
    manifest = {k: v for k, v in checkpoint.manifest.items() if k not in ("state", "state_sha256")}
    manifest.update(weights=name, weights_sha256=_sha256(data), weights_dtype="float16", state=None, state_sha256=None)
    manifest["shipped"] = {"from_weights_sha256": checkpoint.sha256, "data_sha256": train_on.content_sha256(),
                           "retrain": retrain, "shipped": time.time()}
    if train_on.recipe is not None:
        manifest["shipped"]["data_recipe_sha256"] = train_on.recipe
    atomic_write_json(folder / MANIFEST, manifest)
    log(f"shipped {spec.name} ({len(data):,} bytes of float16 weights) to {folder}")
    return Checkpoint.open(folder)


def checkpoint_dir_base(spec: MethodSpec) -> Path:
    """``<cache>/checkpoints/<method>/v<version>/<options hash>``: the checkpoints of ``spec``
    (the hash of its training options, :func:`checkpoint_options_hash`)."""
    from pcfbench.config import cache_dir

    return cache_dir() / "checkpoints" / spec.name / f"v{spec.cls.version}" / checkpoint_options_hash(spec)


def is_trained(cls: type) -> bool:
    return isinstance(cls, type) and issubclass(cls, TrainedMethod)


def estimate_training(spec: MethodSpec) -> str:
    """How long a full training of ``spec`` takes on this machine: from the manifests of
    earlier trainings of the same method and options (wall seconds per step times the
    method's ``training_steps``), else the figure the method states."""
    steps = spec.create().training_steps()
    rates = []
    for mf in checkpoint_dir_base(spec).glob(f"*/{MANIFEST}"):
        try:
            m = json.loads(mf.read_text())
            if m.get("steps"):
                rates.append(float(m["wall_s"]) / int(m["steps"]))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    if rates and steps:
        minutes = max(rates) * steps / 60
        return f"about {minutes:.0f} min on this machine ({steps} steps at {max(rates):.2f} s/step, measured by earlier trainings)"
    return spec.cls.training_time or "an unknown time (no earlier training of it on this machine)"


def missing_checkpoint_message(spec: MethodSpec, train_on: TrainOn) -> str:
    opts = ",".join(f"{k}={v}" for k, v in sorted(spec.raw.items()))
    method = spec.name + (f":{opts}" if opts else "")
    data = train_on.dataset + (f"={train_on.root}" if train_on.root and train_on.dataset not in _embedded() else "")
    split = "" if train_on.split == DEFAULT_SPLIT else f" --split {train_on.split}"
    return (f"no checkpoint of {method} trained on {train_on.label} (looked in {checkpoint_dir(spec, train_on)}): "
            f"train it with `pcfbench train {method} --dataset {data}{split}`, which takes {estimate_training(spec)}")


def _embedded() -> set[str]:
    from pcfbench.plugins import get_plugins

    reg = get_plugins().datasets
    out = set()
    for n in reg.names():
        try:
            if getattr(reg.get(n), "embedded", False):
                out.add(n)
        except PcfbenchError:
            continue
    return out


def checkpoint_for(spec: MethodSpec, *, checkpoint: str | Path | None = None, train_on: str | None = None,
                   split: str = DEFAULT_SPLIT, plugins: Plugins | None = None, progress: bool = True,
                   split_option: str = "--train-split {}") -> Checkpoint:
    """The checkpoint a run of ``spec`` evaluates: the file ``checkpoint`` (verified, and of
    this method and options), else the one trained on ``train_on`` (default: the method's
    ``default_train_on``) and ``split``; a missing one is one error saying how to train it.
    ``split_option``: how the caller's user picks the training split (``{}``: the split)."""
    if checkpoint is not None:
        ck = Checkpoint.open(checkpoint)
        ck.check_method(spec)
        return ck
    data = train_on or spec.cls.default_train_on
    ck = ready_shipped(spec, data, split, plugins)
    if ck is not None:
        return ck
    source = open_training_data(data, split, plugins, progress, split_option)
    ck = find_checkpoint(spec, source.train_on)
    if ck is None:
        raise CheckpointError(missing_checkpoint_message(spec, source.train_on))
    return ck


# -- the training run handed to fit ---------------------------------------------------------------
class TrainingRun:
    """What ``fit`` gets as ``progress``: where to save, what to resume from, when to stop
    (the ``--max-minutes`` budget) and a progress bar.

    ``fit`` calls :meth:`resume` once (None, or the last saved ``{"step", "weights", "state"}``),
    :meth:`start` with its total steps, :meth:`update` after each step, :meth:`save` every so
    often and at the end, and stops early when :meth:`should_stop` says so.
    """

    def __init__(self, spec: MethodSpec, train_on: TrainOn, out_dir: Path, *, max_minutes: float | None = None,
                 fresh: bool = False, progress: bool = True, device: str = "cpu", threads: int | None = None,
                 log=print) -> None:
        self.spec = spec
        self.train_on = train_on
        self.out_dir = Path(out_dir)
        self.max_minutes = max_minutes
        self.fresh = fresh
        self.show = progress
        self.device = device
        #: the thread budget ``fit`` runs under (``pcfbench train --threads``; :func:`train` has
        #: applied it to torch, numba and the BLAS libraries), recorded in the manifest; None
        #: where no budget was applied (a run made outside :func:`train`): not recorded
        self.threads = threads
        self.log = log
        self._t0 = time.monotonic()
        self._c0 = time.process_time()
        self._base_wall = 0.0
        self._base_cpu = 0.0
        self._created = time.time()
        self._bar = None
        self._lines = False  # progress as log lines (off a terminal)
        self._last_line = 0.0
        self._steps = 0
        self._initial = 0
        #: the steps of the whole training (``start``); None before
        self.total: int | None = None
        self.saved_steps: int | None = None

    # resume -----------------------------------------------------------------------------------
    def resume(self) -> dict[str, Any] | None:
        """The last checkpoint's step, weights and state, or None (nothing saved, or ``--fresh``)."""
        if self.fresh or not (self.out_dir / MANIFEST).is_file():
            return None
        ck = Checkpoint.open(self.out_dir)
        ck.check_method(self.spec)
        if ck.manifest["train_on"].get("fingerprint") != self.train_on.fingerprint:
            raise CheckpointError(f"checkpoint {ck.manifest_path} was trained on other data than {self.train_on.label} "
                                  "has now; rerun with --fresh")
        had = ck.manifest.get("device", self.device)
        if had != self.device:  # other numerics and RNG streams: the resumed curve would not be the one it continues
            raise CheckpointError(f"checkpoint {ck.manifest_path} was trained on {had} and this run would resume "
                                  f"it on {self.device}; resume it where it was trained, or rerun with --fresh")
        had = ck.manifest.get("threads")  # unrecorded before the thread budget was (2026-11-26)
        if self.device == "cpu" and None not in (had, self.threads) and had != self.threads:
            # a matrix product cut over another number of threads rounds differently: the resumed
            # curve would drift from the one it continues (measured: 1e-7 at step 10, 1e-5 at 100)
            raise CheckpointError(f"checkpoint {ck.manifest_path} was trained with {had} CPU threads and this run "
                                  f"has {self.threads}; resume it with --threads {had}, or rerun with --fresh")
        self._base_wall = float(ck.manifest.get("wall_s", 0.0))
        self._base_cpu = float(ck.manifest.get("cpu_s", 0.0))
        self._created = ck.manifest.get("created", self._created)
        self.saved_steps = ck.steps
        self.log(f"resuming {ck.dir} at step {ck.steps}")
        return {"step": ck.steps, "weights": ck.load_weights(), "state": ck.load_state()}

    # budget and progress -------------------------------------------------------------------------
    def elapsed_s(self) -> float:
        return time.monotonic() - self._t0

    def should_stop(self) -> bool:
        """True once the time budget is spent (each call trains at least one step)."""
        return self.max_minutes is not None and self._steps > 0 and self.elapsed_s() > 60 * self.max_minutes

    @property
    def step(self) -> int | None:
        """The steps trained so far, the resumed ones included (None before :meth:`start`)."""
        return None if self.total is None else self._initial + self._steps

    def start(self, total: int, initial: int = 0) -> None:
        """Steps of the whole training and those already trained; shows the progress: a bar on
        a terminal, else a log line every ``LOG_EVERY_S`` seconds and at the last step."""
        self.total, self._initial = int(total), int(initial)
        if self.show and not os.environ.get("PCFBENCH_NO_PROGRESS"):
            import sys

            if sys.stderr.isatty():
                from tqdm import tqdm

                self._bar = tqdm(total=total, initial=initial, desc=f"train {self.spec.name}", unit="step",
                                 dynamic_ncols=True)
            else:  # a bar redrawn in a log file floods it
                self._lines = True
                self._last_line = -LOG_EVERY_S  # the first step's line says it started, and how fast

    def update(self, steps: int = 1, **metrics: float) -> None:
        """``steps`` more trained; ``metrics``: the values to show, by their label."""
        self._steps += steps
        if self._bar is not None:
            if metrics:
                self._bar.set_postfix({k: f"{v:.4g}" for k, v in metrics.items()}, refresh=False)
            self._bar.update(steps)
        elif self._lines:
            now = time.monotonic()
            if now - self._last_line >= LOG_EVERY_S or self.step == self.total:
                self._last_line = now
                self.log(self._progress_line(metrics))

    def _progress_line(self, metrics: Mapping[str, float]) -> str:
        """``train NAME: step 40/1200 (3%), 0.81 s/step, 16 min left; loss 0.1234, ...``."""
        step, total = self.step, self.total
        per_step = self.elapsed_s() / max(1, self._steps)
        left = max(0, total - step) * per_step
        eta = f"{left / 60:.0f} min" if left >= 90 else f"{left:.0f} s"
        values = "; " + ", ".join(f"{k} {v:.4g}" for k, v in metrics.items()) if metrics else ""
        return (f"train {self.spec.name}: step {step}/{total} ({100 * step / max(1, total):.0f}%), "
                f"{per_step:.3g} s/step, {eta} left{values}")

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    # save -----------------------------------------------------------------------------------------
    def save(self, step: int, weights: Mapping[str, Any], state: Mapping[str, Any] | None = None, *,
             config: Mapping[str, Any] | None = None, complete: bool = False) -> Checkpoint:
        """Write ``weights`` (tensors) and ``state`` (to resume: optimiser, RNG, curve) for
        ``step``, then the manifest naming them; older files go. Both must load with
        ``torch.load(weights_only=True)``. ``config``: what the method adds to the manifest
        (e.g. its network sizes)."""
        import torch

        from pcfbench.provenance import git_commit
        from pcfbench.store import atomic_write_bytes, atomic_write_json

        self.out_dir.mkdir(parents=True, exist_ok=True)
        files = {}
        # weights on the CPU whatever the training device: a checkpoint trained on a GPU has
        # the bytes (and the sha256) of the same tensors trained anywhere, and loads anywhere
        weights = {k: v.detach().cpu() if isinstance(v, torch.Tensor) else v for k, v in weights.items()}
        for kind, obj in (("weights", weights), ("state", None if state is None else dict(state))):
            if obj is None:
                continue
            buf = io.BytesIO()
            torch.save(obj, buf)
            data = buf.getvalue()
            name = f"{kind}-{step:08d}.pt"
            atomic_write_bytes(self.out_dir / name, data)
            files[kind] = (name, _sha256(data))
        manifest = {
            "format": FORMAT,
            "method": self.spec.name,
            "method_version": str(self.spec.cls.version),
            "options": options_dict(training_options(self.spec)),
            "options_hash": checkpoint_options_hash(self.spec),
            "config": dict(config or {}),
            "train_on": self.train_on.to_meta(),
            "steps": int(step),
            "complete": bool(complete),
            "wall_s": round(self._base_wall + self.elapsed_s(), 3),
            "cpu_s": round(self._base_cpu + time.process_time() - self._c0, 3),
            "device": self.device,
            **({"threads": self.threads} if self.threads is not None else {}),
            "torch": torch.__version__,
            "git_commit": git_commit(),
            "weights": files["weights"][0],
            "weights_sha256": files["weights"][1],
            "state": files["state"][0] if "state" in files else None,
            "state_sha256": files["state"][1] if "state" in files else None,
            "created": self._created,
            "updated": time.time(),
        }
        atomic_write_json(self.out_dir / MANIFEST, manifest)
        keep = {name for name, _ in files.values()}
        for old in list(self.out_dir.glob("weights-*.pt")) + list(self.out_dir.glob("state-*.pt")):
            if old.name not in keep:
                old.unlink(missing_ok=True)
        self.saved_steps = step
        return Checkpoint(self.out_dir, manifest)


# -- the contract -------------------------------------------------------------------------------
class TrainedMethod(Method):
    """A method that learns. Subclasses implement ``fit`` and ``load`` besides ``forecast``.

    A trained method runs only with a checkpoint: ``pcfbench run`` evaluates the one trained
    on ``--train-on`` (default ``default_train_on``, split ``train``) or the file given with
    ``--checkpoint``, and the default run includes the method only when that checkpoint
    exists. Its cells carry the checkpoint's sha256 and training data.
    """

    #: The training data of the default run (an embedded dataset, so it exists everywhere).
    default_train_on: ClassVar[str] = "synthetic-town-realistic"
    #: How long a full training takes, stated for the missing-checkpoint message when no
    #: earlier training on this machine measured it.
    training_time: ClassVar[str] = ""
    #: The folder of the checkpoints it ships (pcfbench train --ship); None: ``checkpoints/``
    #: beside the method's module, installed as package data.
    shipped_checkpoints: ClassVar[str | Path | None] = None
    #: Options that change only how a checkpoint forecasts, never its weights (a sampler's
    #: seed, a rendering threshold): left out of the checkpoint's identity
    #: (:func:`checkpoint_options_hash`), so every value of them evaluates the one checkpoint
    #: trained with the others. A result still records every option it ran with.
    inference_options: ClassVar[tuple[str, ...]] = ()

    checkpoint: Checkpoint | None = None

    @abstractmethod
    def fit(self, train_source: TrainSource, out_dir: Path, progress: TrainingRun) -> None:
        """Train on ``train_source``, saving through ``progress.save`` periodically and at the
        end; start from ``progress.resume()`` when it returns a state (continuing the same
        curve: same data order, same random draws); stop early when ``progress.should_stop()``."""

    @abstractmethod
    def load(self, checkpoint: Checkpoint) -> None:
        """Take the weights of ``checkpoint`` (already verified and of this method and options)."""

    def training_steps(self) -> int | None:
        """Steps of a full training with these options (for the time estimate), if known."""
        return None


# -- the driver -------------------------------------------------------------------------------------
def train(spec: MethodSpec, dataset: str, *, split: str = DEFAULT_SPLIT, max_minutes: float | None = None,
          fresh: bool = False, progress: bool = True, plugins: Plugins | None = None, threads: int | None = None,
          log=print) -> Checkpoint:
    """Train (or resume) ``spec`` on ``dataset`` (``NAME[=ROOT]``) ``split``; returns the checkpoint.

    ``fit`` runs under a budget of ``threads`` CPU threads (default: every CPU this process may
    use), applied to torch, numba and the BLAS libraries for its duration and recorded in the
    manifest. The weights depend on it (float sums cut differently), not the checkpoint's
    identity: a resumed run must use the count it started with."""
    from pcfbench.execution import ExecutionContext, applied

    if not is_trained(spec.cls):
        raise PcfbenchError(f"method {spec.name!r} does not train (it is not a pcfbench.TrainedMethod)")
    source = open_training_data(dataset, split, plugins, progress)
    out = checkpoint_dir(spec, source.train_on)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / ".lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise PcfbenchError(f"checkpoint {out} is being trained by another pcfbench process") from None
        if fresh:
            for old in [*out.glob("*.pt"), out / MANIFEST]:
                old.unlink(missing_ok=True)
        elif (out / MANIFEST).is_file():
            ck = Checkpoint.open(out)
            if ck.manifest.get("complete"):  # nothing left to train (inference options may differ)
                ck.check_method(spec)
                log(f"{spec.name}: {out} is complete ({ck.steps} steps); --fresh trains it again")
                return ck
        device = "cuda" if _cuda() else "cpu"
        context = ExecutionContext(threads) if threads else ExecutionContext()
        run = TrainingRun(spec, source.train_on, out, max_minutes=max_minutes, fresh=fresh, progress=progress,
                          device=device, threads=context.threads, log=log)
        method = spec.create()
        try:
            with applied(context):
                method.fit(source, out, run)
        except KeyboardInterrupt:
            run.close()  # the bar ends before anything says why
            raise TrainingInterrupted(out, run.step, run.total, _saved_step(out)) from None
        finally:
            run.close()
    if run.saved_steps is None:
        raise PcfbenchError(f"method {spec.name!r} finished fit without saving a checkpoint in {out}")
    ck = Checkpoint.open(out)
    ck.check_method(spec)
    return ck


def _saved_step(folder: Path) -> int | None:
    """The step of the checkpoint in ``folder`` as its manifest on the disk says (None: none)."""
    try:
        steps = json.loads((folder / MANIFEST).read_text()).get("steps")
    except (OSError, ValueError, AttributeError):
        return None
    return steps if isinstance(steps, int) else None


def _cuda() -> bool:
    import sys

    torch = sys.modules.get("torch")
    if torch is None:
        import torch
    return bool(torch.cuda.is_available())
