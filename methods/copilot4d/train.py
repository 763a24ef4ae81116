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
    out = {"loss": loss, "l1": l1, "conc": conc, "bce": bce, "vq": l_vq.float(), "codes": codes}
    if cfg.view_consistency:
        view, agree = view_pull(model, z, codes, occ, cfg)
        out.update(loss=loss + cfg.view_consistency * view, view=view, view_agree=agree)
    return out


def observed_tokens(cfg: TokenizerConfig, occ: torch.Tensor) -> torch.Tensor:
    """(B, T, T) bool: the token cells whose BEV patch holds at least one occupied voxel of ``occ``
    (B, X, X, Z)."""
    f = cfg.grid_xy // cfg.bev_tokens
    return F.max_pool2d(occ.amax(-1)[:, None], f)[:, 0] > 0


def view_pull(model: Tokenizer, z: torch.Tensor, codes: torch.Tensor, occ: torch.Tensor, cfg: TokenizerConfig):
    """``cfg.view_consistency``'s term for a batch of view pairs (sweeps 2m and 2m+1 are two frames
    of one window in its t=0 frame): on the token cells both views observe, each view's encoder
    output against the other view's code, |z_a - sg[z_hat_b]|^2 + |z_b - sg[z_hat_a]|^2 (mean
    over those cells and the code dimension, as L_vq's commitment term), and the share of those
    cells where the two views already pick the same code."""
    if z.shape[0] % 2:
        raise ValueError(f"view_consistency needs pairs of views, got a batch of {z.shape[0]} sweeps")
    both = observed_tokens(cfg, occ)
    both = both[0::2] & both[1::2]
    zq = model.vq.lookup(codes).detach().float()
    za, zb, qa, qb = z[0::2].float(), z[1::2].float(), zq[0::2], zq[1::2]
    n = both.sum()
    if n == 0:
        return z.sum() * 0.0, float("nan")
    pull = (((za - qb) ** 2).sum(-1)[both].sum() + ((zb - qa) ** 2).sum(-1)[both].sum()) / (2 * n * z.shape[-1])
    agree = (codes[0::2] == codes[1::2])[both].float().mean().item()
    return pull, agree


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
    load_state(model, checkpoint)
    return model.to(device or default_device()).eval()


def load_state(model: Tokenizer, checkpoint) -> None:
    """``checkpoint``'s weights into ``model`` (``weights_only=True``); one clear error when they do not fit."""
    from pcfbench.errors import PcfbenchError

    try:
        model.load_state_dict(checkpoint.load_weights())
    except RuntimeError as exc:
        raise PcfbenchError(f"checkpoint {checkpoint.weights_path} does not fit the tokenizer "
                            f"{model.cfg.name!r}: {str(exc).splitlines()[0]}") from None


def train(cfg: TokenizerConfig, source: SweepSource, run, *, steps: int | None = None,
          device: torch.device | None = None, seed: int = 0, threads: int | None = None, log=print,
          init=None) -> dict:
    """Train (or resume) until ``steps`` (default ``cfg.max_steps``) or until ``run`` (a
    ``pcfbench.training.TrainingRun``) says the time budget is spent, through
    :func:`pcfbench.training.fit_loop` (resume, random state, saves every
    ``cfg.checkpoint_every`` steps and at the end, the curve every ``cfg.log_every``).
    ``init``: the verified checkpoint of ``cfg.init_from`` a new training starts from (required
    exactly when that names one; a resumed training keeps its own weights). Returns the model,
    step, curve and times."""
    from pcfbench.errors import PcfbenchError

    if bool(cfg.init_from) != (init is not None):
        raise PcfbenchError(f"tokenizer config {cfg.name!r} starts from {cfg.init_from or 'a random initialisation'}"
                            f": {'give its checkpoint' if cfg.init_from else 'no checkpoint to start from'}")
    device = device or default_device()
    steps = steps or cfg.max_steps
    if threads and device.type == "cpu":
        torch.set_num_threads(threads)

    def sample_batch(rand, step: int) -> Batch:
        picks = rand.numpy.integers(0, len(source), cfg.batch_size)
        if cfg.view_consistency:  # two views of one window per example, consecutive in the batch
            views = [v for k in picks for v in source.window_pair(cfg, int(k), rand.numpy)]
            return make_batch(cfg, [p for p, _ in views], cfg.rays_per_step, rand.numpy,
                              sensors=[T for _, T in views]).to(device)
        sensors = None
        if cfg.sensor_moves == "window":
            sensors = [source.window_sensor(cfg, int(k), rand.numpy) for k in picks]
        return make_batch(cfg, [source.points(int(k)) for k in picks], cfg.rays_per_step, rand.numpy,
                          sensors=sensors).to(device)

    def step_fn(model: Tokenizer, batch: Batch):
        out = compute_losses(model, batch, cfg)
        logged = {"loss": out["loss"].item(), "l1": out["l1"].item(), "conc": out["conc"].item(),
                  "bce": out["bce"].item(), "vq": out["vq"].item(), "batch_codes": int(out["codes"].unique().numel())}
        if cfg.view_consistency:
            logged.update(view=out["view"].item(), view_agree=out["view_agree"])
        return out["loss"], logged

    def after_step(model: Tokenizer, opt: torch.optim.Optimizer, step: int) -> dict:
        return codebook_after_step(model.vq, opt, step, log)

    def new_model() -> Tokenizer:
        model = Tokenizer(cfg)
        if init is not None:
            load_state(model, init)
        return model.to(device)

    started = {"init_from": {"config": cfg.init_from, "weights_sha256": init.sha256}} if init is not None else {}
    out = fit_loop(
        new_model, lambda model: make_optimizer(model, cfg), sample_batch, step_fn, run,
        steps=steps, seed=seed, schedule=lambda step: lr_at(cfg, step), grad_clip=cfg.grad_clip,
        log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every, after_step=after_step,
        # labels a reader of the bar or the log understands (the curve keeps the column names)
        progress_values={"total loss": "loss", "L1 depth error (m)": "l1", "share of codes in use": "alive_codes"},
        manifest_config=lambda model: {"tokenizer": cfg.to_dict(), "parameters": count_parameters(model),
                                       "steps_target": steps, "seed": seed, **started},
        log=log)
    return {"model": out.model, "step": out.step, "history": out.history, "elapsed_s": out.elapsed_s,
            "cpu_s": out.cpu_s}


def curve_panels(codebook_size: int | None = None, views: bool = False) -> list[Panel]:
    """The tokenizer curve's figure: depth error and total loss; the loss terms; codebook use."""
    codes = [("alive_codes", "codes used in the last 256 it.")]
    if codebook_size:
        codes.append(("batch_codes", "codes used per step", codebook_size))
    if views:  # view_consistency: the share of co-observed cells where both views pick one code
        codes.append(("view_agree", "same code from both views"))
    terms = (("conc", "weight mass > eps"), ("bce", "coarse BCE"), ("vq", "L_vq"))
    if views:
        terms += (("view", "pull to the other view's code"),)
    return [Panel((("l1", "L1 depth (m)"), ("loss", "total loss")), log=True),
            Panel(terms, log=True),
            Panel(tuple(codes), ylim=(0, 1.05))]


def write_curve(history: list[dict], out_dir: Path, stem: str = "curve",
                codebook_size: int | None = None) -> tuple[Path, Path]:
    """The tokenizer's training curve as CSV and PNG (with the views' agreement when it was logged)."""
    views = any("view_agree" in r for r in history)
    return write_any_curve(history, out_dir, stem, curve_panels(codebook_size, views))
