"""BEVWorld's latent diffusion (methods/bevworld/diffusion.py) and its spatio-temporal
transformer (world.py)."""

from __future__ import annotations

import math

import pytest
import torch

from pcfbench.errors import PcfbenchError
from pcfbench.methods.bevworld.config import tokenizer_config, world_config
from pcfbench.methods.bevworld.diffusion import Schedule, diffusion_loss, sample_future
from pcfbench.methods.bevworld.world import PAPER_PARAMETERS, WorldModel, count_parameters


@pytest.fixture
def one_thread():
    """One torch thread for the short training runs: their tensors are small, and on a shared
    CPU more threads only contend (a run took 20x longer)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_schedule_is_ddpms_linear_one():
    s = Schedule(1000, 1e-4, 0.02)
    ab, ref = [1.0], 1.0
    for i in range(1000):
        ref *= 1.0 - (1e-4 + (0.02 - 1e-4) * i / 999)
        ab.append(ref)
    torch.testing.assert_close(s.alpha_bar, torch.tensor(ab, dtype=torch.float64))
    assert s.ddim_timesteps(5) == [1000, 800, 600, 400, 200, 0]
    assert s.ddim_timesteps(1) == [1000, 0]
    with pytest.raises(PcfbenchError, match="ddim_steps=0: expected 1 to 1000"):
        s.ddim_timesteps(0)


def test_the_forward_marginal_has_its_mean_and_variance():
    s = Schedule(1000, 1e-4, 0.02)
    g = torch.Generator().manual_seed(0)
    x0 = torch.tensor([2.0, -1.0, 0.5], dtype=torch.float64)
    n = 200_000
    for t in (1, 250, 1000):
        eps = torch.randn(n, 3, generator=g, dtype=torch.float64)
        xt = s.q_sample(x0.expand(n, 3), torch.full((n,), t), eps)
        ab = float(s.alpha_bar[t])
        se = math.sqrt((1 - ab) / n)
        torch.testing.assert_close(xt.mean(0), math.sqrt(ab) * x0, rtol=0, atol=5 * se)
        torch.testing.assert_close(xt.var(0), torch.full((3,), 1 - ab, dtype=torch.float64), rtol=0.02, atol=1e-7)


def _perfect_eps(s: Schedule, x0: torch.Tensor, xt: torch.Tensor, t: int) -> torch.Tensor:
    ab = float(s.alpha_bar[t])
    return (xt - math.sqrt(ab) * x0) / math.sqrt(1 - ab)


def test_ddim_with_a_perfect_noise_predictor_recovers_x0_exactly():
    s = Schedule(1000, 1e-4, 0.02)
    g = torch.Generator().manual_seed(1)
    x0 = torch.randn(4, 6, generator=g, dtype=torch.float64)
    for n in (1, 7, 50):
        x = torch.randn(4, 6, generator=g, dtype=torch.float64)
        ts = s.ddim_timesteps(n)
        for t, u in zip(ts[:-1], ts[1:]):
            x = s.ddim_step(x, _perfect_eps(s, x0, x, t), t, u)
        torch.testing.assert_close(x, x0, rtol=0, atol=1e-9)


def test_ddim_carries_noise_to_a_gaussian_data_distribution():
    # data N(mu, sd^2): the exact E[eps | x_t] = sqrt(1 - ab) (x_t - sqrt(ab) mu) / (ab sd^2 + 1 - ab);
    # DDIM is then the probability-flow ODE's discretisation and must land on N(mu, sd^2)
    s = Schedule(1000, 1e-4, 0.02)
    mu, sd = 1.5, 0.3
    noise = torch.randn(20_000, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    noise = (noise - noise.mean()) / noise.std()  # exactly standard: what remains is DDIM's own error
    stds = []
    for n in (50, 1000):  # the ODE's discretisation error shrinks with the steps
        x = noise
        ts = s.ddim_timesteps(n)
        for t, u in zip(ts[:-1], ts[1:]):
            ab = float(s.alpha_bar[t])
            eps = math.sqrt(1 - ab) * (x - math.sqrt(ab) * mu) / (ab * sd ** 2 + 1 - ab)
            x = s.ddim_step(x, eps, t, u)
        assert float(x.mean()) == pytest.approx(mu, abs=0.01)
        stds.append(float(x.std()))
    assert abs(stds[1] - sd) < 0.01 * sd < abs(stds[0] - sd)


class _Oracle(torch.nn.Module):
    """A world model that knows the future: the exact noise of its future frames."""

    def __init__(self, s: Schedule, future: torch.Tensor, n_past: int) -> None:
        super().__init__()
        self.s, self.future, self.n_past, self.calls = s, future, n_past, []

    def forward(self, x, t, poses, frames=None, drop_action=None):
        self.calls.append((t.clone(), drop_action))
        assert (t[:, :self.n_past] == 0).all()  # the past is marked clean
        out = torch.zeros_like(x)
        for b in range(x.shape[0]):
            ab = self.s.alpha_bar[int(t[b, -1])].to(x.dtype)
            out[b, self.n_past:] = (x[b, self.n_past:] - ab.sqrt() * self.future[b]) / (1 - ab).sqrt()
        return out


def test_sampling_denoises_all_future_frames_jointly_from_the_clean_past():
    s = Schedule(100, 1e-4, 0.02)
    g = torch.Generator().manual_seed(3)
    past, future = torch.randn(2, 3, 4, 4, 2, generator=g), torch.randn(2, 2, 4, 4, 2, generator=g)
    oracle = _Oracle(s, future, 3)
    out = sample_future(oracle, s, past, torch.eye(4).expand(2, 5, 4, 4), 2, steps=4, generator=g)
    torch.testing.assert_close(out, future, rtol=0, atol=1e-4)
    assert [int(t[0, -1]) for t, _ in oracle.calls] == [100, 75, 50, 25]
    # the loss of a perfect predictor is 0; the past is fed clean
    losses = diffusion_loss(_Oracle(s, future, 3), s, torch.cat([past, future], 1), torch.eye(4).expand(2, 5, 4, 4),
                            3, generator=g)
    assert float(losses["mse"]) < 1e-8


class _Zero(torch.nn.Module):
    def forward(self, x, t, poses, frames=None, drop_action=None):
        return torch.zeros_like(x)


class _ChangeOracle(torch.nn.Module):
    """Under the ``change`` target: the exact change of every future frame from the last past one."""

    def __init__(self, future: torch.Tensor, n_past: int) -> None:
        super().__init__()
        self.future, self.n_past = future, n_past

    def forward(self, x, t, poses, frames=None, drop_action=None):
        out = torch.zeros_like(x)
        out[:, self.n_past:] = self.future - x[:, self.n_past - 1:self.n_past]
        return out


def test_the_change_target_reads_the_output_as_the_change_from_the_last_past_frame():
    s = Schedule(100, 1e-4, 0.02)
    g = torch.Generator().manual_seed(5)
    past, future = torch.randn(2, 3, 4, 4, 2, generator=g), torch.randn(2, 2, 4, 4, 2, generator=g)
    poses = torch.eye(4).expand(2, 5, 4, 4)
    for steps in (1, 4, 20):
        # an output of zero (every fresh model) forecasts the last past frame: the latent copy, exactly
        out = sample_future(_Zero(), s, past, poses, 2, steps=steps, target="change", generator=g)
        torch.testing.assert_close(out, past[:, -1:].expand_as(out), rtol=0, atol=1e-5)
        out = sample_future(_ChangeOracle(future, 3), s, past, poses, 2, steps=steps, target="change", generator=g)
        torch.testing.assert_close(out, future, rtol=0, atol=1e-5)
    # the same zero output read as noise is no copy
    out = sample_future(_Zero(), s, past, poses, 2, steps=4, generator=g)
    assert (out - past[:, -1:]).abs().amax() > 0.1
    latents = torch.cat([past, future], 1)
    assert float(diffusion_loss(_ChangeOracle(future, 3), s, latents, poses, 3, target="change", generator=g)["mse"]) < 1e-12
    with pytest.raises(PcfbenchError, match="target='x0': expected one of eps, change"):
        diffusion_loss(_Zero(), s, latents, poses, 3, target="x0")
    assert int(WorldModel(_micro())(*_inputs(_micro())).abs().max()) == 0  # so a fresh model copies


def test_the_loss_on_changing_and_unchanging_cells_by_hand():
    # one past frame, one future frame, two cells of one channel: one changes by 1.0 (over CHANGED
    # = 0.5), the other by 0.1; a zero output under the change target scores the copy
    s = Schedule(100, 1e-4, 0.02)
    latents = torch.tensor([[[[[0.0], [2.0]]], [[[1.0], [2.1]]]]])  # (B 1, T 2, H 1, W 2, C 1)
    out = diffusion_loss(_Zero(), s, latents, torch.eye(4).expand(1, 2, 4, 4), 1, target="change",
                         generator=torch.Generator().manual_seed(0))
    assert float(out["loss"]) == pytest.approx((1.0 + 0.01) / 2, rel=1e-5)  # float32: 2.1 - 2.0
    assert float(out["changed"]) == pytest.approx(1.0) and float(out["copy_changed"]) == pytest.approx(1.0)
    assert float(out["static"]) == pytest.approx(0.01, rel=1e-5) and float(out["changed_share"]) == 0.5
    assert float(out["copy_static"]) == pytest.approx(0.01, rel=1e-5)
    # under eps the split is of the noise's error; a batch without a changing cell has no figure for it
    still = latents.clone()
    still[:, 1] = still[:, 0]
    out = diffusion_loss(_Zero(), s, still, torch.eye(4).expand(1, 2, 4, 4), 1, generator=torch.Generator().manual_seed(0))
    assert math.isnan(float(out["changed"])) and float(out["static"]) == pytest.approx(float(out["mse"]))


def test_guidance_mixes_the_prediction_without_the_action():
    s = Schedule(100, 1e-4, 0.02)

    class Fixed(torch.nn.Module):
        def forward(self, x, t, poses, frames=None, drop_action=None):
            return torch.full_like(x, 0.0 if drop_action is not None else 1.0)

    past, noise = torch.zeros(1, 1, 2, 2, 1), torch.zeros(1, 1, 2, 2, 1)
    out = sample_future(Fixed(), s, past, torch.eye(4).expand(1, 2, 4, 4), 1, steps=1, guidance=3.0, noise=noise)
    # eps = 0 + 3 (1 - 0) = 3; one step to t=0: x0 = (0 - sqrt(1 - ab) 3) / sqrt(ab)
    ab = float(s.alpha_bar[100])
    torch.testing.assert_close(out, torch.full_like(out, -math.sqrt(1 - ab) * 3 / math.sqrt(ab)))


def _randomised(cfg) -> WorldModel:
    torch.manual_seed(0)
    m = WorldModel(cfg)
    with torch.no_grad():  # AdaLN-Zero starts as the identity; move every weight off zero
        for p in m.parameters():
            p.add_(torch.randn_like(p) * 0.1)
    return m.eval()


def _micro():
    return world_config("micro", tokenizer_config("micro"))


def _inputs(cfg, seed=0):
    g = torch.Generator().manual_seed(seed)
    T = cfg.frames
    x = torch.randn(1, T, cfg.latent_grid, cfg.latent_grid, cfg.latent_channels, generator=g)
    t = torch.tensor([[0] * cfg.n_past + [30] * cfg.n_future])
    poses = torch.eye(4).repeat(1, T, 1, 1)
    poses[0, :, 0, 3] = torch.arange(T, dtype=torch.float32) - cfg.n_past + 1
    return x, t, poses


def test_a_fresh_model_predicts_zero_noise():
    cfg = _micro()
    x, t, poses = _inputs(cfg)
    assert WorldModel(cfg)(x, t, poses).abs().max() == 0


def test_causal_masking_keeps_later_frames_out_of_earlier_ones():
    cfg = _micro()
    m = _randomised(cfg)
    x, t, poses = _inputs(cfg)
    with torch.no_grad():
        base = m(x, t, poses)
        for k in range(1, cfg.frames):
            x2, p2 = x.clone(), poses.clone()
            x2[:, k] += 1.0
            p2[:, k, 1, 3] += 2.0
            out = m(x2, t, p2)
            torch.testing.assert_close(out[:, :k], base[:, :k], rtol=0, atol=1e-5)
            assert (out[:, k:] - base[:, k:]).abs().amax() > 1e-3


def test_adaln_conditioning_on_action_and_timestep_changes_the_output():
    cfg = _micro()
    m = _randomised(cfg)
    x, t, poses = _inputs(cfg)
    with torch.no_grad():
        base = m(x, t, poses)
        p2 = poses.clone()
        p2[:, -1, 0, 3] += 3.0  # the last frame's pose
        moved = m(x, t, p2)
        assert (moved[:, -1] - base[:, -1]).abs().amax() > 1e-3
        t2 = t.clone()
        t2[:, -1] = 90
        later = m(x, t2, poses)
        assert (later[:, -1] - base[:, -1]).abs().amax() > 1e-3
        dropped = m(x, t, poses, drop_action=torch.tensor([True]))
        assert (dropped - base).abs().amax() > 1e-3
        # the action reaches the tokens only through AdaLN: with its layers zero, poses do nothing
        for blk in m.blocks:
            torch.nn.init.zeros_(blk.ada.weight)
            torch.nn.init.zeros_(blk.ada.bias)
        torch.nn.init.zeros_(m.final_ada.weight)
        torch.nn.init.zeros_(m.final_ada.bias)
        torch.testing.assert_close(m(x, t, p2), m(x, t, poses))


def test_paper_parameter_count_is_the_derived_one():
    d, h, p, C, frames, f = 768, 3072, 2, 4, 10, 256
    block = (3 * d * d + 3 * d) + (d * d + d) + (2 * d * h + h + d) + (2 * d * 6 * d + 6 * d)
    embeddings = (p * p * C * d + d) + frames * d + (f * d + d + d * d + d) + (9 * d + d + d * d + d) + d
    output = (2 * d * 2 * d + 2 * d) + (d * p * p * C + p * p * C)
    assert 12 * block + embeddings + output == PAPER_PARAMETERS
    cfg = world_config("paper", tokenizer_config("paper"))
    assert (cfg.dim, cfg.depth, cfg.patch, cfg.latent_grid, cfg.frames) == (768, 6, 2, 128, 10)
    assert count_parameters(WorldModel(cfg)) == PAPER_PARAMETERS


@pytest.mark.parametrize("target", ["eps", "change"])
def test_a_short_run_overfits_one_window(one_thread, target):
    cfg = _micro()
    torch.manual_seed(0)
    m = WorldModel(cfg)
    s = Schedule.of(cfg)
    x, _, poses = _inputs(cfg, seed=4)
    opt = torch.optim.AdamW(m.parameters(), lr=cfg.lr)
    g = torch.Generator().manual_seed(0)
    losses = []
    for _ in range(300):
        out = diffusion_loss(m, s, x.expand(4, -1, -1, -1, -1), poses.expand(4, -1, -1, -1), cfg.n_past,
                             target=target, generator=g)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(float(out["mse"].detach()))
    first, last = sum(losses[:20]) / 20, sum(losses[-20:]) / 20
    assert last < 0.6 * first, (first, last)  # 0.93 -> 0.44 when written
