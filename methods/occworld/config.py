"""OccWorld's configurations: the scene tokenizer (``TokenizerConfig``) and the world model
(``WorldConfig``), each ``paper`` (the published sizes) and ``tiny`` (CPU scale), plus
``micro`` (tests only).

The paper (section 4.2) and its public configuration (``config/occworld.py`` of the authors'
repository) give: a 200 x 200 x 16 occupancy grid, a learnable class embedding of 8 channels
per voxel folded with the 16 heights into 128 BEV channels, a 2-D encoder and decoder of
residual blocks (base width 64, multipliers 1, 2, 4, two blocks per level, self-attention at
the 50 x 50 token resolution), down-sampling factor 4, a codebook of 512 codes of 128
channels (beta 1), the loss cross entropy x 10 + Lovasz-softmax + VQ; the world model has 3
scales of widths 128, 256, 512, 6 temporal attention layers per scale, 2 ego-pose attention
layers, 8 heads, AdamW (lr 1e-3, weight decay 0.01), cosine schedule, gradient norm clipped
at 35. OccWorld predicts the next frame from 2 s of history (6 frames at 2 Hz in nuScenes) for
3 s of future (6 frames). Our grid covers the protocol's ROI (140 x 140 x 9 m) instead of
Occ3D's 80 x 80 x 6.4 m, so the paper grid's voxels are 0.7 x 0.7 x 0.5625 m.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

from pcfbench.errors import PcfbenchError

#: the protocol's ROI (pcfbench/protocol/protocol.toml); recorded in every configuration
ROI_LO = (-70.0, -70.0, -4.5)
ROI_HI = (70.0, 70.0, 4.5)


@dataclass(frozen=True)
class TokenizerConfig:
    name: str
    # --- the occupancy grid (a sweep's frame, metres) ---
    dims: tuple[int, int, int] = (200, 200, 16)
    box_lo: tuple[float, float, float] = ROI_LO
    box_hi: tuple[float, float, float] = ROI_HI
    num_classes: int = 3  # free, occupied, unknown (pcfbench.methods.occworld.occupancy)
    # --- the VQ-VAE (the public config's VAERes2D) ---
    expansion: int = 8  # class embedding channels per voxel
    ch: int = 64  # base width
    ch_mult: tuple[int, ...] = (1, 2, 4)  # one level per entry; down-sampling 2 ** (levels - 1)
    num_res_blocks: int = 2
    level_attention: bool = True  # attention after each block of the token level (else only in the middle blocks)
    z_channels: int = 128  # the code dimension
    codebook_size: int = 512
    beta: float = 1.0  # the codebook term's weight (the public config's "legacy" VQ loss)
    # --- dead codes (ours, Copilot4D's quantizer, shared): without them the tiny tokenizer used 8 of
    # its 512 codes per step and its VQ loss grew to 10 (300 steps, docs/occworld.md): a K-means
    # start once the memory bank of encoder outputs fills, and a K-means re-initialisation when
    # more than dead_fraction of the codes went unused for dead_after steps ---
    memory_factor: int = 10
    dead_after: int = 100
    dead_fraction: float = 0.03
    reinit_every: int = 100
    kmeans_iters: int = 10
    kmeans_init: bool = True
    # --- the loss ---
    ce_weight: float = 10.0
    lovasz_weight: float = 1.0
    vq_weight: float = 1.0
    # --- sub-voxel planes (ours, not the paper's; surface.py): ``none`` or the offsets' target,
    # ``front`` / ``mean``; not ``none`` adds one offset per voxel to the decoder (a 3x3
    # convolution beside its classifier), trained with L1 on the occupied voxels ---
    surface: str = "none"
    offset_weight: float = 10.0
    # --- optimisation ---
    lr: float = 1e-3
    weight_decay: float = 0.01
    warmup: int = 50
    min_lr_ratio: float = 1e-3
    grad_clip: float = 35.0
    batch_size: int = 8  # 1 per GPU on 8 GPUs in the paper
    max_steps: int = 20000
    log_every: int = 10
    checkpoint_every: int = 100

    def __post_init__(self) -> None:
        from pcfbench.methods.occworld.surface import SURFACES

        if self.surface not in SURFACES:
            raise PcfbenchError(f"surface={self.surface!r}: expected one of {', '.join(SURFACES)}")
        down = 2 ** (len(self.ch_mult) - 1)
        if len(self.dims) != 3 or self.dims[0] % down or self.dims[1] % down:
            raise PcfbenchError(f"occworld tokenizer {self.name!r}: the grid {self.dims} must divide by the "
                                f"down-sampling factor {down} in x and y")

    @property
    def down(self) -> int:
        return 2 ** (len(self.ch_mult) - 1)

    # the names Copilot4D's quantizer reads (methods/copilot4d/model.py)
    @property
    def code_dim(self) -> int:
        return self.z_channels

    @property
    def beta_codebook(self) -> float:
        return self.beta

    @property
    def beta_commit(self) -> float:
        return 1.0

    @property
    def voxel(self) -> tuple[float, float, float]:
        return tuple((h - lo) / n for lo, h, n in zip(self.box_lo, self.box_hi, self.dims))

    @property
    def offset_scale(self) -> float:
        """Metres per unit of the offset head's output: half the largest voxel side."""
        return max(self.voxel) / 2

    @property
    def token_grid(self) -> tuple[int, int]:
        return (self.dims[0] // self.down, self.dims[1] // self.down)

    def to_dict(self) -> dict:
        return asdict(self)

    def with_tokens(self, tokens: int) -> "TokenizerConfig":
        """The same tokenizer with ``tokens`` x ``tokens`` tokens (the paper's Table 3 sweep): the
        levels are those of a down-sampling factor ``dims[0] / tokens`` (a power of 2), widths
        doubling per level up to 4x the base (the public configuration's multipliers)."""
        if tokens <= 0 or self.dims[0] % tokens or self.dims[0] != self.dims[1]:
            raise PcfbenchError(f"tokens={tokens}: expected a divisor of the grid's {self.dims[0]} voxels")
        f = self.dims[0] // tokens
        levels = f.bit_length() - 1
        if 2 ** levels != f:
            raise PcfbenchError(f"tokens={tokens}: the down-sampling factor {f} is not a power of 2")
        return replace(self, ch_mult=tuple(min(2 ** i, 4) for i in range(levels + 1)))


TOKENIZERS = {
    "paper": TokenizerConfig("paper"),
    # CPU scale: the same grid, tokens and codebook; a narrower and shallower network
    # (attention only in the middle blocks: attention over 2,500 tokens dominated the step)
    # base width 32 (16 decoded 74% of the occupied voxels after 1200 steps: docs/occworld.md); 1000 steps:
    # a step took about 1.0 s (median) on this 2-core machine idle
    "tiny": TokenizerConfig("tiny", expansion=4, ch=32, num_res_blocks=1, level_attention=False, z_channels=64,
                            batch_size=1, max_steps=1000, warmup=50),
    # tests: a small grid over the ROI
    "micro": TokenizerConfig("micro", dims=(32, 32, 4), expansion=2, ch=8, ch_mult=(1, 2), num_res_blocks=1,
                             level_attention=False,
                             z_channels=8, codebook_size=16, batch_size=2, max_steps=40, warmup=2, log_every=1,
                             checkpoint_every=20),
}


def tokenizer_config(name: str, tokens: int = 0, surface: str = "none") -> TokenizerConfig:
    if name not in TOKENIZERS:
        raise PcfbenchError(f"occworld config={name!r}: expected one of {', '.join(TOKENIZERS)}")
    cfg = TOKENIZERS[name]
    cfg = cfg.with_tokens(tokens) if tokens else cfg
    return replace(cfg, surface=surface) if surface != cfg.surface else cfg


def tokenizer_config_from_dict(d: dict) -> TokenizerConfig:
    """The ``TokenizerConfig`` a checkpoint manifest records (lists back to tuples)."""
    try:
        return TokenizerConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})
    except TypeError as exc:
        raise PcfbenchError(f"not an occworld tokenizer configuration: {exc}") from None


@dataclass(frozen=True)
class WorldConfig:
    """The spatio-temporal generative transformer (the public ``PlanUAutoRegTransformer``) and
    its training windows. ``code_dim``, ``codebook_size`` and ``token_grid`` are the
    tokenizer's (``for_tokenizer``)."""

    name: str
    channels: tuple[int, ...] = (128, 256, 512)  # one scale each; the last is the middle block's
    temporal_layers: int = 6  # temporal attention layers per scale (encoder and decoder side)
    pose_layers: int = 2  # ego-pose attention layers per scale
    heads: int = 8
    n_past: int = 5  # the protocol's settings: 5 past frames ...
    n_future: int = 5  # ... and 5 future ones
    pose_dim: int = 9  # a motion: translation (3) and the first two columns of the rotation (6)
    pose_weight: float = 0.1  # the public configuration's weight of the pose regression
    code_dim: int = 128
    codebook_size: int = 512
    token_grid: tuple[int, int] = (50, 50)
    # --- optimisation (section 4.2 and the public configuration) ---
    lr: float = 1e-3
    weight_decay: float = 0.01
    warmup: int = 50
    min_lr_ratio: float = 1e-3
    grad_clip: float = 35.0
    batch_size: int = 8
    max_steps: int = 20000
    log_every: int = 10
    checkpoint_every: int = 100

    @property
    def positions(self) -> int:
        """Input frames the model holds: a window of n_past + n_future frames predicts frames 1..T-1 from 0..T-2."""
        return self.n_past + self.n_future - 1

    def for_tokenizer(self, tok: TokenizerConfig) -> "WorldConfig":
        return replace(self, code_dim=tok.z_channels, codebook_size=tok.codebook_size, token_grid=tok.token_grid)

    def to_dict(self) -> dict:
        return asdict(self)


WORLDS = {
    "paper": WorldConfig("paper"),
    # CPU scale: the paper's three scales at a quarter of the widths, one layer of each kind
    # (1200 steps: a step took 0.94 s, median, on this 2-core machine idle; 6.2 s while another training ran)
    "tiny": WorldConfig("tiny", channels=(32, 64, 128), temporal_layers=1, pose_layers=1, heads=4, batch_size=1,
                        max_steps=1200, warmup=50),
    "micro": WorldConfig("micro", channels=(16, 32), temporal_layers=1, pose_layers=1, heads=2, n_past=2, n_future=2,
                         batch_size=2, max_steps=40, warmup=2, log_every=1, checkpoint_every=20),
}


def world_config(name: str, tok: TokenizerConfig) -> WorldConfig:
    if name not in WORLDS:
        raise PcfbenchError(f"occworld config={name!r}: expected one of {', '.join(WORLDS)}")
    return WORLDS[name].for_tokenizer(tok)


def world_config_from_dict(d: dict) -> WorldConfig:
    try:
        return WorldConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})
    except TypeError as exc:
        raise PcfbenchError(f"not an occworld world model configuration: {exc}") from None
