"""The numba ray marcher of BEVWorld inference on the CPU (methods/bevworld/raymarch.py): a
hand-computed ray, the torch path that training uses as the reference, the early stop's bound,
and depths that do not depend on the thread count."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcfbench.execution import ExecutionContext
from pcfbench.methods.bevworld.config import tokenizer_config
from pcfbench.methods.bevworld.latent_copy import render_volume
from pcfbench.methods.bevworld.raymarch import STOP, march
from pcfbench.methods.bevworld.render import render_rays
from pcfbench.methods.bevworld.tokenizer import LatentTokenizer
from pcfbench.methods.copilot4d.render import box_interval

CFG = tokenizer_config("micro")  # 32 x 32 x 4 cells over x, y in [-80, 80], z in [-4.5, 4.5]
BOX = ((CFG.x_range[0], CFG.y_range[0], CFG.z_range[0]), (CFG.x_range[1], CFG.y_range[1], CFG.z_range[1]))


def _constant_density_mlp(sigma: float, F: int, H: int = 3) -> tuple:
    """A density MLP whose output is ``sigma`` everywhere: weights zero, the last bias
    softplus^-1(sigma)."""
    return (np.zeros((H, F), np.float32), np.zeros(H, np.float32), np.zeros((1, H), np.float32),
            np.array([np.log(np.expm1(sigma))], np.float32))


def _rays(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] *= 0.2
    return rng.normal(size=3).astype(np.float32) * 5, (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def _segments(origin, dirs):
    near, far = box_interval(CFG, torch.from_numpy(origin).expand(len(dirs), 3), torch.from_numpy(dirs))
    return near.numpy(), far.numpy()


def test_hand_computed_ray_constant_density():
    """sigma = 0.02 / m everywhere: n samples at the bins' centres of [0, t_far], delta = t_far /
    n, weights (1 - e^{-sigma delta}) e^{-i sigma delta}, the depth sum w_i t_i plus the weight
    left at t_far."""
    vol = np.zeros((8, 8, 4, 2), np.float32)
    origin = np.array([1.0, -2.0, 0.5], np.float32)
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.6, 0.8, 0.0]], np.float32)
    near, far = _segments(origin, dirs)
    n, sigma = 16, 0.02
    got = march(vol, origin, dirs, near, far, BOX, _constant_density_mlp(sigma, 2), samples=n, stop=0)
    for r, d in enumerate(dirs.astype(np.float64)):
        t1 = min(((80.0 if d[k] > 0 else -80.0) - origin[k]) / d[k] for k in range(2) if d[k] != 0)
        assert near[r] == 0 and far[r] == pytest.approx(t1, rel=1e-6)
        t = (np.arange(n) + 0.5) / n * t1
        sd = sigma * t1 / n
        w = (1 - np.exp(-sd)) * np.exp(-sd * np.arange(n))
        assert got[r] == pytest.approx((w * t).sum() + (1 - w.sum()) * t1, rel=1e-5)


def test_a_dense_wall_stops_the_ray_and_the_stop_moves_no_depth_beyond_its_bound():
    """A volume whose first feature is 1 for x >= 40 m, density 50 x that feature: the ray along
    +x ends at the wall, and stops there (``stats``); the depth moves by less than
    stop x segment against marching every sample."""
    vol = np.zeros((32, 32, 4, 2), np.float32)
    vol[24:, :, :, 0] = 1.0
    mlp = (np.array([[1.0, 0.0]], np.float32), np.zeros(1, np.float32), np.array([[50.0]], np.float32),
           np.array([-30.0], np.float32))
    origin = np.zeros(3, np.float32)
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], np.float32)
    near, far = _segments(origin, dirs)
    stats: dict = {}
    full = march(vol, origin, dirs, near, far, BOX, mlp, samples=400, stop=0)
    stopped = march(vol, origin, dirs, near, far, BOX, mlp, samples=400, stats=stats)
    assert 37.5 <= full[0] <= 42.5 and full[1] == pytest.approx(80.0, abs=0.01)  # no wall along y
    assert stats["stopped"] == 1  # the wall's ray, not the empty one
    assert np.all(np.abs(stopped - full) <= STOP * (far - near) + 1e-5)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_marcher_agrees_with_the_torch_path_training_uses(seed):
    """A micro tokenizer's decoded volume: every depth within float rounding of ``render_rays``
    (no jitter), marching every sample and with the default stop; ``render_volume`` (what a
    forecast calls) gives the marcher's depths."""
    torch.manual_seed(seed)
    m = LatentTokenizer(CFG).eval()
    with torch.no_grad():
        m.decoder.mlp2.bias.fill_(-1.0)  # densities from near 0 to several per metre: stops and pass-throughs
        vol = m.decode(torch.randn(1, CFG.latent_grid, CFG.latent_grid, CFG.latent_channels) * 3)[0]
        origin, dirs = _rays(3000, seed)
        o = torch.from_numpy(origin).expand(len(dirs), 3)
        ref = render_rays(m, vol, o, torch.from_numpy(dirs), n=CFG.samples_per_ray, jitter=False)[0].numpy()
        near, far = _segments(origin, dirs)
        mlp = tuple(p.numpy() for p in (m.decoder.mlp1.weight, m.decoder.mlp1.bias, m.decoder.mlp2.weight,
                                        m.decoder.mlp2.bias))
        vol_cl = vol.permute(2, 3, 1, 0).numpy()
        stats: dict = {}
        every = march(vol_cl, origin, dirs, near, far, BOX, mlp, samples=CFG.samples_per_ray, stop=0)
        stopped = march(vol_cl, origin, dirs, near, far, BOX, mlp, samples=CFG.samples_per_ray, stats=stats)
        assert np.abs(every - ref).max() < 1e-4
        assert np.abs(stopped - ref).max() < 1e-4
        assert 0 < stats["stopped"] < len(dirs)  # the stop is exercised, not every ray
        assert np.array_equal(render_volume(m, vol, torch.from_numpy(origin), torch.from_numpy(dirs)), stopped)
        with pytest.raises(ValueError, match="one origin"):  # per-ray origins: refused, not read as the first
            render_volume(m, vol, o, torch.from_numpy(dirs))


def test_depths_do_not_depend_on_the_thread_count(monkeypatch):
    """Rays are cut into pieces marched by the context's threads: 1 and 2 threads, and pieces of
    any size, give the same depths to the bit."""
    import pcfbench.methods.bevworld.raymarch as rm

    rng = np.random.default_rng(3)
    vol = rng.random((32, 32, 4, 4), dtype=np.float32)
    mlp = (rng.normal(size=(5, 4)).astype(np.float32), rng.normal(size=5).astype(np.float32),
           rng.normal(size=(1, 5)).astype(np.float32), np.array([-2.0], np.float32))
    origin, dirs = _rays(5000, 4)
    near, far = _segments(origin, dirs)
    one = march(vol, origin, dirs, near, far, BOX, mlp, samples=24, execution=ExecutionContext(1))
    monkeypatch.setattr(rm, "CHUNK", 777)
    two = march(vol, origin, dirs, near, far, BOX, mlp, samples=24, execution=ExecutionContext(2))
    assert np.array_equal(one, two)


def test_a_channels_last_volume_is_the_same_volume():
    """What a forecast on the CPU decodes: the same (F, Z, X, Y) values, laid out (X, Y, Z, F)
    in memory, so that the marcher reads it without a copy."""
    torch.manual_seed(2)
    m = LatentTokenizer(CFG).eval()
    z = torch.randn(1, CFG.latent_grid, CFG.latent_grid, CFG.latent_channels)
    with torch.no_grad():
        plain, last = m.decode(z)[0], m.decode(z, channels_last=True)[0]
    assert last.shape == plain.shape and torch.equal(last, plain)
    assert last.permute(2, 3, 1, 0).is_contiguous()
