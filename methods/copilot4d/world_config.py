"""World-model configurations: ``paper`` (the sizes of A.2.2 / A.3) and ``tiny`` (CPU scale).

Both build the same network (:mod:`pcfbench.methods.copilot4d.world`). The token grid and the
codebook size come from the matching tokenizer configuration in
:mod:`pcfbench.methods.copilot4d.config`, so a world model always fits its tokenizer's output.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

from pcfbench.methods.copilot4d.config import PAPER as PAPER_TOKENIZER
from pcfbench.methods.copilot4d.config import TINY as TINY_TOKENIZER


@dataclass(frozen=True)
class WorldModelConfig:
    """One U-Net world model over BEV token maps of ``token_grid`` x ``token_grid`` codes.

    Levels 1, 2, 3 run at 1x, 2x, 4x down-sampled resolution with widths ``dims`` and
    ``heads`` attention heads. A *group* is ``spatial_per_group`` Swin blocks followed by one
    GPT-2 temporal block; ``groups_down[i]`` groups run on level i+1 on the way down and
    ``groups_up[i]`` groups on level i+1 on the way up (level 3 has none: it is the bottom).
    """

    name: str
    codebook_size: int  # |V|; the mask token is index ``codebook_size``
    token_grid: int  # tokens along each BEV axis (H = W)
    n_past: int  # past frames, t = -(n_past-1) .. 0
    n_future: int  # future frames predicted
    dims: tuple[int, int, int]
    heads: tuple[int, int, int]
    windows: tuple[int, int, int]  # Swin window size per level
    groups_down: tuple[int, int, int] = (2, 2, 1)
    groups_up: tuple[int, int] = (2, 1)  # levels 1 and 2 on the way up
    spatial_per_group: int = 2
    mlp_ratio: float = 4.0
    # --- where each frame's sensor sees every token from (not the paper's; 0: off) ---
    # ``view_freqs`` > 0 adds to every token of every frame, at the start of every level, the
    # position of the token's centre in that frame's sensor frame (Fourier features with this many
    # octaves, its distance and log distance; :func:`pcfbench.methods.copilot4d.world.view_features`)
    # over a grid of half-width ``bev_extent`` metres (the tokenizer's x and y ranges)
    view_freqs: int = 0
    bev_extent: float = 80.0
    # --- optimisation (A.3, world model); Algorithms 1 and 2 live in diffusion.py ---
    label_smoothing: float = 0.1
    lr: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.95)
    weight_decay: float = 1e-4
    warmup: int = 2000
    decay_steps: int = 750_000
    min_lr_ratio: float = 0.1
    grad_clip: float = 5.0
    batch_size: int = 8
    max_steps: int = 750_000

    def __post_init__(self) -> None:
        from pcfbench.errors import PcfbenchError

        problems = []
        for lvl in range(3):
            size = self.token_grid >> lvl
            if self.token_grid % (1 << lvl) or size % self.windows[lvl]:
                problems.append(f"level {lvl + 1} is {self.token_grid / (1 << lvl):g} tokens wide, "
                                f"not a multiple of its window {self.windows[lvl]}")
            if self.dims[lvl] % self.heads[lvl]:
                problems.append(f"level {lvl + 1} width {self.dims[lvl]} is not divisible by {self.heads[lvl]} heads")
        if self.dims[0] % 4:
            problems.append(f"level 1 width {self.dims[0]} must be divisible by 4 (2-D sine-cosine encoding)")
        if self.view_freqs < 0 or self.bev_extent <= 0:
            problems.append(f"view_freqs={self.view_freqs} must be at least 0 and bev_extent={self.bev_extent:g} positive")
        if self.n_past < 1 or self.n_future < 1:
            problems.append(f"n_past={self.n_past} and n_future={self.n_future} must both be at least 1")
        if problems:
            raise PcfbenchError(f"world model config {self.name!r}: " + "; ".join(problems))

    @property
    def n_frames(self) -> int:
        """Frames in one training sequence: past (including t=0) then future."""
        return self.n_past + self.n_future

    @property
    def tokens_per_frame(self) -> int:
        return self.token_grid * self.token_grid

    def to_dict(self) -> dict:
        return asdict(self)

    def with_overrides(self, **kw) -> "WorldModelConfig":
        return replace(self, **kw)


# A.2.2: 128 x 128 tokens of a 1024-code tokenizer, widths (256, 384, 512), 32 dimensions per
# head, windows 8 / 8 / 16; down (2S 1T 2S 1T), (2S 1T 2S 1T), (2S 1T); up (2S 1T) on level 2
# and (2S 1T 2S 1T) on level 1. KITTI / Argoverse 2 protocol: 5 past and 5 future frames.
PAPER = WorldModelConfig(
    name="paper",
    codebook_size=PAPER_TOKENIZER.codebook_size, token_grid=PAPER_TOKENIZER.bev_tokens,
    n_past=5, n_future=5,
    dims=(256, 384, 512), heads=(8, 12, 16), windows=(8, 8, 16),
    groups_down=(2, 2, 1), groups_up=(2, 1),
)

# CPU scale: the tiny tokenizer's grid and codebook, the paper's block layout at an eighth to a
# fifth of its widths (still 32 dimensions per head) and a batch of one sequence: about 0.35 s
# per training step (10 frames) on an idle 2-core CPU. 600 steps (the schedule decays over them)
# fit the 45 minutes the world model may take on a busy one (docs/journal/copilot4d-2026-11.md,
# "Training times").
TINY = WorldModelConfig(
    name="tiny",
    codebook_size=TINY_TOKENIZER.codebook_size, token_grid=TINY_TOKENIZER.bev_tokens,
    n_past=5, n_future=5,
    dims=(32, 64, 96), heads=(1, 2, 3), windows=(8, 8, 8),
    groups_down=(2, 2, 1), groups_up=(2, 1),
    warmup=100, decay_steps=600, batch_size=1, max_steps=600,
)

# GPU scale on the CPU-scale tokenizer: the paper's network (widths, heads, windows, A.3's batch
# of 8) over the tiny tokenizer's 64 x 64 tokens and 512 codes, 39,219,624 parameters. The paper
# tokenizer takes days on one GPU; this trains in minutes there (0.37 s per step on an H200,
# 59 GiB; docs/copilot4d.md, "On a GPU") and is far too slow for a CPU.
WIDE = replace(PAPER, name="wide", codebook_size=TINY_TOKENIZER.codebook_size, token_grid=TINY_TOKENIZER.bev_tokens,
               warmup=200, decay_steps=2000, max_steps=2000)

# ``tiny`` on the ``tiny-window`` tokenizer (trained on sweeps moved as the windows move them into
# their t=0 frame; issue 42's candidate (a)): the frame t0's ceiling on it beats its token copy
# (docs/copilot4d.md, "The ceiling of each frame"). Trained 800 steps (anchor_every=1) it is its token
# copy to within a few percent; 600 steps more (init_steps=800) it beats it at kitti-3s, not at
# kitti-1s, its curve still falling (docs/copilot4d.md, "Held out against trained"); 1,000 more
# (init_steps=800/600) its objective improves and its forecast does not ("1,000 steps more").
TINY_WINDOW = replace(TINY, name="tiny-window")

# ``tiny`` on the ``tiny-views`` tokenizer (``tiny-window`` whose two views of a window are pulled to
# the same codes): its target changes a quarter to a third fewer tokens, and trained 600 steps it was
# worse than its token copy at both horizons (docs/copilot4d.md, "Two views of a window")
TINY_VIEWS = replace(TINY, name="tiny-views")

# ``tiny-window`` told where each frame's sensor sees every token from (``view_freqs``): the
# tokenizer's codes depend on the viewpoint, most near the sensor, where a look-up table keyed by the
# t=0 code and the future sensor's distance and bearing to the token gets 15 % of the changes right
# (stride 2) and the model 2-6 %. Trained 800 steps its curve is tiny-window's and its forecast not
# better (docs/copilot4d.md, "Where the sensor sees a token from")
TINY_WINDOW_VIEW = replace(TINY, name="tiny-window-view", view_freqs=6)
CONFIGS = {"paper": PAPER, "tiny": TINY, "wide": WIDE, "tiny-window": TINY_WINDOW, "tiny-views": TINY_VIEWS,
           "tiny-window-view": TINY_WINDOW_VIEW}
#: world-model configurations that work on a tokenizer configuration of another name (the
#: others work on the tokenizer configuration of their own name)
TOKENIZER_OF = {"wide": TINY_TOKENIZER.name, "tiny-window-view": "tiny-window"}


def tokenizer_config_name(name: str) -> str:
    """The tokenizer configuration that world-model configuration ``name`` works on."""
    get_world_config(name)  # an unknown name is one clear error
    return TOKENIZER_OF.get(name, name)


def get_world_config(name: str) -> WorldModelConfig:
    from pcfbench.errors import unknown_name

    if name not in CONFIGS:
        raise unknown_name("world model config", name, CONFIGS)
    return CONFIGS[name]
