"""Speed of Copilot4D inference rendering: one decoded token map of the ``tiny`` tokenizer
rendered along one sweep's rays by the numba marcher (``render_codes``'s CPU path) and by the
differentiable torch functions that training uses (``torch_path=True``), on the same input.

With ``PCFBENCH_BENCH_FULL=1`` the rays are a 64-beam, 1800-step toy LiDAR (115,200 rays);
otherwise 16 x 360 keeps the default (disabled, run-once) pass quick. Run with

    PCFBENCH_BENCH_FULL=1 .venv/bin/python -m pytest tests/benchmarks/test_bench_copilot4d.py --benchmark-enable

The tokenizer is the ``tiny`` configuration with its initial weights and a coarse bias that
predicts about a tenth of the coarse voxels occupied (a trained checkpoint is not part of a
fresh clone); extra_info reports ``rays_per_s``.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from pcfbench.methods.copilot4d.config import TINY
from pcfbench.methods.copilot4d.evaluate import decode, render_codes, tokenize_sweep
from pcfbench.methods.copilot4d.model import Tokenizer

FULL = os.environ.get("PCFBENCH_BENCH_FULL") == "1"


@pytest.fixture(scope="module")
def scene():
    from pcfbench.testing import toy_world_sweeps

    kw = dict(beams=64, azimuths=1800) if FULL else dict(beams=16, azimuths=360)
    pts, _, _ = toy_world_sweeps(1, **kw)
    torch.manual_seed(0)
    model = Tokenizer(TINY).eval()
    with torch.no_grad():
        model.decoder.coarse_linear.bias.fill_(-2.0)
    codes = tokenize_sweep(model, pts[0])
    p = pts[0][np.linalg.norm(pts[0], axis=1) > 1.0]
    dirs = (p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32)
    return model, codes, decode(model, codes), dirs


@pytest.mark.parametrize("path", ["numba", "torch"])
def test_render_codes(benchmark, scene, path):
    model, codes, decoded, dirs = scene
    torch.set_num_threads(1)
    kw = dict(origin=np.array([2.0, -1.0, 0.0]), decoded=decoded, threshold=0.02, noise=False, readout="median",
              torch_path=path == "torch")
    render_codes(model, codes, dirs[:100], **kw)  # compile outside the timing
    depths = benchmark(render_codes, model, codes, dirs, **kw)
    assert depths.shape == (len(dirs),) and np.all(np.isfinite(depths))
    if benchmark.stats is not None:
        benchmark.extra_info["rays"] = len(dirs)
        benchmark.extra_info["rays_per_s"] = len(dirs) / benchmark.stats.stats.median
