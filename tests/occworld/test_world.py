"""OccWorld's spatio-temporal generative transformer (methods/occworld/world.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcfbench.methods.occworld.config import tokenizer_config, world_config
from pcfbench.methods.occworld.world import (PAPER_PARAMETERS, WorldModel, cat_keys, causal_mask, count_parameters,
                                              forecast_codes, motion_features, window_motions, world_losses)


def _micro(seed: int = 0) -> WorldModel:
    torch.manual_seed(seed)
    return WorldModel(world_config("micro", tokenizer_config("micro"))).eval()


def _inputs(model: WorldModel, T: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    cfg = model.cfg
    return (torch.randn(2, T, cfg.code_dim, *cfg.token_grid, generator=g),
            torch.randn(2, T, cfg.pose_dim, generator=g))


def test_paper_parameter_count():
    def conv(k, i, o):
        return k * k * i * o + o

    def lin(i, o):
        return i * o + o

    def mha(c):
        return 4 * c * c + 4 * c

    def ffn(c):
        return lin(c, 4 * c) + lin(4 * c, c)

    def tl(c):  # temporal layer
        return mha(c) + ffn(c) + 4 * c

    def pl(c):  # pose layer
        return 2 * mha(c) + ffn(c) + 6 * c

    def ub(s, i, o):
        return 2 * s + conv(3, i, o) + conv(3, o, o) + (conv(1, i, o) if i != o else 0)

    def mlp(i, o):
        return lin(i, o) + lin(o, o)

    expected = (2 * 10 * 128  # temporal embeddings of scene and pose tokens, 9 positions + 1
                + 6 * tl(128) + 2 * ub(50 * 50, 128, 128) + conv(2, 128, 128) + 2 * pl(128) + mlp(128, 128)
                + 6 * tl(128) + ub(25 * 25, 128, 256) + ub(25 * 25, 256, 256) + conv(2, 256, 256) + 2 * pl(128)
                + mlp(128, 256)
                + ub(256 * 12 * 12, 256, 512) + ub(512 * 12 * 12, 512, 512) + mlp(256, 512)
                + (512 * 256 * 4 + 256) + 6 * tl(512) + ub(512 * 25 * 25, 512, 256) + ub(256 * 25 * 25, 256, 256)
                + lin(512, 256) + 2 * pl(512) + mlp(512, 256)
                + (256 * 128 * 4 + 128) + 6 * tl(256) + ub(256 * 50 * 50, 256, 128) + ub(128 * 50 * 50, 128, 128)
                + lin(256, 128) + 2 * pl(256) + mlp(256, 128)
                + conv(3, 128, 512) + lin(128, 128) + lin(9, 128) + lin(128, 128) + lin(128, 128) + lin(128, 9)
                + 2 * lin(128, 128) + lin(512, 512) + lin(256, 256))  # ego to scene, per scale
    assert expected == PAPER_PARAMETERS == 58_578_141
    model = WorldModel(world_config("paper", tokenizer_config("paper")))
    assert count_parameters(model) == PAPER_PARAMETERS
    assert model.cfg.token_grid == (50, 50) and model.cfg.codebook_size == 512 and model.cfg.channels == (128, 256, 512)


def test_causal_mask():
    assert causal_mask(3).tolist() == [[False, True, True], [False, False, True], [False, False, False]]


@pytest.mark.parametrize("k", [1, 2])
def test_a_later_frame_does_not_change_an_earlier_output(k):
    model = _micro()
    T = model.cfg.positions
    x, p = _inputs(model, T)
    logits, pose = model(x, p)
    x2, p2 = x.clone(), p.clone()
    x2[:, k] += torch.randn_like(x2[:, k])
    p2[:, k] += 1.0
    logits2, pose2 = model(x2, p2)
    assert torch.allclose(logits[:, :k], logits2[:, :k], atol=1e-5) and torch.allclose(pose[:, :k], pose2[:, :k],
                                                                                         atol=1e-5)
    assert not torch.allclose(logits[:, k:], logits2[:, k:], atol=1e-3)
    assert not torch.allclose(pose[:, k:], pose2[:, k:], atol=1e-3)


def test_the_pose_conditions_the_prediction():
    model = _micro()
    x, p = _inputs(model, model.cfg.positions)
    p2 = p.clone()
    p2[:, 0] += 1.0
    assert not torch.allclose(model(x, p)[0][:, 0], model(x, p2)[0][:, 0], atol=1e-4)


def test_motions_of_a_window():
    def pose(x, yaw):
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        T[0, 3] = x
        return T

    poses = torch.from_numpy(np.stack([pose(0, 0), pose(2, np.pi / 2), pose(2, np.pi / 2)])[None])
    m = window_motions(poses)[0]
    assert torch.allclose(m[0], torch.tensor([2.0, 0, 0, 0, 1, 0, -1, 0, 0], dtype=m.dtype), atol=1e-12)
    assert torch.allclose(m[1], motion_features(torch.eye(4, dtype=m.dtype)), atol=1e-12)


def test_losses_and_forecast_shapes():
    model = _micro()
    cfg = model.cfg
    T = cfg.n_past + cfg.n_future
    g = torch.Generator().manual_seed(0)
    codes = torch.randint(0, cfg.codebook_size, (2, T, *cfg.token_grid), generator=g)
    book = torch.randn(cfg.codebook_size, cfg.code_dim, generator=g)

    def embed(c):
        return book[c].movedim(-1, -3)

    poses = torch.eye(4).repeat(2, T, 1, 1)
    poses[..., 0, 3] = torch.arange(T, dtype=torch.float32)
    out = world_losses(model, codes, embed(codes), poses)
    assert torch.isfinite(out["loss"]) and out["loss"].item() == pytest.approx(
        (out["ce"] + cfg.pose_weight * out["pose"]).item(), rel=1e-6)
    fut = forecast_codes(model, embed, codes[:, :cfg.n_past], poses, cfg.n_future)
    assert fut.shape == (2, cfg.n_future, *cfg.token_grid)
    fut2 = forecast_codes(model, embed, codes[:, :cfg.n_past], poses, cfg.n_future, predict_poses=True)
    assert fut2.shape == fut.shape


def test_a_window_s_keys_are_its_frames_keys_side_by_side():
    """What the cached forecast relies on: the keys of frames 0..T-1 are those of 0..j-1 beside
    those of j..T-1 computed at their positions; queries of the last frame alone against them
    give the whole window's last logits and motion."""
    model = _micro()
    T = model.cfg.positions
    x, p = _inputs(model, T)
    with torch.no_grad():
        whole = model.keys(x, p)
        parts = cat_keys(model.keys(x[:, :2], p[:, :2]), model.keys(x[:, 2:], p[:, 2:], 2), 2)
        for (pa, ka), (pb, kb) in zip(whole, parts):
            assert torch.allclose(pa, pb, atol=1e-6) and torch.allclose(ka, kb, atol=1e-6)
        logits, pose = model(x, p)
        last, last_pose = model.queries(x[:, -1:], p[:, -1:], parts, T - 1, causal_mask(T)[-1:])
    assert torch.allclose(last[:, 0], logits[:, -1], atol=1e-5) and torch.allclose(last_pose[:, 0], pose[:, -1],
                                                                                     atol=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_cached_forecast_gives_the_codes_of_the_whole_window_each_step(seed):
    """Three past and four future frames (four steps, the cache growing each): the same codes as
    running the whole window at every step."""
    from dataclasses import replace

    torch.manual_seed(seed)
    cfg = replace(world_config("micro", tokenizer_config("micro")), n_past=3, n_future=4)
    model = WorldModel(cfg).eval()
    g = torch.Generator().manual_seed(seed)
    past = torch.randint(0, cfg.codebook_size, (2, cfg.n_past, *cfg.token_grid), generator=g)
    book = torch.randn(cfg.codebook_size, cfg.code_dim, generator=g)

    def embed(c):
        return book[c].movedim(-1, -3)

    poses = torch.eye(4).repeat(2, cfg.n_past + cfg.n_future, 1, 1)
    poses[..., 0, 3] = torch.rand(2, cfg.n_past + cfg.n_future, generator=g).cumsum(1) * 3
    cached = forecast_codes(model, embed, past, poses, cfg.n_future)
    whole = forecast_codes(model, embed, past, poses, cfg.n_future, cached=False)
    assert torch.equal(cached, whole)
    assert len(set(cached.flatten().tolist())) > 3  # not one code everywhere: the comparison means something
