"""Tokenizer training (A.3 optimiser) through the one training loop
(:func:`pcfbench.training.fit_loop`): this module supplies the model, the batches, the
losses of a step and the K-means codebook re-initialisation after it."""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.methods.copilot4d.config import TokenizerConfig
from pcfbench.methods.copilot4d.data import Batch, SweepSource, make_batch
from pcfbench.methods.copilot4d.model import Tokenizer, codebook_after_step, occupancy_grid
from pcfbench.methods.copilot4d.render import pool_mask, render_depth, render_loss, sample_along_rays
# the generic pieces live in the core; their old names here stay for the callers that use them
from pcfbench.training import Panel, adamw, autocast, default_device, fit_loop, param_groups, synchronize, warmup_cosine
from pcfbench.training import write_curve as write_any_curve

__all__ = ["autocast", "compute_losses", "config_from_dict", "count_parameters", "curve_panels", "default_device",
           "load_tokenizer", "lr_at", "make_optimizer", "param_groups", "synchronize", "train", "write_curve"]


def make_optimizer(model: nn.Module, cfg: TokenizerConfig) -> torch.optim.Optimizer:
    """A.3: AdamW, weight decay on weight matrices only; biases, embeddings (codebook, z
    embedding, relative position biases) and LayerNorm parameters are excluded."""
    return adamw(model, cfg.lr, cfg.betas, cfg.weight_decay)


def lr_at(cfg: TokenizerConfig, step: int) -> float:
    """Linear warm-up to ``lr``, then cosine decay over ``decay_steps`` to ``min_lr_ratio * lr``."""
    return warmup_cosine(step, cfg.lr, cfg.warmup, cfg.decay_steps, cfg.min_lr_ratio)


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
    ``pcfbench.training.TrainingRun``) says the time budget is spent, through
    :func:`pcfbench.training.fit_loop` (resume, random state, saves every
    ``cfg.checkpoint_every`` steps and at the end, the curve every ``cfg.log_every``).
    Returns the model, step, curve and times."""
    device = device or default_device()
    steps = steps or cfg.max_steps
    if threads and device.type == "cpu":
        torch.set_num_threads(threads)

    def sample_batch(rand, step: int) -> Batch:
        picks = rand.numpy.integers(0, len(source), cfg.batch_size)
        sensors = None
        if cfg.sensor_moves == "window":
            sensors = [source.window_sensor(cfg, int(k), rand.numpy) for k in picks]
        return make_batch(cfg, [source.points(int(k)) for k in picks], cfg.rays_per_step, rand.numpy,
                          sensors=sensors).to(device)

    def step_fn(model: Tokenizer, batch: Batch):
        out = compute_losses(model, batch, cfg)
        return out["loss"], {"loss": out["loss"].item(), "l1": out["l1"].item(), "conc": out["conc"].item(),
                             "bce": out["bce"].item(), "vq": out["vq"].item(),
                             "batch_codes": int(out["codes"].unique().numel())}

    def after_step(model: Tokenizer, opt: torch.optim.Optimizer, step: int) -> dict:
        return codebook_after_step(model.vq, opt, step, log)

    out = fit_loop(
        lambda: Tokenizer(cfg).to(device), lambda model: make_optimizer(model, cfg), sample_batch, step_fn, run,
        steps=steps, seed=seed, schedule=lambda step: lr_at(cfg, step), grad_clip=cfg.grad_clip,
        log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every, after_step=after_step,
        # labels a reader of the bar or the log understands (the curve keeps the column names)
        progress_values={"total loss": "loss", "L1 depth error (m)": "l1", "share of codes in use": "alive_codes"},
        manifest_config=lambda model: {"tokenizer": cfg.to_dict(), "parameters": count_parameters(model),
                                       "steps_target": steps, "seed": seed},
        log=log)
    return {"model": out.model, "step": out.step, "history": out.history, "elapsed_s": out.elapsed_s,
            "cpu_s": out.cpu_s}


def curve_panels(codebook_size: int | None = None) -> list[Panel]:
    """The tokenizer curve's figure: depth error and total loss; the loss terms; codebook use."""
    codes = [("alive_codes", "codes used in the last 256 it.")]
    if codebook_size:
        codes.append(("batch_codes", "codes used per step", codebook_size))
    return [Panel((("l1", "L1 depth (m)"), ("loss", "total loss")), log=True),
            Panel((("conc", "weight mass > eps"), ("bce", "coarse BCE"), ("vq", "L_vq")), log=True),
            Panel(tuple(codes), ylim=(0, 1.05))]


def write_curve(history: list[dict], out_dir: Path, stem: str = "curve",
                codebook_size: int | None = None) -> tuple[Path, Path]:
    """The tokenizer's training curve as CSV and PNG."""
    return write_any_curve(history, out_dir, stem, curve_panels(codebook_size))
