"""The one training loop of the trained methods, and the generic pieces it uses.

A trained method's ``fit`` hands :func:`fit_loop` what is its own: how to build the model and
its optimiser, how to draw a batch (``sample_batch(rand, step)``, from the loop's random
streams) and one step's loss (``step_fn(model, batch)`` -> ``(loss tensor, logged floats)``).
The loop owns everything else, the same for every method:

* seeding: ``torch.manual_seed(seed)`` before the model is built (so the initial weights are
  the seed's), a numpy ``Generator`` seeded with ``seed`` and, when asked, a torch
  ``Generator`` on the model's device seeded with ``seed + 1`` (:class:`Randoms`);
* resume from what :meth:`~pcfbench.training.TrainingRun.resume` gives: weights, optimiser,
  every random stream, the curve so far (history and the unfinished averaging window), wall
  and CPU time; a resumed run draws the same batches and continues the same curve;
* the learning-rate schedule, autocast (bf16 on CUDA), zero_grad / backward / gradient-norm
  clipping / optimiser step, an ``after_step`` hook (e.g. re-initialising a codebook);
* timing (wall, including the GPU's queued work, and CPU), averaging each ``log_every``
  steps into the history, the progress bar's values, saves every ``checkpoint_every`` steps
  and at the end, and the time budget (``--max-minutes``).

The state it saves beside the weights has one format (:func:`random_state`), and loads with
``torch.load(weights_only=True)``. :func:`write_curve` writes the curve (CSV and PNG).

Nothing here imports torch until it is called, so ``import pcfbench.training`` stays light.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Mapping, Sequence

from pcfbench.errors import PcfbenchError

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np
    import torch
    from torch import nn

__all__ = [
    "LoopResult", "Panel", "Randoms", "STATE_FORMAT", "StateError", "adamw", "autocast", "default_device",
    "fit_loop", "param_groups", "random_state", "restore_random_state", "synchronize", "warmup_cosine",
    "write_curve",
]

#: The format of the resume state :func:`fit_loop` saves (``state["loop_format"]``).
STATE_FORMAT = 1
#: History columns that are timings: never part of a curve's comparison, not averaged.
TIMING_COLUMNS = ("step_s", "elapsed_s", "cpu_s")


class StateError(PcfbenchError):
    """A saved training state this loop cannot resume from."""


# -- generic pieces -------------------------------------------------------------------------------
def default_device() -> "torch.device":
    """CUDA when available, else the CPU."""
    import torch

    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def autocast(device: "torch.device"):
    """bf16 autocast on CUDA, nothing on the CPU."""
    import torch

    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def synchronize(device: "torch.device") -> None:
    """Wait for the GPU's queued work, so a step's wall time includes its backward pass."""
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def param_groups(model: "nn.Module", weight_decay: float) -> list[dict]:
    """Weight decay on the weight matrices of ``nn.Linear`` layers only; biases, embeddings,
    normalisation parameters and every other parameter are excluded."""
    from torch import nn

    decay, no_decay = [], []
    for _, mod in model.named_modules():
        for name, p in mod.named_parameters(recurse=False):
            if not p.requires_grad:
                continue
            if isinstance(mod, nn.Linear) and name == "weight":
                decay.append(p)
            else:
                no_decay.append(p)
    return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]


def adamw(model: "nn.Module", lr: float, betas: tuple[float, float], weight_decay: float) -> "torch.optim.Optimizer":
    """AdamW over :func:`param_groups`."""
    import torch

    return torch.optim.AdamW(param_groups(model, weight_decay), lr=lr, betas=betas)


def warmup_cosine(step: int, lr: float, warmup: int, decay_steps: int, min_lr_ratio: float) -> float:
    """Learning rate at ``step`` (0-based): linear warm-up to ``lr`` over ``warmup`` steps, then
    cosine decay until ``decay_steps`` to ``min_lr_ratio * lr``, constant after."""
    if step < warmup:
        return lr * (step + 1) / warmup
    t = min(1.0, (step - warmup) / max(1, decay_steps - warmup))
    return lr * (min_lr_ratio + (1 - min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


# -- random streams ------------------------------------------------------------------------------
@dataclass
class Randoms:
    """The random streams the loop owns: ``numpy`` (a ``np.random.Generator``, seeded with the
    loop's seed) and ``torch`` (a ``torch.Generator`` on the model's device seeded with
    ``seed + 1``, or None when the method did not ask for one). Torch's global stream (and
    CUDA's, on a GPU) is seeded with ``seed`` and saved too."""

    numpy: "np.random.Generator"
    torch: "torch.Generator | None" = None


def random_state(rand: Randoms, device: "torch.device") -> dict[str, Any]:
    """Every random stream's state, in the one format the loop saves: ``numpy_rng`` the numpy
    bit generator's state as JSON text, ``torch_rng`` torch's global CPU state, ``cuda_rng``
    the global state of ``device`` when it is a GPU, ``torch_gen`` the loop's torch generator
    when there is one (state tensors as they are). Loads with ``weights_only=True``."""
    import torch

    out: dict[str, Any] = {"numpy_rng": json.dumps(rand.numpy.bit_generator.state),
                           "torch_rng": torch.get_rng_state()}
    if device.type == "cuda":
        out["cuda_rng"] = torch.cuda.get_rng_state(device)
    if rand.torch is not None:
        out["torch_gen"] = rand.torch.get_state()
    return out


def restore_random_state(rand: Randoms, state: Mapping[str, Any], device: "torch.device", where: str = "") -> None:
    """Set every stream from :func:`random_state`'s output. Also reads the two formats written
    before the loop was one: the tokenizer's (the numpy state as a dict) and the world model's
    (no torch global state: it drew nothing from that stream). Anything else missing is one
    :class:`StateError`."""
    import torch

    at = f" in {where}" if where else ""
    rng = state.get("numpy_rng")
    if isinstance(rng, str):
        rng = json.loads(rng)
    if not isinstance(rng, dict):
        raise StateError(f"the training state{at} holds no numpy random state (numpy_rng); rerun with --fresh")
    rand.numpy.bit_generator.state = rng
    if state.get("torch_rng") is not None:
        torch.set_rng_state(state["torch_rng"])
    if device.type == "cuda" and state.get("cuda_rng") is not None:
        torch.cuda.set_rng_state(state["cuda_rng"], device)
    if rand.torch is not None:
        if state.get("torch_gen") is None:
            raise StateError(f"the training state{at} holds no torch generator state (torch_gen); rerun with --fresh")
        rand.torch.set_state(state["torch_gen"])


# -- the loop ------------------------------------------------------------------------------------
@dataclass
class LoopResult:
    """What :func:`fit_loop` returns: the model, the step reached, the curve, the times."""

    model: Any
    step: int
    history: list[dict] = field(default_factory=list)
    elapsed_s: float = 0.0
    cpu_s: float = 0.0


_ASK = object()


def fit_loop(build_model: "Callable[[], nn.Module] | nn.Module", make_optimizer: Callable[["nn.Module"], "torch.optim.Optimizer"],
             sample_batch: Callable[[Randoms, int], Any], step_fn: Callable[["nn.Module", Any], tuple[Any, Mapping[str, float]]],
             run, *, steps: int, seed: int = 0, schedule: Callable[[int], float] | None = None,
             grad_clip: float | None = None, log_every: int = 1, checkpoint_every: int = 100,
             torch_generator: bool = False, after_step: Callable[["nn.Module", Any, int], Mapping[str, float] | None] | None = None,
             progress_values: Mapping[str, str] | None = None, weights_prefix: str = "",
             extra_weights: Mapping[str, Any] | None = None,
             manifest_config: Mapping[str, Any] | Callable[["nn.Module"], Mapping[str, Any]] | None = None,
             resumed: Any = _ASK, log: Callable[[str], Any] = print) -> LoopResult:
    """Train until ``steps`` or until ``run`` (a :class:`~pcfbench.training.TrainingRun`) says
    the time budget is spent, saving through ``run.save``.

    ``build_model()`` is called right after ``torch.manual_seed(seed)`` and returns the model
    on its device (batches go there), so the seed makes its initial weights (a model already
    built may be given instead, its initialisation seeded by the caller);
    ``make_optimizer(model)`` returns its optimiser. Each step
    (0-based ``step``): the learning rate of every parameter group is set to
    ``schedule(step)`` (unless None); ``batch = sample_batch(rand, step)``; under
    :func:`autocast`, ``loss, logged = step_fn(model, batch)`` (``logged``: floats for the
    curve, e.g. the loss and its parts); backward, gradient-norm clipping at ``grad_clip``
    (None: the norm is measured, nothing clipped), the optimiser step; then
    ``after_step(model, optimizer, step)``, whose returned floats join the logged ones.

    The curve (``history``) holds one row each ``log_every`` steps and at the last: the
    window's mean (NaN ignored) of ``step, lr, *logged, grad_norm, step_s``, with ``step``,
    ``elapsed_s`` and ``cpu_s`` at its end. The progress (a bar on a terminal, log lines
    elsewhere) shows ``progress_values`` (label -> logged name; default the loss): labels a
    reader understands, e.g. ``"L1 depth error (m)"``, not a column's short name. Saves every ``checkpoint_every`` steps and at
    the end: the weights (``model.state_dict()`` under ``weights_prefix``, then
    ``extra_weights``), the state (optimiser, :func:`random_state`, history, window, times)
    and ``manifest_config`` (a mapping, or a function of the model) in the manifest.

    ``resumed``: what ``run.resume()`` gave when the caller already asked it (it is asked
    here otherwise). The weights under ``weights_prefix`` are loaded; extra weights are not.
    """
    import numpy as np
    import torch

    from torch import nn

    torch.manual_seed(seed)
    model = build_model if isinstance(build_model, nn.Module) else build_model()
    device = next(model.parameters()).device
    opt = make_optimizer(model)
    rand = Randoms(np.random.default_rng(seed), torch.Generator(device).manual_seed(seed + 1) if torch_generator else None)
    step, history, window, elapsed, cpu = 0, [], [], 0.0, 0.0
    if resumed is _ASK:
        resumed = run.resume()
    if resumed is not None:
        st = resumed["state"]
        missing = [k for k in ("optimizer", "history", "elapsed_s", "cpu_s") if k not in st]
        if missing:
            raise StateError(f"the training state of step {resumed['step']} lacks {', '.join(missing)}: it was not "
                             "saved by this training loop; rerun with --fresh")
        n = len(weights_prefix)
        model.load_state_dict({k[n:]: v for k, v in resumed["weights"].items() if k.startswith(weights_prefix)})
        opt.load_state_dict(st["optimizer"])
        step, history, window = int(resumed["step"]), list(st["history"]), list(st.get("window", []))
        elapsed, cpu = float(st["elapsed_s"]), float(st["cpu_s"])
        restore_random_state(rand, st, device, f"step {step}")
    model.train()
    config = dict(manifest_config(model) if callable(manifest_config) else (manifest_config or {}))
    shown = dict(progress_values or {"loss": "loss"})

    def save(complete: bool) -> None:
        weights = {f"{weights_prefix}{k}": v for k, v in model.state_dict().items()} | dict(extra_weights or {})
        state = {"loop_format": STATE_FORMAT, "optimizer": opt.state_dict(), "history": history, "window": window,
                 **random_state(rand, device), "elapsed_s": elapsed, "cpu_s": cpu}
        run.save(step, weights, state, config=config, complete=complete)

    run.start(steps, step)
    saved = step if resumed is not None else -1
    while step < steps:
        if run.should_stop():
            log(f"time budget reached at step {step}")
            break
        t0, c0 = time.monotonic(), time.process_time()
        if schedule is not None:
            for g in opt.param_groups:
                g["lr"] = schedule(step)
        batch = sample_batch(rand, step)
        with autocast(device):
            loss, logged = step_fn(model, batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), math.inf if grad_clip is None else grad_clip)
        opt.step()
        more = after_step(model, opt, step) if after_step is not None else None
        step += 1
        synchronize(device)  # on a GPU the backward pass may still be running
        dt = time.monotonic() - t0
        elapsed += dt
        cpu += time.process_time() - c0
        rec = {"step": step, "lr": opt.param_groups[0]["lr"], **logged, **(more or {}), "grad_norm": float(gnorm),
               "step_s": dt}
        window.append(rec)
        if step % log_every == 0 or step == steps:
            with warnings.catch_warnings():  # a column NaN over the whole window (a stage's own loss) stays NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                avg = {k: float(np.nanmean([r[k] for r in window])) for k in rec}
            avg.update(step=step, elapsed_s=elapsed, cpu_s=cpu)
            history.append(avg)
            window = []
        run.update(1, **{label: rec[name] for label, name in shown.items() if name in rec})
        if step % checkpoint_every == 0 or step == steps:
            save(step >= steps)
            saved = step
    if saved != step:
        save(step >= steps)
    return LoopResult(model, step, history, elapsed, cpu)


# -- the curve -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Panel:
    """One panel of a curve's figure: ``lines`` of ``(column, label)`` or ``(column, label,
    divisor)`` (the column divided by it), a log y axis or not, y limits. Columns the history
    lacks are left out."""

    lines: tuple[tuple, ...]
    log: bool = False
    ylim: tuple[float, float] | None = None


def default_panels(columns: Iterable[str]) -> list[Panel]:
    """One panel per logged column (a log axis for those named like a loss), the learning
    rate last; the step and the timings are not drawn."""
    cols = [c for c in columns if c not in ("step", "lr", *TIMING_COLUMNS)]
    panels = [Panel(((c, c),), log=c == "loss" or c.endswith("_loss")) for c in cols]
    if "lr" in columns:
        panels.append(Panel((("lr", "learning rate"),)))
    return panels


def write_curve(history: Sequence[Mapping[str, float]], out_dir: Path, stem: str = "curve",
                panels: Sequence[Panel] | None = None) -> tuple[Path, Path]:
    """The training curve as ``<stem>.csv`` (every column of ``history``) and ``<stem>.png``
    (``panels``, by default :func:`default_panels`, against the step)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = out_dir / f"{stem}.csv"
    keys = list(history[0].keys()) if history else []
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(history)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drawn = []
    for p in (default_panels(keys) if panels is None else panels):
        lines = [ln for ln in p.lines if ln[0] in keys]
        if lines:
            drawn.append((p, lines))
    fig, axes = plt.subplots(1, max(1, len(drawn)), figsize=(0.4 + 4.2 * max(1, len(drawn)), 3.6), squeeze=False)
    s = [r["step"] for r in history]
    for ax, (p, lines) in zip(axes[0], drawn):
        for col, label, *div in lines:
            d = float(div[0]) if div and div[0] else 1.0
            ax.plot(s, [r[col] / d for r in history], label=label)
        if p.log:
            ax.set_yscale("log")
        if p.ylim is not None:
            ax.set_ylim(*p.ylim)
        ax.set_xlabel("step")
        ax.legend()
    fig.tight_layout()
    png_path = out_dir / f"{stem}.png"
    fig.savefig(png_path, dpi=110)
    plt.close(fig)
    return csv_path, png_path
