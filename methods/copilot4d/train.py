"""Tokenizer training (A.3 optimiser), with checkpoints and resume."""

from __future__ import annotations

import contextlib
import csv
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.methods.copilot4d.config import TokenizerConfig
from pcfbench.methods.copilot4d.data import Batch, SweepSource, make_batch
from pcfbench.methods.copilot4d.model import Tokenizer, occupancy_grid
from pcfbench.methods.copilot4d.render import pool_mask, render_depth, render_loss, sample_along_rays


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def autocast(device: torch.device):
    """bf16 autocast on CUDA, nothing on CPU."""
    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def synchronize(device: torch.device) -> None:
    """Wait for the GPU's queued work, so a step's wall time includes its backward pass."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def param_groups(model: nn.Module, weight_decay: float) -> list[dict]:
    """A.3: weight decay on weight matrices only; biases, embeddings (codebook, z embedding,
    relative position biases) and LayerNorm parameters are excluded."""
    decay, no_decay = [], []
    for mod_name, mod in model.named_modules():
        for name, p in mod.named_parameters(recurse=False):
            if not p.requires_grad:
                continue
            if isinstance(mod, nn.Linear) and name == "weight":
                decay.append(p)
            else:
                no_decay.append(p)
    return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]


def make_optimizer(model: nn.Module, cfg: TokenizerConfig) -> torch.optim.Optimizer:
    return torch.optim.AdamW(param_groups(model, cfg.weight_decay), lr=cfg.lr, betas=cfg.betas)


def lr_at(cfg: TokenizerConfig, step: int) -> float:
    """Linear warm-up to ``lr``, then cosine decay over ``decay_steps`` to ``min_lr_ratio * lr``."""
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    t = min(1.0, (step - cfg.warmup) / max(1, cfg.decay_steps - cfg.warmup))
    return cfg.lr * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def compute_losses(model: Tokenizer, batch: Batch, cfg: TokenizerConfig) -> dict[str, torch.Tensor]:
    """Forward pass of one training step: L_vq + equation 5 (L1 depth, weight concentration,
    coarse BCE). Training samples ray points inside the ground-truth non-empty voxels max-pooled
    by ``skip_pool`` (figure 8), plus ``train_uniform_samples`` uniform ones along the ray."""
    B = batch.size
    z = model.encoder(batch.points, batch.point_batch, B)
    zq, codes, l_vq = model.vq(z)
    nfg, coarse = model.decoder(zq)
    with torch.no_grad():
        occ = occupancy_grid(cfg, batch.points, batch.point_batch, B)
        mask = pool_mask(cfg, occ)
    bce = F.binary_cross_entropy_with_logits(coarse.float(), occ)
    h = sample_along_rays(cfg, batch.origins, batch.dirs, batch.ray_batch, mask, cfg.samples_per_ray, jitter=True,
                          extra_uniform=cfg.train_uniform_samples)
    depth, w = render_depth(model.decoder, nfg, cfg, batch.origins, batch.dirs, batch.ray_batch, h)
    l1, conc = render_loss(depth, w, h, batch.depth, cfg.epsilon)
    loss = l1 + conc + bce + l_vq.float()
    return {"loss": loss, "l1": l1, "conc": conc, "bce": bce, "vq": l_vq.float(), "codes": codes}


def config_from_dict(d: dict) -> TokenizerConfig:
    """The ``TokenizerConfig`` a checkpoint manifest records (lists back to tuples)."""
    return TokenizerConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def load_tokenizer(checkpoint, device: torch.device | None = None) -> Tokenizer:
    """The trained tokenizer of a verified ``pcfbench.training.Checkpoint`` (its network sizes
    from the manifest's ``config.tokenizer``; weights loaded with ``weights_only=True``)."""
    from pcfbench.errors import PcfbenchError

    tok = checkpoint.manifest.get("config", {}).get("tokenizer")
    if not isinstance(tok, dict):
        raise PcfbenchError(f"checkpoint {checkpoint.manifest_path} records no tokenizer configuration (config.tokenizer)")
    model = Tokenizer(config_from_dict(tok))
    try:
        model.load_state_dict(checkpoint.load_weights())
    except RuntimeError as exc:
        raise PcfbenchError(f"checkpoint {checkpoint.weights_path} does not fit the tokenizer it records: "
                            f"{str(exc).splitlines()[0]}") from None
    return model.to(device or default_device()).eval()


def train(cfg: TokenizerConfig, source: SweepSource, run, *, steps: int | None = None,
          device: torch.device | None = None, seed: int = 0, threads: int | None = None, log=print) -> dict:
    """Train (or resume) until ``steps`` (default ``cfg.max_steps``) or until ``run`` (a
    ``pcfbench.training.TrainingRun``) says the time budget is spent. ``run.resume()`` gives
    the last checkpoint (weights, optimiser, both RNGs, the curve so far), so a resumed run
    draws the same batches and continues the same curve; ``run.save`` is called every
    ``cfg.checkpoint_every`` steps and at the end. Returns the model, step, curve and times."""
    device = device or default_device()
    steps = steps or cfg.max_steps
    if threads and device.type == "cpu":
        torch.set_num_threads(threads)
    torch.manual_seed(seed)
    model = Tokenizer(cfg).to(device)
    opt = make_optimizer(model, cfg)
    rng = np.random.default_rng(seed)
    step, history, elapsed, cpu = 0, [], 0.0, 0.0
    resumed = run.resume()
    if resumed is not None:
        st = resumed["state"]
        model.load_state_dict(resumed["weights"])
        opt.load_state_dict(st["optimizer"])
        step, history, elapsed, cpu = resumed["step"], list(st["history"]), float(st["elapsed_s"]), float(st["cpu_s"])
        rng.bit_generator.state = st["numpy_rng"]
        torch.set_rng_state(st["torch_rng"])
    model.train()
    codebook_params = {id(model.vq.codebook)}
    manifest_config = {"tokenizer": cfg.to_dict(), "parameters": count_parameters(model), "steps_target": steps,
                       "seed": seed}

    def save(complete: bool) -> None:
        state = {"optimizer": opt.state_dict(), "history": history, "numpy_rng": rng.bit_generator.state,
                 "torch_rng": torch.get_rng_state(), "elapsed_s": elapsed, "cpu_s": cpu, "window": window}
        run.save(step, model.state_dict(), state, config=manifest_config, complete=complete)

    window: list[dict] = list(resumed["state"].get("window", [])) if resumed is not None else []
    run.start(steps, step)
    saved = step if resumed is not None else -1
    while step < steps:
        if run.should_stop():
            log(f"time budget reached at step {step}")
            break
        t0, c0 = time.monotonic(), time.process_time()
        for g in opt.param_groups:
            g["lr"] = lr_at(cfg, step)
        picks = rng.integers(0, len(source), cfg.batch_size)
        batch = make_batch(cfg, [source.points(int(k)) for k in picks], cfg.rays_per_step, rng).to(device)
        with autocast(device):
            out = compute_losses(model, batch, cfg)
        opt.zero_grad(set_to_none=True)
        out["loss"].backward()
        gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        opt.step()
        if model.vq.maybe_reinit():
            for p in model.vq.parameters():
                if id(p) in codebook_params:
                    opt.state.pop(p, None)  # stale Adam moments would drag the new codes
            log(f"step {step}: K-means re-initialised the codebook ({int(model.vq.reinits)} so far)")
        step += 1
        synchronize(device)
        dt = time.monotonic() - t0
        elapsed += dt
        cpu += time.process_time() - c0
        alive = 1.0 - model.vq.dead_codes().float().mean().item()
        rec = {"step": step, "lr": opt.param_groups[0]["lr"], "loss": out["loss"].item(), "l1": out["l1"].item(),
               "conc": out["conc"].item(), "bce": out["bce"].item(), "vq": out["vq"].item(),
               "batch_codes": int(out["codes"].unique().numel()), "alive_codes": alive,
               "grad_norm": float(gnorm), "step_s": dt, "elapsed_s": elapsed, "cpu_s": cpu}
        window.append(rec)
        if step % cfg.log_every == 0 or step == steps:
            avg = {k: float(np.mean([r[k] for r in window])) for k in rec}
            avg["step"], avg["elapsed_s"], avg["cpu_s"] = step, elapsed, cpu
            history.append(avg)
            window = []
        run.update(1, loss=rec["loss"], l1=rec["l1"], codes=alive)
        if step % cfg.checkpoint_every == 0 or step == steps:
            save(step >= steps)
            saved = step
    if saved != step:
        save(step >= steps)
    return {"model": model, "step": step, "history": history, "elapsed_s": elapsed, "cpu_s": cpu}


def write_curve(history: list[dict], out_dir: Path, stem: str, codebook_size: int | None = None) -> tuple[Path, Path]:
    """The training curve as CSV and PNG."""
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

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    s = [r["step"] for r in history]
    axes[0].plot(s, [r["l1"] for r in history], label="L1 depth (m)")
    axes[0].plot(s, [r["loss"] for r in history], label="total loss")
    axes[0].set_yscale("log")
    axes[0].legend()
    axes[0].set_xlabel("step")
    axes[1].plot(s, [r["conc"] for r in history], label="weight mass > eps")
    axes[1].plot(s, [r["bce"] for r in history], label="coarse BCE")
    axes[1].plot(s, [r["vq"] for r in history], label="L_vq")
    axes[1].set_yscale("log")
    axes[1].legend()
    axes[1].set_xlabel("step")
    axes[2].plot(s, [r["alive_codes"] for r in history], label="codes used in the last 256 it.")
    if codebook_size:
        axes[2].plot(s, [r["batch_codes"] / codebook_size for r in history], label="codes used per step")
    axes[2].set_ylim(0, 1.05)
    axes[2].legend()
    axes[2].set_xlabel("step")
    fig.tight_layout()
    png_path = out_dir / f"{stem}.png"
    fig.savefig(png_path, dpi=110)
    plt.close(fig)
    return csv_path, png_path
