"""BEVWorld's ceiling (methods/bevworld/ceiling.py) and its command."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from pcfbench.methods.bevworld.config import tokenizer_config


class _Occupancy(torch.nn.Module):
    """A stand-in tokenizer whose latent is the sweep's occupancy on its grid (one channel per
    height) and whose volume is that occupancy, opaque where occupied (density softplus(100 f -
    30): 70 / m in an occupied voxel, 1e-13 in a free one): a perfect tokenizer at the grid's
    resolution, so the ceiling measures the frames, origins and rendering alone. Its density MLP
    is the real decoder's shape, which inference on the CPU reads."""

    def __init__(self, cfg) -> None:
        super().__init__()
        self.cfg = cfg
        self.unit = torch.nn.Parameter(torch.ones(()))
        self.decoder = torch.nn.Module()
        self.decoder.mlp1, self.decoder.mlp2 = torch.nn.Linear(1, 1), torch.nn.Linear(1, 1)
        with torch.no_grad():
            for layer, w, b in ((self.decoder.mlp1, 1.0, 0.0), (self.decoder.mlp2, 100.0, -30.0)):
                layer.weight.fill_(w)
                layer.bias.fill_(b)

    def encode(self, points, batch, batch_size):
        cfg = self.cfg
        lo = points.new_tensor([cfg.x_range[0], cfg.y_range[0], cfg.z_range[0]])
        idx = torch.floor((points - lo) / points.new_tensor(cfg.voxel_size)).long()
        occ = torch.zeros(1, cfg.grid_xy, cfg.grid_xy, cfg.grid_z)
        occ[0, idx[:, 0], idx[:, 1], idx[:, 2]] = 1.0
        return occ

    def normalise(self, z):
        return z

    def decode(self, z, channels_last=False):  # (1, X, Y, Z) -> (1, 1, Z, X, Y), (X, Y, Z, 1) in memory
        return z.permute(0, 3, 1, 2)[:, None]

    def density(self, f):
        d = self.decoder
        return torch.nn.functional.softplus(d.mlp2(torch.relu(d.mlp1(f)))).squeeze(-1)


@pytest.mark.parametrize("frame", ["own", "t0"])
def test_ceiling_renders_each_target_from_the_right_origin(tmp_path, frame):
    """With a perfect tokenizer (0.25 m voxels) the ceiling's rays end near their own return in
    either frame: the target's points, the frame they are encoded in and the rays' origin and
    directions in that frame all agree. Its chamfer is a fraction of the latent copy's (rendering
    the t0 target from the future sensor's own-frame origin instead gave 11.2 against the copy's
    9.6, here 0.14); its median error stays under 1 m, not within a voxel: trilinear features
    make a surface opaque up to a voxel early, and grazing ground rays stretch that."""
    from conftest import write_tiny_kitti

    from pcfbench.methods.bevworld.ceiling import evaluate_ceiling, write_ceiling
    from pcfbench.methods.copilot4d.data import open_dataset

    root = write_tiny_kitti(tmp_path / "kitti", sequences=("08",), num_sweeps=24, beams=16, azimuths=360)
    adapter = open_dataset("kitti", root)
    cfg = replace(tokenizer_config("micro"), name="test", grid_xy=640, grid_z=36, samples_per_ray=1000)
    res = evaluate_ceiling(_Occupancy(cfg), adapter, "test", "kitti-1s", frame=frame, max_samples=1,
                           log=lambda *a: None)
    o, lcp = res["means"]["ceiling"], res["means"]["bevworld-latent-copy"]
    assert res["samples"] == 1 and res["sweeps"] == 5
    assert o["chamfer_nf"] < 0.3 * lcp["chamfer_nf"] and o["l1_mean"] < lcp["l1_mean"], (o, lcp)
    assert o["l1_median"] < 1.0, o
    assert res["change"]["mean"] > 0
    md, csv_path = write_ceiling(res, {"config": "test"}, tmp_path / "rep", "ceiling")
    assert "sees the future" in md.read_text() and csv_path.read_text().startswith("entry,")


def test_ceiling_frame_is_checked():
    from pcfbench.errors import PcfbenchError
    from pcfbench.methods.bevworld.ceiling import evaluate_ceiling

    with pytest.raises(PcfbenchError, match="frame"):
        evaluate_ceiling(_Occupancy(tokenizer_config("micro")), None, "test", "kitti-1s", frame="world")


def test_the_command_scores_a_trained_tokenizer(tmp_path, monkeypatch):
    from click.testing import CliRunner
    from conftest import write_tiny_kitti

    from pcfbench.cli import build_cli

    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")
    root = write_tiny_kitti(tmp_path / "kitti", sequences=("00", "08"), num_sweeps=24, beams=8, azimuths=180)
    runner, cli = CliRunner(), build_cli()
    spec = "bevworld-latent-copy:config=micro,steps=2,frame=t0"
    r = runner.invoke(cli, ["train", spec, "--dataset", f"kitti={root}"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(cli, ["bevworld-ceiling", "--method", spec, "--train-on", f"kitti={root}", "--dataset",
                            f"kitti={root}", "--samples", "1", "--reports", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert "ceiling (kitti-1s, frame t0, 1 samples) / bevworld-latent-copy: chamfer_nf" in r.output
    md = next((tmp_path / "rep" / "bevworld").glob("ceiling-micro-kitti-on-kitti-test-kitti-1s-t0-1-samples.md")).read_text()
    assert "pcfbench bevworld-ceiling --method" in md and np.isfinite(float(md.split("| ceiling | ")[1].split()[0]))
    r = runner.invoke(cli, ["bevworld-ceiling", "--method", "copy-last", "--dataset", f"kitti={root}"])
    assert r.exit_code != 0 and "expected bevworld-latent-copy" in r.output
