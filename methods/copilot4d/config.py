"""Tokenizer configurations: ``paper`` (the exact sizes of A.2.1 / A.3) and ``tiny`` (CPU scale).

Both build the same architecture; ``tiny`` only shrinks the grid, widths, depths, codebook
and the number of rays per step so that it trains on a 2-core CPU in minutes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace


#: how moved-sensor training sweeps are drawn (``TokenizerConfig.sensor_moves``)
SENSOR_MOVES = ("disc", "window")


@dataclass(frozen=True)
class TokenizerConfig:
    name: str
    # --- grid (sensor frame of the sweep, metres) ---
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    z_range: tuple[float, float]
    grid_xy: int  # voxels along x and along y
    grid_z: int  # voxels along z
    # --- encoder ---
    pointnet_dim: int  # voxel-wise PointNet feature size
    bev_dim: int  # feature size after z-pooling to BEV
    patch_size: int  # first Swin stage patch size (the second stage doubles it)
    dims: tuple[int, int]  # Swin feature sizes of the two stages
    heads: tuple[int, int]
    depths: tuple[int, int]  # Swin blocks per stage (encoder; the decoder mirrors them)
    window: int
    mlp_ratio: float
    # --- vector quantizer ---
    codebook_size: int
    code_dim: int
    beta_codebook: float = 0.25  # lambda_1 on |sg[E(o)] - z_hat|^2
    beta_commit: float = 1.0  # lambda_2 on |sg[z_hat] - E(o)|^2
    memory_factor: int = 10  # memory bank = factor x codebook size
    dead_after: int = 256  # iterations unused before a code counts as dead
    dead_fraction: float = 0.03  # re-initialise when more than this fraction is dead
    reinit_every: int = 200  # at least this many iterations between re-initialisations
    kmeans_iters: int = 10
    kmeans_init: bool = True  # K-means initialisation once the memory bank first fills
    # --- decoder ---
    nfg_up: int = 2  # NFG BEV upsampling of the decoder output (paper: 2^2 cells per BEV cell)
    nfg_dim: int = 16  # feature size of each NFG voxel
    nfg_z: int = 64  # NFG voxels along z
    mlp_hidden: int = 32
    coarse_bias: float = -5.0
    # --- rendering ---
    rays_per_step: int = 4096  # rays sampled per sweep per training step
    samples_per_ray: int = 64  # N_r
    # Training only: this many extra samples per ray drawn uniformly over the whole in-box
    # segment, besides the N_r inside the ground-truth mask (the paper samples inside the mask
    # only, so 0 there). They teach the NFG that space outside the mask is free, which keeps
    # inference sound where the predicted coarse mask has false positives.
    train_uniform_samples: int = 0
    candidate_step: float = 0.2  # spacing (m) of the candidate points used for spatial skipping
    skip_pool: int = 8  # max-pool factor in BEV for spatial skipping
    epsilon: float = 0.4  # margin of the weight-concentration term (m)
    # --- optimisation (A.3) ---
    lr: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.95)
    weight_decay: float = 1e-4
    warmup: int = 4000
    decay_steps: int = 400_000
    min_lr_ratio: float = 0.1
    grad_clip: float = 0.1
    batch_size: int = 16
    max_steps: int = 400_000
    checkpoint_every: int = 1000
    log_every: int = 50
    # --- moved sensors (issue 42, candidate (a)): the share of training sweeps seen from a sensor
    # moved by up to ``sensor_shift`` m (radius uniform, direction uniform) and turned by up to
    # ``sensor_turn`` degrees about z (uniform), as sweeps moved into the t=0 frame of a window are.
    # 0 (every built-in configuration but tiny-moved): each sweep in its own sensor frame.
    sensor_moved_share: float = 0.0
    sensor_shift: float = 0.0
    sensor_turn: float = 0.0
    # ``disc``: the move above; ``window``: a moved sweep is frame j (uniform over the window's
    # ``window_past + window_future`` frames) of a window of stride s (uniform over
    # ``window_strides``) in its own sequence, seen from that window's t=0 sensor: the real
    # relative pose ``inv(T_world_s0) @ T_world_sk`` (clipped at the sequence's ends), as the
    # world model's t=0 frame holds it (issue 42's candidate (a): "over the range the windows need").
    sensor_moves: str = "disc"
    window_strides: tuple[int, ...] = (2, 6)
    window_past: int = 5
    window_future: int = 5
    # --- views of one window (issue 42's lever after the t0 training): with ``sensor_moves ==
    # "window"``, every training sweep comes with a second frame of the same window, both in that
    # window's t=0 frame (``SweepSource.window_pair``), and on the token cells both sweeps observe
    # each one's encoder output is pulled towards the other's code by this weight (the commitment
    # term of L_vq with the other view's code): a static world should get the same tokens from
    # wherever in the window it is seen. 0: one sweep per example, no pull.
    view_consistency: float = 0.0
    # the tokenizer configuration whose complete checkpoint, trained on the same data, this one's
    # training starts from (weights, codebook and its bookkeeping; a fresh optimiser and schedule);
    # "": from a random initialisation
    init_from: str = ""

    def __post_init__(self) -> None:
        if self.sensor_moves not in SENSOR_MOVES:
            from pcfbench.errors import PcfbenchError

            raise PcfbenchError(f"tokenizer config {self.name!r}: sensor_moves must be one of {', '.join(SENSOR_MOVES)}, "
                                f"not {self.sensor_moves!r}")
        if self.view_consistency and self.sensor_moves != "window":
            from pcfbench.errors import PcfbenchError

            raise PcfbenchError(f"tokenizer config {self.name!r}: view_consistency pairs the frames of a window, so it "
                                f"needs sensor_moves='window', not {self.sensor_moves!r}")

    @property
    def voxel_size(self) -> tuple[float, float, float]:
        return (
            (self.x_range[1] - self.x_range[0]) / self.grid_xy,
            (self.y_range[1] - self.y_range[0]) / self.grid_xy,
            (self.z_range[1] - self.z_range[0]) / self.grid_z,
        )

    @property
    def bev_tokens(self) -> int:
        """Tokens along each BEV axis: the grid down-sampled 2 x patch_size times."""
        return self.grid_xy // (2 * self.patch_size)

    def to_dict(self) -> dict:
        return asdict(self)

    def with_overrides(self, **kw) -> "TokenizerConfig":
        return replace(self, **kw)


# A.2.1: [-80, 80]^2 x [-4.5, 4.5] m, 15.625 x 15.625 x 14.0625 cm voxels (1024 x 1024 x 64),
# PointNet 64, Swin 2 x (128, 8 heads) at patch 4 then 6 x (256, 16 heads) at patch 8,
# 128 x 128 tokens, code dimension 1024, 1024 codes; NFG 512 x 512 x 64 x 16; A.3 optimiser.
PAPER = TokenizerConfig(
    name="paper",
    x_range=(-80.0, 80.0), y_range=(-80.0, 80.0), z_range=(-4.5, 4.5),
    grid_xy=1024, grid_z=64,
    pointnet_dim=64, bev_dim=64, patch_size=4,
    dims=(128, 256), heads=(8, 16), depths=(2, 6), window=8, mlp_ratio=4.0,
    codebook_size=1024, code_dim=1024,
    nfg_up=2, nfg_dim=16, nfg_z=64, mlp_hidden=32,
    rays_per_step=4096, samples_per_ray=64, candidate_step=0.1,
    warmup=4000, decay_steps=400_000, grad_clip=0.1, batch_size=16, max_steps=400_000,
)

# CPU scale: the paper's extent [-80, 80]^2 m, which covers the protocol's ROI (+-70 m around
# the t=0 sensor) also from a future sensor that moved up to 10 m, at 0.625 x 0.625 x 0.5625 m
# voxels (256 x 256 x 16), 64 x 64 tokens (2.5 m each; patch 2, then 4), 512 codes; NFG
# 256 x 256 x 16 x 8 (0.625 m cells), candidate points every 0.5 m for spatial skipping (its
# cells are 5 m wide), 1200 steps (docs/copilot4d.md: what was measured). 32 x 32 tokens
# (5 m, patch 4; version 2) reconstructed about 5x worse than copy-last's forecast error: 9 bits
# per 25 m^2 column cannot hold the scene (docs/journal/copilot4d-2026-11.md).
TINY = TokenizerConfig(
    name="tiny",
    x_range=(-80.0, 80.0), y_range=(-80.0, 80.0), z_range=(-4.5, 4.5),
    grid_xy=256, grid_z=16,
    pointnet_dim=32, bev_dim=32, patch_size=2,
    dims=(48, 96), heads=(3, 6), depths=(2, 2), window=8, mlp_ratio=2.0,
    codebook_size=512, code_dim=64,
    nfg_up=2, nfg_dim=8, nfg_z=16, mlp_hidden=32,
    rays_per_step=2048, samples_per_ray=64, candidate_step=0.5,
    warmup=60, decay_steps=1200, grad_clip=0.1, batch_size=1, max_steps=1200,
    checkpoint_every=100, log_every=10,
)

# ``tiny`` trained on sweeps as the t=0 frame of a world-model window holds them: three in four
# seen from a sensor moved up to 40 m and turned up to 75 degrees (synthetic-town-realistic's
# train split: of sensors 3 s apart, half lie within 10 m of each other, 99 % within 39 m and
# 69 degrees, all within 40 m and 74 degrees), the rest in their own frame.
TINY_MOVED = replace(TINY, name="tiny-moved", sensor_moved_share=0.75, sensor_shift=40.0, sensor_turn=75.0)

# ``tiny`` trained on sweeps moved exactly as the world model's windows (5 past, 5 future, strides 2
# and 6: kitti-1s and kitti-3s) move them into their t=0 frame: every sweep is drawn as one frame
# of such a window (one in ten is the t=0 frame itself); on synthetic-town-realistic's train split
# the moves reach 25 m, most along the road, with small turns.
TINY_WINDOW = replace(TINY, name="tiny-window", sensor_moved_share=1.0, sensor_moves="window")

# ``tiny-window`` fine-tuned with every training example two frames of one window seen from its t=0
# sensor, each view's encoder output pulled towards the other's code where both see the token cell
# (``view_consistency``): codes that depend less on where in the window the sensor stands. Two
# sweeps per step at half the rays each (the same rays rendered per step as ``tiny-window``; a
# step costs 1.9x its). It starts from the trained ``tiny-window``: from a random start the pull
# collapsed the codebook to one code within 60 steps (every view agrees on a single code), before
# the reconstruction had shaped any. Weight 5 and no K-means re-initialisation while it
# fine-tunes (``dead_fraction`` 1): at weight 1 with re-initialisation the target still changed
# 30 % of its tokens at kitti-1s (tiny-window: 32 %), at weight 5 without it 22 %
# (docs/copilot4d.md, "Two views of a window").
TINY_VIEWS = replace(TINY_WINDOW, name="tiny-views", view_consistency=5.0, dead_fraction=1.0, rays_per_step=1024,
                     init_from="tiny-window", lr=3e-4, warmup=20, decay_steps=400, max_steps=400)

CONFIGS = {"paper": PAPER, "tiny": TINY, "tiny-moved": TINY_MOVED, "tiny-window": TINY_WINDOW, "tiny-views": TINY_VIEWS}


def get_config(name: str) -> TokenizerConfig:
    from pcfbench.errors import PcfbenchError

    if name not in CONFIGS:
        raise PcfbenchError(f"unknown tokenizer config {name!r}; known: {', '.join(CONFIGS)}")
    return CONFIGS[name]
