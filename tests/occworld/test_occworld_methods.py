"""OccWorld's trained methods (occworld-occ-copy, occworld): a short overfit of each network,
train and resume through the one training loop, and forecasts through the harness."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from pcfbench.errors import PcfbenchError
from pcfbench.method import resolve_method
from pcfbench.methods.occworld.config import tokenizer_config, world_config

MICRO = "config=micro,strides=2,anchor_every=4,tokenizer_steps=2"


@pytest.fixture
def micro(monkeypatch, tmp_path):
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")
    torch.set_num_threads(1)


@pytest.fixture
def kitti(tmp_path):
    from conftest import write_tiny_kitti

    return write_tiny_kitti(tmp_path / "kitti", sequences=("00", "08"), num_sweeps=20, beams=8, azimuths=180)


def _train(spec: str, root, **kw):
    from pcfbench.training import train

    return train(resolve_method(spec), f"kitti={root}", progress=False, log=lambda *_: None, **kw)


def test_options_are_checked():
    for bad, what in (("frame=world", "frame"), ("readout=median", "readout"), ("pose=maybe", "pose"),
                      ("config=huge", "config"), ("tokens=40", "tokens")):
        with pytest.raises(PcfbenchError, match=what):
            resolve_method(f"occworld:{bad}")
    assert resolve_method("occworld-occ-copy:frame=t0").options.frame == "t0"
    with pytest.raises(PcfbenchError, match="surface"):
        resolve_method("occworld-occ-copy:surface=plane")
    # the planes' readout needs the planes; OccWorld's own readouts work without them
    with pytest.raises(PcfbenchError, match="readout=surface renders the planes of surface=front or mean"):
        resolve_method("occworld:surface=none")
    assert resolve_method("occworld:surface=none,readout=expected").create().tok_cfg.surface == "none"
    assert resolve_method("occworld-occ-copy").create().cfg.surface == "front"


def test_tokenizer_overfits_one_grid():
    from pcfbench.methods.occworld.tokenizer import SceneTokenizer, tokenizer_losses

    torch.manual_seed(0)
    cfg = tokenizer_config("micro")
    model = SceneTokenizer(cfg)
    g = torch.Generator().manual_seed(0)
    labels = torch.randint(0, 3, (1, *cfg.dims), generator=g)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        out = tokenizer_losses(model, labels)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(out["ce"].item())
    assert losses[-1] < 0.6 * losses[0]


def test_world_model_overfits_one_window():
    from pcfbench.methods.occworld.world import WorldModel, world_losses

    torch.manual_seed(0)
    cfg = world_config("micro", tokenizer_config("micro"))
    model = WorldModel(cfg)
    g = torch.Generator().manual_seed(0)
    T = cfg.n_past + cfg.n_future
    codes = torch.randint(0, cfg.codebook_size, (1, T, *cfg.token_grid), generator=g)
    book = torch.randn(cfg.codebook_size, cfg.code_dim, generator=g)
    vec = book[codes].movedim(-1, -3)
    poses = torch.eye(4).repeat(1, T, 1, 1)
    poses[..., 0, 3] = torch.arange(T, dtype=torch.float32)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    first = None
    for _ in range(40):
        out = world_losses(model, codes, vec, poses)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        first = first if first is not None else out["ce"].item()
    assert out["ce"].item() < 0.5 * first and out["accuracy"].item() > 0.5


def test_missing_tokenizer_is_one_error_with_the_command(micro, kitti):
    from pcfbench.training import CheckpointError

    with pytest.raises(CheckpointError, match=r"pcfbench train occworld-occ-copy:config=micro,steps=2 "):
        _train(f"occworld:{MICRO},steps=2", kitti)


@pytest.mark.parametrize("frame", ["own", "t0"])
def test_train_resume_continues_the_same_curve(micro, kitti, frame):
    tok = _train(f"occworld-occ-copy:config=micro,frame={frame},steps=2", kitti)
    assert tok.manifest["config"]["tokenizer"]["name"] == "micro" and tok.manifest["config"]["frame"] == frame
    spec = f"occworld:{MICRO},frame={frame},steps=3"
    first = _train(spec, kitti, max_minutes=0)
    assert first.steps == 1 and not first.manifest["complete"]
    resumed = _train(spec, kitti)
    assert resumed.steps == 3 and resumed.manifest["complete"]
    curve = (resumed.dir / "curve.csv").read_text()
    straight = _train(spec, kitti, fresh=True)
    assert (straight.dir / "curve.csv").read_text().splitlines()[0] == curve.splitlines()[0]
    import csv
    import io

    keys = ("step", "loss", "ce", "accuracy", "grad_norm")
    rows = [[r[k] for k in keys] for r in csv.DictReader(io.StringIO(curve))]
    assert rows == [[r[k] for k in keys] for r in csv.DictReader(open(straight.dir / "curve.csv"))]
    w = straight.load_weights()
    for k, v in resumed.load_weights().items():
        assert torch.equal(v, w[k]), k
    conf = straight.manifest["config"]
    assert {k.split(".")[0] for k in w} == {"world", "tokenizer"} and conf["tokenizer_sha256"] == tok.sha256


def test_both_methods_forecast_through_the_harness(micro, kitti, tmp_path):
    """Trained through `pcfbench train` (micro configuration, a few steps), evaluated by
    `pcfbench run` at kitti-1s: finite depths for every future sweep."""
    import pandas as pd

    from pcfbench.cli import build_cli

    runner, cli = CliRunner(), build_cli()
    r = runner.invoke(cli, ["train", "occworld-occ-copy:config=micro,steps=2", "--dataset", f"kitti={kitti}"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(cli, ["train", f"occworld:{MICRO},steps=2", "--dataset", f"kitti={kitti}"])
    assert r.exit_code == 0, r.output
    args = ["run", "-m", "occworld-occ-copy:config=micro,steps=2", "-m", f"occworld:{MICRO},steps=2",
            "-m", f"occworld:{MICRO},steps=2,pose=predicted,readout=threshold",
            "--train-on", f"kitti={kitti}", "-d", f"kitti={kitti}", "-s", "kitti-1s", "--limit", "1", "-q",
            "--store", str(tmp_path / "store"), "--reports", str(tmp_path / "rep")]
    r = runner.invoke(cli, args)
    assert r.exit_code == 0, r.output
    cells = sorted((tmp_path / "store").rglob("cell.json"))
    assert len(cells) == 3
    for cell in cells:
        df = pd.concat([pd.read_parquet(p) for p in sorted((cell.parent / "rows").glob("*.parquet"))])
        assert len(df) == 5 and np.isfinite(df["l1_mean"].to_numpy(dtype=float)).all(), json.loads(cell.read_text())


def test_in_the_default_run_when_ready(monkeypatch):
    """With a checkpoint ready (here: every trained method's shipped one, pretended), the
    default run holds both: the world model and the occupancy copy it must beat."""
    import pcfbench.training.checkpoints as cks
    from pcfbench.cli import _selected_methods
    from pcfbench.plugins import get_plugins

    monkeypatch.setattr(cks, "ready_shipped", lambda *a, **k: object())
    names = {m.name for m in _selected_methods(get_plugins(), ())}
    assert {"copilot4d-token-copy", "occworld", "occworld-occ-copy"} <= names


@pytest.mark.parametrize("frame", ["own", "t0"])
def test_world_inputs_label_each_past_sweep_in_the_frame(tmp_path, monkeypatch, frame):
    """The forecast's past maps are the labels of each past sweep in its own sensor frame
    (``own``) or moved into the t=0 sensor frame from its sensor's position there (``t0``),
    exactly as the training windows label them; the poses are every sensor's in the t=0 frame."""
    from conftest import write_tiny_kitti

    from pcfbench.methods.copilot4d.data import open_dataset
    from pcfbench.methods.occworld import occ_copy as oc
    from pcfbench.methods.occworld.forecaster import OccWorld, OccWorldOptions
    from pcfbench.plugins import get_setting
    from pcfbench.protocol import SampleBuilder

    monkeypatch.setattr(oc, "tokenize_labels", lambda model, labels: torch.from_numpy(labels))
    monkeypatch.setattr("pcfbench.methods.occworld.forecaster.tokenize_labels",
                        lambda model, labels: torch.from_numpy(labels))
    root = write_tiny_kitti(tmp_path / "kitti", sequences=("08",), num_sweeps=24)
    builder = SampleBuilder(open_dataset("kitti", root), get_setting("kitti-1s"))
    seq_name, ref = builder.sample_keys("test")[0]
    sample, _ = builder.build(seq_name, ref)
    m = OccWorld(OccWorldOptions(config="micro", frame=frame))
    maps, poses, T_s0_ref = m.world_inputs(sample.for_method())
    seq = builder.sequence(seq_name)
    P = m.world_cfg.n_past
    for j, i in enumerate(range(ref - (P - 1) * 2, ref + 1, 2)):
        T_s0_i = np.linalg.inv(seq.T_world_sensor[ref]) @ seq.T_world_sensor[i]
        want = oc.sweep_labels(m.tok_cfg, builder.points_sensor(seq, i), None if frame == "own" else T_s0_i)
        assert (maps[j].numpy() != want).mean() < 1e-3  # float32 round trips may move a point across a face
        assert np.allclose(poses[j].numpy(), T_s0_i, atol=1e-6)
    assert np.allclose(poses[P].numpy(), np.linalg.inv(seq.T_world_sensor[ref]) @ seq.T_world_sensor[ref + 2], atol=1e-6)
