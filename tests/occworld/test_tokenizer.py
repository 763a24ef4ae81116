"""OccWorld's scene tokenizer (methods/occworld/tokenizer.py, config.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld.config import tokenizer_config
from pcfbench.methods.occworld.occupancy import FREE, OCCUPIED, UNKNOWN
from pcfbench.methods.occworld.tokenizer import (PAPER_PARAMETERS, SceneTokenizer, count_parameters, lovasz_softmax,
                                                  occupancy_probability, tokenizer_losses)


def _conv(k, i, o):
    return k * k * i * o + o


def _rb(i, o):
    return 2 * i + _conv(3, i, o) + 2 * o + _conv(3, o, o) + (_conv(1, i, o) if i != o else 0)


def _at(c):
    return 2 * c + 4 * _conv(1, c, c)


def test_paper_parameter_count_is_the_public_configurations():
    # the public configuration, layer by layer (the derivation is in tokenizer.py's docstring)
    expected = (3 * 8  # class embedding (3 classes, 8 channels)
                + _conv(3, 128, 64) + 2 * _rb(64, 64) + _conv(3, 64, 64) + _rb(64, 128) + _rb(128, 128)
                + _conv(3, 128, 128) + _rb(128, 256) + _rb(256, 256) + 2 * _at(256) + 2 * _rb(256, 256) + _at(256)
                + 2 * 256 + _conv(3, 256, 128)  # encoder
                + 2 * _conv(1, 128, 128) + 512 * 128  # quantizer
                + _conv(3, 128, 256) + 2 * _rb(256, 256) + _at(256) + 2 * _rb(256, 256) + 2 * _at(256)
                + _conv(3, 256, 256) + _rb(256, 128) + _rb(128, 128) + _conv(3, 128, 128) + _rb(128, 64)
                + _rb(64, 64) + 2 * 64 + _conv(3, 64, 128))  # decoder
    assert expected == PAPER_PARAMETERS == 14_168_152
    assert count_parameters(SceneTokenizer(tokenizer_config("paper"))) == PAPER_PARAMETERS


def test_paper_shapes_and_token_resolution_option():
    cfg = tokenizer_config("paper")
    assert cfg.dims == (200, 200, 16) and cfg.token_grid == (50, 50) and cfg.codebook_size == 512
    assert np.allclose(np.subtract(cfg.box_hi, cfg.box_lo) / np.array(cfg.dims), (0.7, 0.7, 0.5625))
    assert tokenizer_config("paper", tokens=100).token_grid == (100, 100)
    assert tokenizer_config("paper", tokens=25).ch_mult == (1, 2, 4, 4)
    with pytest.raises(PcfbenchError, match="power of 2"):
        tokenizer_config("paper", tokens=40)
    with pytest.raises(PcfbenchError, match="config"):
        tokenizer_config("huge")
    micro = tokenizer_config("micro", tokens=8)
    model = SceneTokenizer(micro)
    labels = torch.randint(0, 3, (2, *micro.dims))
    logits, codes, _ = model(labels)
    assert codes.shape == (2, 8, 8) and logits.shape == (2, *micro.dims, 3)
    assert torch.equal(model.tokenize(labels), codes)
    assert torch.allclose(model.decode_codes(codes), logits, atol=1e-5)


def _lovasz_reference(probs: np.ndarray, labels: np.ndarray, ignore: int) -> float:
    """The Lovasz extension of the Jaccard loss from its definition, with sets: for each class
    present, the errors sorted down, each weighted by the growth of the Jaccard loss of the
    set of voxels taken so far."""
    keep = labels != ignore
    probs, labels = probs[keep], labels[keep]
    out = []
    for c in range(probs.shape[1]):
        g = {i for i in range(len(labels)) if labels[i] == c}
        if not g:
            continue
        err = [abs(float(labels[i] == c) - probs[i, c]) for i in range(len(labels))]
        order = sorted(range(len(err)), key=lambda i: -err[i])

        def jaccard_loss(s: set) -> float:
            return 1.0 - len(g - s) / len(g | s)

        taken, prev, total = set(), 0.0, 0.0
        for i in order:
            taken.add(i)
            cur = jaccard_loss(taken)
            total += err[i] * (cur - prev)
            prev = cur
        out.append(total)
    return float(np.mean(out))


def test_lovasz_softmax_by_hand():
    # labels free, occupied, occupied, unknown (ignored); p(occupied) 0.2, 0.6, 0.9.
    # occupied: errors 0.2, 0.4, 0.1 -> 0.4 * 1/2 + 0.2 * (2/3 - 1/2) + 0.1 * (1 - 2/3) = 4/15
    # free:     errors 0.2, 0.4, 0.1 -> 0.4 * 1/2 + 0.2 * (1 - 1/2) + 0.1 * 0 = 3/10;  mean 17/60
    p_occ = torch.tensor([0.2, 0.6, 0.9, 0.5], dtype=torch.float64)
    probs = torch.stack([1 - p_occ, p_occ, torch.zeros_like(p_occ)], dim=1)
    labels = torch.tensor([FREE, OCCUPIED, OCCUPIED, UNKNOWN])
    assert lovasz_softmax(probs, labels).item() == pytest.approx(17 / 60, abs=1e-6)
    assert _lovasz_reference(probs.numpy(), labels.numpy(), UNKNOWN) == pytest.approx(17 / 60, abs=1e-9)


def test_lovasz_softmax_matches_the_reference_on_random_cases():
    rng = np.random.default_rng(1)
    for _ in range(20):
        n = int(rng.integers(1, 30))
        probs = rng.dirichlet(np.ones(3), n)
        labels = rng.integers(0, 3, n)
        if not (labels != UNKNOWN).any():
            continue
        got = lovasz_softmax(torch.from_numpy(probs), torch.from_numpy(labels)).item()
        assert got == pytest.approx(_lovasz_reference(probs, labels, UNKNOWN), abs=1e-9)


def test_unknown_is_an_input_class_and_an_ignored_target():
    torch.manual_seed(0)
    cfg = tokenizer_config("micro")
    model = SceneTokenizer(cfg)
    labels = torch.randint(0, 3, (2, *cfg.dims))
    # an input class: turning labelled voxels unknown changes the tokens' features
    other = labels.clone()
    other[labels == FREE] = UNKNOWN
    assert not torch.allclose(model.encoder(model.bev(labels)), model.encoder(model.bev(other)))
    # an ignored target: the loss's gradient on the logits of unknown voxels is zero
    logits = model(labels)[0].detach().requires_grad_(True)
    from pcfbench.methods.occworld import tokenizer as tk

    flat, target = logits.reshape(-1, 3), labels.reshape(-1)
    loss = cfg.ce_weight * torch.nn.functional.cross_entropy(flat, target, ignore_index=UNKNOWN) \
        + tk.lovasz_softmax(torch.softmax(flat, 1), target)
    loss.backward()
    g = logits.grad.reshape(-1, 3)
    assert g[target == UNKNOWN].abs().max() == 0 and g[target != UNKNOWN].abs().max() > 0


def test_losses_and_occupancy_probability():
    torch.manual_seed(0)
    cfg = tokenizer_config("micro")
    model = SceneTokenizer(cfg)
    labels = torch.randint(0, 3, (2, *cfg.dims))
    out = tokenizer_losses(model, labels)
    expected = cfg.ce_weight * out["ce"] + cfg.lovasz_weight * out["lovasz"] + cfg.vq_weight * out["vq"]
    assert out["loss"].item() == pytest.approx(expected.item(), rel=1e-6)
    logits = torch.tensor([[2.0, 0.0, 0.0], [0.0, 3.0, 1.0]])
    p = torch.softmax(logits, 1)
    assert torch.allclose(occupancy_probability(logits), 1 - p[:, FREE])


def test_offset_head_adds_one_plane_offset_per_voxel():
    """surface=front (ours): a 3x3 convolution beside the classifier decodes one offset per voxel
    (metres: the head's output times half the largest voxel side); its loss is the mean absolute
    error over the occupied voxels only, in those units, weighted into the total."""
    from pcfbench.methods.occworld.tokenizer import OFFSET_HEAD_PARAMETERS

    assert OFFSET_HEAD_PARAMETERS == _conv(3, 64, 16)
    assert count_parameters(SceneTokenizer(tokenizer_config("paper", surface="front"))) == \
        PAPER_PARAMETERS + OFFSET_HEAD_PARAMETERS
    with pytest.raises(PcfbenchError, match="surface"):
        tokenizer_config("micro", surface="plane")
    torch.manual_seed(0)
    cfg = tokenizer_config("micro", surface="front")
    assert cfg.offset_scale == pytest.approx(max(140 / 32, 9 / 4) / 2)
    model = SceneTokenizer(cfg)
    labels = torch.randint(0, 3, (2, *cfg.dims))
    codes, quantized, _ = model.encode(labels)
    logits, offsets = model.decode_all(quantized)
    assert offsets.shape == labels.shape and torch.allclose(logits, model.decode_codes(codes), atol=1e-5)
    target = torch.randn(labels.shape)
    with pytest.raises(PcfbenchError, match="offset head needs"):
        tokenizer_losses(model, labels)
    with pytest.raises(PcfbenchError, match="without an offset head"):
        tokenizer_losses(SceneTokenizer(tokenizer_config("micro")), labels, target)
    out = tokenizer_losses(model, labels, target)
    occ = labels == OCCUPIED
    by_hand = (offsets - target).abs()[occ].mean() / cfg.offset_scale
    assert out["offset"].item() == pytest.approx(by_hand.item(), rel=1e-5)
    expected = (cfg.ce_weight * out["ce"] + cfg.lovasz_weight * out["lovasz"] + cfg.vq_weight * out["vq"]
                + cfg.offset_weight * out["offset"])
    assert out["loss"].item() == pytest.approx(expected.item(), rel=1e-5)
    # the free and unknown voxels' targets do not count
    other = target.clone()
    other[~occ] = 1e3
    assert tokenizer_losses(model, labels, other)["offset"].item() == pytest.approx(out["offset"].item(), rel=1e-6)


def test_offset_head_learns_the_offsets():
    torch.manual_seed(0)
    cfg = tokenizer_config("micro", surface="front")
    model = SceneTokenizer(cfg)
    g = torch.Generator().manual_seed(0)
    labels = torch.randint(0, 3, (1, *cfg.dims), generator=g)
    target = (torch.rand(labels.shape, generator=g) - 0.5) * 0.6
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    errs = []
    for _ in range(60):
        out = tokenizer_losses(model, labels, target)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        errs.append(out["offset"].item())
    assert errs[-1] < 0.5 * errs[0], errs[::10]
