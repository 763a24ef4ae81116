"""Latent diffusion for BEVWorld (section 3.2): DDPM's forward process on the future frames'
standardised latents, the clean past as condition, and DDIM sampling (eta 0) of all future
frames jointly, with optional classifier-free guidance on the action.

What the network's output means (``target``):

- ``eps`` (the paper's, equation 7): the noise; MSE against the drawn noise;
- ``change``: the future frame's change from the last past frame, x0_hat = z_last + output;
  MSE between x0_hat and the future latent. The noise it implies is
  eps_hat = (x_t - sqrt(ab_t) x0_hat) / sqrt(1 - ab_t), so DDIM runs unchanged. Not the paper's:
  a network whose output is zero (every fresh model: AdaLN-Zero) forecasts the last past latent
  exactly, the latent copy, and training learns only what moves.

Timesteps run 1..T with alpha_bar[t] = prod_{s<=t} (1 - beta_s); t = 0 means clean
(alpha_bar[0] = 1), which is how the past frames are marked for the network.
"""

from __future__ import annotations

import torch

from pcfbench.errors import PcfbenchError

#: what the network predicts (module docstring)
TARGETS = ("eps", "change")
#: a latent cell "changes" when its change from the last past frame, over its channels (L2, in
#: standardised units), exceeds this: the training log reports the loss on such cells apart
CHANGED = 0.5


def check_target(target: str) -> None:
    if target not in TARGETS:
        raise PcfbenchError(f"target={target!r}: expected one of {', '.join(TARGETS)}")


class Schedule:
    """DDPM's linear beta schedule; ``alpha_bar`` (T + 1,) float64 with alpha_bar[0] = 1."""

    def __init__(self, steps: int, beta_start: float, beta_end: float) -> None:
        self.steps = steps
        betas = torch.linspace(beta_start, beta_end, steps, dtype=torch.float64)
        self.alpha_bar = torch.cat([torch.ones(1, dtype=torch.float64), torch.cumprod(1.0 - betas, 0)])

    @classmethod
    def of(cls, cfg) -> "Schedule":
        return cls(cfg.diffusion_steps, cfg.beta_start, cfg.beta_end)

    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
        """x_t = sqrt(alpha_bar_t) x0 + sqrt(1 - alpha_bar_t) eps; ``t`` broadcasts from the left
        (one per leading element of x0)."""
        ab = self.alpha_bar.to(x0.device)[t].to(x0.dtype).view(*t.shape, *([1] * (x0.dim() - t.dim())))
        return ab.sqrt() * x0 + (1.0 - ab).sqrt() * eps

    def ddim_timesteps(self, n: int) -> list[int]:
        """``n`` DDIM steps: the descending timesteps T = t_0 > ... > t_n = 0, evenly spaced."""
        if not 1 <= n <= self.steps:
            raise PcfbenchError(f"ddim_steps={n}: expected 1 to {self.steps} (the diffusion's steps)")
        return [round(self.steps * (n - k) / n) for k in range(n + 1)]

    def ddim_step(self, x_t: torch.Tensor, eps: torch.Tensor, t: int, s: int) -> torch.Tensor:
        """One deterministic DDIM step (eta 0) from timestep t to s < t given the predicted noise:
        x0_hat = (x_t - sqrt(1 - ab_t) eps) / sqrt(ab_t), x_s = sqrt(ab_s) x0_hat + sqrt(1 - ab_s) eps."""
        return self.ddim_to(*self.predicted(eps, x_t, t, None, "eps"), s)

    def ddim_to(self, x0: torch.Tensor, eps: torch.Tensor, s: int) -> torch.Tensor:
        """DDIM's (eta 0) x_s = sqrt(ab_s) x0_hat + sqrt(1 - ab_s) eps_hat."""
        ab_s = float(self.alpha_bar[s])
        return ab_s ** 0.5 * x0 + (1.0 - ab_s) ** 0.5 * eps

    def predicted(self, out: torch.Tensor, x_t: torch.Tensor, t: int, last: torch.Tensor | None,
                  target: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(x0_hat, eps_hat) at timestep t >= 1 from the network's ``out`` on ``x_t``; ``last``:
        the last past frame (broadcast over the future frames)."""
        ab_t = float(self.alpha_bar[t])
        if target == "eps":
            return (x_t - (1.0 - ab_t) ** 0.5 * out) / ab_t ** 0.5, out
        check_target(target)
        x0 = last + out
        return x0, (x_t - ab_t ** 0.5 * x0) / (1.0 - ab_t) ** 0.5


def diffusion_loss(model, schedule: Schedule, latents: torch.Tensor, poses: torch.Tensor, n_past: int, *,
                   frames: torch.Tensor | None = None, cond_dropout: float = 0.0, target: str = "eps",
                   generator: torch.Generator | None = None) -> dict:
    """The loss on windows of standardised latents (B, T, H, W, C') with poses (B, T, 4, 4) in the
    t=0 frame: one timestep per window for all its future frames, the past clean (t = 0). With
    ``target`` eps, equation 7 (MSE between the future frames' noise and its prediction); with
    ``change``, MSE between the future latents and the last past one plus the prediction. With
    ``cond_dropout`` each window loses its action with that probability (classifier-free
    guidance's training).

    Besides ``loss``: ``mse`` (the same), ``changed`` and ``static`` (the loss over the cells that
    change by more than :data:`CHANGED` from the last past frame, and over the rest; nan when a
    batch has none), ``copy_changed`` and ``copy_static`` (the mean squared change on each: what the
    latent copy scores there, comparable with ``changed`` and ``static`` under the ``change``
    target) and ``changed_share``; with ``change``, ``x0``: the predicted future latents (B, F, H,
    W, C'), differentiable."""
    check_target(target)
    B, T = latents.shape[:2]
    dev = latents.device
    gdev = generator.device if generator is not None else dev
    tt = torch.randint(1, schedule.steps + 1, (B,), generator=generator, device=gdev).to(dev)
    eps = torch.randn(latents[:, n_past:].shape, generator=generator, device=gdev).to(dev, latents.dtype)
    noisy = schedule.q_sample(latents[:, n_past:], tt, eps)
    x = torch.cat([latents[:, :n_past], noisy], dim=1)
    t_frames = torch.cat([torch.zeros(B, n_past, dtype=torch.long, device=dev), tt[:, None].expand(B, T - n_past)],
                         dim=1)
    drop = None
    if cond_dropout > 0:
        drop = (torch.rand(B, generator=generator, device=gdev) < cond_dropout).to(dev)
    pred = model(x, t_frames, poses, frames=frames, drop_action=drop)[:, n_past:].float()
    future, last = latents[:, n_past:].float(), latents[:, n_past - 1:n_past].float()
    err = (pred - eps.float()) ** 2 if target == "eps" else (last + pred - future) ** 2
    mse = err.mean()
    change2 = ((future - last) ** 2).sum(-1)
    moving = change2 > CHANGED ** 2
    with torch.no_grad():  # masked means: 0 / 0 is nan for a batch without such cells, and no branch syncs
        cell_err, copy_err, m = err.mean(-1), change2 / latents.shape[-1], moving.float()
        n, n_static = m.sum(), (1 - m).sum()
        out = {"changed": (cell_err * m).sum() / n, "static": (cell_err * (1 - m)).sum() / n_static,
               "copy_changed": (copy_err * m).sum() / n, "copy_static": (copy_err * (1 - m)).sum() / n_static,
               "changed_share": m.mean()}
    if target == "change":
        out["x0"] = last + pred  # the predicted clean future latents, with their graph (the render stage)
    return {"loss": mse, "mse": mse, **out}


@torch.no_grad()
def sample_future(model, schedule: Schedule, past: torch.Tensor, poses: torch.Tensor, n_future: int, *,
                  steps: int, guidance: float = 1.0, frames: torch.Tensor | None = None, target: str = "eps",
                  generator: torch.Generator | None = None, noise: torch.Tensor | None = None) -> torch.Tensor:
    """Standardised future latents (B, n_future, H, W, C') from the clean past (B, P, H, W, C')
    and every frame's pose (B, P + n_future, 4, 4): all future frames start from pure noise
    (``noise``, or drawn from ``generator``) and are denoised jointly by ``steps`` DDIM steps, the
    network's output read as ``target``. ``guidance`` != 1: out = out(no action) + guidance
    (out(action) - out(no action)) (the same mix of the noise: it is affine in the output)."""
    check_target(target)
    B, P = past.shape[:2]
    shape = (B, n_future, *past.shape[2:])
    if noise is None:
        gdev = generator.device if generator is not None else past.device
        noise = torch.randn(shape, generator=generator, device=gdev).to(past.device, past.dtype)
    x = noise
    ts = schedule.ddim_timesteps(steps)
    for t, s in zip(ts[:-1], ts[1:]):
        t_frames = torch.cat([torch.zeros(B, P, dtype=torch.long), torch.full((B, n_future), t)], 1).to(past.device)
        inp = torch.cat([past, x], dim=1)
        out = model(inp, t_frames, poses, frames=frames)[:, P:]
        if guidance != 1.0:
            drop = torch.ones(B, dtype=torch.bool, device=past.device)
            free = model(inp, t_frames, poses, frames=frames, drop_action=drop)[:, P:]
            out = free + guidance * (out - free)
        x = schedule.ddim_to(*schedule.predicted(out, x, t, past[:, -1:], target), s)
    return x
