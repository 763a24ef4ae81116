"""OccWorld as a trained method (``occworld``): the ``occworld-occ-copy`` tokenizer of the same
configuration, tokens and frame, trained on the same data, plus the spatio-temporal
generative transformer (:mod:`.world`).

**Training** (``fit``): every training window (5 past and 5 future sweeps at strides 2 and 6,
every ``anchor_every``-th anchor; Copilot4D's ``build_windows``) is labelled and tokenized
once in the option ``frame`` (``own``: each sweep in its own sensor frame; ``t0``: moved into
the window's t=0 sensor frame) and cached under ``<cache>/occworld/world-windows/<tokenizer
sha256[:16]>/...``; the world model then learns to predict frames 1..9 from frames 0..8
(teacher forcing under the causal mask: cross entropy over the codebook + 0.1 x the next
motion's squared error) through :func:`pcfbench.training.fit_loop`. The checkpoint holds the
world model's weights (``world.``) and the tokenizer's (``tokenizer.``); its manifest records
the tokenizer checkpoint's sha256 and a digest of its tensors, which ``load`` checks.

**Forecast**: the newest 5 past sweeps are labelled and tokenized in the frame, every frame's
sensor pose moved into the t=0 sensor frame; the world model predicts the future token maps
one frame at a time (arg max, as the public inference), conditioned on the given motion into
each next frame (``pose=given``) or on its own predicted motion (``pose=predicted``, the
paper's planner); each map is decoded to occupancy probabilities (1 - p(free)) and rendered
along its sweep's query rays (``readout``) from the future sensor's origin in the frame of
that map (``t0``: the t=0 frame; ``own``: the future sensor's own frame, origin 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld.occ_copy import OccOptions, decode_grid, render_sample, sweep_labels, tokenize_labels
from pcfbench.options import option
from pcfbench.training import Checkpoint, TrainedMethod, TrainingRun, TrainSource
from pcfbench.training.tokenized import OnTokenizer

TOKENIZER_METHOD = "occworld-occ-copy"
POSES = ("given", "predicted")


@dataclass(frozen=True)
class OccWorldOptions(OccOptions):
    pose: str = option("given", help="the motion into each future frame: given (the benchmark's future poses) or "
                                     "predicted (the model's pose decoder, as the paper plans)")
    steps: int = option(0, help="training steps (0: the configuration's max_steps)", min=0)
    seed: int = option(0, help="training seed")
    tokenizer_steps: int = option(0, help="the occworld-occ-copy checkpoint used: its steps option (0: its default)",
                                  min=0)
    strides: tuple[int, ...] = option((2, 6), help="training windows: source sweeps between frames (kitti-1s "
                                                   "uses 2, kitti-3s 6)", min=1)
    anchor_every: int = option(2, help="training windows: every n-th t=0 sweep of the split", min=1)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.pose not in POSES:
            raise PcfbenchError(f"pose={self.pose!r}: expected one of {', '.join(POSES)}")


def window_tokenizer(model, cfg):
    """``build_windows``'s ``tokenize``: a sweep's occupancy labels in a frame, tokenized."""
    def tokenize(points, T_frame_sensor):
        return tokenize_labels(model, sweep_labels(cfg, points, T_frame_sensor)).cpu().numpy()
    return tokenize


def train_world(model, cfg, windows: dict, embed, run, *, steps: int, seed: int = 0, manifest_config,
                extra_weights: dict | None = None, resumed=None, log=print) -> dict:
    """The world model on ``windows`` (``tokens`` (A, T, h, w), ``poses`` (A, T, 4, 4)) through
    :func:`pcfbench.training.fit_loop`; ``embed`` maps codes to the tokenizer's code vectors."""
    import torch

    from pcfbench.methods.occworld.world import world_losses
    from pcfbench.training import fit_loop, warmup_cosine

    tokens = torch.from_numpy(windows["tokens"].astype(np.int64))
    poses = torch.from_numpy(windows["poses"].astype(np.float64))

    def sample_batch(rand, step: int):
        picks = torch.from_numpy(rand.numpy.integers(0, len(tokens), cfg.batch_size))
        return tokens[picks], poses[picks]

    def step_fn(model, batch):
        codes, pose = batch
        dev = next(model.parameters()).device
        codes = codes.to(dev)
        out = world_losses(model, codes, embed(codes), pose.to(dev).float())
        return out["loss"], {k: float(out[k].item()) for k in ("loss", "ce", "pose", "accuracy", "changed_accuracy",
                                                               "changed_share")}

    out = fit_loop(model, lambda m: torch.optim.AdamW(m.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay),
                   sample_batch, step_fn, run, steps=steps, seed=seed,
                   schedule=lambda step: warmup_cosine(step, cfg.lr, cfg.warmup, steps, cfg.min_lr_ratio),
                   grad_clip=cfg.grad_clip, log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                   progress_values={"cross entropy": "ce", "token accuracy": "accuracy",
                                    "changed-token accuracy": "changed_accuracy"},
                   weights_prefix="world.", extra_weights=extra_weights, manifest_config=manifest_config,
                   resumed=resumed, log=log)
    return {"model": out.model, "step": out.step, "history": out.history}


def world_curve_panels() -> list:
    from pcfbench.training import Panel

    return [Panel((("loss", "total loss"), ("ce", "cross entropy over the codebook"), ("pose", "next-motion MSE")),
                  log=True),
            Panel((("accuracy", "token accuracy"), ("changed_accuracy", "accuracy on tokens that changed"),
                   ("changed_share", "share of tokens that changed")), ylim=(0, 1))]


class OccWorld(OnTokenizer, TrainedMethod):
    """OccWorld: occupancy tokenizer + spatio-temporal generative transformer, autoregressive."""

    name = "occworld"
    # the default run scores 8 evenly spaced samples of each cell (its 10-minute budget on a
    # 2-core CPU; docs/protocol.md, "The default run's subset"); --subset 0 or naming the method: all
    default_run_subset = 8
    version = "1"
    Options = OccWorldOptions
    tokenizer_outputs = "tokens"
    inference_options = ("readout", "pose")
    # measured 2026-11-29 (the shipped checkpoint, idle 2-core machine): 1,398 s in all, the 216 windows about 8 min
    training_time = ("about 25 min for the tiny configuration on an idle 2-core CPU (labelling and tokenizing 216 "
                     "windows, about 8 min, then 1200 steps at about 0.8 s), plus its tokenizer's training")

    def __init__(self, options: OccWorldOptions | None = None) -> None:
        super().__init__(options)
        from pcfbench.methods.occworld.config import tokenizer_config, world_config

        self.tok_cfg = tokenizer_config(self.options.config, self.options.tokens, self.options.surface)
        self.world_cfg = world_config(self.options.config, self.tok_cfg)
        self.tokenizer = None
        self.world = None

    def training_steps(self) -> int:
        return self.options.steps or self.world_cfg.max_steps

    def tokenizer_spec(self):
        from pcfbench.method import resolve_method

        o = self.options
        opts = {"config": o.config}
        for k in ("frame", "surface"):  # the tokenizer's options as the world model's, written when not default
            if getattr(o, k) != getattr(OccOptions, k):
                opts[k] = getattr(o, k)
        if o.tokens:
            opts["tokens"] = str(o.tokens)
        if o.tokenizer_steps:
            opts["steps"] = str(o.tokenizer_steps)
        return resolve_method((TOKENIZER_METHOD, opts))

    def fit(self, train_source: TrainSource, out_dir: Path, progress: TrainingRun) -> None:
        import torch

        from pcfbench.config import cache_dir
        from pcfbench.methods.copilot4d.forecaster import build_windows
        from pcfbench.methods.occworld.occ_copy import load_tokenizer
        from pcfbench.methods.occworld.world import WorldModel, count_parameters
        from pcfbench.training import default_device, write_curve
        from pcfbench.training.tokenized import tensor_digest

        resumed = progress.resume()
        tok_ck = self.tokenizer_checkpoint(train_source)  # before any work: missing is one error
        tokenizer = load_tokenizer(tok_ck, self.tok_cfg)
        tok_state = tokenizer.state_dict()
        if resumed is not None:
            self.check_resumed_tokenizer(out_dir, tok_ck)
        cfg, o = self.world_cfg, self.options
        progress.log(f"{self.name} ({cfg.name}, frame {o.frame}): tokenizer {tok_ck.dir} (sha256 "
                     f"{tok_ck.sha256[:12]}), {train_source.train_on.label}")
        cache = cache_dir() / "occworld" / "world-windows" / tok_ck.sha256[:16] / train_source.train_on.key
        windows = build_windows(None, train_source.adapter, train_source.split, cfg.n_past, cfg.n_future,
                                tuple(o.strides), o.anchor_every, cache, log=progress.log, frame=o.frame,
                                tokenize=window_tokenizer(tokenizer, self.tok_cfg), token_shape=cfg.token_grid)
        progress.log(f"{len(windows['tokens'])} training windows of {cfg.n_past + cfg.n_future} frames")
        book = tokenizer.vq.codebook.detach().clone()

        def embed(codes):
            return book.to(codes.device)[codes].movedim(-1, -3)

        manifest_config = lambda model: {  # noqa: E731
            "world": cfg.to_dict(), "tokenizer": self.tok_cfg.to_dict(), "tokenizer_sha256": tok_ck.sha256,
            "tokenizer_digest": tensor_digest(tok_state), "tokenizer_checkpoint": str(tok_ck.manifest_path),
            "parameters": count_parameters(model), "steps_target": self.training_steps(),
            "windows": int(len(windows["tokens"])), "strides": list(o.strides), "frame": o.frame,
        }
        device = default_device()
        torch.manual_seed(o.seed)  # built on the CPU, then moved: its initial weights do not depend on the device
        out = train_world(WorldModel(cfg).to(device), cfg, windows, embed, progress, steps=self.training_steps(),
                          seed=o.seed, manifest_config=manifest_config, resumed=resumed,
                          extra_weights={f"tokenizer.{k}": v for k, v in tok_state.items()}, log=progress.log)
        if out["history"]:
            csv_path, png = write_curve(out["history"], Path(out_dir), "curve", world_curve_panels())
            progress.log(f"training curve: {csv_path} and {png}")

    def read_tokenizer(self, checkpoint: Checkpoint, prefix: str = "", weights: dict | None = None):
        from pcfbench.methods.occworld.occ_copy import load_tokenizer

        return load_tokenizer(checkpoint, self.tok_cfg, prefix=prefix, weights=weights)

    def load(self, checkpoint: Checkpoint) -> None:
        from pcfbench.methods.occworld.config import world_config_from_dict
        from pcfbench.methods.occworld.world import WorldModel
        from pcfbench.training import default_device

        tokenizer, world = self.load_world(checkpoint, WorldModel(self.world_cfg), world_config_from_dict)
        self.tokenizer, self.world = tokenizer, world.to(default_device()).eval()

    # -- forecasting --------------------------------------------------------------------------
    def world_inputs(self, sample: Sample):
        """The past token maps (P, h, w) of the newest ``n_past`` past sweeps in the frame, every
        past and future sensor pose in the t=0 sensor frame (P + F, 4, 4), and ``T_s0_ref``."""
        import torch

        T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
        past = list(range(len(sample.past_points_ref)))[-self.world_cfg.n_past:]
        maps = []
        for k in past:
            T_s0_k = T_s0_ref @ sample.past_T_ref_sensor[k]
            T_k_ref = np.linalg.inv(sample.past_T_ref_sensor[k])
            pts_k = sample.past_points_ref[k].astype(np.float64) @ T_k_ref[:3, :3].T + T_k_ref[:3, 3]
            maps.append(tokenize_labels(self.tokenizer, sweep_labels(self.tok_cfg, pts_k,
                                                                     T_s0_k if self.options.frame == "t0" else None)))
        poses = np.concatenate([sample.past_T_ref_sensor[past], sample.future_T_ref_sensor])
        return torch.stack(maps), torch.from_numpy(T_s0_ref @ poses), T_s0_ref

    def forecast_codes(self, sample: Sample):
        import torch

        from pcfbench.methods.occworld.world import forecast_codes

        past, poses, T_s0_ref = self.world_inputs(sample)
        dev = next(self.world.parameters()).device
        book = self.tokenizer.vq.codebook.detach()

        def embed(codes):
            return book[codes].movedim(-1, -3)

        with torch.no_grad():
            codes = forecast_codes(self.world, embed, past[None].to(dev), poses[None].to(dev).float(),
                                   sample.num_future, predict_poses=self.options.pose == "predicted")[0]
        return codes, T_s0_ref

    def forecast(self, sample: Sample) -> Forecast:
        if self.world is None:
            raise PcfbenchError(f"{self.name}: no checkpoint loaded (the runner loads it; call load() first)")
        codes, T_s0_ref = self.forecast_codes(sample)
        probs = [decode_grid(self.tokenizer, c) for c in codes]
        frames = (T_s0_ref if self.options.frame == "t0"
                  else [np.linalg.inv(T) for T in sample.future_T_ref_sensor])  # each from its own origin
        return Forecast.from_depths(sample, render_sample(self.tokenizer, probs, sample, frames, self.options.readout))
