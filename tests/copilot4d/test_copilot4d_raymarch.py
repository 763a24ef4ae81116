"""The numba ray marcher of Copilot4D inference (methods/copilot4d/raymarch.py): a hand-computed
ray, the torch path that training uses as the reference, and early stopping that changes no
depth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcfbench.methods.copilot4d.evaluate import decode, render_codes, tokenize_sweep
from pcfbench.methods.copilot4d.model import Tokenizer
from pcfbench.methods.copilot4d.raymarch import march
from pcfbench.methods.copilot4d.render import logistic_noise_mask
from test_copilot4d import MICRO


@pytest.fixture(scope="module")
def micro_model():
    from pcfbench.testing import toy_world_sweeps

    pts, _, _ = toy_world_sweeps(1, beams=16, azimuths=360)
    torch.manual_seed(0)
    model = Tokenizer(MICRO).eval()
    with torch.no_grad():
        model.decoder.coarse_linear.bias.fill_(-1.0)  # a coarse mask with holes: skipping matters
    return model, tokenize_sweep(model, pts[0])


def _rays(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 2] *= 0.2
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def _constant_alpha_mlp(alpha: float, F: int, H: int = 4) -> tuple:
    """An occupancy MLP whose output is ``alpha`` everywhere (weights zero, the last bias its logit)."""
    logit = np.log(alpha / (1 - alpha))
    return (np.zeros((H, F), np.float32), np.zeros(H, np.float32), np.zeros((1, H), np.float32),
            np.array([logit], np.float32))


def test_hand_computed_ray_constant_alpha():
    """alpha = 0.5 everywhere, no mask: n samples at t0 + (i + 0.5) / n (t1 - t0); the weights
    0.5 (0.5 + 1e-7)^i; the median is the first sample (its weight alone is half of the total),
    the expected depth sum w_i h_i plus the transmittance left at the box's exit."""
    cfg = MICRO
    nfg = np.zeros((8, 8, 4, 2), np.float32)
    origin = np.array([1.0, -2.0, 0.5])
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.6, 0.8, 0.0]], np.float32)
    mlp = _constant_alpha_mlp(0.5, 2)
    n = 16
    med = march(cfg, nfg, None, origin, dirs, mlp, samples=n, readout="median")
    exp = march(cfg, nfg, None, origin, dirs, mlp, samples=n, readout="expected")
    lo, hi = np.array([cfg.x_range[0], cfg.y_range[0]]), np.array([cfg.x_range[1], cfg.y_range[1]])
    for r, d in enumerate(dirs.astype(np.float64)):
        # the ray leaves the box through a side wall (|z| stays inside)
        t1 = min(((hi if d[k] > 0 else lo)[k] - origin[k]) / d[k] for k in range(2) if d[k] != 0)
        h = (np.arange(n) + 0.5) / n * t1
        w = 0.5 * (0.5 + 1e-7) ** np.arange(n)
        assert med[r] == pytest.approx(h[0], rel=1e-6)
        assert exp[r] == pytest.approx((w * h).sum() + (1 - w.sum()) * t1, rel=1e-5)


def test_hand_computed_ray_through_one_occupied_coarse_cell():
    """A mask with one occupied coarse voxel on the +x axis: every sample lies in the part of
    the ray inside it, spread evenly over the occupied candidates' segments."""
    cfg = MICRO  # x in [-25.6, 25.6], candidates every 0.5 m
    mask = np.zeros((8, 8, 16), np.bool_)  # 6.4 m coarse cells in x and y
    mask[5, 4, 8] = True  # x in [6.4, 12.8), y in [0, 6.4), z cell 8 of 16 (around 0)
    origin = np.array([0.0, 0.1, 0.05])
    n = 8
    med = march(cfg, np.zeros((8, 8, 4, 2), np.float32), mask, origin, np.array([[1.0, 0.0, 0.0]], np.float32),
                _constant_alpha_mlp(0.5, 2), samples=n, readout="median")
    hc = (np.arange(200) + 0.5) * cfg.candidate_step
    occupied = hc[(hc >= 6.4) & (hc < 12.8)]  # candidates 6.75 .. 12.75: 13 segments of 0.5 m
    assert len(occupied) == 13
    # the first sample: target 0.5 / 8 of 6.5 m = 0.40625 m into the first occupied segment
    assert med[0] == pytest.approx(occupied[0] - 0.25 + 0.40625, abs=1e-5)


@pytest.mark.parametrize("readout", ["median", "expected"])
@pytest.mark.parametrize("skipping", [True, False])
def test_march_matches_the_torch_path(micro_model, readout, skipping):
    """render_codes through the numba marcher and through the differentiable torch functions
    that training uses give the same depths up to float rounding (sums are sequential in the
    marcher, pairwise in torch), from inside and from outside the tokenized sweep's origin."""
    model, codes = micro_model
    for seed, origin in enumerate(([0.0, 0.0, 0.0], [3.0, -4.0, 0.3], [30.0, 5.0, 0.0])):
        dirs = _rays(400, seed)
        kw = dict(origin=np.array(origin), noise=False, threshold=0.3, readout=readout, skipping=skipping)
        fast = render_codes(model, codes, dirs, **kw)
        ref = render_codes(model, codes, dirs, torch_path=True, **kw)
        assert np.all(np.isfinite(fast)) and np.ptp(fast) > 1.0
        if readout == "median":  # a sample depth: equal, or one sample over where a cdf ties the half
            assert np.mean(fast == ref) >= 0.99
        else:
            np.testing.assert_allclose(fast, ref, rtol=1e-5, atol=1e-3)


def _marcher_inputs(micro_model):
    """(NFG channels last, the coarse mask at threshold 0.3 without noise, the MLP's four
    arrays as a list of copies) of the micro model's decoded tokens."""
    model, codes = micro_model
    with torch.no_grad():
        nfg, coarse = decode(model, codes)
    mask = logistic_noise_mask(MICRO, coarse.float(), noise=False, threshold=0.3)[0].numpy()
    dec = model.decoder
    mlp = [t.detach().numpy().copy() for t in (dec.mlp1.weight, dec.mlp1.bias, dec.mlp2.weight, dec.mlp2.bias)]
    return nfg[0].permute(2, 3, 1, 0).contiguous().numpy(), mask, mlp


def test_early_stop_changes_no_depth(micro_model):
    """The median readout stops a ray once the weight still to come cannot move its answer:
    marching every ray to its end gives the very same depths, and rays did stop early."""
    nfg_cl, mask, mlp = _marcher_inputs(micro_model)
    mlp[3] = mlp[3] + 6.0  # opaque surfaces, so that transmittance runs out before the last sample
    dirs = _rays(2000, 7)
    for mk in (mask, None):
        stats = {}
        early = march(MICRO, nfg_cl, mk, np.zeros(3), dirs, mlp, samples=32, readout="median", stats=stats)
        full = march(MICRO, nfg_cl, mk, np.zeros(3), dirs, mlp, samples=32, readout="median", early_stop=False)
        assert stats["stopped"] > 100
        np.testing.assert_array_equal(early, full)


def test_threads_change_no_depth(micro_model, monkeypatch):
    """Marched in pieces over 1, 2 or 3 threads, every ray's depth is the same bit for bit (and
    so is the early-stop count): a ray's answer does not depend on the piece it is in."""
    import pcfbench.methods.copilot4d.raymarch as rm
    from pcfbench.execution import ExecutionContext

    nfg_cl, mask, mlp = _marcher_inputs(micro_model)
    dirs = _rays(1000, 11)
    origin = np.array([0.7, -0.4, 0.2])
    whole_stats = {}
    whole = march(MICRO, nfg_cl, mask, origin, dirs, mlp, samples=32, readout="median", stats=whole_stats,
                  execution=ExecutionContext(1))
    monkeypatch.setattr(rm, "CHUNK", 97)  # 11 pieces, the last one short
    for threads in (1, 2, 3):
        stats = {}
        got = march(MICRO, nfg_cl, mask, origin, dirs, mlp, samples=32, readout="median", stats=stats,
                    execution=ExecutionContext(threads))
        np.testing.assert_array_equal(got, whole)
        assert stats == whole_stats
    assert march(MICRO, nfg_cl, mask, origin, dirs[:0], mlp, samples=32, readout="median").shape == (0,)


def test_decode_lays_the_grid_out_for_the_march_without_changing_it(micro_model):
    """On the CPU ``decode`` gives the NFG with its memory channels last, the layout the march
    reads (so rendering copies no grid): the same shape and values as the decoder's default."""
    model, codes = micro_model
    with torch.no_grad():
        ref, ref_coarse = model.decode_codes(codes[None])
        nfg, coarse = decode(model, codes)
    assert nfg.shape == ref.shape and torch.equal(nfg, ref) and torch.equal(coarse, ref_coarse)
    assert ref[0].permute(2, 3, 1, 0).is_contiguous() is False
    assert nfg[0].permute(2, 3, 1, 0).is_contiguous()
