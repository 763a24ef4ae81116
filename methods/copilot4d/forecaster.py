"""The Copilot4D world model as two trained methods: ``copilot4d`` (absorbing-uniform discrete
diffusion, Algorithms 1 and 2) and ``copilot4d-maskgit`` (the same network and tokenizer
trained and sampled as MaskGIT). One class; the :class:`~.diffusion.Variant` is the only
difference.

**The frame** (option ``frame``). ``t0``: every sweep of a window is tokenized in the sensor
frame of its t=0 sweep (the last past frame, the harness's reference sweep), and a predicted
future token map is rendered along the future sweep's query rays from the future sensor origin
expressed in that frame, as the token-copy baseline renders the t=0 tokens. ``own``: every
sweep is tokenized in its own sensor frame, and a future map is rendered from its own origin.
Either way the actions are each frame's 4x4 sensor pose in the t=0 sensor frame
(``inv(T_ref_s0) @ T_ref_sensor_k``; identity at t=0). A static world keeps only part of its
tokens in the t=0 frame, and with the shipped ``tiny`` tokenizer (trained on sensor-centred
sweeps) too few at kitti-3s; ``config=tiny-window`` works on a tokenizer trained on sweeps moved
as the windows move them, whose t0 ceiling beats its token copy at both horizons. ``pcfbench
tokenizer-report --ceiling`` measures each frame's ceiling (docs/copilot4d.md).

**Training** (``fit``): the ``copilot4d-token-copy`` checkpoint of the same configuration
trained on the same data tokenizes every training window once (cached under
``<cache>/copilot4d/world-windows/<tokenizer sha256[:16]>/...``); the world model then trains
with Algorithm 1 (mixture of objectives) through the :class:`~pcfbench.training.TrainingRun`
(periodic checkpoints, exact resume). The checkpoint holds the world model's weights and the
tokenizer's (prefixes ``world.`` and ``tokenizer.``) and its manifest records the tokenizer's
checkpoint sha256 and a digest of its tensors, which ``load`` checks.

**Forecast**: Algorithm 2 one future frame at a time (``sampling_steps`` K, guidance weight
``cfg_weight``, each token drawn among its ``top_k`` guided logits), seeded by the sample id and
``seed``, so a forecast is reproducible.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.methods.copilot4d.options import RenderingOptions
from pcfbench.options import option
from pcfbench.training import Checkpoint, CheckpointError, TrainedMethod, TrainingRun, TrainSource
from pcfbench.training.tokenized import OnTokenizer, load_network, tensor_digest

TOKENIZER_METHOD = "copilot4d-token-copy"
CHECKPOINT_EVERY = 100
#: ``neighbour_targets``: the share of the target's mass its k nearest codes share
NEIGHBOUR_SHARE = 0.5
LOG_EVERY = 10


@dataclass(frozen=True)
class WorldOptions(RenderingOptions):
    config: str = option("tiny-window", help="world model and tokenizer configuration: tiny-window (the default: "
                                             "tiny on the tiny-window tokenizer, trained on sweeps moved as the "
                                             "windows move them), tiny (CPU scale, on the tiny tokenizer), "
                                             "tiny-window-view (tiny-window told where each frame's sensor sees every "
                                             "token from; not the paper's), tiny-views (on tiny-views), paper (A.2.2 "
                                             "sizes) or wide (the paper's network on the tiny tokenizer; GPU scale)")
    cfg_weight: float = option(2.0, help="classifier-free guidance weight w (0: no guidance; 1 is not 'none')",
                               min=0)
    sampling_steps: int = option(10, help="Algorithm 2 steps K per future frame", min=1)
    top_k: int = option(3, help="Algorithm 2 samples each token among its top_k guided logits (1: arg max)",
                        min=1)
    seed: int = option(0, help="sampler seed, combined with the sample id (training uses seed 0)")
    steps: int = option(0, help="training steps (0: the configuration's max_steps); the learning rate's cosine "
                                "decay runs over them", min=0)
    tokenizer_steps: int = option(0, help="the copilot4d-token-copy checkpoint used: its steps option "
                                          "(0: its default)", min=0)
    strides: tuple[int, ...] = option((2, 6), help="training windows: source sweeps between frames, one "
                                                   "stride drawn per window (kitti-1s uses 2, kitti-3s 6)", min=1)
    anchor_every: int = option(1, help="training windows: every n-th t=0 sweep of the split", min=1)
    frame: str = option("t0", help="the frame every sweep of a window is tokenized in: t0 (moved into the t=0 "
                                   "sensor frame) or own (its own sensor frame; the poses say where it is)")
    init_steps: int | tuple[int, ...] = option(
        0, help="train on from the complete checkpoint of these options with steps=init_steps (its weights; a new "
                "optimiser, warm-up and cosine decay over steps); 0: from random weights; a chain a/b/c: from the "
                "training with steps=c that went on from init_steps=a/b", min=0, quiet_default=True)
    mbr: bool = option(False, help="choose each token's code as the one of least expected codebook distance under "
                                   "the guided distribution (minimum Bayes risk; not the paper's), instead of "
                                   "sampling among the top_k", quiet_default=True)
    change_confidence: float = option(
        0.0, help="a future token takes a code other than the t=0 map's only where its guided probability is more "
                  "than this (not the paper's; 1: the t=0 map, token-copy's forecast); 0: off", min=0, max=1,
        quiet_default=True)
    soft_mix: float = option(
        0.0, help="render each future map from code embeddings mixed by the model's distribution instead of its "
                  "sampled codes (not the paper's): at every token, this weight times the expected code embedding "
                  "under the guided distribution of Algorithm 2's last step, plus the rest times the embedding of "
                  "the t=0 map's code (1: the distribution alone); the sampled codes still make the next frame's "
                  "context; 0: off", min=0, max=1, quiet_default=True)
    neighbour_targets: int = option(
        0, help="train towards the true code and its k nearest codes in the codebook (half the mass shared "
                "among the k; not the paper's): near codes render nearly alike; 0: the true code (label "
                "smoothing 0.1)", min=0, quiet_default=True)
    render_weight: float = option(
        0.0, help="train through the rendering (not the paper's): add this weight times the L1 depth error (m) of "
                  "one future frame rendered from the model's masked tokens (this training only, not those it "
                  "goes on from; measured harmful at 1: docs/copilot4d.md); 0: cross entropy alone", min=0,
        quiet_default=True)
    stride_models: tuple[int, ...] = option(
        (), help="strides forecast by a network of their own, as the paper trains one model per horizon: each the "
                 "complete training of these options with strides=S alone (and steps=stride_steps), used for the "
                 "samples whose frame spacing is nearest that stride's training windows'; the other strides keep "
                 "the network trained on all of strides; (): one network for every stride", min=1,
        quiet_default=True)
    stride_steps: int = option(0, help="with stride_models: the training steps of each stride's own network "
                                       "(0: steps)", min=0, quiet_default=True)
    stride_cfg_weight: float | None = option(
        None, help="with stride_models: the guidance weight w of the samples a stride's own network forecasts "
                   "(inference only; default: cfg_weight)", min=0, quiet_default=True)
    stride_soft_mix: float | None = option(
        None, help="with stride_models: soft_mix of the samples a stride's own network forecasts (inference only; "
                   "default: soft_mix)", min=0, max=1, quiet_default=True)
    one_pass: bool = option(
        False, help="decode every future frame at once, each token the guided arg max of one network pass over the "
                    "past and all-mask future frames (the future-prediction objective's input at a full mask; not "
                    "the paper's sampler, which decodes one frame at a time, each joining the next one's context); "
                    "needs sampling_steps=1 and top_k=1 (inference only)", quiet_default=True)
    stride_ensemble: bool = option(
        False, help="with stride_models: forecast a stride that has a network of its own with that network and the "
                    "network of every stride (trained on its windows too) together, by the mean of their "
                    "log-probabilities (not the paper's; inference only)", quiet_default=True)

    def __post_init__(self) -> None:
        super().__post_init__()
        from pcfbench.methods.copilot4d.evaluate import CEILING_FRAMES

        if self.frame not in CEILING_FRAMES:
            raise PcfbenchError(f"frame={self.frame!r}: expected one of {', '.join(CEILING_FRAMES)}")
        if self.change_confidence > 0 and self.frame != "t0":
            raise PcfbenchError(f"change_confidence={self.change_confidence:g} keeps the t=0 map's codes: it needs "
                                f"frame=t0, not frame={self.frame}")
        for name, mix in (("soft_mix", self.soft_mix), ("stride_soft_mix", self.stride_soft_mix or 0.0)):
            if 0 < mix < 1 and self.frame != "t0":
                raise PcfbenchError(f"{name}={mix:g} mixes in the t=0 map's codes: it needs frame=t0, not "
                                    f"frame={self.frame} ({name}=1 renders the distribution alone in any frame)")
            if mix > 0 and self.change_confidence > 0:
                raise PcfbenchError(f"{name}={mix:g} renders the model's distribution and "
                                    f"change_confidence={self.change_confidence:g} gates its codes: one at a time")
        if self.one_pass and (self.sampling_steps != 1 or self.top_k != 1 or self.mbr or self.change_confidence):
            raise PcfbenchError("one_pass=true takes each future token's guided arg max in one pass: it needs "
                                "sampling_steps=1 and top_k=1, and not mbr or change_confidence (they choose among "
                                "Algorithm 2's samples)")
        if self.stride_models:
            shown = "/".join(map(str, self.stride_models))
            if len(set(self.stride_models)) != len(self.stride_models) or not set(self.stride_models) <= set(self.strides):
                raise PcfbenchError(f"stride_models={shown}: expected distinct strides among strides="
                                    f"{'/'.join(map(str, self.strides))}")
            if self.init_steps or self.render_weight or self.neighbour_targets:
                raise PcfbenchError(f"stride_models={shown} puts together trainings of the plain recipe: not with "
                                    "init_steps, render_weight or neighbour_targets")
            if self.stride_ensemble and set(self.strides) <= set(self.stride_models):
                raise PcfbenchError(f"stride_ensemble=true forecasts with the network of every stride beside a "
                                    f"stride's own: stride_models={shown} leaves none of strides="
                                    f"{'/'.join(map(str, self.strides))} to train it")
        else:
            named = [f"{k}={v}" for k, v in (("stride_steps", self.stride_steps or None),
                                             ("stride_cfg_weight", self.stride_cfg_weight),
                                             ("stride_soft_mix", self.stride_soft_mix),
                                             ("stride_ensemble", "true" if self.stride_ensemble else None))
                     if v is not None]
            if named:
                raise PcfbenchError(f"{named[0]} applies to the stride_models' networks: name stride_models too")
        if isinstance(self.init_steps, tuple) and (len(self.init_steps) < 2 or 0 in self.init_steps):
            shown = "/".join(map(str, self.init_steps)) + ("/" if len(self.init_steps) == 1 else "")
            raise PcfbenchError(f"init_steps={shown}: expected one number of steps "
                                "or a chain of two or more, none of them 0")

    @property
    def init_chain(self) -> tuple[int, ...]:
        """The steps of the trainings this one goes on from, first to last (() from random weights)."""
        if isinstance(self.init_steps, tuple):
            return self.init_steps
        return (self.init_steps,) if self.init_steps else ()


def sample_seed(sample_id: str, seed: int) -> int:
    return int.from_bytes(hashlib.sha256(f"{sample_id}#{seed}".encode()).digest()[:8], "little")


def relative_poses(T_ref_s0: np.ndarray, T_ref_sensor: np.ndarray) -> np.ndarray:
    """Poses (..., 4, 4) of ``T_ref_sensor`` in the sensor frame of ``T_ref_s0``."""
    return np.linalg.inv(T_ref_s0) @ T_ref_sensor


def transform(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    return (points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


# --------------------------------------------------------------------------- training windows
def window_cache_dir(tokenizer_sha: str, train_on_key: str) -> Path:
    from pcfbench.config import cache_dir

    return cache_dir() / "copilot4d" / "world-windows" / tokenizer_sha[:16] / train_on_key


def window_sweeps(n_past: int, n_future: int, stride: int, anchor_every: int, *, n_sweeps: int | None = None,
                  n_windows: int | None = None) -> np.ndarray:
    """(A, T) sweep indices of training windows, T = n_past + n_future: window a, anchored at
    sweep ``i_a = (n_past - 1) stride + a anchor_every``, holds sweeps ``i_a + (j - n_past + 1)
    stride``. Every window that fits in a sequence of ``n_sweeps`` sweeps, or the first
    ``n_windows`` (a cached window file keeps no anchors: its count gives them back)."""
    if (n_sweeps is None) == (n_windows is None):
        raise PcfbenchError("window_sweeps: give exactly one of n_sweeps and n_windows")
    first = (n_past - 1) * stride
    if n_windows is None:
        n_windows = len(range(first, n_sweeps - n_future * stride, anchor_every))
    anchors = first + anchor_every * np.arange(n_windows, dtype=np.int64)
    return anchors[:, None] + (np.arange(n_past + n_future, dtype=np.int64) - n_past + 1) * stride


def build_windows(tokenizer, adapter, split: str, n_past: int, n_future: int, strides: tuple[int, ...],
                  anchor_every: int, cache: Path | None, log=print, frame: str = "t0", tokenize=None,
                  token_shape: tuple[int, ...] | None = None, token_dtype=np.int16) -> dict[str, np.ndarray]:
    """Token maps of every training window: ``tokens`` (A, T, H, W) int16, ``poses`` (A, T, 4, 4)
    float32 (each frame's sensor pose in the window's t=0 sensor frame), ``stride`` (A,), and
    where each frame comes from: ``sequence`` (A,) (an index into ``sequences``, the split's
    sequence names) and ``sweeps`` (A, T) (the sweep's index in its sequence).

    A window of stride s anchored at sweep i holds sweeps i + (j - n_past + 1) s, j = 0..T-1,
    each tokenized (ego returns removed) in the ``frame`` of ``WorldOptions``: ``t0``, after
    moving its points into sweep i's sensor frame; ``own``, in its own sensor frame. Cached per
    (sequence, stride, anchor spacing, frame) under ``cache``.

    ``tokenize(points_sensor, T_frame_sensor)`` (another world model's tokenizer, with its
    ``token_shape``) gives the (H, W) token map of a sweep seen in the frame ``T_frame_sensor``
    maps its sensor frame into (None: its own frame); default: the Copilot4D ``tokenizer``'s.
    ``token_dtype``: what the token maps are stored as (a continuous latent's: float32)."""
    if tokenize is None:
        from pcfbench.methods.copilot4d.evaluate import tokenize_sweep

        def tokenize(points, T_frame_sensor):
            moved = points if T_frame_sensor is None else transform(points, T_frame_sensor)
            return tokenize_sweep(tokenizer, moved).cpu().numpy()

        token_shape = (tokenizer.cfg.bev_tokens, tokenizer.cfg.bev_tokens)
    T = n_past + n_future
    toks, poses, strides_out, seq_out, sweeps_out = [], [], [], [], []
    names = list(adapter.sequence_names(split))
    for q, name in enumerate(names):
        seq = None
        own_tokens: dict[int, np.ndarray] = {}  # frame own: each sweep tokenized once, whatever its windows
        for s in strides:
            key = f"P{n_past}F{n_future}-s{s}-every{anchor_every}" + ("" if frame == "t0" else f"-{frame}")
            path = None if cache is None else cache / key / f"{name}.npz"
            if path is not None and path.is_file():
                with np.load(path, allow_pickle=False) as z:
                    t, p = z["tokens"], z["poses"]
            else:
                seq = seq or adapter.sequence(name)
                sweeps = window_sweeps(n_past, n_future, s, anchor_every, n_sweeps=len(seq))
                t = np.zeros((len(sweeps), T, *token_shape), token_dtype)
                p = np.zeros((len(sweeps), T, 4, 4), np.float32)
                clouds: dict[int, np.ndarray] = {}
                t0 = time.monotonic()
                for a, i in enumerate(sweeps[:, n_past - 1]):
                    T_s0_world = np.linalg.inv(seq.T_world_sensor[i])
                    for j in range(T):
                        k = int(sweeps[a, j])
                        T_s0_k = T_s0_world @ seq.T_world_sensor[k]
                        p[a, j] = T_s0_k
                        if frame == "own":  # a sweep's tokens in its own frame do not depend on the window
                            if k not in own_tokens:
                                points = adapter.ego_box.remove(seq.load_points(k))
                                own_tokens[k] = tokenize(points, None)
                            t[a, j] = own_tokens[k]
                            continue
                        if k not in clouds:
                            clouds[k] = adapter.ego_box.remove(seq.load_points(k))
                        t[a, j] = tokenize(clouds[k], T_s0_k)
                    for k in [k for k in clouds if k < sweeps[a, 0] + anchor_every]:  # before the next window's first
                        del clouds[k]
                log(f"{name} stride {s}: {len(sweeps)} windows tokenized in {time.monotonic() - t0:.0f} s")
                if path is not None:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_name(path.name + ".tmp.npz")
                    np.savez_compressed(tmp, tokens=t, poses=p)
                    tmp.replace(path)
            toks.append(t)
            poses.append(p)
            strides_out.append(np.full(len(t), s, np.int64))
            seq_out.append(np.full(len(t), q, np.int64))
            sweeps_out.append(window_sweeps(n_past, n_future, s, anchor_every, n_windows=len(t)))
    out = {"tokens": np.concatenate(toks), "poses": np.concatenate(poses), "stride": np.concatenate(strides_out),
           "sequence": np.concatenate(seq_out), "sweeps": np.concatenate(sweeps_out).reshape(-1, T),
           "sequences": np.array(names)}
    if not len(out["tokens"]):
        raise PcfbenchError(f"dataset {adapter.name!r} split {split!r}: no sequence is long enough for a window of "
                            f"{n_past} past and {n_future} future sweeps at strides {list(strides)}")
    return out


# --------------------------------------------------------------------------- training
def train_world(model, cfg, windows: dict[str, np.ndarray], variant, run, *, steps: int, seed: int = 0,
                manifest_config, extra_weights: dict | None = None, resumed=None, log=print, render=None,
                targets=None) -> dict:
    """Algorithm 1 on ``windows`` through :func:`pcfbench.training.fit_loop`, until ``steps``
    or until ``run`` says stop; checkpoints every ``CHECKPOINT_EVERY`` steps (weights
    ``world.*`` plus ``extra_weights``); ``resumed`` (what ``run.resume()`` gave) restores
    weights, optimiser, the random streams and the curve, so a resumed run continues the same
    curve. ``model``: the world model, or a function building it (called after the loop seeded
    torch with ``seed``). ``render``: a :class:`~.render_stage.RenderTerm` (the rendered depth
    added to the loss; its frames and rays drawn from the loop's numpy stream after the
    windows). ``targets``: (|V|, |V|) target distributions instead of ``cfg.label_smoothing``
    (:func:`~.diffusion.neighbour_targets`). Returns the model, the step reached and the curve."""
    import torch

    from pcfbench.methods.copilot4d import diffusion as D
    from pcfbench.training import fit_loop

    tokens = torch.from_numpy(windows["tokens"].astype(np.int64))  # on the CPU; each batch moves to the device
    poses = torch.from_numpy(windows["poses"].astype(np.float32))

    def sample_batch(rand, step: int):
        picks = rand.numpy.integers(0, len(tokens), cfg.batch_size)
        drawn = None if render is None else [render.draw(int(w), rand.numpy) for w in picks]
        picks = torch.from_numpy(picks)
        return tokens[picks], poses[picks], rand.torch, drawn  # the masking draws from the loop's torch generator

    def step_fn(model, batch):
        x0, pose, gen, drawn = batch
        device = next(model.parameters()).device
        extra = None if render is None else lambda logits, targets, masked: render(logits, targets, masked, drawn)
        smoothing = cfg.label_smoothing if targets is None else targets.to(device)
        return D.training_loss(model, x0.to(device), pose.to(device), cfg.n_past, variant, smoothing,
                               generator=gen, extra=extra)

    out = fit_loop(model, lambda m: D.make_optimizer(m, cfg), sample_batch, step_fn, run, steps=steps, seed=seed,
                   schedule=lambda step: D.lr_at(cfg, step), grad_clip=cfg.grad_clip, log_every=LOG_EVERY,
                   checkpoint_every=CHECKPOINT_EVERY, torch_generator=True,
                   progress_values={"cross entropy": "loss", "token accuracy": "accuracy",
                                    "changed-token accuracy": "changed_accuracy",
                                    **({} if render is None else {"rendered L1 (m)": "render_l1"})},
                   weights_prefix="world.",
                   extra_weights=extra_weights, manifest_config=manifest_config, resumed=resumed, log=log)
    return {"model": out.model, "step": out.step, "history": out.history, "elapsed_s": out.elapsed_s,
            "cpu_s": out.cpu_s}


def world_curve_panels(render: bool = False) -> list:
    """The world model curve's figure: the loss; token accuracy on the scored and the masked
    tokens; loss and accuracy on the masked future tokens that changed since the last past
    frame and on those that did not; with ``render``, the render stage's depth error beside
    the copy's on the same rays."""
    from pcfbench.training import Panel

    extra = [Panel((("render_l1", "rendered L1 (m), the model's masked tokens"),
                    ("render_l1_copy", "rendered L1 (m), the last past frame's on them")))] if render else []
    return extra + [Panel((("loss", "cross entropy (label smoothing 0.1)"),)),
            Panel((("accuracy", "token accuracy (scored tokens)"), ("masked_accuracy", "token accuracy (masked tokens)")),
                  ylim=(0, 1)),
            Panel((("changed_loss", "cross entropy, masked future tokens that changed"),
                   ("unchanged_loss", "cross entropy, masked future tokens that did not"))),
            Panel((("changed_accuracy", "accuracy, changed tokens"), ("unchanged_accuracy", "accuracy, unchanged tokens"),
                   ("changed_share", "share of future tokens that changed")), ylim=(0, 1))]


# --------------------------------------------------------------------------- the methods
class Copilot4D(OnTokenizer, TrainedMethod):
    """Copilot4D: tokenizer + discrete-diffusion world model, forecasting autoregressively."""

    name = "copilot4d"
    # the default run scores 8 evenly spaced samples of each cell (its 10-minute budget on a
    # 2-core CPU; docs/protocol.md, "The default run's subset"); --subset 0 or naming the method: all
    default_run_subset = 8
    version = "1"
    Options = WorldOptions
    tokenizer_outputs = "tokens"
    variant_name = "copilot4d"
    # the measurements behind it: docs/copilot4d.md, "Shipped, and on the default leaderboard"
    training_time = ("about 32 min for the default (tiny-window) configuration on both threads of a 2-core CPU "
                     "(about 18 min tokenizing 432 windows, once for both variants; 600 steps at 1.4 s), plus its "
                     "tokenizer's training")
    inference_options = ("cfg_weight", "sampling_steps", "top_k", "mbr", "change_confidence", "soft_mix", "one_pass",
                         "stride_cfg_weight", "stride_soft_mix", "stride_ensemble", "seed",
                         *(f.name for f in fields(RenderingOptions)))
    # the default run samples one arg-max step, the paper's K = 10 top-3 being the options'
    # defaults: one step forecast best on tiny-window and in half the time; and renders 0.3 of the
    # expected code embedding beside 0.7 of the t=0 code's, chosen on validation; copilot4d
    # forecasts kitti-3s with a network of its own, trained 500 steps on stride-6 windows (the
    # paper's one model per horizon), chosen on validation; and decodes every future frame in one
    # causal pass (one_pass), as the future-prediction objective trains it: sampled frame by frame
    # it repeats its first future frame (docs/copilot4d.md, "One pass")
    default_run_options = ({"sampling_steps": "1", "top_k": "1", "soft_mix": "0.3", "stride_models": "6",
                            "stride_steps": "500", "one_pass": "true"},)

    def __init__(self, options: WorldOptions | None = None) -> None:
        super().__init__(options)
        from pcfbench.methods.copilot4d.config import get_config
        from pcfbench.methods.copilot4d.diffusion import get_variant
        from pcfbench.methods.copilot4d.evaluate import rendering_kwargs
        from pcfbench.methods.copilot4d.world_config import get_world_config, tokenizer_config_name

        self.tok_cfg = get_config(tokenizer_config_name(self.options.config))
        if self.options.neighbour_targets >= self.tok_cfg.codebook_size:
            raise PcfbenchError(f"neighbour_targets={self.options.neighbour_targets}: the '{self.tok_cfg.name}' "
                                f"tokenizer has {self.tok_cfg.codebook_size} codes, so at most "
                                f"{self.tok_cfg.codebook_size - 1} neighbours")
        self.world_cfg = world_config_for(get_world_config(self.options.config), self.tok_cfg)
        if self.options.steps:  # a longer (or shorter) run decays its learning rate over its own steps
            self.world_cfg = self.world_cfg.with_overrides(max_steps=self.options.steps,
                                                           decay_steps=self.options.steps)
        self.variant = get_variant(self.variant_name)
        self.render = rendering_kwargs(self.options)
        self.world = None
        self.networks: list = []  # stride_models: (frame spacing s, network) pairs
        self.stride_networks: dict = {}  # stride_models: the network of each training stride
        self.own_networks: list = []  # stride_models: the networks of a stride of their own
        self.tokenizer = None

    def training_steps(self) -> int:
        if self.options.stride_models:  # the parts' trainings, put together
            return sum(spec.create().training_steps() for spec in self.part_specs().values())
        return self.world_cfg.max_steps

    # -- the tokenizer this world model is trained on -------------------------------------------
    def tokenizer_spec(self):
        from pcfbench.methods.copilot4d.token_copy import tokenizer_spec

        return tokenizer_spec(self.tok_cfg.name, self.options.tokenizer_steps)

    def fit(self, train_source: TrainSource, out_dir: Path, progress: TrainingRun) -> None:
        from pcfbench.methods.copilot4d.train import default_device, load_tokenizer
        from pcfbench.methods.copilot4d.world import WorldModel, count_parameters
        from pcfbench.training import write_curve

        if self.options.stride_models:
            return self.assemble(train_source, progress)
        device = default_device()  # CPU threads: the harness applied `pcfbench train --threads` (every CPU)
        resumed = progress.resume()
        tok_ck = self.tokenizer_checkpoint(train_source)  # before any work: missing is one error
        tokenizer = load_tokenizer(tok_ck, device)
        if tokenizer.cfg != self.tok_cfg:
            raise CheckpointError(f"tokenizer checkpoint {tok_ck.manifest_path} records another '{self.tok_cfg.name}' "
                                  f"configuration than this pcfbench defines; retrain it with `pcfbench train "
                                  f"{TOKENIZER_METHOD} --dataset {train_source.train_on.dataset} --fresh`")
        tok_state = tokenizer.state_dict()
        tok_digest = tensor_digest(tok_state)
        if resumed is not None:  # the same tokenizer, or the cached tokens and the weights disagree
            self.check_resumed_tokenizer(out_dir, tok_ck)
        cfg = self.world_cfg
        progress.log(f"{self.name} ({self.variant.name}, {cfg.name}): tokenizer {tok_ck.dir} "
                     f"(sha256 {tok_ck.sha256[:12]}), {train_source.train_on.label}")
        windows = build_windows(tokenizer, train_source.adapter, train_source.split, cfg.n_past, cfg.n_future,
                                tuple(self.options.strides), self.options.anchor_every,
                                window_cache_dir(tok_ck.sha256, train_source.train_on.key), log=progress.log,
                                frame=self.options.frame)
        progress.log(f"{len(windows['tokens'])} training windows of {cfg.n_frames} frames, "
                     f"{cfg.token_grid}x{cfg.token_grid} tokens")
        manifest_config = lambda model: {  # noqa: E731
            "world": cfg.to_dict(), "variant": self.variant.name, "tokenizer": self.tok_cfg.to_dict(),
            "tokenizer_sha256": tok_ck.sha256, "tokenizer_digest": tok_digest,
            "tokenizer_checkpoint": str(tok_ck.manifest_path), "tokenizer_steps": tok_ck.steps,
            "parameters": count_parameters(model), "steps_target": self.training_steps(),
            "windows": int(len(windows["tokens"])), "strides": list(self.options.strides),
            "frame": self.options.frame,
        }
        start = self.start_checkpoint(train_source, out_dir, tok_ck)
        if start is not None:
            before = start.steps + start.manifest["config"].get("init_from", {}).get("steps", 0)  # its own start's
            progress.log(f"starting from {start.dir} ({before} steps, sha256 {start.sha256[:12]})")
            started = {"init_from": {"steps": before, "weights_sha256": start.sha256,
                                     "checkpoint": str(start.manifest_path)}}
            build = lambda: load_network(WorldModel(cfg), start, start.load_weights(), "world.",  # noqa: E731
                                         "world model").to(device)
        else:  # built on the CPU (then moved), so its initial weights do not depend on the device
            started, build = {}, lambda: WorldModel(cfg).to(device)  # noqa: E731
        render = None
        if self.options.render_weight:
            from pcfbench.methods.bevworld.render_loss import WindowRays
            from pcfbench.methods.copilot4d.render_stage import RENDER_PER_SWEEP, RENDER_RAYS, RenderTerm

            rays = WindowRays(train_source.adapter, windows, cfg.n_past, per_sweep=RENDER_PER_SWEEP, seed=0,
                              log=progress.log)
            render = RenderTerm(tokenizer, rays, cfg.n_past, cfg.n_future,
                                self.options.frame == "own", self.options.render_weight)
            started = {**started, "render": {"weight": self.options.render_weight, "rays": RENDER_RAYS,
                                             "per_sweep": RENDER_PER_SWEEP}}
        targets = None
        if self.options.neighbour_targets:
            from pcfbench.methods.copilot4d.diffusion import neighbour_targets

            targets = neighbour_targets(tokenizer.vq.codebook, self.options.neighbour_targets, NEIGHBOUR_SHARE,
                                        cfg.label_smoothing)
            started = {**started, "targets": {"neighbours": self.options.neighbour_targets, "share": NEIGHBOUR_SHARE,
                                              "label_smoothing": cfg.label_smoothing}}
        with_start = lambda model: {**manifest_config(model), **started}  # noqa: E731
        out = train_world(build, cfg, windows, self.variant, progress,
                          steps=self.training_steps(), seed=0, manifest_config=with_start, resumed=resumed,
                          extra_weights={f"tokenizer.{k}": v for k, v in tok_state.items()}, log=progress.log,
                          render=render, targets=targets)
        if out["history"]:
            csv_path, png = write_curve(out["history"], Path(out_dir), "curve", world_curve_panels(render is not None))
            progress.log(f"training curve: {csv_path} and {png}")

    def start_spec(self):
        """The spec whose complete checkpoint a training with ``init_steps`` goes on from: these
        options with ``steps=init_steps`` and no ``init_steps``, or for a chain ``a/b/c`` with
        ``steps=c`` and ``init_steps=a/b`` (None without ``init_steps``)."""
        chain = self.options.init_chain
        if not chain:
            return None
        before = chain[:-1]
        defaults = type(self.options)()  # the render stage and the neighbour targets are this training's only
        return self.spec_with(steps=chain[-1], init_steps=(before if len(before) > 1 else sum(before)),
                              render_weight=defaults.render_weight, neighbour_targets=defaults.neighbour_targets)

    def spec_with(self, **changes):
        """The :class:`~pcfbench.method.MethodSpec` of this method with these options changed."""
        from dataclasses import asdict, replace

        from pcfbench.method import MethodSpec
        from pcfbench.options import options_hash

        defaults = type(self.options)()
        opts = replace(self.options, **changes)
        raw = {k: "/".join(map(str, v)) if isinstance(v, tuple) else str(v)
               for k, v in asdict(opts).items() if v != getattr(defaults, k)}
        return MethodSpec(self.name, raw, opts, options_hash(opts), type(self))

    # -- one network per stride (stride_models) -----------------------------------------------
    def part_specs(self) -> dict[tuple[int, ...], object]:
        """With ``stride_models``: the trainings put together, by the strides each forecasts:
        ``(s,)`` the training of these options on stride s alone (``steps=stride_steps`` when
        given), the other strides the training of these options on every stride (if any is
        left)."""
        plain = {"stride_models": (), "stride_steps": 0}
        own = self.options.stride_models
        parts = {}
        rest = tuple(s for s in self.options.strides if s not in own)
        if rest:
            parts[rest] = self.spec_with(**plain)
        for s in own:
            parts[(s,)] = self.spec_with(**plain, strides=(s,), steps=self.options.stride_steps or self.options.steps)
        return parts

    def assemble(self, train_source: TrainSource, progress: TrainingRun) -> None:
        """A ``stride_models`` checkpoint: the world networks of :meth:`part_specs`' complete
        checkpoints on the same data and tokenizer (each trained first where it is not, as
        ``pcfbench train`` trains it: its own checkpoint, resumable), the rest's under ``world.``,
        stride s's under ``world_s<s>.``, with the tokenizer's tensors; the manifest records each
        part's checkpoint, weights sha256, steps and the frame spacing (s) of its strides'
        training windows, by which a sample picks it."""
        from pcfbench.methods.copilot4d.train import load_tokenizer
        from pcfbench.training import checkpoint_dir, find_checkpoint, train
        from pcfbench.training.checkpoints import dataset_argument

        tok_ck = self.tokenizer_checkpoint(train_source)
        on = train_source.train_on
        parts = {}
        for strides, spec in self.part_specs().items():
            ck = find_checkpoint(spec, on)
            trains = spec.text(drop=self.inference_options)  # its training options: the command that trains it
            # a complete one trained here is used (or refused below); a shipped one only on this tokenizer
            if not (ck is not None and ck.manifest.get("complete") and (
                    ck.dir == checkpoint_dir(spec, on)
                    or ck.manifest.get("config", {}).get("tokenizer_sha256") == tok_ck.sha256)):
                progress.log(f"{self.name}: training the network of strides {'/'.join(map(str, strides))} first: "
                             f"{trains}")
                ck = train(spec, dataset_argument(on), split=on.split, progress=progress.show, threads=progress.threads,
                           log=progress.log)
            check_same_tokenizer(ck, tok_ck, f"pcfbench train {trains} --dataset {dataset_argument(on)} --fresh")
            parts[strides] = ck
        period = sweep_period_s(train_source.adapter, train_source.split)
        tok_state = load_tokenizer(tok_ck, "cpu").state_dict()
        weights = {f"tokenizer.{k}": v for k, v in tok_state.items()}
        networks = []
        for strides, ck in parts.items():
            prefix = part_prefix(strides, self.options.stride_models)
            weights |= {prefix + k[len("world."):]: v for k, v in ck.load_weights().items() if k.startswith("world.")}
            conf = ck.manifest["config"]
            networks.append({"strides": list(strides), "prefix": prefix, "trained_strides": conf["strides"],
                             "frame_interval_s": [round(s * period, 6) for s in strides], "world": conf["world"],
                             "checkpoint": str(ck.manifest_path), "weights_sha256": ck.sha256, "steps": ck.steps,
                             "wall_s": ck.manifest.get("wall_s"), "windows": conf.get("windows")})
            progress.count_time(ck.manifest.get("wall_s", 0.0), ck.manifest.get("cpu_s", 0.0))
            progress.log(f"{self.name}: strides {'/'.join(map(str, strides))} from {ck.dir} ({ck.steps} steps, "
                         f"sha256 {ck.sha256[:12]})")
        steps = sum(ck.steps for ck in parts.values())
        progress.start(steps, steps)
        progress.save(steps, weights, None, complete=True, config={
            "world": self.world_cfg.to_dict(), "variant": self.variant.name, "tokenizer": self.tok_cfg.to_dict(),
            "tokenizer_sha256": tok_ck.sha256, "tokenizer_digest": tensor_digest(tok_state),
            "tokenizer_checkpoint": str(tok_ck.manifest_path), "tokenizer_steps": tok_ck.steps,
            "strides": list(self.options.strides), "frame": self.options.frame, "sweep_period_s": period,
            "networks": networks})

    def start_checkpoint(self, train_source: TrainSource, out_dir: Path, tok_ck: Checkpoint) -> Checkpoint | None:
        """The verified, complete checkpoint of :meth:`start_spec` on the same training data and
        tokenizer (None without ``init_steps``); a training resumed in ``out_dir`` goes on only
        from the weights it started from."""
        import json

        from pcfbench.training import find_checkpoint, missing_checkpoint_message
        from pcfbench.training.checkpoints import MANIFEST

        spec = self.start_spec()
        if spec is None:
            return None
        ck = find_checkpoint(spec, train_source.train_on)
        if ck is None or not ck.manifest.get("complete"):
            chain = self.options.init_chain
            raise PcfbenchError(f"{self.name} with init_steps={'/'.join(map(str, chain))} goes on from a complete "
                                f"training of {sum(chain)} steps: "
                                + missing_checkpoint_message(spec, train_source.train_on))
        check_same_tokenizer(ck, tok_ck)
        manifest = Path(out_dir) / MANIFEST
        had = json.loads(manifest.read_text())["config"].get("init_from", {}) if manifest.is_file() else {}
        if had and had.get("weights_sha256") != ck.sha256:
            raise PcfbenchError(f"checkpoint {manifest} started from weights {str(had.get('weights_sha256'))[:12]}, "
                                f"and {ck.manifest_path} is now {ck.sha256[:12]}: rerun with --fresh")
        return ck

    # -- loading ------------------------------------------------------------------------------
    def read_tokenizer(self, checkpoint: Checkpoint, prefix: str = "", weights: dict | None = None):
        from pcfbench.methods.copilot4d.model import Tokenizer

        weights = checkpoint.load_weights() if weights is None else weights
        return load_network(Tokenizer(self.tok_cfg), checkpoint, weights, prefix, "tokenizer")

    def load(self, checkpoint: Checkpoint) -> None:
        from pcfbench.methods.copilot4d.train import config_from_dict, default_device
        from pcfbench.methods.copilot4d.world import WorldEnsemble, WorldModel
        from pcfbench.methods.copilot4d.world_config import WorldModelConfig

        mf = checkpoint.manifest_path
        conf = checkpoint.manifest.get("config", {})
        for key in ("world", "tokenizer", "tokenizer_digest", "variant"):
            if key not in conf:
                raise CheckpointError(f"checkpoint {mf} records no config.{key}: not a {self.name} checkpoint")
        if conf["variant"] != self.variant.name:
            raise CheckpointError(f"checkpoint {mf} holds a {conf['variant']} world model, not {self.variant.name}")
        tok_cfg = config_from_dict(conf["tokenizer"])
        world_cfg = WorldModelConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in conf["world"].items()})
        if tok_cfg != self.tok_cfg or world_cfg != self.world_cfg:
            raise CheckpointError(f"checkpoint {mf} was trained with another '{self.options.config}' tokenizer or "
                                  "world model configuration than this pcfbench defines; retrain it with --fresh")
        weights = checkpoint.load_weights()
        tokenizer = self.checkpoint_tokenizer(checkpoint, weights)
        device = default_device()
        self.tokenizer = tokenizer.to(device).eval()
        self.networks, self.stride_networks = [], {}
        for part in conf.get("networks", ()):  # stride_models: one network per part
            part_cfg = WorldModelConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in part["world"].items()})
            expected = self.part_world_cfg(tuple(part["strides"]))
            if part_cfg != expected:
                raise CheckpointError(f"checkpoint {mf}: the network of strides {part['strides']} was trained with "
                                      "another world model configuration than these options give; retrain it")
            net = load_network(WorldModel(part_cfg), checkpoint, weights, part["prefix"], "world model").to(device)
            self.networks += [(interval, net.eval()) for interval in part["frame_interval_s"]]
            self.stride_networks |= dict.fromkeys(part["strides"], net)
        if self.options.stride_ensemble:
            shared = self.stride_networks[next(s for s in self.options.strides if s not in self.options.stride_models)]
            together = {id(net): net if net is shared else WorldEnsemble([net, shared])
                        for net in self.stride_networks.values()}
            self.networks = [(interval, together[id(net)]) for interval, net in self.networks]
            self.stride_networks = {s: together[id(net)] for s, net in self.stride_networks.items()}
        self.own_networks = [net for s, net in self.stride_networks.items() if s in self.options.stride_models]
        if conf.get("networks") is not None:
            self.world = self.networks[0][1]
            return
        world = load_network(WorldModel(world_cfg), checkpoint, weights, "world.", "world model")
        self.world = world.to(device).eval()

    def part_world_cfg(self, strides: tuple[int, ...]):
        """The world model configuration of the ``stride_models`` part forecasting ``strides``."""
        steps = self.options.stride_steps if strides[0] in self.options.stride_models else 0
        if not steps:
            return self.world_cfg
        return self.world_cfg.with_overrides(max_steps=steps, decay_steps=steps)

    def network_for_stride(self, stride: int):
        """The world network that forecasts windows of ``stride`` source sweeps: with
        ``stride_models``, the one put together for it (one error for a stride it has none for);
        else the one network."""
        if not self.stride_networks:
            return self.world
        if stride not in self.stride_networks:
            raise PcfbenchError(f"{self.name} with stride_models has networks for strides "
                                f"{'/'.join(map(str, sorted(self.stride_networks)))}, not {stride}")
        return self.stride_networks[stride]

    def network_for(self, sample: Sample):
        """The world network that forecasts ``sample``: with ``stride_models``, the one whose
        training windows' frame spacing is nearest (in ratio) the sample's (the median of its
        frames' spacing from the last past sweep on); else the one network."""
        if not self.networks:
            return self.world
        ts = np.concatenate([sample.past_timestamps_ns[-1:], sample.future_timestamps_ns]).astype(np.float64)
        spacing = float(np.median(np.diff(ts))) / 1e9
        if not spacing > 0:
            raise PcfbenchError(f"sample {sample.sample_id}: future timestamps do not increase from the last past "
                                f"sweep's: no frame spacing to choose a stride's network by")
        return min(self.networks, key=lambda pair: abs(np.log(spacing / pair[0])))[1]

    def sampling_for(self, world) -> tuple[float, float]:
        """The guidance weight and ``soft_mix`` of the samples ``world`` forecasts: with
        ``stride_models``, a stride's own network takes ``stride_cfg_weight`` and
        ``stride_soft_mix`` where they are given; else ``cfg_weight`` and ``soft_mix``."""
        o = self.options
        if any(world is net for net in self.own_networks):
            return (o.cfg_weight if o.stride_cfg_weight is None else o.stride_cfg_weight,
                    o.soft_mix if o.stride_soft_mix is None else o.stride_soft_mix)
        return o.cfg_weight, o.soft_mix

    # -- forecasting --------------------------------------------------------------------------
    def forecast(self, sample: Sample) -> Forecast:
        import torch

        from pcfbench.methods.copilot4d.evaluate import render_queries

        if self.world is None:
            raise PcfbenchError(f"{self.name}: no checkpoint loaded (the runner loads it; call load() first)")
        soft_mix = self.sampling_for(self.network_for(sample))[1]
        if soft_mix > 0:
            inputs: dict = {}
            codes, rel_future, T_s0_ref = self.forecast_tokens(sample, soft_inputs=inputs)
            codes = self.soft_maps(inputs["logits"], inputs["t0"], soft_mix)
        else:
            codes, rel_future, T_s0_ref = self.forecast_tokens(sample)
        gen = torch.Generator(next(self.tokenizer.parameters()).device)
        gen.manual_seed(sample_seed(sample.sample_id, self.options.seed) ^ 1)
        frames = (T_s0_ref if self.options.frame == "t0"
                  else [np.linalg.inv(T) for T in sample.future_T_ref_sensor])  # each from its own origin
        return Forecast.from_depths(sample, render_queries(self.tokenizer, list(codes), sample, frames,
                                                           generator=gen, execution=self.execution, **self.render))

    def world_inputs(self, sample: Sample):
        """What the world model is given: the past token maps (P, H, W) of the newest
        ``n_past`` past sweeps, each tokenized in the t=0 sensor frame (``frame=t0``) or in its
        own (``frame=own``); every past and future sensor pose in the t=0 sensor frame
        (P + F, 4, 4) float32; the transform from the reference frame into it (4, 4) float64."""
        import torch

        from pcfbench.methods.copilot4d.evaluate import tokenize_sweep

        T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
        past = list(range(len(sample.past_points_ref)))[-self.world_cfg.n_past:]  # the model's window at most
        into = (lambda k: T_s0_ref) if self.options.frame == "t0" else (lambda k: np.linalg.inv(sample.past_T_ref_sensor[k]))
        seq = torch.stack([tokenize_sweep(self.tokenizer, transform(sample.past_points_ref[k], into(k)))
                           for k in past])
        poses = np.concatenate([sample.past_T_ref_sensor[past], sample.future_T_ref_sensor])
        return seq, torch.from_numpy((T_s0_ref @ poses).astype(np.float32)), T_s0_ref

    def forecast_tokens(self, sample: Sample, soft_inputs: dict | None = None):
        """The future token maps (F, H, W) of ``sample`` in its t=0 sensor frame, the future poses
        in that frame (F, 4, 4), and the transform from the reference frame into it.
        ``soft_inputs``, if a dict, receives what :meth:`soft_maps` reads: ``logits``, per future
        frame the guided logits (1, H, W, |V|) of its last sampling step, and ``t0``, the last
        past map (H, W)."""
        import torch

        world = self.network_for(sample)
        dev = next(world.parameters()).device
        seq, rel, T_s0_ref = self.world_inputs(sample)
        final_logits = None if soft_inputs is None else soft_inputs.setdefault("logits", [])
        seq, rel = seq[None].to(dev), rel[None].to(dev)
        gen = torch.Generator(dev).manual_seed(sample_seed(sample.sample_id, self.options.seed))
        P = seq.shape[1]
        out = [x[0] for x in self.decode_future(world, seq, rel, sample.num_future, generator=gen,
                                                final_logits=final_logits, name=f"sample {sample.sample_id}")]
        if soft_inputs is not None:
            soft_inputs["t0"] = seq[0, -1]
        return out, rel[0, P:].cpu().numpy(), T_s0_ref

    def decode_future(self, world, past, T_ref_sensor, n_future: int, *, generator=None,
                      final_logits: list | None = None, name: str = "the window") -> list:
        """The ``n_future`` code maps (B, H, W) network ``world`` forecasts after ``past`` (B, P, H, W)
        with poses ``T_ref_sensor`` (B, P + n_future, 4, 4), decoded as the options say: every
        future frame in one pass (``one_pass``), else Algorithm 2 a frame at a time, the context
        every frame so far at the positions of training (t=0 at n_past - 1), sliding once past and
        future outgrow the trained sequence; bf16 on CUDA (logits in float32). ``name`` (a sample,
        a window) goes into the one error of a forecast too long for one pass."""
        from pcfbench.methods.copilot4d.diffusion import forecast_one_pass, forecast_sequence
        from pcfbench.training import autocast

        cfg, o = self.world_cfg, self.options
        dev = past.device
        guidance = self.sampling_for(world)[0]
        if o.one_pass:  # the future-prediction objective's input: the past and every future frame masked
            if n_future > cfg.n_future:
                raise PcfbenchError(f"{name}: one_pass=true forecasts its {n_future} future frames in one pass; the "
                                    f"network was trained on {cfg.n_future}")
            return forecast_one_pass(world, past, T_ref_sensor, n_future, n_frames=cfg.n_frames, n_past=cfg.n_past,
                                     guidance=guidance, context=lambda: autocast(dev), final_logits=final_logits)
        return forecast_sequence(world, past, T_ref_sensor, n_future, n_frames=cfg.n_frames, n_past=cfg.n_past,
                                 steps=o.sampling_steps, guidance=guidance, top_k=o.top_k, revise=self.variant.revise,
                                 metric=self.code_metric(), change_confidence=o.change_confidence,
                                 final_logits=final_logits, generator=generator, context=lambda: autocast(dev))

    def decoding(self) -> str:
        """How :meth:`decode_future` decodes under these options, in words (for a report)."""
        if self.options.one_pass:
            return "every future frame in one pass, each token its guided arg max (one_pass)"
        return f"Algorithm 2, a frame at a time: {self.options.sampling_steps} step(s), top-{self.options.top_k}"

    def soft_maps(self, final_logits: list, t0, a: float | None = None) -> list:
        """``soft_mix`` a (default: the option's): per future frame the (H, W, D) code embeddings the tokenizer decodes,
        a E_p[e] + (1 - a) e(c0) at every token, p the guided distribution of the frame's last
        sampling step (``final_logits``, (1, H, W, |V|) each), c0 the code of the t=0 map ``t0``
        (H, W) there and e the tokenizer's codebook."""
        import torch

        a = self.options.soft_mix if a is None else a
        codebook = self.tokenizer.vq.codebook.detach().float()
        maps = []
        for logits in final_logits:
            expected = torch.softmax(logits[0].float(), dim=-1) @ codebook
            maps.append(expected if a == 1 else a * expected + (1 - a) * codebook[t0])
        return maps

    def code_metric(self):
        """With ``mbr``, the (|V|, |V|) Euclidean distances between the tokenizer's code embeddings
        that Algorithm 2 chooses codes by (float32, the tokenizer's device); None otherwise."""
        import torch

        if not self.options.mbr:
            return None
        cb = self.tokenizer.vq.codebook.detach().float()
        return torch.cdist(cb, cb)


class Copilot4DMaskGIT(Copilot4D):
    """The same world model and tokenizer, trained and sampled as MaskGIT (eta = 0, loss on masked
    tokens only, decoded tokens frozen): Table 4's comparison."""

    name = "copilot4d-maskgit"
    variant_name = "maskgit"
    # one network for both strides; one_pass chosen on validation as copilot4d's was
    default_run_options = ({"sampling_steps": "1", "top_k": "1", "soft_mix": "0.3", "one_pass": "true"},)


def check_same_tokenizer(ck: Checkpoint, tok_ck: Checkpoint, retrain: str = "") -> None:
    """One error unless world checkpoint ``ck`` was trained on the tokenizer checkpoint ``tok_ck``
    (``retrain``: the command that retrains it, for the message)."""
    had = ck.manifest.get("config", {}).get("tokenizer_sha256")
    if had != tok_ck.sha256:
        raise PcfbenchError(f"checkpoint {ck.manifest_path} was trained on tokenizer weights {str(had)[:12]}, and "
                            f"{tok_ck.manifest_path} is now {tok_ck.sha256[:12]}: retrain it first"
                            + (f" (`{retrain}`)" if retrain else ""))


def part_prefix(strides: tuple[int, ...], stride_models: tuple[int, ...]) -> str:
    """Where a ``stride_models`` checkpoint keeps the network of ``strides``: ``world_s<s>.``
    for a stride of its own, ``world.`` for the network of the other strides."""
    return f"world_s{strides[0]}." if strides[0] in stride_models else "world."


def sweep_period_s(adapter, split: str) -> float:
    """The median time (s) between consecutive sweeps of ``split``'s sequences: a training
    window of stride s spaces its frames s of these apart."""
    gaps = [np.diff(np.asarray(adapter.sequence(n).timestamps_ns, np.float64)) for n in adapter.sequence_names(split)]
    gaps = np.concatenate([g for g in gaps if len(g)]) if gaps else np.zeros(0)
    if not len(gaps):
        raise PcfbenchError(f"dataset {adapter.name!r} split {split!r}: no sequence of two sweeps or more to time")
    return float(np.median(gaps)) / 1e9


def world_config_for(world_cfg, tok_cfg):
    """``world_cfg`` fitted to a tokenizer's output: its codebook size and token grid (and, where
    the world model is told where each sensor sees a token from, the grid's extent)."""
    fitted = {"codebook_size": tok_cfg.codebook_size, "token_grid": tok_cfg.bev_tokens}
    if world_cfg.view_freqs:
        if tok_cfg.x_range != tok_cfg.y_range or tok_cfg.x_range[0] != -tok_cfg.x_range[1]:
            raise PcfbenchError(f"world model config {world_cfg.name!r} places tokens on a square grid centred on the "
                                f"sensor; the '{tok_cfg.name}' tokenizer's ranges are x {tok_cfg.x_range}, y {tok_cfg.y_range}")
        fitted["bev_extent"] = float(tok_cfg.x_range[1])
    if all(getattr(world_cfg, k) == v for k, v in fitted.items()):
        return world_cfg
    return world_cfg.with_overrides(**fitted)

