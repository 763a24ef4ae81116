"""BEVWorld's LiDAR tokenizer and its rendering (methods/bevworld/tokenizer.py, render.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcfbench.errors import PcfbenchError
from pcfbench.methods.bevworld.config import tokenizer_config
from pcfbench.methods.bevworld.render import expected_depth, ray_weights, render_rays, sample_depths
from pcfbench.methods.bevworld.tokenizer import LatentTokenizer, tokenizer_losses
from pcfbench.methods.copilot4d.data import make_batch


@pytest.fixture
def one_thread():
    """One torch thread for the short training runs: their tensors are small, and on a shared
    CPU more threads only contend (a run took 20x longer)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _scene(rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    """A ground plane at -1.7 m and a ring of walls at 20 m, as a sensor sees them."""
    az = rng.uniform(-np.pi, np.pi, n)
    wall = np.stack([20 * np.cos(az), 20 * np.sin(az), rng.uniform(-1.5, 2.0, n)], 1)
    r = rng.uniform(3, 19, n)
    ground = np.stack([r * np.cos(az), r * np.sin(az), np.full(n, -1.7)], 1)
    return np.concatenate([wall, ground]).astype(np.float32)


def test_shapes_cover_the_roi_and_four_channels():
    for name in ("paper", "tiny"):
        cfg = tokenizer_config(name)
        assert cfg.latent_channels == 4
        assert cfg.x_range == cfg.y_range == (-80.0, 80.0) and cfg.z_range == (-4.5, 4.5)
    assert tokenizer_config("paper").latent_grid == 128 and tokenizer_config("paper").samples_per_ray == 150
    cfg = tokenizer_config("micro")
    m = LatentTokenizer(cfg)
    rng = np.random.default_rng(0)
    b = make_batch(cfg, [_scene(rng), _scene(rng)], cfg.rays_per_step, rng)
    z = m.encode(b.points, b.point_batch, 2)
    assert z.shape == (2, 16, 16, 4)
    vol = m.decode(z)
    assert vol.shape == (2, cfg.vol_dim, cfg.vol_z, 32, 32)
    with pytest.raises(PcfbenchError, match="expected one of paper, tiny, micro"):
        tokenizer_config("huge")


def test_running_statistics_normalise_per_channel():
    m = LatentTokenizer(tokenizer_config("micro"))
    g = torch.Generator().manual_seed(0)
    scale, shift = torch.tensor([1.0, 5.0, 0.1, 2.0]), torch.tensor([3.0, -1.0, 0.0, 10.0])
    a = torch.randn(2, 16, 16, 4, generator=g) * scale + shift
    b = torch.randn(2, 16, 16, 4, generator=g) * scale * 2 + shift
    m._track(a)
    m._track(b)
    both = torch.cat([a, b]).reshape(-1, 4)
    # two equal batches: the statistics are exactly the pooled ones
    torch.testing.assert_close(m.latent_mean, both.mean(0), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(m.latent_var, both.var(0, unbiased=False), rtol=1e-5, atol=1e-5)
    x = m.normalise(both)
    torch.testing.assert_close(x.mean(0), torch.zeros(4), rtol=0, atol=1e-4)
    torch.testing.assert_close(x.std(0, unbiased=False), torch.ones(4), rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(m.denormalise(x), both, rtol=1e-5, atol=1e-4)
    # encoding takes a batch into the statistics in training only
    cfg = m.cfg
    rng = np.random.default_rng(1)
    batch = make_batch(cfg, [_scene(rng)], 8, rng)
    m.eval()
    m.encode(batch.points, batch.point_batch, 1)
    assert int(m.stats_updates) == 2
    m.train()
    m.encode(batch.points, batch.point_batch, 1)
    assert int(m.stats_updates) == 3


def test_after_warm_up_the_statistics_move_by_the_momentum():
    m = LatentTokenizer(tokenizer_config("micro"))
    m.stats_updates.fill_(1000)
    m._track(torch.full((1, 16, 16, 4), 2.0))
    torch.testing.assert_close(m.latent_mean, torch.full((4,), 0.01 * 2.0))
    # variance about the new mean: 0.99 (1 + 0.02^2) + 0.01 (0 + 1.98^2)
    torch.testing.assert_close(m.latent_var, torch.full((4,), 0.99 * (1 + 0.02 ** 2) + 0.01 * 1.98 ** 2))


def test_one_occupied_sample_takes_all_the_weight():
    t = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0]])
    delta = torch.ones(1, 5)
    sigma = torch.tensor([[0.0, 0.0, 1e4, 0.0, 1e4]])  # the first opaque sample hides the second
    w = ray_weights(sigma, delta)
    torch.testing.assert_close(w, torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0]]))
    assert float(expected_depth(w, t, torch.tensor([9.0]))[0]) == pytest.approx(3.0)
    # nothing on the ray: all of it at the far end; half of it: half-way there
    assert float(expected_depth(torch.zeros(1, 5), t, torch.tensor([9.0]))[0]) == pytest.approx(9.0)
    assert float(expected_depth(0.5 * w, t, torch.tensor([9.0]))[0]) == pytest.approx(6.0)
    # two half-transparent samples: 1/2, then 1/2 of the remaining 1/2
    sigma = torch.tensor([[0.0, float(np.log(2.0)), float(np.log(2.0)), 0.0, 0.0]])
    torch.testing.assert_close(ray_weights(sigma, delta), torch.tensor([[0.0, 0.5, 0.25, 0.0, 0.0]]))


def test_weights_match_the_product_formula_on_random_rays():
    g = torch.Generator().manual_seed(3)
    sigma = torch.rand(50, 30, generator=g, dtype=torch.float64) * 0.5
    delta = torch.rand(50, 30, generator=g, dtype=torch.float64)
    alpha = 1 - torch.exp(-sigma * delta)
    ref = torch.zeros_like(alpha)
    for r in range(50):
        trans = 1.0
        for i in range(30):
            ref[r, i] = alpha[r, i] * trans
            trans *= 1 - alpha[r, i]
    torch.testing.assert_close(ray_weights(sigma, delta), ref)


def test_samples_cover_the_in_box_segment():
    cfg = tokenizer_config("micro")
    o = torch.tensor([[0.0, 0.0, 0.0], [70.0, 0.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    t, delta, far = sample_depths(cfg, o, d, 4, jitter=False)
    torch.testing.assert_close(far, torch.tensor([80.0, 150.0]))
    torch.testing.assert_close(t, torch.tensor([[10.0, 30.0, 50.0, 70.0], [18.75, 56.25, 93.75, 131.25]]))
    torch.testing.assert_close(delta, torch.tensor([[20.0] * 4, [37.5] * 4]))


class _Wall(torch.nn.Module):
    """A stand-in model whose density is the first feature x 1000."""

    def __init__(self, cfg) -> None:
        super().__init__()
        self.cfg = cfg

    def density(self, f):
        return f[..., 0] * 1000.0


def test_a_wall_in_the_volume_is_rendered_at_its_distance():
    cfg = tokenizer_config("micro")  # 32 x 32 x 4 cells of 5 m x 5 m x 2.25 m over +-80 m
    vol = torch.zeros(1, 4, 32, 32)
    vol[0, :, 24:, :] = 1.0  # x >= 40 m occupied
    o, d = torch.zeros(3, 3), torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.8, 0.6, 0.0]])
    depth, _, w = render_rays(_Wall(cfg), vol, o, d, n=400, jitter=False)
    # trilinear features rise from cell centre 37.5 m to 42.5 m: density 1000 stops the ray within a sample
    assert 37.5 <= float(depth[0]) <= 38.5
    assert float(w[1].sum()) < 1e-3  # no wall along y: no weight; the ray ends at the box's edge
    assert float(depth[1]) == pytest.approx(80.0, abs=0.1)
    assert 37.5 / 0.8 <= float(depth[2]) <= 38.5 / 0.8


def test_rendering_in_chunks_gives_the_same_depths():
    """A forecast renders RENDER_CHUNK rays at a time (for memory and cache). The production size
    gives the depths of no chunking (and of the 8192 it replaced) to the bit, here as on the
    synthetic town's sweeps; an arbitrary chunk size only changes the matrix kernel's float
    rounding (odd sizes measured up to 2e-5 m)."""
    from pcfbench.methods.bevworld.latent_copy import RENDER_CHUNK

    torch.manual_seed(0)
    cfg = tokenizer_config("micro")
    m = LatentTokenizer(cfg).eval()
    with torch.no_grad():
        vol = m.decode(torch.randn(1, cfg.latent_grid, cfg.latent_grid, cfg.latent_channels))[0]
        d = torch.nn.functional.normalize(torch.randn(20000, 3), dim=1)
        o = torch.randn(20000, 3) * 5
        whole = render_rays(m, vol, o, d, n=24, jitter=False)[0]
        for chunk in (RENDER_CHUNK, 8192):
            assert torch.equal(render_rays(m, vol, o, d, n=24, jitter=False, chunk=chunk)[0], whole), chunk
        for chunk in (1, 7, 999):
            got = render_rays(m, vol, o, d, n=24, jitter=False, chunk=chunk)[0]
            assert torch.allclose(got, whole, rtol=0, atol=1e-4), chunk


def test_a_short_run_overfits_one_batch(one_thread):
    cfg = tokenizer_config("micro")
    torch.manual_seed(0)
    m = LatentTokenizer(cfg)
    rng = np.random.default_rng(0)
    b = make_batch(cfg, [_scene(rng), _scene(rng)], cfg.rays_per_step, rng)
    opt = torch.optim.AdamW(m.parameters(), lr=cfg.lr, betas=cfg.betas)
    losses = []
    for _ in range(60):
        out = tokenizer_losses(m, b)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(float(out["l1"].detach()))
    assert losses[-1] < 0.25 * losses[0], losses[::10]
