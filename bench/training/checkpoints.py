"""Checkpoints with identity: the cache's, verified on opening, and those shipped inside a
method's package (the layout is described in :mod:`pcfbench.training`)."""

from __future__ import annotations

import hashlib
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from pcfbench.errors import PcfbenchError
from pcfbench.method import MethodSpec, options_dict, options_hash
from pcfbench.training.data import DEFAULT_SPLIT, TrainOn, data_recipe_sha256, open_training_data

if TYPE_CHECKING:  # pragma: no cover
    from pcfbench.plugins import Plugins

FORMAT = 1
MANIFEST = "manifest.json"


class CheckpointError(PcfbenchError):
    """A checkpoint that is missing, unreadable, altered or made by something else."""


# -- checkpoints --------------------------------------------------------------------------------
def sha256_hex(data: bytes) -> str:
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
        if sha256_hex(data) != sha:
            raise CheckpointError(f"checkpoint file {p} does not match the sha256 in {self.manifest_path} "
                                  f"({len(data):,} bytes, sha256 {sha256_hex(data)[:16]}..., expected {sha[:16]}...): "
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
#: The most all shipped checkpoints of one import package (one distribution) may weigh together (bytes).
# 40 MiB (16 until the BEVWorld world model shipped, 24 until Copilot4D's two world models and
# their tiny-window tokenizer did, 32 until copilot4d's one network per horizon did: each issue
# that ships a world model asks for its tiny checkpoint, and the tiny world models are 1-4 M
# parameters, 2-7 MB in float16)
SHIPPED_LIMIT_BYTES = 40 * 1024 * 1024


def shipped_root(cls: type) -> Path | None:
    """Where the shipped checkpoints of ``cls`` live: its ``shipped_checkpoints``, else
    ``checkpoints/`` beside its module (package data of the method's package)."""
    import sys

    if getattr(cls, "shipped_checkpoints", None) is not None:
        return Path(cls.shipped_checkpoints)
    module = sys.modules.get(cls.__module__)
    path = getattr(module, "__file__", None)
    return None if path is None else Path(path).resolve().parent / "checkpoints"


def shipped_files(cls: type) -> list[Path]:
    """Every file of the shipped checkpoints of the import package ``cls`` belongs to (its
    top-level package: all of pcfbench for a built-in method, whose method packages live in
    other folders than ``pcfbench`` itself in an editable install), plus ``cls``'s own
    ``shipped_checkpoints``: what one installed distribution carries."""
    import sys

    top = cls.__module__.split(".")[0]
    dirs = {Path(m.__file__).resolve().parent for name, m in list(sys.modules.items())  # packages only: a
            if (name == top or name.startswith(top + "."))  # lone module's folder may be site-packages
            and getattr(m, "__path__", None) is not None and getattr(m, "__file__", None)}
    outer = {d for d in dirs if not any(o in d.parents for o in dirs)}
    roots = {c for d in outer for c in d.rglob("checkpoints") if c.is_dir()}
    own = shipped_root(cls)
    if own is not None and own.is_dir() and not any(r == own or r in own.parents for r in roots):
        roots.add(own)
    return sorted({f for r in roots for f in r.rglob("*") if f.is_file()})


def shipped_dir(spec: MethodSpec, dataset: str, split: str = DEFAULT_SPLIT) -> Path | None:
    """``<shipped root>/<method>/v<version>/<options hash>/<dataset>.<split>``. The folder is
    not keyed by the data's fingerprint (a generated split's bytes differ by CPU, and older
    manifests record file times): the shipped manifest holds the data's content sha256,
    checked by :func:`find_shipped`."""
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
    # as a manifest holds them (JSON: a tuple option reads back as a list), so equal values compare equal
    mine = json.loads(json.dumps(options_dict(training_options(spec)), default=str))
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
    threads = manifest.get("threads") if manifest.get("device") == "cpu" else None
    return (f"pcfbench train {spec.text()} --dataset {dataset}"
            f"{'' if split == DEFAULT_SPLIT else ' --split ' + split}{f' --threads {threads}' if threads else ''}"
            " --fresh --ship")


def ship(spec: MethodSpec, checkpoint: Checkpoint, train_on: TrainOn, retrain: str, log=print) -> Checkpoint:
    """Copy a complete ``checkpoint`` of ``spec`` into the method's package
    (:func:`shipped_dir`): weights cast to float16, no optimiser state, a manifest that
    keeps the trained one's record (config, training data and fingerprint, steps, wall and
    CPU time, device, git commit) plus ``weights_dtype`` and ``shipped`` (the cache
    checkpoint's sha256, the data's content sha256, ``retrain``: the command that rebuilds
    it; ``left_out``: where the method finds tensors it did not ship,
    ``TrainedMethod.shipped_weights``). Refused for an incomplete checkpoint, or when the package's shipped checkpoints
    would weigh more than ``SHIPPED_LIMIT_BYTES``."""
    import torch

    from pcfbench.store.cells import atomic_write_bytes, atomic_write_json

    checkpoint.check_method(spec)
    if not checkpoint.manifest.get("complete"):
        raise CheckpointError(f"checkpoint {checkpoint.manifest_path} is not complete ({checkpoint.steps} steps): "
                              "finish its training before shipping it")
    folder = shipped_dir(spec, train_on.dataset, train_on.split)
    if folder is None:
        raise CheckpointError(f"method {spec.name!r} has no package folder to ship a checkpoint into")
    weights, left_out = spec.create().shipped_weights(checkpoint, checkpoint.load_weights())
    half = {k: v.half() if torch.is_tensor(v) and v.dtype == torch.float32 else v for k, v in weights.items()}
    buf = io.BytesIO()
    torch.save(half, buf)
    data = buf.getvalue()
    top = spec.cls.__module__.split(".")[0]
    others = sum(f.stat().st_size for f in shipped_files(spec.cls) if folder not in f.parents)
    if others + len(data) > SHIPPED_LIMIT_BYTES:
        raise CheckpointError(f"shipping {spec.name} ({len(data):,} bytes) into {folder} would exceed "
                              f"{SHIPPED_LIMIT_BYTES:,} bytes of shipped checkpoints in package {top} ({others:,} "
                              "there already)")
    if folder.is_dir():
        for old in folder.iterdir():
            if old.is_file():
                old.unlink()
    folder.mkdir(parents=True, exist_ok=True)
    name = f"weights-{checkpoint.steps:08d}.fp16.pt"
    atomic_write_bytes(folder / name, data)
    manifest = {k: v for k, v in checkpoint.manifest.items() if k not in ("state", "state_sha256")}
    manifest.update(weights=name, weights_sha256=sha256_hex(data), weights_dtype="float16", state=None, state_sha256=None)
    manifest["shipped"] = {"from_weights_sha256": checkpoint.sha256, "data_sha256": train_on.content_sha256(),
                           "retrain": retrain, "shipped": time.time()}
    if train_on.recipe is not None:
        manifest["shipped"]["data_recipe_sha256"] = train_on.recipe
    if left_out:
        manifest["shipped"]["left_out"] = left_out
    atomic_write_json(folder / MANIFEST, manifest)
    log(f"shipped {spec.name} ({len(data):,} bytes of float16 weights) to {folder}")
    return Checkpoint.open(folder)


def checkpoint_dir_base(spec: MethodSpec) -> Path:
    """``<cache>/checkpoints/<method>/v<version>/<options hash>``: the checkpoints of ``spec``
    (the hash of its training options, :func:`checkpoint_options_hash`)."""
    from pcfbench.config import cache_dir

    return cache_dir() / "checkpoints" / spec.name / f"v{spec.cls.version}" / checkpoint_options_hash(spec)


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
    stated = spec.cls.training_time
    if not stated:
        return "an unknown time (no earlier training of it on this machine)"
    try:  # the stated figure is for the method's default options: say so when these train another count
        default = spec.cls(type(spec.options)()).training_steps()
    except (PcfbenchError, TypeError, ValueError):  # options without a default set: the stated figure alone
        default = None
    if steps and default and steps != default:
        return f"{stated}; that figure is for {default} steps, these options train {steps}"
    return stated


def dataset_argument(train_on: TrainOn) -> str:
    """The ``--dataset`` argument that opens ``train_on``'s data again: ``NAME``, or ``NAME=ROOT``
    (with its root options) for a dataset that is not embedded."""
    return train_on.dataset + (f"={train_on.root}" if train_on.root and train_on.dataset not in _embedded() else "")


def missing_checkpoint_message(spec: MethodSpec, train_on: TrainOn) -> str:
    method = spec.text()
    data = dataset_argument(train_on)
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


