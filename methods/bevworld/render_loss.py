"""The world model's render stage (**not the paper's**; docs/bevworld.md, "The render stage"):
after its latent training, the world model trains on for ``render_steps`` more steps with, beside
the latent MSE, the L1 depth error of its predicted clean future latents rendered through the
frozen tokenizer's decoder along the true future sweep's rays from the future sensor's origin,
weighted by ``render_weight``. The latent MSE is blind to how an error renders (a small error
in a cell of open space becomes density a ray stops at); the depth loss is what the tokenizer
itself was trained on.

:class:`WindowRays` holds, for every sweep a training window's future frames use, ``per_sweep``
of its returns (ego returns removed, nearer than 0.5 m dropped) drawn once with a seeded
generator, in the sweep's sensor frame; a batch moves them into the window's frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

#: returns nearer than this (m) are not rays (the tokenizer's ``make_batch``'s ``min_range``)
MIN_RANGE = 0.5


class WindowRays:
    """The future sweeps' returns of ``windows`` (``build_windows``'s: ``sequence``,
    ``sweeps``, ``sequences``, ``poses``)."""

    def __init__(self, adapter, windows: dict, n_past: int, *, per_sweep: int, seed: int, log=print) -> None:
        import time

        t0 = time.monotonic()
        self.n_past, self.poses = n_past, windows["poses"]
        self.sequence, self.sweeps = windows["sequence"], windows["sweeps"]
        rng = np.random.default_rng(seed)
        self.points: dict[tuple[int, int], np.ndarray] = {}
        for q, name in enumerate(windows["sequences"]):
            mine = self.sequence == q
            if not mine.any():
                continue
            seq = adapter.sequence(str(name))
            for k in np.unique(self.sweeps[mine][:, n_past:]).tolist():
                p = adapter.ego_box.remove(seq.load_points(k)).astype(np.float32)
                p = p[np.linalg.norm(p, axis=1) > MIN_RANGE]
                if not len(p):
                    continue  # a sweep without returns gives no rays (the frame is skipped)
                self.points[(q, k)] = p[rng.choice(len(p), min(per_sweep, len(p)), replace=False)]
        log(f"render stage: {len(self.points)} future sweeps' returns ({per_sweep} each at most) read in "
            f"{time.monotonic() - t0:.0f} s")

    def rays(self, cfg, window: int, frame: int, own: bool, count: int, rng: np.random.Generator):
        """``count`` rays (drawn without replacement, so at most the sweep's returns in the grid:
        drawn with replacement, the stage lost kitti-3s's win in every training; docs/bevworld.md)
        of window ``window``'s frame ``frame`` (0-based,
        past frames first) whose return lies inside the tokenizer's grid, seen in the window's
        frame (``own``: the sweep's own sensor frame, origin 0; else the t=0 frame): (origins,
        unit directions (count, 3), depths (count,)) float32, or None when it has none."""
        from pcfbench.methods.copilot4d.data import in_box

        p = self.points.get((int(self.sequence[window]), int(self.sweeps[window, frame])))
        if p is None:
            return None
        T = np.eye(4) if own else self.poses[window, frame].astype(np.float64)
        moved = (p.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        ok = np.nonzero(in_box(cfg, moved))[0]
        if not len(ok):
            return None
        pick = rng.choice(ok, min(count, len(ok)), replace=False)
        origin = T[:3, 3].astype(np.float32)
        v = moved[pick] - origin
        depth = np.linalg.norm(v, axis=1)
        return np.broadcast_to(origin, v.shape).copy(), v / depth[:, None], depth


def render_l1(tokenizer, x0, rays) -> "torch.Tensor":
    """The mean L1 depth error of standardised clean latents rendered through the frozen
    ``tokenizer``: ``x0`` (B, F, H, W, C') with grad, ``rays`` a list of (b, f, origins, dirs,
    depths) (tensors on x0's device); jittered samples, as the tokenizer trained."""
    import torch

    from pcfbench.methods.bevworld.render import render_rays

    errs = []
    for b, f, o, d, depth in rays:
        volume = tokenizer.decode(tokenizer.denormalise(x0[b, f])[None])[0]
        pred, _, _ = render_rays(tokenizer, volume, o, d, n=tokenizer.cfg.samples_per_ray, jitter=True)
        errs.append((pred - depth).abs().mean())
    return torch.stack(errs).mean()
