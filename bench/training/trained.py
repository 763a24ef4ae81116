"""The contract of a method that learns (:class:`TrainedMethod`), the run handed to its
``fit`` (:class:`TrainingRun`) and the one training driver (:func:`train`)."""

from __future__ import annotations

import fcntl
import io
import json
import os
import time
from abc import abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Mapping

from pcfbench.dataset import FINGERPRINT_KIND
from pcfbench.errors import PcfbenchError
from pcfbench.method import Method, MethodSpec, options_dict
from pcfbench.training.checkpoints import (FORMAT, MANIFEST, Checkpoint, CheckpointError, checkpoint_dir,
                                           checkpoint_options_hash, sha256_hex, training_options)
from pcfbench.training.data import DEFAULT_SPLIT, TrainOn, TrainSource, open_training_data

if TYPE_CHECKING:  # pragma: no cover
    from pcfbench.plugins import Plugins

#: Off a terminal, training progress is a log line this often (seconds), not a bar.
LOG_EVERY_S = 30.0


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

def is_trained(cls: type) -> bool:
    return isinstance(cls, type) and issubclass(cls, TrainedMethod)




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
        self._train_shas: list[str] | None = None

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
    def count_time(self, wall_s: float, cpu_s: float) -> None:
        """Count time spent on this checkpoint outside this run (trainings whose weights it puts
        together) in the ``wall_s`` and ``cpu_s`` its manifest records."""
        self._base_wall += float(wall_s)
        self._base_cpu += float(cpu_s)

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
    def _train_files_sha256(self) -> list[str]:
        """The training files' content hashes (:mod:`pcfbench.training.claims`), read once per run:
        what lets a cell tell its evaluated data is this data, whatever its name."""
        if self._train_shas is None:
            from pcfbench.training.claims import train_files_sha256

            self._train_shas = train_files_sha256(self.train_on.files)
        return self._train_shas

    def save(self, step: int, weights: Mapping[str, Any], state: Mapping[str, Any] | None = None, *,
             config: Mapping[str, Any] | None = None, complete: bool = False) -> Checkpoint:
        """Write ``weights`` (tensors) and ``state`` (to resume: optimiser, RNG, curve) for
        ``step``, then the manifest naming them; older files go. Both must load with
        ``torch.load(weights_only=True)``. ``config``: what the method adds to the manifest
        (e.g. its network sizes)."""
        import torch

        from pcfbench.provenance import git_commit
        from pcfbench.store.cells import atomic_write_bytes, atomic_write_json

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
            files[kind] = (name, sha256_hex(data))
        manifest = {
            "format": FORMAT,
            "method": self.spec.name,
            "method_version": str(self.spec.cls.version),
            "options": options_dict(training_options(self.spec)),
            "options_hash": checkpoint_options_hash(self.spec),
            "config": dict(config or {}),
            "train_on": {**self.train_on.to_meta(), "fingerprint_kind": FINGERPRINT_KIND},
            "train_files_sha256": self._train_files_sha256(),
            "steps": int(step),
            "steps_planned": self.total,
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

    def shipped_weights(self, checkpoint: Checkpoint, weights: dict) -> tuple[dict, dict | None]:
        """What ``pcfbench train --ship`` puts in the package from ``checkpoint``'s ``weights``:
        the tensors to ship and, when some are left out, a record of where ``load`` finds them
        (written to the shipped manifest as ``shipped.left_out``). Default: every tensor. A
        method whose checkpoint holds a copy of another shipped checkpoint (a world model's
        tokenizer) may leave the copy out and load it from there."""
        return weights, None


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
