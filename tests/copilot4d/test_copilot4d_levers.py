"""copilot4d's training levers that are not the paper's: the render stage (`render_weight`: the
straight-through code embeddings, the rendered depth error against the tokenizer's own renderer,
the term of a step, a training with it) and the neighbour targets (`neighbour_targets`)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pcfbench.method import resolve_method
from pcfbench.methods.copilot4d.model import Tokenizer
from pcfbench.methods.copilot4d.render_stage import RenderTerm, frame_embeddings, render_l1
from test_copilot4d_forecast import MICRO_TOK, MICRO_TRAIN, _tokenizer, _train, kitti, micro  # noqa: F401 (fixtures)


def test_frame_embeddings_are_the_arg_max_codes_with_the_softmax_gradient():
    """Hand-built: 3 codes of dimension 2, a 1 x 2 frame whose second token is masked. The value
    is the true code's embedding where visible and the arg max code's where masked; the gradient
    reaches the masked token's logits only, as the softmax's Jacobian says."""
    cb = torch.tensor([[1.0, 0.0], [0.0, 2.0], [3.0, 1.0]])
    logits = torch.tensor([[[5.0, 0.0, 0.0], [0.0, 1.0, 2.0]]], requires_grad=True)  # arg max 0, 2
    targets = torch.tensor([[1, 0]])
    masked = torch.tensor([[False, True]])
    emb = frame_embeddings(cb, logits, targets, masked)
    assert torch.equal(emb.detach(), torch.tensor([[[0.0, 2.0], [3.0, 1.0]]]))  # code 1 (visible), code 2 (masked)
    g = torch.tensor([0.5, -1.0])
    (emb * g).sum().backward()
    assert torch.equal(logits.grad[0, 0], torch.zeros(3))
    p = torch.softmax(torch.tensor([0.0, 1.0, 2.0]), 0)
    s = cb @ g  # each code's score: 0.5, -2, 0.5
    assert torch.allclose(logits.grad[0, 1], p * (s - (p * s).sum()), atol=1e-7)


@pytest.fixture
def tokenizer():
    torch.manual_seed(0)
    return Tokenizer(MICRO_TOK).eval()


def _rays(n=40, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3)) * [1, 1, 0.1]
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    o = np.tile(np.array([2.0, -1.0, 0.0], np.float32), (n, 1))
    return o, d, rng.uniform(2, 20, n).astype(np.float32)


def test_render_l1_is_the_tokenizer_renderers_depth_error(tokenizer):
    """The depth error of a code map's embeddings equals the one computed from the depths
    `copilot4d` renders for the same codes and origin (the torch path: skipping without noise,
    no background term), to float precision."""
    from pcfbench.methods.copilot4d.evaluate import render_codes

    codes = torch.randint(0, tokenizer.cfg.codebook_size, (8, 8), generator=torch.Generator().manual_seed(1))
    o, d, depth = _rays()
    with torch.no_grad():
        got = render_l1(tokenizer, F.embedding(codes, tokenizer.vq.codebook), torch.from_numpy(o),
                        torch.from_numpy(d), torch.from_numpy(depth))
    rendered = render_codes(tokenizer, codes, d, origin=o[0], noise=False, far_bound=False, torch_path=True)
    assert float(got) == pytest.approx(float(np.abs(rendered - depth).mean()), rel=1e-5)


class _FixedRays:
    def __init__(self, got):
        self.got, self.asked = got, []

    def rays(self, cfg, window, frame, own, count, rng):
        self.asked.append((window, frame, own))
        return self.got


def test_render_term_renders_the_models_masked_tokens_beside_the_copy(tokenizer):
    """A sequence of 2 past and 2 future frames: the term renders the drawn future frame with
    the arg max codes on its masked tokens and, without gradient, with the last past frame's
    there; nothing masked in the drawn frame, or nothing drawn, adds nothing."""
    K = tokenizer.cfg.codebook_size
    gen = torch.Generator().manual_seed(2)
    targets = torch.randint(0, K, (1, 4, 8, 8), generator=gen)
    masked = torch.zeros(1, 4, 8, 8, dtype=torch.bool)
    masked[0, 3, :4] = True
    wrong = (targets + 1) % K
    logits = (F.one_hot(wrong, K).float() * 10).requires_grad_(True)
    o, d, depth = _rays()
    term = RenderTerm(tokenizer, _FixedRays((o, d, depth)), n_past=2, n_future=2, own=False, weight=0.5)
    rng = np.random.default_rng(0)
    drawn = [term.draw(7, rng)]
    while drawn[0][0] != 3:  # the frame is drawn from the future ones
        assert drawn[0][0] == 2
        drawn = [term.draw(7, rng)]
    assert term.rays.asked[-1] == (7, 3, False)
    value, stats = term(logits, targets, masked, drawn)
    cb = tokenizer.vq.codebook
    tensors = [torch.from_numpy(a) for a in (o, d, depth)]
    with torch.no_grad():
        expect = render_l1(tokenizer, F.embedding(torch.where(masked[0, 3], wrong[0, 3], targets[0, 3]), cb), *tensors)
        copy = render_l1(tokenizer, F.embedding(torch.where(masked[0, 3], targets[0, 1], targets[0, 3]), cb), *tensors)
    assert stats["render_l1"] == pytest.approx(float(expect), rel=1e-6)
    assert stats["render_l1_copy"] == pytest.approx(float(copy), rel=1e-6)
    assert float(value.detach()) == pytest.approx(0.5 * float(expect), rel=1e-6)
    value.backward()
    assert logits.grad[0, 3, :4].abs().sum() > 0
    assert logits.grad[0, 3, 4:].abs().sum() == 0 and logits.grad[0, :3].abs().sum() == 0
    assert all(p.grad is None for p in tokenizer.parameters())  # frozen
    for none in ([None], [(2, o, d, depth)]):  # nothing drawn; frame 2 has no masked token
        value, stats = term(logits, targets, masked, none)
        assert float(value) == 0 and np.isnan(stats["render_l1"]) and np.isnan(stats["render_l1_copy"])


def test_a_training_with_render_weight_records_the_stage(micro, kitti):  # noqa: F811 (the imported fixtures)
    """`render_weight` is a quiet training option (0 keeps every checkpoint's name); a training
    with it goes on from the plain training it names (the stage is this training's), records the
    weight in its manifest, logs the rendered error beside the copy's, and learns other weights
    than the same training without it."""
    _tokenizer(kitti)
    plain = f"copilot4d:{MICRO_TRAIN},steps=2"
    assert resolve_method(f"{plain},render_weight=0").options_hash == resolve_method(plain).options_hash
    rendered = resolve_method(f"copilot4d:{MICRO_TRAIN},steps=3,init_steps=2,render_weight=1")
    assert rendered.options_hash != resolve_method(f"copilot4d:{MICRO_TRAIN},steps=3,init_steps=2").options_hash
    assert rendered.create().start_spec().options_hash == resolve_method(plain).options_hash
    _train(plain, kitti)
    with_stage = _train(f"copilot4d:{MICRO_TRAIN},steps=3,init_steps=2,render_weight=1", kitti)
    without = _train(f"copilot4d:{MICRO_TRAIN},steps=3,init_steps=2", kitti)
    assert with_stage.manifest["config"]["render"] == {"weight": 1.0, "rays": 512, "per_sweep": 4096}
    assert "render" not in without.manifest["config"]
    with open(with_stage.dir / "curve.csv") as f:
        rows = list(csv.DictReader(f))
    assert any(np.isfinite(float(r["render_l1"])) and np.isfinite(float(r["render_l1_copy"])) for r in rows)
    a, b = with_stage.load_weights(), without.load_weights()
    assert any(not torch.equal(a[k], b[k]) for k in a if k.startswith("world."))


def test_neighbour_targets_by_hand():
    """Codes at 0, 1, 3 and 10 on a line, k = 1: each code's nearest is 1, 0, 1 and 3. With half
    the mass to the neighbour and label smoothing 0.1, code 0's target is 0.9 (0.5, 0.5, 0, 0) +
    0.025; the cross entropy is the target's against the log softmax; with share 0 it is
    PyTorch's label-smoothed cross entropy."""
    from pcfbench.methods.copilot4d.diffusion import _cross_entropies, neighbour_targets

    cb = torch.tensor([[0.0], [1.0], [3.0], [10.0]])
    q = neighbour_targets(cb, 1, 0.5, 0.1)
    expect = torch.tensor([[0.475, 0.475, 0.025, 0.025], [0.475, 0.475, 0.025, 0.025],
                           [0.025, 0.475, 0.475, 0.025], [0.025, 0.025, 0.475, 0.475]])
    assert torch.allclose(q, expect)
    logits = torch.tensor([[2.0, 0.0, 0.0, -1.0], [0.0, 1.0, 0.0, 0.0]])
    target = torch.tensor([2, 3])
    logp = logits.log_softmax(-1)
    by_hand = -(0.025 * logp[0, 0] + 0.475 * logp[0, 1] + 0.475 * logp[0, 2] + 0.025 * logp[0, 3]), \
        -(0.025 * logp[1, :2].sum() + 0.475 * logp[1, 2:].sum())
    mean, got = _cross_entropies(logits, target, q)
    assert torch.allclose(got, torch.stack(by_hand))
    assert float(mean) == pytest.approx(float(got.mean()))
    for bad in (0, 4):
        with pytest.raises(ValueError, match=f"k={bad} nearest codes: expected 1 to 3 for a codebook of 4 codes"):
            neighbour_targets(cb, bad, 0.5, 0.1)
    plain = neighbour_targets(cb, 1, 0.0, 0.1)
    assert torch.allclose(_cross_entropies(logits, target, plain)[1],
                          F.cross_entropy(logits, target, label_smoothing=0.1, reduction="none"))


def test_a_training_with_neighbour_targets_records_them(micro, kitti):  # noqa: F811 (the imported fixtures)
    """`neighbour_targets` is a quiet training option, this training's only (the one it goes on
    from is the plain one); its manifest records the targets, and its weights differ from the same
    training's without them."""
    from pcfbench.errors import PcfbenchError

    with pytest.raises(PcfbenchError, match="neighbour_targets=64: the 'micro' tokenizer has 64 codes, so at most 63"):
        resolve_method(f"copilot4d:{MICRO_TRAIN},neighbour_targets=64").create()
    _tokenizer(kitti)
    plain = f"copilot4d:{MICRO_TRAIN},steps=2"
    assert resolve_method(f"{plain},neighbour_targets=0").options_hash == resolve_method(plain).options_hash
    spec = f"copilot4d:{MICRO_TRAIN},steps=3,init_steps=2,neighbour_targets=2"
    assert resolve_method(spec).create().start_spec().options_hash == resolve_method(plain).options_hash
    _train(plain, kitti)
    with_targets = _train(spec, kitti)
    without = _train(f"copilot4d:{MICRO_TRAIN},steps=3,init_steps=2", kitti)
    assert with_targets.manifest["config"]["targets"] == {"neighbours": 2, "share": 0.5, "label_smoothing": 0.1}
    assert "targets" not in without.manifest["config"]
    a, b = with_targets.load_weights(), without.load_weights()
    assert any(not torch.equal(a[k], b[k]) for k in a if k.startswith("world."))
