"""The latent-copy baseline: BEVWorld's LiDAR tokenizer as a trained method
(``bevworld-latent-copy``).

``fit`` trains the tokenizer (L1 on rendered depth) through the one training loop on the
training split's sweeps. ``forecast`` encodes the last past sweep (t=0) in its sensor frame,
decodes its latent to a feature volume and renders it along every future sweep's query rays
from that sweep's origin moved into the t=0 frame: the world seen through the tokenizer, not
changing. What ``bevworld`` adds is measured against it.

**The frame** (option ``frame``, the world model's): ``t0`` (default) trains on sweeps moved
into the frame of another sweep of the same sequence, as far before or after it as the world
model's windows reach (Copilot4D's lesson: an encoder that only ever saw sensor-centred sweeps
fails on moved ones); ``own`` on each sweep in its own sensor frame. Either way the copy encodes
the t=0 sweep in its own frame, which is the t=0 frame. The default is the ceilings' choice
(docs/bevworld.md, "The frame, by the ceiling"): an ``own`` tokenizer's field is only right
seen from its centre (its copy, rendered from the future origins, misses by metres).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.options import option
from pcfbench.training import Checkpoint, TrainedMethod, TrainingRun, TrainSource

FRAMES = ("own", "t0")
#: the world model's windows (the protocol's settings): 5 past and 5 future frames, strides up to 6
WINDOW_PAST, WINDOW_FUTURE, MAX_STRIDE = 5, 5, 6
#: rays rendered at a time by the torch path (a GPU's; the CPU marches them with numba,
#: :mod:`.raymarch`): bounds the memory of their samples' features, and 1024 keeps them in cache
#: (a sweep 0.64x the time of 8192 at one thread, the same depths to the bit)
RENDER_CHUNK = 1024


@dataclass(frozen=True)
class BevOptions:
    """What the tokenizer and the world model share."""

    config: str = option("tiny", help="configuration: tiny (CPU scale), paper (the published sizes, the rest "
                                      "inferred) or micro (tests)")
    frame: str = option("t0", help="the frame of a window's latents: t0 (moved into the t=0 sensor frame; the "
                                   "ceiling's choice, docs/bevworld.md) or own (each sweep in its own sensor frame)")

    def __post_init__(self) -> None:
        from pcfbench.methods.bevworld.config import tokenizer_config

        if self.frame not in FRAMES:
            raise PcfbenchError(f"frame={self.frame!r}: expected one of {', '.join(FRAMES)}")
        tokenizer_config(self.config)  # one error for an unknown configuration


@dataclass(frozen=True)
class LatentCopyOptions(BevOptions):
    steps: int = option(0, help="training steps (0: the configuration's max_steps)", min=0)
    seed: int = option(0, help="training seed (initialisation, batches)")


def moved(points_sensor: np.ndarray, T_frame_sensor: np.ndarray | None) -> np.ndarray:
    if T_frame_sensor is None:
        return points_sensor
    T = np.asarray(T_frame_sensor, np.float64)
    return (points_sensor.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def make_batch(cfg, sweeps: list[tuple[np.ndarray, np.ndarray | None]], rays: int | None,
               rng: np.random.Generator, min_range: float = 0.5):
    """Copilot4D's :class:`~pcfbench.methods.copilot4d.data.Batch` of sweeps, each its points in
    its sensor frame and the transform ``T_frame_sensor`` into the frame it is seen in (None:
    its own): every moved point inside the grid is encoder input; ``rays`` of them (all when
    None) are rays from the moved sensor's origin."""
    import torch

    from pcfbench.methods.copilot4d.data import Batch, in_box

    pts, pb, origins, dirs, depth, rb = [], [], [], [], [], []
    for b, (p_sensor, T) in enumerate(sweeps):
        p = moved(p_sensor, T)
        p = p[in_box(cfg, p)]
        o = np.zeros(3, np.float32) if T is None else np.asarray(T, np.float32)[:3, 3]
        v = p - o
        r = np.linalg.norm(v, axis=1)
        ok = np.nonzero(r > min_range)[0]
        if rays is not None and len(ok) > rays:
            ok = rng.choice(ok, rays, replace=False)
        pts.append(p)
        pb.append(np.full(len(p), b))
        dirs.append(v[ok] / r[ok, None])
        depth.append(r[ok])
        origins.append(np.broadcast_to(o, (len(ok), 3)))
        rb.append(np.full(len(ok), b))
    t = lambda a, dt=torch.float32: torch.from_numpy(np.concatenate(a)).to(dt)  # noqa: E731
    return Batch(t(pts), t(pb, torch.long), t(origins), t(dirs), t(depth), t(rb, torch.long), len(sweeps))


class TokenizerSource:
    """The tokenizer's training sweeps: every sweep of a split (ego returns removed), each in its
    own frame (``own``) or moved into the frame of a sweep drawn uniformly from the window
    offsets around it (``t0``)."""

    def __init__(self, adapter, split: str, frame: str) -> None:
        self.adapter, self.frame = adapter, frame
        self.sequences = {n: adapter.sequence(n) for n in adapter.sequence_names(split)}
        self.keys = [(n, i) for n, s in self.sequences.items() for i in range(len(s))]
        if not self.keys:
            raise PcfbenchError(f"dataset {adapter.name!r} has no sweeps in split {split!r} under {adapter.root}")

    def __len__(self) -> int:
        return len(self.keys)

    def sweep(self, k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
        name, i = self.keys[k]
        seq = self.sequences[name]
        points = self.adapter.ego_box.remove(seq.load_points(i))
        if self.frame == "own":
            return points, None
        # sweep i is frame j of a window anchored at a: i - a in [-(P - 1) s, F s]
        off = int(rng.integers(-WINDOW_FUTURE * MAX_STRIDE, (WINDOW_PAST - 1) * MAX_STRIDE + 1))
        a = min(max(i + off, 0), len(seq) - 1)
        return points, np.linalg.inv(seq.T_world_sensor[a]) @ seq.T_world_sensor[i]


def train_tokenizer(cfg, source: TokenizerSource, run, *, steps: int, seed: int = 0, log=print) -> dict:
    """The tokenizer through :func:`pcfbench.training.fit_loop` (AdamW with the paper's betas,
    warm-up and cosine decay, gradient clipping at ``cfg.grad_clip``)."""
    import torch

    from pcfbench.methods.bevworld.tokenizer import LatentTokenizer, count_parameters, tokenizer_losses
    from pcfbench.training import default_device, fit_loop, warmup_cosine

    device = default_device()

    def sample_batch(rand, step: int):
        picks = rand.numpy.integers(0, len(source), cfg.batch_size)
        return make_batch(cfg, [source.sweep(int(k), rand.numpy) for k in picks], cfg.rays_per_step,
                          rand.numpy).to(device)

    def step_fn(model, batch):
        out = tokenizer_losses(model, batch)
        return out["loss"], {"loss": out["loss"].item(), "l1": out["l1"].item(), "median": out["median"].item()}

    out = fit_loop(lambda: LatentTokenizer(cfg).to(device),
                   lambda m: torch.optim.AdamW(m.parameters(), lr=cfg.lr, betas=cfg.betas,
                                               weight_decay=cfg.weight_decay),
                   sample_batch, step_fn, run, steps=steps, seed=seed,
                   schedule=lambda step: warmup_cosine(step, cfg.lr, cfg.warmup, steps, cfg.min_lr_ratio),
                   grad_clip=cfg.grad_clip, log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                   progress_values={"L1 depth error (m)": "l1", "median depth error (m)": "median"},
                   manifest_config=lambda m: {"tokenizer": cfg.to_dict(), "parameters": count_parameters(m),
                                              "steps_target": steps, "seed": seed, "frame": source.frame},
                   log=log)
    return {"model": out.model, "step": out.step, "history": out.history}


def tokenizer_curve_panels() -> list:
    from pcfbench.training import Panel

    return [Panel((("l1", "mean L1 depth error (m)"), ("median", "median L1 depth error (m)")), log=True)]


def load_tokenizer(checkpoint: Checkpoint, cfg, prefix: str = "", weights: dict | None = None):
    """The tokenizer of ``checkpoint`` (weights under ``prefix``), which must record ``cfg``;
    ``weights``: its weights already read (``checkpoint.load_weights()``), else read here."""
    from pcfbench.methods.bevworld.config import tokenizer_config_from_dict
    from pcfbench.methods.bevworld.tokenizer import LatentTokenizer
    from pcfbench.training import CheckpointError, default_device
    from pcfbench.training.tokenized import load_network

    recorded = checkpoint.manifest.get("config", {}).get("tokenizer")
    if not isinstance(recorded, dict):
        raise CheckpointError(f"checkpoint {checkpoint.manifest_path} records no config.tokenizer: not a bevworld one")
    if tokenizer_config_from_dict(recorded) != cfg:
        raise CheckpointError(f"checkpoint {checkpoint.manifest_path} was trained with another '{cfg.name}' tokenizer "
                              "configuration than this pcfbench defines; retrain it with --fresh")
    weights = checkpoint.load_weights() if weights is None else weights
    model = load_network(LatentTokenizer(cfg), checkpoint, weights, prefix, "tokenizer")
    return model.to(default_device()).eval()


def encode_sweep(model, points_sensor: np.ndarray, T_frame_sensor: np.ndarray | None = None):
    """The raw latent (H, W, C') of one sweep (its points in its sensor frame) seen in the frame
    ``T_frame_sensor`` maps its sensor frame into (None: its own)."""
    import torch

    from pcfbench.methods.copilot4d.data import in_box

    p = moved(points_sensor, T_frame_sensor)
    p = torch.from_numpy(np.ascontiguousarray(p[in_box(model.cfg, p)], np.float32))
    dev = next(model.parameters()).device
    with torch.no_grad():
        return model.encode(p.to(dev), torch.zeros(len(p), dtype=torch.long, device=dev), 1)[0]


def render_sample(model, latents, sample: Sample, T_frame_ref) -> list[np.ndarray]:
    """Depths along every future sweep's query rays: ``latents`` one raw latent (H, W, C') per
    future sweep (or one for all), latent k in the frame ``T_frame_ref[k]`` maps the reference
    frame into (one 4x4 for all, or one per sweep); the query's origin and directions are moved
    there, the latent decoded and rendered (:func:`render_volume`)."""
    import torch

    F = sample.num_future
    Ts = [np.asarray(T_frame_ref, np.float64)] * F if np.ndim(T_frame_ref) == 2 else list(T_frame_ref)
    zs = [latents] * F if getattr(latents, "dim", lambda: 0)() == 3 else list(latents)
    dev = next(model.parameters()).device
    out, volume, decoded = [], None, None
    with torch.no_grad():
        for k, q in enumerate(sample.queries):
            if decoded is not zs[k]:  # one decode when one latent serves every sweep
                volume, decoded = model.decode(zs[k][None].to(dev), channels_last=dev.type == "cpu")[0], zs[k]
            R, t = Ts[k][:3, :3], Ts[k][:3, 3]
            dirs = torch.from_numpy((q.directions_ref.astype(np.float64) @ R.T).astype(np.float32)).to(dev)
            o = torch.from_numpy((R @ q.origin_ref + t).astype(np.float32)).to(dev)
            out.append(render_volume(model, volume, o, dirs).astype(np.float64))
    return out


def render_volume(model, volume, origin, dirs) -> np.ndarray:
    """Expected depths (float32 numpy, (R,)) of rays from one ``origin`` (3,) along unit ``dirs``
    (R, 3) (tensors in the grid frame) through one decoded ``volume`` (F, Z, X, Y) of
    ``model``, at inference: on the CPU by the numba marcher (:func:`.raymarch.march`, its
    early stop included: docs/bevworld.md, "Inference time"), elsewhere by the torch path
    training uses, ``RENDER_CHUNK`` rays at a time."""
    from pcfbench.methods.bevworld import raymarch
    from pcfbench.methods.bevworld.render import render_rays
    from pcfbench.methods.copilot4d.render import box_interval

    cfg = model.cfg
    if origin.shape != (3,):
        raise ValueError(f"render_volume: one origin (3,) for every ray, not {tuple(origin.shape)}")
    if len(dirs) == 0:
        return np.zeros(0, np.float32)
    origins = origin.expand(len(dirs), 3)
    if volume.device.type != "cpu":
        return render_rays(model, volume, origins, dirs, n=cfg.samples_per_ray, jitter=False,
                           chunk=RENDER_CHUNK)[0].cpu().numpy()
    near, far = box_interval(cfg, origins, dirs)
    mlp = tuple(p.detach().float().numpy() for p in (model.decoder.mlp1.weight, model.decoder.mlp1.bias,
                                                       model.decoder.mlp2.weight, model.decoder.mlp2.bias))
    box = ((cfg.x_range[0], cfg.y_range[0], cfg.z_range[0]), (cfg.x_range[1], cfg.y_range[1], cfg.z_range[1]))
    return raymarch.march(volume.float().permute(2, 3, 1, 0).numpy(), origin.numpy(), dirs.numpy(), near.numpy(),
                          far.numpy(), box, mlp, samples=cfg.samples_per_ray)


class LatentCopy(TrainedMethod):
    """BEVWorld's tokenizer rendering the t=0 sweep's latent from every future pose."""

    name = "bevworld-latent-copy"
    version = "1"
    Options = LatentCopyOptions
    # out of the default run, for its 10-minute budget: beside bevworld it took the README's first
    # command to 688 s (2026-11-30, docs/bevworld.md); `-m bevworld-latent-copy` runs it
    in_default_runs = False
    # measured: the tiny tokenizer trained in frame t0 on the idle 2-core machine (docs/bevworld.md)
    training_time = "about 9 min for the tiny configuration on an idle 2-core CPU (600 steps in 554 s, frame t0)"

    def __init__(self, options: LatentCopyOptions | None = None) -> None:
        super().__init__(options)
        from pcfbench.methods.bevworld.config import tokenizer_config

        self.cfg = tokenizer_config(self.options.config)
        self.model = None

    def training_steps(self) -> int:
        return self.options.steps or self.cfg.max_steps

    def fit(self, train_source: TrainSource, out_dir: Path, progress: TrainingRun) -> None:
        from pcfbench.training import write_curve

        source = TokenizerSource(train_source.adapter, train_source.split, self.options.frame)
        progress.log(f"bevworld tokenizer {self.cfg.name} ({self.cfg.latent_grid}x{self.cfg.latent_grid}x"
                     f"{self.cfg.latent_channels} latent, frame {self.options.frame}): {len(source)} "
                     f"{train_source.split} sweeps of {train_source.adapter.name}")
        out = train_tokenizer(self.cfg, source, progress, steps=self.training_steps(), seed=self.options.seed,
                              log=progress.log)
        if out["history"]:
            csv_path, png = write_curve(out["history"], Path(out_dir), "curve", tokenizer_curve_panels())
            progress.log(f"training curve: {csv_path} and {png}")

    def load(self, checkpoint: Checkpoint) -> None:
        self.model = load_tokenizer(checkpoint, self.cfg)

    def forecast(self, sample: Sample) -> Forecast:
        if self.model is None:
            raise PcfbenchError(f"{self.name}: no checkpoint loaded (the runner loads it; call load() first)")
        return copy_forecast(self.model, sample)


def copy_forecast(model, sample: Sample) -> Forecast:
    """The latent copy: the t=0 sweep encoded in its sensor frame, decoded and rendered along
    every future query ray from its origin in that frame."""
    T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
    last = moved(sample.past_points_ref[-1], T_s0_ref)
    return Forecast.from_depths(sample, render_sample(model, encode_sweep(model, last), sample, T_s0_ref))
