"""BEVWorld as a trained method (``bevworld``): the ``bevworld-latent-copy`` tokenizer of the
same configuration and frame, trained on the same data, plus the latent diffusion world model
(:mod:`.world`, :mod:`.diffusion`).

**Training** (``fit``): every training window (5 past and 5 future sweeps at the ``strides``,
every ``anchor_every``-th anchor; Copilot4D's ``build_windows``) is encoded once in the option
``frame`` (``own``: each sweep in its own sensor frame; ``t0``: moved into the window's t=0
sensor frame), standardised per channel with the tokenizer's statistics, and cached under
``<cache>/bevworld/world-windows/<tokenizer sha256[:16]>/...``; the world model learns its
``target`` (the future frames' change from the last past frame, or their noise: equation 7)
through :func:`pcfbench.training.fit_loop`. With
``curriculum=on`` (the paper's three stages, 2 : 2 : 3 of the steps): the next frame from the 2
frames before it at stride 1, then all future frames at stride 1, then the ``strides``. The
checkpoint holds the world model's weights (``world.``) and the tokenizer's (``tokenizer.``);
its manifest records the tokenizer checkpoint's sha256 and a digest of its tensors.

**Forecast**: the newest past sweeps are encoded in the frame and standardised, every frame's
sensor pose moved into the t=0 sensor frame; all future frames are denoised jointly from noise
(seeded per sample) by ``ddim_steps`` DDIM steps (with ``guidance`` != 1, classifier-free
guidance on the action); each latent is de-standardised, decoded and rendered along its sweep's
query rays from the future sensor's origin in its frame (``t0``: the t=0 frame; ``own``: the
future sensor's own frame, origin 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.methods.bevworld.latent_copy import BevOptions, encode_sweep, load_tokenizer, moved, render_sample
from pcfbench.options import option
from pcfbench.training import Checkpoint, CheckpointError, TrainedMethod, TrainingRun, TrainSource
from pcfbench.training.tokenized import OnTokenizer

TOKENIZER_METHOD = "bevworld-latent-copy"
CURRICULA = ("off", "on")
#: the curriculum's stages: their shares of the steps (the paper's 20k, 20k, 30k iterations)
STAGE_SHARES = (2 / 7, 2 / 7, 3 / 7)


@dataclass(frozen=True)
class BevWorldOptions(BevOptions):
    ddim_steps: int = option(0, help="DDIM steps of a forecast (0: the configuration's; paper 50)", min=0)
    guidance: float = option(1.0, help="classifier-free guidance scale on the action (1: none, as the paper); "
                                       "needs a model trained with cond_dropout > 0")
    sample_seed: int = option(0, help="seed of a forecast's starting noise (with the sample's id)")
    steps: int = option(0, help="training steps (0: the configuration's max_steps)", min=0)
    seed: int = option(0, help="training seed")
    curriculum: str = option("off", help="on: the paper's three stages (next frame at stride 1, all future frames "
                                         "at stride 1, then the strides); off: the strides throughout")
    cond_dropout: float = option(0.0, help="training: the share of windows whose action is dropped (classifier-free "
                                           "guidance; the paper: 0)", min=0.0)
    target: str = option("change", help="what the world model predicts: change (a future latent's change from the "
                                        "last past one; a fresh model forecasts the latent copy) or eps (the "
                                        "noise, the paper's equation 7)")
    tokenizer_steps: int = option(0, help="the bevworld-latent-copy checkpoint used: its steps option (0: its "
                                          "default)", min=0)
    strides: tuple[int, ...] = option((2, 6), help="training windows: source sweeps between frames (kitti-1s "
                                                   "uses 2, kitti-3s 6)", min=1)
    anchor_every: int = option(2, help="training windows: every n-th t=0 sweep of the split", min=1)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.curriculum not in CURRICULA:
            raise PcfbenchError(f"curriculum={self.curriculum!r}: expected one of {', '.join(CURRICULA)}")
        from pcfbench.methods.bevworld.diffusion import check_target

        check_target(self.target)
        if self.cond_dropout >= 1:
            raise PcfbenchError(f"cond_dropout={self.cond_dropout}: expected a share below 1")


def window_encoder(model):
    """``build_windows``'s ``tokenize``: a sweep's standardised latent (H, W, C') in a frame."""
    def tokenize(points, T_frame_sensor):
        return model.normalise(encode_sweep(model, points, T_frame_sensor)).cpu().numpy()
    return tokenize


def stage_of(step: int, steps: int, curriculum: str) -> int:
    """The curriculum stage (1, 2 or 3) of a 0-based step; 3 throughout without a curriculum."""
    if curriculum == "off":
        return 3
    a = STAGE_SHARES[0] * steps
    return 1 if step < a else 2 if step < a + STAGE_SHARES[1] * steps else 3


def stage_batch(windows: dict, stage: int, n_past: int, strides: tuple[int, ...], picks_rng, batch_size: int):
    """A batch of ``stage``: (latents (B, T', H, W, C'), poses (B, T', 4, 4), frames (T',), past
    count). Stage 1: frames n_past - 2 .. n_past of stride-1 windows (the next frame from 2);
    stage 2: stride-1 windows whole; stage 3: windows of ``strides``."""
    import torch

    pool = windows["by_stride"][1] if stage < 3 else np.concatenate([windows["by_stride"][s] for s in strides])
    picks = pool[picks_rng.integers(0, len(pool), batch_size)]
    lat, poses = windows["latents"][picks], windows["poses"][picks]
    if stage == 1:
        frames = np.arange(n_past - 2, n_past + 1)
        lat, poses, past = lat[:, frames], poses[:, frames], 2
    else:
        frames, past = np.arange(lat.shape[1]), n_past
    return torch.from_numpy(lat), torch.from_numpy(poses), torch.from_numpy(frames), past


def train_world(cfg, windows: dict, run, *, steps: int, seed: int, strides: tuple[int, ...], curriculum: str,
                cond_dropout: float, target: str, manifest_config, extra_weights: dict | None = None, resumed=None,
                log=print) -> dict:
    """The world model on ``windows`` through :func:`pcfbench.training.fit_loop` (AdamW, warm-up
    and cosine decay); the diffusion's timesteps and noise come from the loop's torch stream."""
    import torch

    from pcfbench.methods.bevworld.diffusion import Schedule, diffusion_loss
    from pcfbench.methods.bevworld.world import WorldModel
    from pcfbench.training import default_device, fit_loop, warmup_cosine

    schedule = Schedule.of(cfg)
    device = default_device()

    def sample_batch(rand, step: int):
        stage = stage_of(step, steps, curriculum)
        lat, poses, frames, past = stage_batch(windows, stage, cfg.n_past, strides, rand.numpy, cfg.batch_size)
        return lat.to(device), poses.to(device), frames.to(device), past, stage, rand.torch

    def step_fn(model, batch):
        lat, poses, frames, past, stage, gen = batch
        out = diffusion_loss(model, schedule, lat, poses, past, frames=frames, cond_dropout=cond_dropout,
                             target=target, generator=gen)
        keys = ("loss", "mse", "changed", "static", "copy_changed", "copy_static", "changed_share")
        return out["loss"], {**{k: float(out[k].detach()) for k in keys}, "stage": float(stage)}

    out = fit_loop(lambda: WorldModel(cfg).to(device),
                   lambda m: torch.optim.AdamW(m.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay),
                   sample_batch, step_fn, run, steps=steps, seed=seed, torch_generator=True,
                   schedule=lambda step: warmup_cosine(step, cfg.lr, cfg.warmup, steps, cfg.min_lr_ratio),
                   grad_clip=cfg.grad_clip, log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                   progress_values={"loss": "mse", "changed cells": "changed", "curriculum stage": "stage"},
                   weights_prefix="world.", extra_weights=extra_weights, manifest_config=manifest_config,
                   resumed=resumed, log=log)
    return {"model": out.model, "step": out.step, "history": out.history}


def world_curve_panels() -> list:
    from pcfbench.training import Panel

    return [Panel((("mse", "loss (MSE of the target)"),), log=True),
            Panel((("changed", "loss, cells that change"), ("copy_changed", "latent copy's, cells that change"),
                   ("static", "loss, cells that do not"), ("copy_static", "latent copy's, cells that do not")),
                  log=True),
            Panel((("stage", "curriculum stage"),))]


class BevWorld(OnTokenizer, TrainedMethod):
    """BEVWorld: a continuous BEV latent tokenizer + latent diffusion transformer, DDIM."""

    name = "bevworld"
    version = "2"  # 2: tiny's DDIM steps 20 -> 2
    Options = BevWorldOptions
    tokenizer_outputs = "latents"
    inference_options = ("ddim_steps", "guidance", "sample_seed")
    # measured (docs/bevworld.md): 2000 steps in 915 s on the idle 2-core machine; the windows' encoding
    # took about 11 min beside the test suite; the tokenizer's 600 steps 554 s idle
    training_time = ("about 15 min for the tiny configuration on an idle 2-core CPU (2000 steps at 0.46 s), plus "
                     "encoding the training windows once (about 11 min) and its tokenizer's training (about 9 min)")

    def __init__(self, options: BevWorldOptions | None = None) -> None:
        super().__init__(options)
        from pcfbench.methods.bevworld.config import tokenizer_config, world_config

        self.tok_cfg = tokenizer_config(self.options.config)
        self.world_cfg = world_config(self.options.config, self.tok_cfg)
        self.tokenizer = None
        self.world = None

    def training_steps(self) -> int:
        return self.options.steps or self.world_cfg.max_steps

    def tokenizer_spec(self):
        from pcfbench.method import resolve_method

        o = self.options
        opts = {"config": o.config, "frame": o.frame}
        if o.tokenizer_steps:
            opts["steps"] = str(o.tokenizer_steps)
        return resolve_method((TOKENIZER_METHOD, opts))

    def fit(self, train_source: TrainSource, out_dir: Path, progress: TrainingRun) -> None:
        from pcfbench.config import cache_dir
        from pcfbench.methods.bevworld.world import count_parameters
        from pcfbench.methods.copilot4d.forecaster import build_windows
        from pcfbench.training import write_curve
        from pcfbench.training.tokenized import tensor_digest

        resumed = progress.resume()
        tok_ck = self.tokenizer_checkpoint(train_source)  # before any work: missing is one error
        tokenizer = load_tokenizer(tok_ck, self.tok_cfg)
        tok_state = tokenizer.state_dict()
        if resumed is not None:
            self.check_resumed_tokenizer(out_dir, tok_ck)
        cfg, o = self.world_cfg, self.options
        strides = tuple(sorted(set(o.strides) | ({1} if o.curriculum == "on" else set())))
        progress.log(f"{self.name} ({cfg.name}, frame {o.frame}, curriculum {o.curriculum}): tokenizer {tok_ck.dir} "
                     f"(sha256 {tok_ck.sha256[:12]}), {train_source.train_on.label}")
        cache = cache_dir() / "bevworld" / "world-windows" / tok_ck.sha256[:16] / train_source.train_on.key
        g = cfg.latent_grid
        built = build_windows(None, train_source.adapter, train_source.split, cfg.n_past, cfg.n_future, strides,
                              o.anchor_every, cache, log=progress.log, frame=o.frame,
                              tokenize=window_encoder(tokenizer), token_shape=(g, g, cfg.latent_channels),
                              token_dtype=np.float32)
        windows = {"latents": built["tokens"], "poses": built["poses"],
                   "by_stride": {s: np.nonzero(built["stride"] == s)[0] for s in strides}}
        for s in strides:
            if not len(windows["by_stride"][s]):
                raise PcfbenchError(f"dataset {train_source.adapter.name!r} split {train_source.split!r}: no window "
                                    f"of stride {s} (the curriculum's stride-1 stages need one)")
        progress.log(f"{len(built['tokens'])} training windows of {cfg.frames} frames")
        manifest_config = lambda model: {  # noqa: E731
            "world": cfg.to_dict(), "tokenizer": self.tok_cfg.to_dict(), "tokenizer_sha256": tok_ck.sha256,
            "tokenizer_digest": tensor_digest(tok_state), "tokenizer_checkpoint": str(tok_ck.manifest_path),
            "parameters": count_parameters(model), "steps_target": self.training_steps(),
            "windows": int(len(built["tokens"])), "strides": list(o.strides), "frame": o.frame,
            "curriculum": o.curriculum, "cond_dropout": o.cond_dropout, "target": o.target,
        }
        out = train_world(cfg, windows, progress, steps=self.training_steps(), seed=o.seed, strides=tuple(o.strides),
                          curriculum=o.curriculum, cond_dropout=o.cond_dropout, target=o.target,
                          manifest_config=manifest_config,
                          resumed=resumed, extra_weights={f"tokenizer.{k}": v for k, v in tok_state.items()},
                          log=progress.log)
        if out["history"]:
            csv_path, png = write_curve(out["history"], Path(out_dir), "curve", world_curve_panels())
            progress.log(f"training curve: {csv_path} and {png}")

    def read_tokenizer(self, checkpoint: Checkpoint, prefix: str = "", weights: dict | None = None):
        return load_tokenizer(checkpoint, self.tok_cfg, prefix=prefix, weights=weights)

    def load(self, checkpoint: Checkpoint) -> None:
        from pcfbench.methods.bevworld.config import world_config_from_dict
        from pcfbench.methods.bevworld.world import WorldModel
        from pcfbench.training import default_device

        tokenizer, world = self.load_world(checkpoint, WorldModel(self.world_cfg), world_config_from_dict)
        mf = checkpoint.manifest_path
        conf = checkpoint.manifest.get("config", {})
        if conf.get("target", "eps") != self.options.target:
            raise CheckpointError(f"checkpoint {mf} predicts target={conf.get('target', 'eps')}, and these options "
                                  f"read its output as target={self.options.target}")
        if self.options.guidance != 1.0 and not conf.get("cond_dropout"):
            raise PcfbenchError(f"guidance={self.options.guidance}: checkpoint {mf} was trained without dropping the "
                                "action (cond_dropout=0), so it has no unconditional prediction to guide from; train "
                                "with cond_dropout > 0 (e.g. 0.1) or use guidance=1")
        self.tokenizer, self.world = tokenizer, world.to(default_device()).eval()

    # -- forecasting --------------------------------------------------------------------------
    def world_inputs(self, sample: Sample):
        """The standardised past latents (P, H, W, C') of the newest ``n_past`` past sweeps in the
        frame, every past and future sensor pose in the t=0 sensor frame (P + F, 4, 4), and
        ``T_s0_ref``."""
        import torch

        P = self.world_cfg.n_past
        if len(sample.past_points_ref) < P:
            raise PcfbenchError(f"{self.name}: sample {sample.sample_id} has {len(sample.past_points_ref)} past sweeps; "
                                f"the world model needs {P}")
        if sample.num_future > self.world_cfg.n_future:
            raise PcfbenchError(f"{self.name}: sample {sample.sample_id} asks for {sample.num_future} future sweeps; "
                                f"the world model denoises at most {self.world_cfg.n_future}")
        T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
        past = list(range(len(sample.past_points_ref)))[-P:]
        maps = []
        for k in past:
            T_s0_k = T_s0_ref @ sample.past_T_ref_sensor[k]
            pts_k = moved(sample.past_points_ref[k], np.linalg.inv(sample.past_T_ref_sensor[k]))
            maps.append(self.tokenizer.normalise(encode_sweep(self.tokenizer, pts_k,
                                                              T_s0_k if self.options.frame == "t0" else None)))
        poses = np.concatenate([sample.past_T_ref_sensor[past], sample.future_T_ref_sensor])
        return torch.stack(maps), torch.from_numpy(T_s0_ref @ poses), T_s0_ref

    def forecast_latents(self, sample: Sample):
        """Raw (de-standardised) future latents (F, H, W, C') and ``T_s0_ref``."""
        import torch

        from pcfbench.methods.bevworld.diffusion import Schedule, sample_future
        from pcfbench.methods.copilot4d.forecaster import sample_seed

        past, poses, T_s0_ref = self.world_inputs(sample)
        dev = next(self.world.parameters()).device
        cfg, o = self.world_cfg, self.options
        P, F = len(past), sample.num_future
        gen = torch.Generator(dev).manual_seed(sample_seed(sample.sample_id, o.sample_seed))
        x = sample_future(self.world, Schedule.of(cfg), past[None].to(dev), poses[None].to(dev).float(), F,
                          steps=o.ddim_steps or cfg.ddim_steps, guidance=o.guidance, target=o.target,
                          frames=torch.arange(P + F, device=dev), generator=gen)[0]
        return self.tokenizer.denormalise(x), T_s0_ref

    def forecast(self, sample: Sample) -> Forecast:
        if self.world is None:
            raise PcfbenchError(f"{self.name}: no checkpoint loaded (the runner loads it; call load() first)")
        latents, T_s0_ref = self.forecast_latents(sample)
        frames = (T_s0_ref if self.options.frame == "t0"
                  else [np.linalg.inv(T) for T in sample.future_T_ref_sensor])  # each from its own origin
        return Forecast.from_depths(sample, render_sample(self.tokenizer, latents, sample, frames))
