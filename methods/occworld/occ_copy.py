"""The occupancy-copy baseline: OccWorld's scene tokenizer as a trained method
(``occworld-occ-copy``).

``fit`` trains the tokenizer (cross entropy x 10 + Lovasz + VQ) through the one training loop
on the occupancy of the training split's sweeps, labelled from their rays
(:mod:`.occupancy`). ``forecast`` labels the last past sweep (t=0) in its sensor frame,
tokenizes it, decodes the tokens to occupancy probabilities (1 - p(free)) and renders them
along every future sweep's query rays from that sweep's origin (:mod:`.render`): the world
seen through the tokenizer, not changing. What ``occworld`` adds is measured against it.

**The frame** (option ``frame``, the world model's): ``own`` trains on each sweep in its own
sensor frame; ``t0`` on sweeps moved into the frame of another sweep of the same sequence,
as far before or after it as the world model's windows reach (Copilot4D's lesson: a tokenizer
that only ever saw sensor-centred sweeps fails on moved ones). Either way the copy tokenizes
the t=0 sweep in its own frame, which is the t=0 frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld.occupancy import OccGrid, label_occupancy
from pcfbench.options import option
from pcfbench.training import Checkpoint, TrainedMethod, TrainingRun, TrainSource

FRAMES = ("own", "t0")
#: the world model's windows (the protocol's settings): 5 past and 5 future frames, strides 2 and 6
WINDOW_PAST, WINDOW_FUTURE, MAX_STRIDE = 5, 5, 6


@dataclass(frozen=True)
class OccOptions:
    """What the tokenizer and the world model share."""

    config: str = option("tiny", help="configuration: tiny (CPU scale), paper (the published sizes) or micro (tests)")
    tokens: int = option(0, help="tokens per side (0: the configuration's, 50); a power-of-2 fraction of the "
                                 "grid's 200 voxels (the paper's Table 3 sweep)", min=0)
    frame: str = option("t0", help="the frame of a window's occupancy: t0 (moved into the t=0 sensor frame; chosen by "
                                   "the ceiling, docs/occworld.md) or own (each sweep in its own sensor frame)")
    surface: str = option("front", help="sub-voxel planes (ours): the tokenizer also decodes one plane offset per "
                                        "voxel, at the front (or mean) of its returns; none: OccWorld's occupancy alone")
    readout: str = option("surface", help="a ray's depth: surface (where it crosses the first occupied voxel's "
                                          "plane; needs surface front or mean), expected (over the voxels' "
                                          "occupancy) or threshold (the middle of the first voxel at occupancy 0.5)")

    def __post_init__(self) -> None:
        from pcfbench.methods.occworld.config import tokenizer_config
        from pcfbench.methods.occworld.render import READOUTS

        if self.frame not in FRAMES:
            raise PcfbenchError(f"frame={self.frame!r}: expected one of {', '.join(FRAMES)}")
        if self.readout not in READOUTS + ("surface",):
            raise PcfbenchError(f"readout={self.readout!r}: expected one of {', '.join(READOUTS + ('surface',))}")
        # one error for an unknown configuration, token count or surface
        tokenizer_config(self.config, self.tokens, self.surface)
        if self.readout == "surface" and self.surface == "none":
            raise PcfbenchError("readout=surface renders the planes of surface=front or mean; with surface=none "
                                "choose readout=expected or threshold")


@dataclass(frozen=True)
class OccCopyOptions(OccOptions):
    steps: int = option(0, help="training steps (0: the configuration's max_steps)", min=0)
    seed: int = option(0, help="training seed (initialisation, batches)")


def grid_of(cfg) -> OccGrid:
    return OccGrid(tuple(cfg.box_lo), tuple(cfg.dims), cfg.voxel)


def sweep_labels(cfg, points_sensor: np.ndarray, T_frame_sensor: np.ndarray | None = None) -> np.ndarray:
    """(X, Y, Z) uint8 labels of a sweep (its points in its sensor frame) seen in the frame
    ``T_frame_sensor`` maps its sensor frame into (None: its own; the sensor at the origin)."""
    if T_frame_sensor is None:
        return label_occupancy(grid_of(cfg), points_sensor, np.zeros(3))
    T = np.asarray(T_frame_sensor, np.float64)
    moved = points_sensor.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    return label_occupancy(grid_of(cfg), moved, T[:3, 3])


def surface_targets(cfg, points_sensor: np.ndarray, T_frame_sensor: np.ndarray | None = None, at: str = "front"):
    """A sweep's labels with its sub-voxel planes (``surface.py``): (X, Y, Z) labels
    (``sweep_labels``), (X, Y, Z, 3) normals from its free voxels and (X, Y, Z) offsets of its
    returns (``at``: front or mean), in the frame ``T_frame_sensor`` maps its sensor frame into."""
    from pcfbench.methods.occworld.occupancy import FREE
    from pcfbench.methods.occworld.surface import free_normals, surface_offsets

    labels = sweep_labels(cfg, points_sensor, T_frame_sensor)
    pts = points_sensor.astype(np.float64)
    if T_frame_sensor is not None:
        T = np.asarray(T_frame_sensor, np.float64)
        pts = pts @ T[:3, :3].T + T[:3, 3]
    grid = grid_of(cfg)
    normals = free_normals(labels == FREE, grid.voxel)
    return labels, normals, surface_offsets(grid, pts, normals, at)


def sweep_targets(cfg, points_sensor: np.ndarray, T_frame_sensor: np.ndarray | None = None):
    """The tokenizer's target for a sweep: its (X, Y, Z) labels (``sweep_labels``) and, with
    ``cfg.surface`` not ``none``, the (X, Y, Z) float32 offsets of its returns' planes
    (:func:`surface_targets`; else None)."""
    if cfg.surface == "none":
        return sweep_labels(cfg, points_sensor, T_frame_sensor), None
    labels, _, offsets = surface_targets(cfg, points_sensor, T_frame_sensor, cfg.surface)
    return labels, offsets.astype(np.float32)


def tokenize_labels(model, labels: np.ndarray):
    """(h, w) codes of one (X, Y, Z) label grid."""
    import torch

    dev = next(model.parameters()).device
    with torch.no_grad():
        return model.tokenize(torch.from_numpy(labels)[None].to(dev))[0]


def decode_grid(model, codes) -> tuple[np.ndarray, np.ndarray | None]:
    """One (h, w) token map decoded: the (X, Y, Z) occupancy probability (1 - p(free)) and,
    with the offset head, the (X, Y, Z) plane offsets in metres (else None)."""
    import torch

    from pcfbench.methods.occworld.tokenizer import occupancy_probability

    with torch.no_grad():
        logits, offsets = model.decode_all(model.vq.embed(codes[None]))
    prob = occupancy_probability(logits)[0].cpu().numpy()
    return prob, None if offsets is None else offsets[0].float().cpu().numpy()


def decoded_normals(prob: np.ndarray, voxel) -> np.ndarray:
    """The planes' normals of a decoded grid: ``surface.free_normals`` with each face neighbour
    weighted by its free probability ``1 - prob``, not by whether it is below 0.5. Why
    (measured, docs/occworld.md): a tokenizer decodes about a quarter of the occupied voxels
    free, so a ground voxel often has a "free" neighbour beside it; counted whole, it tilts the
    normal by 45 degrees towards it, and the tilted plane stops grazing rays in front of their
    returns. Weighted (a free voxel above), a neighbour decoded at 0.45 tilts it by 29 degrees,
    one at 0.1 by 42. A certain grid (0 or 1) gives the same normals either way. Not yet
    handled: a decoded voxel whose neighbours are all occupied keeps a tiny, non-zero free sum
    and so a unit normal of little meaning, where a certain grid gives none and stops the ray at
    the voxel's entry (``surface.render_surface``). Dropping the normal where the weighted free
    sum is under 0.5 was measured (2026-12-01, docs/occworld.md): it helps under-trained
    tokenizers' copies, and worsens the shipped one's l1_median (0.291 -> 0.315), so not adopted."""
    from pcfbench.methods.occworld.surface import free_normals

    return free_normals(1.0 - np.asarray(prob, np.float64), voxel)


def render_grid(cfg, decoded, origin: np.ndarray, dirs: np.ndarray, readout: str,
                normals: np.ndarray | None = None) -> np.ndarray:
    """Depths along ``dirs`` from ``origin`` (the grid's frame) through one ``decode_grid``
    result: ``readout="surface"`` through the sub-voxel planes (occupied where the
    probability is >= 0.5; ``normals`` :func:`decoded_normals`' when not given;
    ``surface.render_surface``), else :func:`.render.render_depths`."""
    from pcfbench.methods.occworld.render import render_depths
    from pcfbench.methods.occworld.surface import render_surface

    prob, offsets = decoded
    grid = grid_of(cfg)
    if readout != "surface":
        return render_depths(grid, prob, origin, dirs, readout)
    if offsets is None:
        raise PcfbenchError(f"readout=surface: the occworld tokenizer {cfg.name!r} has no offset head "
                            "(trained with surface=none)")
    if normals is None:
        normals = decoded_normals(prob, grid.voxel)
    return render_surface(grid, prob, normals, offsets, origin, dirs)


def render_sample(model, grids, sample: Sample, T_frame_ref, readout: str) -> list[np.ndarray]:
    """Depths along every future sweep's query rays: ``grids`` one ``decode_grid`` result per
    future sweep (or one tuple for all), grid k in the frame ``T_frame_ref[k]`` maps the
    reference frame into (one 4x4 for all, or one per sweep); the query's origin and directions
    are moved there and rendered (:func:`render_grid`)."""
    F = sample.num_future
    Ts = [np.asarray(T_frame_ref, np.float64)] * F if np.ndim(T_frame_ref) == 2 else list(T_frame_ref)
    gs = [grids] * F if isinstance(grids, tuple) else list(grids)
    normals = None
    if readout == "surface" and isinstance(grids, tuple) and grids[1] is not None:
        normals = decoded_normals(grids[0], grid_of(model.cfg).voxel)  # one grid for every sweep: once
    out = []
    for k, q in enumerate(sample.queries):
        R, t = Ts[k][:3, :3], Ts[k][:3, 3]
        dirs = q.directions_ref.astype(np.float64) @ R.T
        out.append(render_grid(model.cfg, gs[k], R @ q.origin_ref + t, dirs, readout, normals))
    return out


class TokenizerSource:
    """The tokenizer's training sweeps: every sweep of a split (ego returns removed), each
    labelled in its own frame (``own``) or in the frame of a sweep drawn uniformly from the
    window offsets around it (``t0``)."""

    def __init__(self, adapter, split: str, frame: str) -> None:
        self.adapter, self.frame = adapter, frame
        self.sequences = {n: adapter.sequence(n) for n in adapter.sequence_names(split)}
        self.keys = [(n, i) for n, s in self.sequences.items() for i in range(len(s))]
        if not self.keys:
            raise PcfbenchError(f"dataset {adapter.name!r} has no sweeps in split {split!r} under {adapter.root}")

    def __len__(self) -> int:
        return len(self.keys)

    def targets(self, cfg, k: int, rng: np.random.Generator):
        """Sweep ``k``'s ``sweep_targets`` (labels, offsets or None) in its training frame."""
        name, i = self.keys[k]
        seq = self.sequences[name]
        points = self.adapter.ego_box.remove(seq.load_points(i))
        if self.frame == "own":
            return sweep_targets(cfg, points)
        # sweep i is frame j of a window anchored at a: i - a in [-(P - 1) s, F s]
        off = int(rng.integers(-WINDOW_FUTURE * MAX_STRIDE, (WINDOW_PAST - 1) * MAX_STRIDE + 1))
        a = min(max(i + off, 0), len(seq) - 1)
        T_a_i = np.linalg.inv(seq.T_world_sensor[a]) @ seq.T_world_sensor[i]
        return sweep_targets(cfg, points, T_a_i)


def train_tokenizer(cfg, source: TokenizerSource, run, *, steps: int, seed: int = 0, log=print) -> dict:
    """The tokenizer through :func:`pcfbench.training.fit_loop` (AdamW, warm-up and cosine decay,
    gradient clipping at ``cfg.grad_clip``)."""
    import torch

    from pcfbench.methods.copilot4d.model import codebook_after_step
    from pcfbench.methods.occworld.tokenizer import SceneTokenizer, count_parameters, tokenizer_losses
    from pcfbench.training import default_device, fit_loop, warmup_cosine

    device = default_device()

    def sample_batch(rand, step: int):
        picks = rand.numpy.integers(0, len(source), cfg.batch_size)
        targets = [source.targets(cfg, int(k), rand.numpy) for k in picks]
        labels = torch.from_numpy(np.stack([t[0] for t in targets])).to(device)
        offsets = None if targets[0][1] is None else torch.from_numpy(np.stack([t[1] for t in targets])).to(device)
        return labels, offsets

    def step_fn(model, batch):
        out = tokenizer_losses(model, *batch)
        return out["loss"], {"loss": out["loss"].item(), "ce": out["ce"].item(), "lovasz": out["lovasz"].item(),
                             "vq": out["vq"].item(), "offset": out["offset"].item(),
                             "accuracy": out["accuracy"].item(), "batch_codes": int(out["codes"].unique().numel())}

    def after_step(model, opt, step: int) -> dict:
        return codebook_after_step(model.vq.core, opt, step, log)

    out = fit_loop(lambda: SceneTokenizer(cfg).to(device),
                   lambda m: torch.optim.AdamW(m.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay),
                   sample_batch, step_fn, run, steps=steps, seed=seed,
                   schedule=lambda step: warmup_cosine(step, cfg.lr, cfg.warmup, steps, cfg.min_lr_ratio),
                   grad_clip=cfg.grad_clip, log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                   after_step=after_step,
                   progress_values={"total loss": "loss", "voxel accuracy": "accuracy", "share of codes in use": "alive_codes"},
                   manifest_config=lambda m: {"tokenizer": cfg.to_dict(), "parameters": count_parameters(m),
                                              "steps_target": steps, "seed": seed, "frame": source.frame},
                   log=log)
    return {"model": out.model, "step": out.step, "history": out.history}


def tokenizer_curve_panels() -> list:
    from pcfbench.training import Panel

    return [Panel((("loss", "total loss"), ("ce", "cross entropy"), ("lovasz", "Lovasz-softmax"), ("vq", "VQ"),
                   ("offset", "plane offset L1 (half voxels)")), log=True),
            Panel((("accuracy", "accuracy of the labelled voxels"),), ylim=(0, 1)),
            Panel((("batch_codes", "codes used per step"),)),
            Panel((("alive_codes", "share of codes used within dead_after steps"),), ylim=(0, 1))]


def load_tokenizer(checkpoint: Checkpoint, cfg, prefix: str = "", weights: dict | None = None):
    """The tokenizer of ``checkpoint`` (weights under ``prefix``), which must record ``cfg``;
    ``weights``: its weights already read (``checkpoint.load_weights()``), else read here."""
    from pcfbench.methods.occworld.config import tokenizer_config_from_dict
    from pcfbench.methods.occworld.tokenizer import SceneTokenizer
    from pcfbench.training import CheckpointError, default_device
    from pcfbench.training.tokenized import load_network

    recorded = checkpoint.manifest.get("config", {}).get("tokenizer")
    if not isinstance(recorded, dict):
        raise CheckpointError(f"checkpoint {checkpoint.manifest_path} records no config.tokenizer: not an occworld one")
    if tokenizer_config_from_dict(recorded) != cfg:
        raise CheckpointError(f"checkpoint {checkpoint.manifest_path} was trained with another '{cfg.name}' tokenizer "
                              "configuration than this pcfbench defines; retrain it with --fresh")
    weights = checkpoint.load_weights() if weights is None else weights
    model = load_network(SceneTokenizer(cfg), checkpoint, weights, prefix, "tokenizer")
    return model.to(default_device()).eval()


class OccCopy(TrainedMethod):
    """OccWorld's tokenizer decoding the t=0 sweep's occupancy tokens at every future pose."""

    name = "occworld-occ-copy"
    # the default run scores 8 evenly spaced samples of each cell (its 10-minute budget on a
    # 2-core CPU; docs/protocol.md, "The default run's subset"); --subset 0 or naming the method: all
    default_run_subset = 8
    version = "1"
    Options = OccCopyOptions
    inference_options = ("readout",)
    # measured: 1000 steps in 775 s (the shipped checkpoint) and 921 s on this 2-core CPU, idle (2026-11-29)
    training_time = "about 13-15 min for the tiny configuration on an idle 2-core CPU (1000 steps at 0.8-0.95 s)"

    def __init__(self, options: OccCopyOptions | None = None) -> None:
        super().__init__(options)
        from pcfbench.methods.occworld.config import tokenizer_config

        self.cfg = tokenizer_config(self.options.config, self.options.tokens, self.options.surface)
        self.model = None

    def training_steps(self) -> int:
        return self.options.steps or self.cfg.max_steps

    def fit(self, train_source: TrainSource, out_dir: Path, progress: TrainingRun) -> None:
        from pcfbench.training import write_curve

        source = TokenizerSource(train_source.adapter, train_source.split, self.options.frame)
        progress.log(f"occworld tokenizer {self.cfg.name} ({self.cfg.token_grid[0]}x{self.cfg.token_grid[1]} tokens, "
                     f"frame {self.options.frame}): {len(source)} {train_source.split} sweeps of "
                     f"{train_source.adapter.name}")
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
        return copy_forecast(self.model, sample, self.options.readout)


def copy_forecast(model, sample: Sample, readout: str, tokenize=None, decode=None) -> Forecast:
    """The occupancy copy: the t=0 sweep labelled in its sensor frame, ``tokenize``d and
    ``decode``d (default: ``model``'s), rendered along every future query ray."""
    tokenize, decode = tokenize or tokenize_labels, decode or decode_grid
    T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
    last = (sample.past_points_ref[-1].astype(np.float64) @ T_s0_ref[:3, :3].T + T_s0_ref[:3, 3])
    prob = decode(model, tokenize(model, sweep_labels(model.cfg, last)))
    return Forecast.from_depths(sample, render_sample(model, prob, sample, T_s0_ref, readout))
