"""BEVWorld's configurations: the LiDAR tokenizer (``TokenizerConfig``) and the latent
diffusion world model (``WorldConfig``), each ``paper`` (the published sizes as far as the
paper states them), ``tiny`` (CPU scale) and ``micro`` (tests only).

What the paper states (sections 3.1, 3.2, 4.3.1, appendix B): the BEV range +-80 m x +-80 m x
+-4.5 m; a latent of C' = 4 channels, standardised per channel for the world model; a decoder
of up-sampling layers and Swin blocks to a 3-D feature volume, rendered NeRF-style along each
LiDAR ray with N_r = 150 uniform samples and expected depth, L1 loss (LiDAR weight 1.0); the
tokenizer's AdamW at 5e-4, betas (0.5, 0.9), cosine decay, batch 32 (1 per GPU); the world
model's AdamW at 5e-4, batch 128, DDIM sampling, a three-stage curriculum (next frame from 2
frames; 5 future frames; 6 future frames at 0.5 s from 3 past ones), no classifier-free
guidance. Everything else is **inferred** and says so below: the grid, the Swin widths and
depths and the volume take Copilot4D's (A.2.1 of its paper, the method BEVWorld compares with,
whose encoder pieces we reuse); the world model's width, depth, heads, patch size and noise
schedule take DiT-B/2's (the diffusion transformer the paper's spatial blocks follow, [24]).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

from pcfbench.errors import PcfbenchError

#: the paper's BEV range (section 4.2); it covers the protocol's ROI (+-70 m x +-4.5 m)
PAPER_X = (-80.0, 80.0)
PAPER_Z = (-4.5, 4.5)


@dataclass(frozen=True)
class TokenizerConfig:
    """The LiDAR tokenizer. The encoder fields are those Copilot4D's encoder reads
    (:class:`pcfbench.methods.copilot4d.model.Encoder`), which this tokenizer reuses."""

    name: str
    # --- the grid (a sweep's frame, metres) ---
    x_range: tuple[float, float] = PAPER_X
    y_range: tuple[float, float] = PAPER_X
    z_range: tuple[float, float] = PAPER_Z
    grid_xy: int = 1024  # inferred (Copilot4D's 15.6 cm voxels)
    grid_z: int = 64  # inferred
    # --- the encoder (voxel PointNet, z-pooling to BEV, two Swin stages; inferred sizes) ---
    pointnet_dim: int = 64
    bev_dim: int = 64
    patch_size: int = 4
    dims: tuple[int, int] = (128, 256)
    heads: tuple[int, int] = (8, 16)
    depths: tuple[int, int] = (2, 6)
    window: int = 8
    mlp_ratio: float = 4.0
    latent_channels: int = 4  # C' (stated)
    stats_momentum: float = 0.01  # the running per-channel statistics' momentum once warmed up
    # --- the decoder: a volume of vol_dim features on (grid_xy / patch_size * vol_up)^2 x vol_z cells ---
    vol_up: int = 2  # inferred (Copilot4D's 2x2 cells per decoded BEV cell)
    vol_z: int = 64  # inferred
    vol_dim: int = 16  # inferred
    mlp_hidden: int = 32  # the density MLP (inferred)
    # --- rendering ---
    samples_per_ray: int = 150  # N_r (stated)
    rays_per_step: int = 4096  # rays per sweep per training step (inferred)
    # --- optimisation (appendix B) ---
    lr: float = 5e-4
    betas: tuple[float, float] = (0.5, 0.9)
    weight_decay: float = 0.01  # AdamW's default (not stated)
    warmup: int = 1000  # not stated
    min_lr_ratio: float = 0.01
    grad_clip: float = 1.0  # not stated
    batch_size: int = 32
    max_steps: int = 100_000  # not stated
    log_every: int = 50
    checkpoint_every: int = 1000
    # --- moved sensors (read by Copilot4D's make_batch; 0: every sweep in its own frame) ---
    sensor_moved_share: float = 0.0
    sensor_shift: float = 0.0
    sensor_turn: float = 0.0

    def __post_init__(self) -> None:
        if self.grid_xy % (2 * self.patch_size * self.window):
            raise PcfbenchError(f"bevworld tokenizer {self.name!r}: grid_xy {self.grid_xy} must divide by "
                                f"2 x patch_size x window = {2 * self.patch_size * self.window}")

    @property
    def code_dim(self) -> int:
        """The encoder's output width (Copilot4D's name): the latent's channels."""
        return self.latent_channels

    @property
    def latent_grid(self) -> int:
        """Latent cells along each BEV axis."""
        return self.grid_xy // (2 * self.patch_size)

    @property
    def volume_xy(self) -> int:
        return 2 * self.latent_grid * self.vol_up

    @property
    def voxel_size(self) -> tuple[float, float, float]:
        return ((self.x_range[1] - self.x_range[0]) / self.grid_xy, (self.y_range[1] - self.y_range[0]) / self.grid_xy,
                (self.z_range[1] - self.z_range[0]) / self.grid_z)

    def to_dict(self) -> dict:
        return asdict(self)


TOKENIZERS = {
    "paper": TokenizerConfig("paper"),
    # CPU scale: Copilot4D's tiny encoder (256 x 256 x 16 voxels of 0.625 x 0.625 x 0.5625 m, 64 x 64
    # latent cells of 2.5 m) with 4 latent channels; a 256 x 256 x 16 volume of 8 features.
    # 600 steps (a step: a 120k-point sweep, 2,048 rays of 64 samples): 554 s in frame t0 on this
    # 2-core machine idle (docs/bevworld.md); the curve still falls at 600
    "tiny": TokenizerConfig("tiny", grid_xy=256, grid_z=16, pointnet_dim=32, bev_dim=32, patch_size=2, dims=(48, 96),
                            heads=(3, 6), depths=(2, 2), window=8, mlp_ratio=2.0, vol_up=2, vol_z=16, vol_dim=8,
                            samples_per_ray=64, rays_per_step=2048, warmup=50, batch_size=1, max_steps=600,
                            log_every=10, checkpoint_every=100),
    # tests: 16 x 16 latent cells
    "micro": TokenizerConfig("micro", grid_xy=64, grid_z=4, pointnet_dim=8, bev_dim=8, patch_size=2, dims=(16, 16),
                             heads=(2, 2), depths=(1, 1), window=4, mlp_ratio=2.0, vol_up=1, vol_z=4, vol_dim=4,
                             mlp_hidden=8, samples_per_ray=24, rays_per_step=256, warmup=2, lr=3e-3, betas=(0.9, 0.99),
                             batch_size=2, max_steps=40, log_every=1, checkpoint_every=20),
}


def tokenizer_config(name: str) -> TokenizerConfig:
    if name not in TOKENIZERS:
        raise PcfbenchError(f"bevworld config={name!r}: expected one of {', '.join(TOKENIZERS)}")
    return TOKENIZERS[name]


def _from_dict(cls, d: dict, what: str):
    try:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})
    except TypeError as exc:
        raise PcfbenchError(f"not a bevworld {what} configuration: {exc}") from None


def tokenizer_config_from_dict(d: dict) -> TokenizerConfig:
    """The ``TokenizerConfig`` a checkpoint manifest records (lists back to tuples)."""
    return _from_dict(TokenizerConfig, d, "tokenizer")


@dataclass(frozen=True)
class WorldConfig:
    """The spatio-temporal diffusion transformer and its training. ``latent_channels`` and
    ``latent_grid`` are the tokenizer's (``for_tokenizer``)."""

    name: str
    dim: int = 768  # inferred (DiT-B)
    depth: int = 6  # (temporal + spatial) block pairs: DiT-B's 12 blocks, inferred
    heads: int = 12  # inferred (DiT-B)
    patch: int = 2  # latent cells per token side, inferred (DiT-B/2)
    mlp_ratio: float = 4.0
    pose_dim: int = 9  # a frame's pose in the t=0 frame: translation and the rotation's first two columns
    freq_dim: int = 256  # the timestep's sinusoidal embedding (DiT)
    n_past: int = 5  # the protocol's settings: 5 past frames ...
    n_future: int = 5  # ... and 5 future ones
    # --- diffusion (DDPM's linear schedule, as DiT; not stated) ---
    diffusion_steps: int = 1000
    beta_start: float = 1e-4
    beta_end: float = 0.02
    ddim_steps: int = 50  # the paper's "around 50 steps" (section D)
    cond_dropout: float = 0.0  # the action dropped (replaced by a learned null) in training: CFG (the paper: none)
    # --- the tokenizer's latent ---
    latent_channels: int = 4
    latent_grid: int = 128
    # --- optimisation (section 4.3.1) ---
    lr: float = 5e-4
    weight_decay: float = 0.0
    warmup: int = 1000
    min_lr_ratio: float = 0.01
    grad_clip: float = 1.0
    batch_size: int = 128
    max_steps: int = 70_000  # the three stages: 20k + 20k + 30k
    log_every: int = 50
    checkpoint_every: int = 1000
    # --- the render stage (not the paper's; render_loss.py): steps after max_steps at a constant
    # learning rate, the depth L1 of the predicted latents rendered by the frozen tokenizer added
    # with weight render_weight (0: no render stage) ---
    render_weight: float = 0.0
    render_steps: int = 0
    render_lr: float = 1e-4
    render_rays: int = 512  # rays per rendered frame
    render_frames: int = 1  # future frames rendered per window per step
    render_per_sweep: int = 4096  # returns kept per future sweep to draw rays from

    def __post_init__(self) -> None:
        if self.dim % self.heads or self.dim % 2:
            raise PcfbenchError(f"bevworld world model {self.name!r}: dim {self.dim} must divide by heads "
                                f"{self.heads} and by 2")

    @property
    def frames(self) -> int:
        return self.n_past + self.n_future

    @property
    def token_grid(self) -> int:
        return self.latent_grid // self.patch

    def for_tokenizer(self, tok: TokenizerConfig) -> "WorldConfig":
        if tok.latent_grid % self.patch:
            raise PcfbenchError(f"bevworld world model {self.name!r}: the tokenizer's {tok.latent_grid} latent cells "
                                f"do not divide into patches of {self.patch}")
        return replace(self, latent_channels=tok.latent_channels, latent_grid=tok.latent_grid)

    def to_dict(self) -> dict:
        return asdict(self)


WORLDS = {
    "paper": WorldConfig("paper"),
    # CPU scale: 16 x 16 tokens of 4 x 4 latent cells, 4 block pairs of width 128. 2000 steps: a step
    # (batch 2, 10 frames) about 0.6 s on this 2-core machine idle, within the 30-minute budget with
    # the windows' encoding (docs/bevworld.md). 2 DDIM steps: measured better than 20 on every
    # column at kitti-3s and on the L1 columns at kitti-1s (chamfer_nf a tie), and cheaper. Then the
    # render stage: 300 steps with the rendered depth L1 at weight 1 (about 0.8 s a step), which broke
    # that tie (docs/bevworld.md, "The render stage")
    "tiny": WorldConfig("tiny", dim=128, depth=4, heads=4, patch=4, freq_dim=64, warmup=50, batch_size=2,
                        max_steps=2000, log_every=10, checkpoint_every=100, ddim_steps=2, render_weight=1.0,
                        render_steps=300),
    "micro": WorldConfig("micro", dim=32, depth=2, heads=2, patch=2, freq_dim=16, n_past=2, n_future=5,
                         diffusion_steps=100, ddim_steps=5, lr=2e-3, warmup=2, batch_size=2, max_steps=40,
                         log_every=1, checkpoint_every=20),
}


def world_config(name: str, tok: TokenizerConfig) -> WorldConfig:
    if name not in WORLDS:
        raise PcfbenchError(f"bevworld config={name!r}: expected one of {', '.join(WORLDS)}")
    return WORLDS[name].for_tokenizer(tok)


def world_config_from_dict(d: dict) -> WorldConfig:
    return _from_dict(WorldConfig, d, "world model")
