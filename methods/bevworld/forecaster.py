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
frames before it at stride 1, then all future frames at stride 1, then the ``strides``. With
a render stage (``render_weight`` > 0; ``tiny``'s default, not the paper's: :mod:`.render_loss`),
``render_steps`` more steps follow at a constant learning rate, the predicted future latents'
rendered depth L1 added to the loss. The checkpoint holds the world model's weights (``world.``) and the tokenizer's (``tokenizer.``);
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
    render_weight: float = option(-1.0, help="the render stage's weight on the rendered depth L1 (m) beside the "
                                             "latent MSE (-1: the configuration's, 1 in tiny, none in paper; "
                                             "0: no render stage; not the paper's)", min=-1.0)
    render_steps: int = option(0, help="the render stage's steps after the latent training (0: the "
                                       "configuration's, 300 in tiny)", min=0)
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
        if self.render_weight not in (-1.0, 0.0) and self.render_weight < 0:
            raise PcfbenchError(f"render_weight={self.render_weight}: expected -1 (the configuration's), 0 or a "
                                "positive weight")
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
    count, the windows' indices (B,)). Stage 1: frames n_past - 2 .. n_past of stride-1 windows
    (the next frame from 2); stage 2: stride-1 windows whole; stage 3 (and the render stage):
    windows of ``strides``."""
    import torch

    pool = windows["by_stride"][1] if stage < 3 else np.concatenate([windows["by_stride"][s] for s in strides])
    picks = pool[picks_rng.integers(0, len(pool), batch_size)]
    lat, poses = windows["latents"][picks], windows["poses"][picks]
    if stage == 1:
        frames = np.arange(n_past - 2, n_past + 1)
        lat, poses, past = lat[:, frames], poses[:, frames], 2
    else:
        frames, past = np.arange(lat.shape[1]), n_past
    return torch.from_numpy(lat), torch.from_numpy(poses), torch.from_numpy(frames), past, picks


#: the render stage's number in the curve's ``stage`` column (after the curriculum's 1-3)
RENDER_STAGE = 4


@dataclass(frozen=True)
class RenderStage:
    """What the render stage (:mod:`.render_loss`) needs: the frozen tokenizer, the future
    sweeps' returns, whether latents are in each sweep's own frame, its weight and steps."""

    tokenizer: object
    rays: object  # a render_loss.WindowRays
    own: bool
    weight: float
    steps: int


def reseed_stage(rand, seed: int, stage: int) -> None:
    """Reseed the loop's streams (``rand``'s numpy and torch generators, torch's global one) from
    ``(seed, stage)`` in place: a stage that starts here draws the same windows, rays, timesteps,
    noise and jitter whatever the steps before it drew (how many latent steps, which
    curriculum). The loop saves the streams after each step, so a resumed run goes on from where
    the stage had got to."""
    import torch

    words = np.random.SeedSequence([seed, stage]).generate_state(3, np.uint64)
    rand.numpy.bit_generator.state = np.random.default_rng(int(words[0])).bit_generator.state
    if rand.torch is not None:
        rand.torch.manual_seed(int(words[1]))
    torch.manual_seed(int(words[2]))


def train_world(cfg, windows: dict, run, *, steps: int, seed: int, strides: tuple[int, ...], curriculum: str,
                cond_dropout: float, target: str, manifest_config, extra_weights: dict | None = None, resumed=None,
                render: RenderStage | None = None, log=print) -> dict:
    """The world model on ``windows`` through :func:`pcfbench.training.fit_loop` (AdamW, warm-up
    and cosine decay over ``steps``); the diffusion's timesteps and noise come from the loop's
    torch stream. With ``render``, ``render.steps`` more steps follow at the constant
    ``cfg.render_lr`` with the optimiser's state cleared and the streams reseeded
    (:func:`reseed_stage`), the render loss added (:mod:`.render_loss`); the steps before it draw
    exactly what they draw without it."""
    import torch

    from pcfbench.methods.bevworld.diffusion import Schedule, diffusion_loss
    from pcfbench.methods.bevworld.render_loss import render_l1
    from pcfbench.methods.bevworld.world import WorldModel
    from pcfbench.training import default_device, fit_loop, warmup_cosine

    schedule = Schedule.of(cfg)
    device = default_device()
    total = steps + (render.steps if render is not None else 0)

    def sample_batch(rand, step: int):
        stage = stage_of(step, steps, curriculum) if step < steps else RENDER_STAGE
        if step == steps and render is not None:
            reseed_stage(rand, seed, RENDER_STAGE)
        lat, poses, frames, past, picks = stage_batch(windows, min(stage, 3), cfg.n_past, strides, rand.numpy,
                                                      cfg.batch_size)
        rays = []
        if stage == RENDER_STAGE:
            tcfg = render.tokenizer.cfg
            for b, w in enumerate(picks.tolist()):
                for f in rand.numpy.choice(cfg.n_future, cfg.render_frames, replace=False).tolist():
                    r = render.rays.rays(tcfg, w, cfg.n_past + f, render.own, cfg.render_rays, rand.numpy)
                    if r is not None:
                        rays.append((b, f, *(torch.from_numpy(a).to(device) for a in r)))
        return lat.to(device), poses.to(device), frames.to(device), past, stage, rays, rand.torch

    def step_fn(model, batch):
        lat, poses, frames, past, stage, rays, gen = batch
        out = diffusion_loss(model, schedule, lat, poses, past, frames=frames, cond_dropout=cond_dropout,
                             target=target, generator=gen)
        keys = ("loss", "mse", "changed", "static", "copy_changed", "copy_static", "changed_share")
        loss, logged = out["loss"], {"render_l1": float("nan")}
        if rays:
            # the decoder's transmittance underflows behind sharp surfaces; subnormal floats there make
            # its backward several times slower on x86 (docs/bevworld.md); this stage is new, so flushing
            # them changes no earlier training's numbers
            torch.set_flush_denormal(True)
            l1 = render_l1(render.tokenizer, out["x0"], rays)
            loss = loss + render.weight * l1
            logged["render_l1"] = float(l1.detach())
        return loss, {**{k: float(out[k].detach()) for k in keys}, **logged, "loss": float(loss.detach()),
                      "stage": float(stage)}

    def lr(step: int) -> float:
        return warmup_cosine(step, cfg.lr, cfg.warmup, steps, cfg.min_lr_ratio) if step < steps else cfg.render_lr

    def after_step(model, opt, step: int):
        # the render stage starts its optimiser afresh: AdamW's second moments hold the latent loss's
        # gradient scale, and the depth loss's larger gradients divided by them would take steps far
        # larger than render_lr for the hundreds of steps they take to adapt (the stage was measured
        # with a fresh AdamW)
        if render is not None and step == steps - 1:
            opt.state.clear()

    shown = {"loss": "mse", "changed cells": "changed", "curriculum stage": "stage"}
    if render is not None:
        shown["rendered depth L1 (m)"] = "render_l1"
    try:
        out = fit_loop(lambda: WorldModel(cfg).to(device),
                       lambda m: torch.optim.AdamW(m.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay),
                       sample_batch, step_fn, run, steps=total, seed=seed, torch_generator=True, schedule=lr,
                       after_step=after_step,
                       grad_clip=cfg.grad_clip, log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                       progress_values=shown, weights_prefix="world.", extra_weights=extra_weights,
                       manifest_config=manifest_config, resumed=resumed, log=log)
    finally:
        torch.set_flush_denormal(False)
    return {"model": out.model, "step": out.step, "history": out.history}


def world_curve_panels() -> list:
    from pcfbench.training import Panel

    return [Panel((("mse", "loss (MSE of the target)"),), log=True),
            Panel((("changed", "loss, cells that change"), ("copy_changed", "latent copy's, cells that change"),
                   ("static", "loss, cells that do not"), ("copy_static", "latent copy's, cells that do not")),
                  log=True),
            Panel((("render_l1", "rendered depth L1 (m), render stage"),)),
            Panel((("stage", "curriculum stage (4: render stage)"),))]


class BevWorld(OnTokenizer, TrainedMethod):
    """BEVWorld: a continuous BEV latent tokenizer + latent diffusion transformer, DDIM."""

    name = "bevworld"
    # the default run scores 8 evenly spaced samples of each cell (its 10-minute budget on a
    # 2-core CPU; docs/protocol.md, "The default run's subset"); --subset 0 or naming the method: all
    default_run_subset = 8
    version = "3"  # 2: tiny's DDIM steps 20 -> 2; 3: tiny's render stage (300 steps, weight 1)
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

    def latent_steps(self) -> int:
        """The latent training's steps (the render stage's follow them)."""
        return self.options.steps or self.world_cfg.max_steps

    def training_steps(self) -> int:
        return self.latent_steps() + self.render_plan()[1]

    def render_plan(self) -> tuple[float, int]:
        """The render stage's (weight, steps); (0, 0) without one."""
        o, cfg = self.options, self.world_cfg
        weight = cfg.render_weight if o.render_weight < 0 else o.render_weight
        steps = o.render_steps or cfg.render_steps
        if o.render_weight > 0 and not steps:
            raise PcfbenchError(f"render_weight={o.render_weight}: configuration {cfg.name!r} has no render stage "
                                "steps; give render_steps too")
        return (weight, steps) if weight > 0 and steps > 0 else (0.0, 0)

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
        from pcfbench.training import default_device, write_curve
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
        weight, render_steps = self.render_plan()
        render = None
        if render_steps:
            from pcfbench.methods.bevworld.render_loss import WindowRays

            if o.target != "change":
                raise PcfbenchError(f"{self.name}: the render stage renders the predicted clean latents, which "
                                    f"target={o.target} does not give stably; use target=change or render_weight=0")
            rays = WindowRays(train_source.adapter, built, cfg.n_past, per_sweep=cfg.render_per_sweep, seed=o.seed,
                              log=progress.log)
            tokenizer.eval()
            for p in tokenizer.parameters():
                p.requires_grad_(False)
            render = RenderStage(tokenizer.to(default_device()), rays, o.frame == "own", weight, render_steps)
        manifest_config = lambda model: {  # noqa: E731
            "world": cfg.to_dict(), "tokenizer": self.tok_cfg.to_dict(), "tokenizer_sha256": tok_ck.sha256,
            "tokenizer_digest": tensor_digest(tok_state), "tokenizer_checkpoint": str(tok_ck.manifest_path),
            "parameters": count_parameters(model), "steps_target": self.training_steps(),
            "windows": int(len(built["tokens"])), "strides": list(o.strides), "frame": o.frame,
            "curriculum": o.curriculum, "cond_dropout": o.cond_dropout, "target": o.target,
            "render_weight": weight, "render_steps": render_steps,
        }
        out = train_world(cfg, windows, progress, steps=self.latent_steps(), seed=o.seed, strides=tuple(o.strides),
                          curriculum=o.curriculum, cond_dropout=o.cond_dropout, target=o.target,
                          manifest_config=manifest_config,
                          resumed=resumed, extra_weights={f"tokenizer.{k}": v for k, v in tok_state.items()},
                          render=render, log=progress.log)
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
