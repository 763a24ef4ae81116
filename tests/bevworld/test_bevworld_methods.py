"""BEVWorld's trained methods (bevworld-latent-copy, bevworld): options, train and resume
through the one training loop, the curriculum, and forecasts through the harness."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from pcfbench.errors import PcfbenchError
from pcfbench.method import resolve_method


@pytest.fixture
def one_thread():
    """One torch thread for the short training runs: their tensors are small, and on a shared
    CPU more threads only contend (a run took 20x longer)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)

MICRO = "config=micro,strides=2,anchor_every=4,tokenizer_steps=2"


@pytest.fixture
def micro(monkeypatch, tmp_path, one_thread):
    monkeypatch.setenv("PCFBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("PCFBENCH_NO_PROGRESS", "1")


@pytest.fixture
def kitti(tmp_path):
    from conftest import write_tiny_kitti

    return write_tiny_kitti(tmp_path / "kitti", sequences=("00", "08"), num_sweeps=20, beams=8, azimuths=180)


def _train(spec: str, root, **kw):
    from pcfbench.training import train

    return train(resolve_method(spec), f"kitti={root}", progress=False, log=lambda *_: None, **kw)


def test_options_are_checked():
    for bad, what in (("frame=world", "frame"), ("curriculum=maybe", "curriculum"), ("config=huge", "config"),
                      ("cond_dropout=1", "cond_dropout"), ("target=x0", "target")):
        with pytest.raises(PcfbenchError, match=what):
            resolve_method(f"bevworld:{bad}")
    assert resolve_method("bevworld-latent-copy:frame=t0").options.frame == "t0"


def test_the_curriculum_has_the_papers_three_stages():
    from pcfbench.methods.bevworld.forecaster import stage_batch, stage_of

    assert [stage_of(s, 70, "on") for s in (0, 19, 20, 39, 40, 69)] == [1, 1, 2, 2, 3, 3]
    assert {stage_of(s, 70, "off") for s in range(70)} == {3}
    lat = np.arange(6 * 10, dtype=np.float32).reshape(6, 10, 1, 1, 1)
    poses = np.tile(np.eye(4, dtype=np.float32), (6, 10, 1, 1))
    windows = {"latents": lat, "poses": poses, "by_stride": {1: np.array([0, 1]), 2: np.array([2, 3]),
                                                              6: np.array([4, 5])}}
    rng = np.random.default_rng(0)
    x, p, frames, past, _ = stage_batch(windows, 1, 5, (2, 6), rng, 8)
    assert x.shape[1] == 3 and frames.tolist() == [3, 4, 5] and past == 2
    assert set((x[:, 0, 0, 0, 0] // 10).tolist()) <= {0, 1}  # stride-1 windows only
    x, _, frames, past, _ = stage_batch(windows, 2, 5, (2, 6), rng, 8)
    assert x.shape[1] == 10 and past == 5 and set((x[:, 0, 0, 0, 0] // 10).tolist()) <= {0, 1}
    x, _, _, _, _ = stage_batch(windows, 3, 5, (2, 6), rng, 64)
    assert set((x[:, 0, 0, 0, 0] // 10).tolist()) == {2, 3, 4, 5}


def test_missing_tokenizer_is_one_error_with_the_command(micro, kitti):
    from pcfbench.training import CheckpointError

    with pytest.raises(CheckpointError, match=r"pcfbench train bevworld-latent-copy:config=micro,frame=t0,steps=2"):
        _train(f"bevworld:{MICRO},steps=2", kitti)


def _rows(path, keys):
    return [[r[k] for k in keys] for r in csv.DictReader(open(path))]


@pytest.mark.parametrize("frame", ["own", "t0"])
def test_train_resume_continues_the_same_curve(micro, kitti, frame):
    tok = _train(f"bevworld-latent-copy:config=micro,frame={frame},steps=2", kitti)
    assert tok.manifest["config"]["tokenizer"]["name"] == "micro" and tok.manifest["config"]["frame"] == frame
    tok_spec = f"bevworld-latent-copy:config=micro,frame={frame},steps=3"
    first = _train(tok_spec, kitti, max_minutes=0)
    assert first.steps == 1 and not first.manifest["complete"]
    resumed = _train(tok_spec, kitti)
    straight = _train(tok_spec, kitti, fresh=True)
    assert resumed.steps == 3 and resumed.manifest["complete"]
    keys = ("step", "loss", "l1", "grad_norm")
    assert _rows(resumed.dir / "curve.csv", keys) == _rows(straight.dir / "curve.csv", keys)
    w = straight.load_weights()
    for k, v in resumed.load_weights().items():
        assert torch.equal(v, w[k]), k
    assert int(w["stats_updates"]) == 3  # the latent statistics took in every step
    spec = f"bevworld:{MICRO},frame={frame},steps=3,curriculum=on"
    first = _train(spec, kitti, max_minutes=0)
    assert first.steps == 1 and not first.manifest["complete"]
    resumed = _train(spec, kitti)
    straight = _train(spec, kitti, fresh=True)
    keys = ("step", "loss", "mse", "stage", "grad_norm")
    rows = _rows(straight.dir / "curve.csv", keys)
    assert _rows(resumed.dir / "curve.csv", keys) == rows and [r[3] for r in rows] == ["1.0", "2.0", "3.0"]
    w = straight.load_weights()
    for k, v in resumed.load_weights().items():
        assert torch.equal(v, w[k]), k
    conf = straight.manifest["config"]
    assert {k.split(".")[0] for k in w} == {"world", "tokenizer"} and conf["tokenizer_sha256"] == tok.sha256
    assert conf["curriculum"] == "on" and conf["frame"] == frame
    # guidance needs a model that learned the unconditional prediction
    with pytest.raises(PcfbenchError, match="trained without dropping the action"):
        resolve_method(spec + ",guidance=2").create().load(straight)
    # its output read as the other target would be a plausible wrong forecast: refused
    from pcfbench.training import CheckpointError

    assert conf["target"] == "change"
    with pytest.raises(CheckpointError, match="predicts target=change, and these options read its output as "
                                              "target=eps"):
        resolve_method(spec + ",target=eps").create().load(straight)


def test_the_render_stage_follows_the_latent_training_and_resumes(micro, kitti):
    """render_weight > 0: render_steps more steps (stage 4) add the rendered depth L1; the latent
    steps before them log exactly what a run without the stage logs, and a run stopped before the
    stage resumes into it as a straight run trains."""
    _train("bevworld-latent-copy:config=micro,frame=t0,steps=2", kitti)
    plain = _train(f"bevworld:{MICRO},steps=2,render_weight=0", kitti)
    spec = f"bevworld:{MICRO},steps=2,render_weight=0.5,render_steps=2"
    first = _train(spec, kitti, max_minutes=0)
    assert first.steps == 1 and not first.manifest["complete"]
    resumed = _train(spec, kitti)
    straight = _train(spec, kitti, fresh=True)
    assert straight.steps == 4 and straight.manifest["config"]["render_weight"] == 0.5
    assert straight.manifest["config"]["render_steps"] == 2 and straight.manifest["config"]["steps_target"] == 4
    keys = ("step", "loss", "mse", "render_l1", "stage", "grad_norm")
    rows = _rows(straight.dir / "curve.csv", keys)
    assert _rows(resumed.dir / "curve.csv", keys) == rows
    assert [r[4] for r in rows] == ["3.0", "3.0", "4.0", "4.0"]
    assert [r[3] for r in rows[:2]] == ["nan", "nan"] and all(float(r[3]) > 0 for r in rows[2:])
    # the render stage's loss is the MSE plus its weight times the depth L1
    for r in rows[2:]:
        assert float(r[1]) == pytest.approx(float(r[2]) + 0.5 * float(r[3]), rel=1e-5)
    base = ("step", "loss", "mse", "grad_norm")
    assert _rows(plain.dir / "curve.csv", base) == _rows(straight.dir / "curve.csv", base)[:2]
    for k, v in resumed.load_weights().items():
        assert torch.equal(v, straight.load_weights()[k]), k
    # the stage's optimiser started afresh: AdamW has counted its 2 steps, not 4
    state = torch.load(straight.dir / "state-00000004.pt", weights_only=True)
    assert {int(v["step"]) for v in state["optimizer"]["state"].values()} == {2}
    for bad in ("-2", "-0.5"):
        with pytest.raises(PcfbenchError, match="render_weight"):
            resolve_method(f"bevworld:{MICRO},render_weight={bad}")
    # a weight asked for where the configuration has no stage steps is not silently dropped
    with pytest.raises(PcfbenchError, match="give render_steps too"):
        resolve_method(f"bevworld:{MICRO},render_weight=1").create().training_steps()
    assert resolve_method("bevworld").create().render_plan() == (1.0, 300)
    assert resolve_method("bevworld:config=paper").create().render_plan() == (0.0, 0)


def test_a_reseeded_stage_draws_the_same_whatever_came_before():
    """reseed_stage: streams that drew different amounts before draw the same after it, and
    another seed or stage draws otherwise."""
    from pcfbench.methods.bevworld.forecaster import reseed_stage
    from pcfbench.training.loop import Randoms

    def draws(used: int, seed: int = 0, stage: int = 4):
        rand = Randoms(np.random.default_rng(7), torch.Generator().manual_seed(8))
        rand.numpy.random(used), torch.randn(used, generator=rand.torch), torch.rand(used)
        reseed_stage(rand, seed, stage)
        return (rand.numpy.integers(0, 1000, 4).tolist(), torch.randint(0, 1000, (4,), generator=rand.torch).tolist(),
                torch.randint(0, 1000, (4,)).tolist())

    assert draws(0) == draws(5) == draws(123)
    assert draws(0, seed=1)[0] != draws(0)[0] and draws(0, stage=3)[1] != draws(0)[1]


def test_render_stage_rays_are_the_future_sweeps_seen_from_their_sensor():
    """A return 10 m ahead of a sensor standing 5 m ahead of the t=0 one: in the t=0 frame the ray
    starts at (5, 0, 0) and reaches 10 m along +x; in its own frame it starts at the origin."""
    from pcfbench.methods.bevworld.config import tokenizer_config
    from pcfbench.methods.bevworld.render_loss import WindowRays

    class Seq:
        def load_points(self, k):
            return np.array([[10.0, 0.0, 0.0], [0.2, 0.0, 0.0]], np.float32) if k == 3 else np.zeros((0, 3))

    class Adapter:
        class ego_box:  # noqa: N801
            @staticmethod
            def remove(p):
                return p

        def sequence(self, name):
            assert name == "a"
            return Seq()

    pose = np.eye(4, dtype=np.float32)
    pose[0, 3] = 5.0
    windows = {"sequences": np.array(["a"]), "sequence": np.array([0]), "sweeps": np.array([[1, 2, 3, 4]]),
               "poses": np.stack([np.eye(4, dtype=np.float32)] * 2 + [pose, pose])[None]}
    wr = WindowRays(Adapter(), windows, 2, per_sweep=8, seed=0, log=lambda *_: None)
    cfg, rng = tokenizer_config("micro"), np.random.default_rng(0)
    o, d, depth = wr.rays(cfg, 0, 2, False, 3, rng)  # the 0.2 m return is no ray; each return at most once
    np.testing.assert_allclose(o, [[5, 0, 0]])
    np.testing.assert_allclose(d, [[1, 0, 0]])
    np.testing.assert_allclose(depth, [10.0])
    o, _, depth = wr.rays(cfg, 0, 2, True, 1, rng)
    np.testing.assert_allclose(o, [[0, 0, 0]]) and np.testing.assert_allclose(depth, [10.0])
    assert wr.rays(cfg, 0, 3, False, 1, rng) is None  # sweep 4 has no returns


def test_both_methods_forecast_through_the_harness(micro, kitti, tmp_path):
    """Trained through `pcfbench train` (micro configuration, a few steps), evaluated by
    `pcfbench run` at kitti-1s: finite depths for every future sweep, guided or not."""
    import pandas as pd

    from pcfbench.cli import build_cli

    runner, cli = CliRunner(), build_cli()
    r = runner.invoke(cli, ["train", "bevworld-latent-copy:config=micro,steps=2", "--dataset", f"kitti={kitti}"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(cli, ["train", f"bevworld:{MICRO},steps=2,cond_dropout=0.5", "--dataset", f"kitti={kitti}"])
    assert r.exit_code == 0, r.output
    args = ["run", "-m", "bevworld-latent-copy:config=micro,steps=2",
            "-m", f"bevworld:{MICRO},steps=2,cond_dropout=0.5",
            "-m", f"bevworld:{MICRO},steps=2,cond_dropout=0.5,ddim_steps=2,guidance=2",
            "--train-on", f"kitti={kitti}", "-d", f"kitti={kitti}", "-s", "kitti-1s", "--limit", "1", "-q",
            "--store", str(tmp_path / "store"), "--reports", str(tmp_path / "rep")]
    r = runner.invoke(cli, args)
    assert r.exit_code == 0, r.output
    cells = sorted((tmp_path / "store").rglob("cell.json"))
    assert len(cells) == 3
    for cell in cells:
        df = pd.concat([pd.read_parquet(p) for p in sorted((cell.parent / "rows").glob("*.parquet"))])
        assert len(df) == 5 and np.isfinite(df["l1_mean"].to_numpy(dtype=float)).all(), json.loads(cell.read_text())


def test_in_the_default_run_once_shipped(monkeypatch):
    import pcfbench.training.checkpoints as cks
    from pcfbench.cli import _selected_methods
    from pcfbench.plugins import get_plugins

    monkeypatch.setattr(cks, "ready_shipped", lambda *a, **k: object())
    names = {m.name for m in _selected_methods(get_plugins(), ())}
    assert {"occworld", "bevworld"} <= names and "bevworld-latent-copy" not in names  # budget: docs/bevworld.md


@pytest.mark.parametrize("frame", ["own", "t0"])
def test_world_inputs_encode_each_past_sweep_in_the_frame(tmp_path, monkeypatch, frame):
    """The forecast's past latents are each past sweep encoded in its own sensor frame (``own``)
    or moved into the t=0 sensor frame (``t0``), as the training windows encode them; the poses
    are every sensor's in the t=0 frame."""
    from conftest import write_tiny_kitti

    from pcfbench.methods.bevworld import forecaster as fc
    from pcfbench.methods.bevworld.tokenizer import LatentTokenizer
    from pcfbench.methods.copilot4d.data import open_dataset
    from pcfbench.plugins import get_setting
    from pcfbench.protocol import SampleBuilder

    def centroid(model, points, T_frame_sensor=None):  # a stand-in encoder: the moved sweep's centroid
        p = fc.moved(points, T_frame_sensor).astype(np.float64).mean(0)
        return torch.from_numpy(np.resize(p, (16, 16, 4))).float()

    monkeypatch.setattr(fc, "encode_sweep", centroid)
    root = write_tiny_kitti(tmp_path / "kitti", sequences=("08",), num_sweeps=24)
    builder = SampleBuilder(open_dataset("kitti", root), get_setting("kitti-1s"))
    seq_name, ref = builder.sample_keys("test")[0]
    sample, _ = builder.build(seq_name, ref)
    m = fc.BevWorld(fc.BevWorldOptions(config="micro", frame=frame))
    m.tokenizer = LatentTokenizer(m.tok_cfg)
    m.tokenizer.latent_mean.fill_(1.0)
    m.tokenizer.latent_var.fill_(4.0)
    maps, poses, T_s0_ref = m.world_inputs(sample.for_method())
    seq = builder.sequence(seq_name)
    P = m.world_cfg.n_past
    for j, i in enumerate(range(ref - (P - 1) * 2, ref + 1, 2)):
        T_s0_i = np.linalg.inv(seq.T_world_sensor[ref]) @ seq.T_world_sensor[i]
        want = centroid(None, builder.points_sensor(seq, i), None if frame == "own" else T_s0_i)
        torch.testing.assert_close(maps[j], (want - 1.0) / np.sqrt(4.0 + 1e-6), rtol=0, atol=1e-3)
        assert np.allclose(poses[j].numpy(), T_s0_i, atol=1e-6)
    assert np.allclose(poses[P].numpy(), np.linalg.inv(seq.T_world_sensor[ref]) @ seq.T_world_sensor[ref + 2], atol=1e-6)
