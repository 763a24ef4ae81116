"""Copilot4D world model as trained methods (copilot4d, copilot4d-maskgit): options, training
windows in the t=0 frame, train/resume through the TrainingRun surface, checkpoint refusals,
the context window of settings unlike training's, and forecasts through the harness."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from pcfbench.errors import PcfbenchError
from pcfbench.method import resolve_method
from pcfbench.methods.copilot4d import config as tok_config
from pcfbench.methods.copilot4d import world_config
from pcfbench.methods.copilot4d.forecaster import Copilot4D, Copilot4DMaskGIT, build_windows
from pcfbench.methods.copilot4d.world import WorldEnsemble
from pcfbench.training.tokenized import tensor_digest

# the same architectures, small enough for seconds: 8 x 8 tokens of 64 codes, 2 past + 1 future
MICRO_TOK = tok_config.TINY.with_overrides(
    name="micro", x_range=(-25.6, 25.6), y_range=(-25.6, 25.6), grid_xy=64, grid_z=16, nfg_z=16, nfg_up=2,
    pointnet_dim=16, bev_dim=16, patch_size=4, dims=(16, 32), heads=(2, 4), depths=(2, 2), window=4,
    codebook_size=64, code_dim=16, nfg_dim=8, rays_per_step=256, samples_per_ray=16, skip_pool=4, warmup=10, decay_steps=200,
    max_steps=200, checkpoint_every=2, log_every=1,
)
MICRO_WORLD = world_config.WorldModelConfig(
    name="micro", codebook_size=64, token_grid=8, n_past=2, n_future=1,
    dims=(16, 16, 16), heads=(1, 1, 1), windows=(4, 4, 2), groups_down=(1, 1, 1), groups_up=(1, 1),
    mlp_ratio=2.0, lr=3e-3, warmup=5, decay_steps=200, max_steps=200,
)
MICRO_TRAIN = "config=micro,strides=1,anchor_every=4,tokenizer_steps=2"
MICRO = MICRO_TRAIN + ",sampling_steps=2"


@pytest.fixture
def micro(monkeypatch, tmp_path):
    monkeypatch.setitem(tok_config.CONFIGS, "micro", MICRO_TOK)
    monkeypatch.setitem(world_config.CONFIGS, "micro", MICRO_WORLD)
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


def _tokenizer(root):
    return _train("copilot4d-token-copy:config=micro,steps=2", root)


# --------------------------------------------------------------------------- options
def test_options_are_typed_and_checked():
    s = resolve_method("copilot4d:cfg_weight=1,sampling_steps=3,strides=2/6,seed=4")
    assert (s.options.cfg_weight, s.options.sampling_steps, s.options.strides, s.options.seed) == (1.0, 3, (2, 6), 4)
    # the defaults: the shipped world models' training (issue 42: tiny-window, every window), the
    # paper's sampling (K = 10, top-3, w = 2); the default run samples one arg-max step
    d = resolve_method("copilot4d-maskgit").options
    assert (d.cfg_weight, d.sampling_steps, d.config, d.anchor_every, d.frame) == (2.0, 10, "tiny-window", 1, "t0")
    assert (d.top_k, resolve_method("copilot4d:top_k=1").options.top_k) == (3, 1)
    for bad in ("cfg_weight=-1", "sampling_steps=0", "top_k=0", "cfg_weight=x", "threshold=1", "strides=0", "bogus=1",
                "readout=mean"):
        with pytest.raises(PcfbenchError):
            resolve_method(f"copilot4d:{bad}")
    with pytest.raises(PcfbenchError, match="huge"):
        Copilot4D(resolve_method("copilot4d:config=huge").options)
    assert Copilot4DMaskGIT().variant.name == "maskgit" and Copilot4D().variant.name == "copilot4d"
    assert not Copilot4DMaskGIT().variant.revise and Copilot4D().variant.revise


# --------------------------------------------------------------------------- training windows
class _Seq:
    def __init__(self, n):
        self.T_world_sensor = np.repeat(np.eye(4)[None], n, 0)
        self.T_world_sensor[:, 0, 3] = np.arange(n) * 2.0  # 2 m forward per sweep
        self.n = n

    def __len__(self):
        return self.n

    def load_points(self, i):  # one point 10 m ahead of the sensor, tagged by its index in z
        return np.array([[10.0, 0.0, i / 100.0]], np.float32)


class _Adapter:
    name = "toy"

    class ego_box:  # noqa: N801
        @staticmethod
        def remove(p):
            return p

    def sequence_names(self, split):
        return ["a"]

    def sequence(self, name):
        return _Seq(12)


def test_windows_are_tokenized_in_the_t0_frame(monkeypatch, tmp_path):
    """Window (stride s, anchor i) holds sweeps i + (j - n_past + 1) s, each moved into sweep i's
    sensor frame before tokenizing; its poses are each frame's pose in that frame."""
    from pcfbench.methods.copilot4d import evaluate

    seen = []

    def fake_tokenize(model, pts):  # code = where the point lands, in metres (x), and its index
        seen.append((float(pts[0, 0]), round(float(pts[0, 2]) * 100)))
        return torch.full((2, 2), int(round(pts[0, 0])))

    monkeypatch.setattr(evaluate, "tokenize_sweep", fake_tokenize)
    tok = type("Tok", (), {"cfg": type("C", (), {"bev_tokens": 2})()})()
    w = build_windows(tok, _Adapter(), "train", 2, 1, (2,), 3, tmp_path / "c", log=lambda *_: None)
    # n = 12, stride 2: anchors 2, 5 (every 3rd from (n_past - 1) s = 2, while i + s < 12)
    anchors = [2, 5, 8]
    assert w["tokens"].shape == (3, 3, 2, 2) and list(w["stride"]) == [2, 2, 2]
    for a, i in enumerate(anchors):
        frames = [i - 2, i, i + 2]
        assert [int(w["tokens"][a, j, 0, 0]) for j in range(3)] == [10 + 2 * (k - i) for k in frames]
        np.testing.assert_allclose(w["poses"][a, :, 0, 3], [2.0 * (k - i) for k in frames])
    assert [k for _, k in seen] == [k for i in anchors for k in (i - 2, i, i + 2)]
    # where each frame comes from: the sequence and the sweep index
    assert list(w["sequences"]) == ["a"] and list(w["sequence"]) == [0, 0, 0]
    assert w["sweeps"].tolist() == [[i - 2, i, i + 2] for i in anchors]
    # cached: a second call tokenizes nothing and returns the same arrays
    seen.clear()
    w2 = build_windows(tok, _Adapter(), "train", 2, 1, (2,), 3, tmp_path / "c", log=lambda *_: None)
    assert not seen and np.array_equal(w2["tokens"], w["tokens"]) and np.array_equal(w2["poses"], w["poses"])
    assert np.array_equal(w2["sweeps"], w["sweeps"]) and np.array_equal(w2["sequence"], w["sequence"])
    with pytest.raises(PcfbenchError, match="no sequence is long enough"):
        build_windows(tok, _Adapter(), "train", 5, 5, (2,), 1, None, log=lambda *_: None)


def test_window_sweeps_name_the_sweeps_whose_poses_the_windows_hold(monkeypatch, tmp_path):
    """The provenance (``sequence``, ``sweeps``) names, for every frame of every window, the sweep
    whose pose the window holds: ``poses[a, j]`` is T_s0_k = inv(T_world_sensor[i]) T_world_sensor[k]
    for k = ``sweeps[a, j]`` and the anchor i = ``sweeps[a, n_past - 1]``, on a drive that turns
    and changes speed, at two strides, in both frames, built and read back from the cache (which
    keeps no anchors)."""
    from pcfbench.methods.copilot4d import evaluate
    from pcfbench.methods.copilot4d.forecaster import window_sweeps

    rng = np.random.default_rng(3)
    lengths = {"a": 23, "b": 17}
    drives = {}
    for name, n in lengths.items():
        yaw, xy = np.cumsum(rng.uniform(-0.2, 0.2, n)), np.cumsum(rng.uniform(0.5, 3.0, (n, 2)), axis=0)
        T = np.repeat(np.eye(4)[None], n, 0)
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
        T[:, :2, 3], T[:, 2, 3] = xy, rng.uniform(-1, 1, n)
        drives[name] = T

    class Seq(_Seq):
        def __init__(self, name):
            super().__init__(lengths[name])
            self.T_world_sensor = drives[name]

    class Adapter(_Adapter):
        def sequence_names(self, split):
            return list(lengths)

        def sequence(self, name):
            return Seq(name)

    monkeypatch.setattr(evaluate, "tokenize_sweep", lambda model, pts: torch.zeros((2, 2), dtype=torch.int64))
    tok = type("Tok", (), {"cfg": type("C", (), {"bev_tokens": 2})()})()
    n_past, n_future, strides, every = 3, 2, (1, 3), 2
    for frame in ("t0", "own"):
        built = [build_windows(tok, Adapter(), "train", n_past, n_future, strides, every, tmp_path / "c",
                               log=lambda *_: None, frame=frame) for _ in range(2)]  # the second from the cache
        for w in built:
            assert w["sweeps"].shape == (len(w["poses"]), n_past + n_future) and list(w["sequences"]) == ["a", "b"]
            for a in range(len(w["poses"])):
                T = drives[str(w["sequences"][w["sequence"][a]])]
                i = w["sweeps"][a, n_past - 1]
                for j, k in enumerate(w["sweeps"][a]):
                    np.testing.assert_allclose(w["poses"][a, j], np.linalg.inv(T[i]) @ T[k], atol=1e-5)
            # every window that fits: per sequence and stride, (n - n_future s - (n_past - 1) s) / every, rounded up
            assert len(w["poses"]) == sum(-(-(n - (n_future + n_past - 1) * s) // every)
                                          for n in lengths.values() for s in strides)
        np.testing.assert_array_equal(built[0]["sweeps"], built[1]["sweeps"])
    assert window_sweeps(2, 1, 2, 3, n_sweeps=12).tolist() == [[0, 2, 4], [3, 5, 7], [6, 8, 10]]
    np.testing.assert_array_equal(window_sweeps(2, 1, 2, 3, n_windows=2), window_sweeps(2, 1, 2, 3, n_sweeps=12)[:2])
    with pytest.raises(PcfbenchError, match="exactly one"):
        window_sweeps(2, 1, 2, 3)


def test_windows_in_their_own_frame_keep_each_sweep_sensor_centred(monkeypatch, tmp_path):
    """frame=own: each sweep is tokenized as the sensor saw it (the point 10 m ahead stays 10 m
    ahead in every frame), once however many windows hold it, the poses are still each frame's
    pose in the t=0 frame, and the cache keeps the two frames apart."""
    from pcfbench.methods.copilot4d import evaluate

    seen, which = [], []

    def fake_tokenize(model, pts):
        seen.append(float(pts[0, 0]))
        which.append(round(float(pts[0, 2]) * 100))
        return torch.full((2, 2), int(round(pts[0, 0])))

    monkeypatch.setattr(evaluate, "tokenize_sweep", fake_tokenize)
    tok = type("Tok", (), {"cfg": type("C", (), {"bev_tokens": 2})()})()
    t0 = build_windows(tok, _Adapter(), "train", 2, 1, (2,), 3, tmp_path / "c", log=lambda *_: None)
    seen.clear()
    own = build_windows(tok, _Adapter(), "train", 2, 1, (2,), 3, tmp_path / "c", log=lambda *_: None, frame="own")
    assert seen and set(seen) == {10.0} and np.all(own["tokens"] == 10)
    which.clear()  # every sweep of every window at anchors 2..10 (spacing 1), stride 2: sweeps 0..11, once each
    every = build_windows(tok, _Adapter(), "train", 2, 1, (2,), 1, tmp_path / "c", log=lambda *_: None, frame="own")
    assert len(every["tokens"]) == 8 and sorted(which) == list(range(12))
    np.testing.assert_array_equal(own["poses"], t0["poses"])
    assert not np.array_equal(own["tokens"], t0["tokens"])
    assert sorted(p.name for p in (tmp_path / "c").iterdir()) == ["P2F1-s2-every1-own", "P2F1-s2-every3",
                                                                 "P2F1-s2-every3-own"]


def test_own_frame_forecasts_tokenize_the_past_and_render_the_future_in_each_sensor_frame(monkeypatch):
    """frame=own at inference: each past sweep is tokenized in its own sensor frame, and each
    future map is rendered with the query moved into that future sensor's frame (origin 0)."""
    from pcfbench.data import RayQuery, Sample
    from pcfbench.methods.copilot4d import evaluate

    P, F = 2, 2
    poses = np.repeat(np.eye(4)[None], P + F, 0)
    poses[:, 0, 3] = np.arange(P + F) * 3.0 + 50.0  # sensors 3 m apart, the reference 50 m away
    pts = tuple(np.array([[poses[k, 0, 3] + 10.0, 0.0, 0.0]], np.float32) for k in range(P))  # 10 m ahead, ref frame
    q = tuple(RayQuery(poses[P + f, :3, 3].copy(), np.array([[1.0, 0, 0]], np.float32)) for f in range(F))
    s = Sample("s/1", "toy", "s", 1, pts, poses[:P], np.arange(P), poses[P:], np.arange(F), q)
    tokenized, origins = [], []
    monkeypatch.setattr(evaluate, "tokenize_sweep", lambda m, p: tokenized.append(p.copy()) or torch.zeros(2, 2))
    monkeypatch.setattr(evaluate, "render_codes",
                        lambda m, c, d, origin=None, **kw: origins.append(np.asarray(origin)) or np.ones(len(d)))
    for frame, want_x, want_o in (("own", [10.0, 10.0], [0.0, 0.0]), ("t0", [7.0, 10.0], [3.0, 6.0])):
        m = Copilot4D(resolve_method(f"copilot4d:frame={frame}").options)
        m.world, m.tokenizer = torch.nn.Linear(1, 1), torch.nn.Linear(1, 1)
        monkeypatch.setattr(m, "forecast_tokens", lambda smp: ([torch.zeros(2, 2)] * F, None,
                                                                np.linalg.inv(smp.past_T_ref_sensor[-1])))
        tokenized.clear(), origins.clear()
        seq, _, _ = m.world_inputs(s)
        assert [float(p[0, 0]) for p in tokenized] == pytest.approx(want_x)
        m.forecast(s)
        assert [float(o[0]) for o in origins] == pytest.approx(want_o)
    with pytest.raises(PcfbenchError, match="frame='moved'"):
        resolve_method("copilot4d:frame=moved")


# --------------------------------------------------------------------------- the context window
class _Recorder(torch.nn.Module):
    """A world model that records the temporal positions and poses it is given."""

    def __init__(self, cfg):
        super().__init__()
        self.cfg, self.mask_token = cfg, cfg.codebook_size
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.calls = []

    def forward(self, tokens, poses, mask, frame_index=None, past_kv=None, return_kv=False):
        # what the frames attend to: the cached frames' positions and x, then their own
        seen = ([], []) if past_kv is None else (past_kv.positions, past_kv.xs)
        self.calls.append((frame_index.tolist(), poses[0, :, 0, 3].tolist(), return_kv, seen))
        out = torch.zeros(*tokens.shape, self.cfg.codebook_size)
        if return_kv:
            kv = type("KV", (), {"frames": (past_kv.frames if past_kv else 0) + tokens.shape[1],
                                 "batch": tokens.shape[0], "kv": [], "positions": seen[0] + frame_index.tolist(),
                                 "xs": seen[1] + poses[0, :, 0, 3].tolist()})()
            return out, kv
        return out


@pytest.mark.parametrize("P,F", [(2, 2), (5, 5), (6, 6)])
def test_context_positions_follow_training(P, F, monkeypatch):
    """t=0 keeps its training position (n_past - 1) while past + future fit the trained
    sequence; beyond it the context slides (the newest n_frames - 1 frames)."""
    from pcfbench.data import RayQuery, Sample
    from pcfbench.methods.copilot4d import evaluate

    monkeypatch.setattr(evaluate, "tokenize_sweep", lambda m, p: torch.zeros(4, 4, dtype=torch.long))
    cfg = world_config.WorldModelConfig(name="r", codebook_size=8, token_grid=4, n_past=5, n_future=5,
                                        dims=(8, 8, 8), heads=(1, 1, 1), windows=(4, 2, 1))
    m = Copilot4D()
    m.world_cfg, m.world = cfg, _Recorder(cfg)
    m.options = resolve_method("copilot4d:sampling_steps=1,cfg_weight=0").options
    x = np.arange(P + F, dtype=np.float64) - (P - 1)  # frame k at x = k - (P - 1): t=0 at 0
    poses = np.repeat(np.eye(4)[None], P + F, 0)
    poses[:, 0, 3] = x + 100.0  # a reference frame 100 m away from t=0's sensor
    q = RayQuery(np.zeros(3), np.array([[1.0, 0, 0]], np.float32))
    s = Sample("s/1", "toy", "s", 1, tuple(np.zeros((1, 3), np.float32) for _ in range(P)), poses[:P],
               np.arange(P), poses[P:], np.arange(F), (q,) * F)
    codes, rel, _ = m.forecast_tokens(s)
    assert len(codes) == F
    np.testing.assert_allclose(rel[:, 0, 3], x[P:])  # future poses in the t=0 sensor frame
    steps = [c for c in m.world.calls if not c[2]]  # the sampling passes (one step each), on the cached context
    assert len(steps) == F
    for f in range(F):
        used_past = min(P, 5)
        n_ctx = min(used_past + f, 9)
        first = (5 - used_past) if used_past + f < 10 else 0
        first = min(first, 9 - n_ctx)
        assert steps[f][3][0] == list(range(first, first + n_ctx))  # the context's positions ...
        assert steps[f][3][1] == pytest.approx(list(x[P + f - n_ctx: P + f]))  # ... and poses
        assert steps[f][0] == [first + n_ctx]
        assert steps[f][1] == [pytest.approx(x[P + f])]


# --------------------------------------------------------------------------- training and checkpoints
def test_missing_tokenizer_is_one_error_with_the_command(micro, kitti):
    from pcfbench.training import CheckpointError

    with pytest.raises(CheckpointError, match=r"pcfbench train copilot4d-token-copy:config=micro,steps=2"):
        _train(f"copilot4d:{MICRO},steps=2", kitti)


def test_train_resume_continues_the_same_curve(micro, kitti, monkeypatch, tmp_path):
    """Stopped after one step (--max-minutes 0) and resumed: the curve and weights of an
    uninterrupted run; the checkpoint holds the world model and its tokenizer."""
    _tokenizer(kitti)
    spec = f"copilot4d:{MICRO},steps=3"
    first = _train(spec, kitti, max_minutes=0)
    assert first.steps == 1 and not first.manifest["complete"]
    resumed = _train(spec, kitti)
    assert resumed.steps == 3 and resumed.manifest["complete"]
    curve = (resumed.dir / "curve.csv").read_text()  # the same folder is overwritten by the straight run
    straight = _train(spec, kitti, fresh=True)
    assert _same_losses(straight.dir / "curve.csv", resumed.dir / "curve.csv", curve)
    w = straight.load_weights()
    for k, v in resumed.load_weights().items():
        assert torch.equal(v, w[k]), k
    conf = straight.manifest["config"]
    assert {k.split(".")[0] for k in w} == {"world", "tokenizer"}
    assert conf["variant"] == "copilot4d" and conf["world"]["codebook_size"] == 64
    tok = resolve_method("copilot4d-token-copy:config=micro,steps=2")
    from pcfbench.training import checkpoint_for

    tok_ck = checkpoint_for(tok, train_on=f"kitti={kitti}", progress=False)
    assert conf["tokenizer_sha256"] == tok_ck.sha256
    assert conf["tokenizer_digest"] == tensor_digest(tok_ck.load_weights())


def _same_losses(a, b, b_text):
    """The two curves agree step for step on everything but the timings."""
    import csv
    import io

    ra, rb = list(csv.DictReader(open(a))), list(csv.DictReader(io.StringIO(b_text)))
    keys = ("step", "loss", "accuracy", "masked_accuracy", "grad_norm")
    return [[r[k] for k in keys] for r in ra] == [[r[k] for k in keys] for r in rb]


def test_checkpoint_refused_when_its_tokenizer_differs(micro, kitti):
    import io

    from pcfbench.training import Checkpoint, CheckpointError
    from pcfbench.training.checkpoints import sha256_hex

    _tokenizer(kitti)
    ck = _train(f"copilot4d-maskgit:{MICRO},steps=1", kitti)
    m = Copilot4DMaskGIT(resolve_method(f"copilot4d-maskgit:{MICRO},steps=1").options)
    m.load(ck)
    assert m.world is not None and m.tokenizer is not None
    with pytest.raises(CheckpointError, match="holds a maskgit world model"):
        Copilot4D(resolve_method(f"copilot4d:{MICRO},steps=1").options).load(ck)
    # another tokenizer's weights in the checkpoint (its files re-hashed, so only the digest tells)
    w = ck.load_weights()
    key = next(k for k in w if k.startswith("tokenizer.") and w[k].is_floating_point())
    w[key] = w[key] + 0.5
    buf = io.BytesIO()
    torch.save(w, buf)
    ck.weights_path.write_bytes(buf.getvalue())
    manifest = dict(ck.manifest, weights_sha256=sha256_hex(buf.getvalue()))
    ck.manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(CheckpointError, match="tokenizer weights are not the tokenizer it was trained with"):
        m.load(Checkpoint.open(ck.dir))
    # resuming (an incomplete checkpoint: a complete one is returned as it is) on the tokens of
    # a retrained tokenizer is refused
    manifest["config"] = dict(manifest["config"], tokenizer_sha256="0" * 64)
    manifest["complete"] = False
    ck.manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(CheckpointError, match="trained on the tokens of tokenizer 000000000000.*--fresh"):
        _train(f"copilot4d-maskgit:{MICRO},steps=1", kitti)


def test_init_steps_goes_on_from_the_shorter_trainings_weights(micro, kitti, monkeypatch):
    """copilot4d:init_steps=N trains from the complete checkpoint of the same options with
    steps=N: a missing one is one error naming its train command; the weights it starts from are
    that checkpoint's, recorded in its manifest; a resumed training whose start changed since is
    refused; init_steps=0 is the options (and checkpoint) of before; a chain a/b goes on from the
    training with steps=b that went on from a."""
    from pcfbench.methods.copilot4d import forecaster

    _tokenizer(kitti)
    spec = f"copilot4d:{MICRO_TRAIN},steps=2,init_steps=1"
    with pytest.raises(PcfbenchError, match=r"init_steps=1 goes on.*pcfbench train copilot4d:.*steps=1"):
        _train(spec, kitti)
    start = _train(f"copilot4d:{MICRO_TRAIN},steps=1", kitti)
    assert resolve_method(f"copilot4d:{MICRO_TRAIN},steps=1,init_steps=0").options_hash == \
        resolve_method(f"copilot4d:{MICRO_TRAIN},steps=1").options_hash
    assert "init_from" not in start.manifest["config"]
    built = {}
    original = forecaster.train_world

    def spy(model, *a, **kw):
        built.update(model().state_dict())
        return original(model, *a, **kw)

    monkeypatch.setattr(forecaster, "train_world", spy)
    ck = _train(spec, kitti)
    w = start.load_weights()
    assert set(built) == {k[len("world."):] for k in w if k.startswith("world.")}
    for k, v in built.items():
        assert torch.equal(v, w[f"world.{k}"]), k
    assert ck.dir != start.dir and ck.steps == 2 and ck.manifest["complete"]
    assert ck.manifest["config"]["init_from"] == {"steps": 1, "weights_sha256": start.sha256,
                                                  "checkpoint": str(start.manifest_path)}
    # a chain: init_steps=1/2 goes on from the 2 steps that went on from 1 (3 in all)
    assert resolve_method(f"copilot4d:{MICRO_TRAIN},steps=1,init_steps=1/2").create().start_spec().options_hash \
        == resolve_method(spec).options_hash
    with pytest.raises(PcfbenchError, match=r"init_steps=2/1 goes on from a complete training of 3 steps: "
                                            r".*pcfbench train copilot4d:.*init_steps=2,steps=1"):
        _train(f"copilot4d:{MICRO_TRAIN},steps=1,init_steps=2/1", kitti)
    built.clear()
    chained = _train(f"copilot4d:{MICRO_TRAIN},steps=1,init_steps=1/2", kitti)
    w = ck.load_weights()
    for k, v in built.items():
        assert torch.equal(v, w[f"world.{k}"]), k
    assert chained.manifest["config"]["init_from"] == {"steps": 3, "weights_sha256": ck.sha256,
                                                       "checkpoint": str(ck.manifest_path)}
    for bad in ("1/", "1/0"):
        with pytest.raises(PcfbenchError, match=f"init_steps={bad}: .*a chain of two or more, none of them 0"):
            resolve_method(f"copilot4d:{MICRO_TRAIN},init_steps={bad}")
    manifest = dict(ck.manifest, complete=False)
    manifest["config"] = dict(manifest["config"], init_from=dict(manifest["config"]["init_from"],
                                                                 weights_sha256="0" * 64))
    ck.manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(PcfbenchError, match="started from weights 000000000000.*--fresh"):
        _train(spec, kitti)


def _timed_sample(spacing_s: float, points: int = 400, seed: int = 0, rays: int = 1):
    """A sample of 2 past sweeps and 1 future one, ``spacing_s`` apart, 0.5 m forward a frame,
    queried along ``rays`` level rays around the sensor (the first straight ahead)."""
    from pcfbench.data import RayQuery, Sample

    rng = np.random.default_rng(seed)
    poses = np.repeat(np.eye(4)[None], 3, 0)
    poses[:, 0, 3] = [-0.5, 0.0, 0.5]
    past = tuple((rng.uniform(-20, 20, (points, 3)) * [1, 1, 0.1]).astype(np.float32) for _ in range(2))
    ts = (np.arange(3) * spacing_s * 1e9).astype(np.int64)
    yaw = np.arange(rays) * 2 * np.pi / rays
    q = RayQuery(poses[2, :3, 3].copy(), np.stack([np.cos(yaw), np.sin(yaw), 0 * yaw], 1).astype(np.float32))
    return Sample(f"s/{spacing_s}", "toy", "s", 1, past, poses[:2], ts[:2], poses[2:], ts[2:], (q,))


def test_stride_models_put_one_network_per_stride_together(micro, kitti):
    """stride_models=S (the paper's one model per horizon): the training of the same options on
    stride S alone (steps=stride_steps) forecasts the samples whose frame spacing is nearest S
    sweeps', the training on every stride the others. Its one command trains each part first
    (their own checkpoints), then puts their very weights together; a sample forecasts exactly
    as the part of its spacing does alone. Old options keep their identity; bad ones are refused."""
    micro = MICRO.replace("strides=1,", "")
    base, own = f"copilot4d:{micro},strides=1/2,steps=1", f"copilot4d:{micro},strides=2,steps=2"
    assert resolve_method(f"{base},stride_models=").options_hash == resolve_method(base).options_hash
    _tokenizer(kitti)
    ck = _train(f"{base},stride_models=2,stride_steps=2", kitti)
    parts = {spec: _train(spec, kitti) for spec in (base, own)}  # trained by the command above: found complete
    assert all(p.manifest["complete"] for p in parts.values())
    nets = ck.manifest["config"]["networks"]
    assert [(n["strides"], n["prefix"], n["steps"], n["weights_sha256"]) for n in nets] == [
        ([1], "world.", 1, parts[base].sha256), ([2], "world_s2.", 2, parts[own].sha256)]
    period = ck.manifest["config"]["sweep_period_s"]
    assert period == pytest.approx(0.1) and [n["frame_interval_s"] for n in nets] == [[period], [2 * period]]
    w = ck.load_weights()
    for spec, prefix in ((base, "world."), (own, "world_s2.")):
        part = {k[len("world."):]: v for k, v in parts[spec].load_weights().items() if k.startswith("world.")}
        assert {k[len(prefix):] for k in w if k.startswith(prefix)} == set(part)
        for k, v in part.items():
            assert torch.equal(w[prefix + k], v), (prefix, k)
    both = resolve_method(f"{base},stride_models=2,stride_steps=2").create()
    both.load(ck)
    alone = {}
    for spec in (base, own):
        alone[spec] = resolve_method(spec).create()
        alone[spec].load(parts[spec])
    for spacing, spec in ((0.1, base), (0.13, base), (0.2, own), (0.6, own)):
        sample = _timed_sample(spacing)
        got, want = both.forecast_tokens(sample)[0], alone[spec].forecast_tokens(sample)[0]
        assert all(torch.equal(a, b) for a, b in zip(got, want)), (spacing, spec)
    assert not all(torch.equal(a, b) for a, b in zip(alone[base].forecast_tokens(_timed_sample(0.2))[0],
                                                     alone[own].forecast_tokens(_timed_sample(0.2))[0]))
    with pytest.raises(PcfbenchError, match=r"sample s/0.0: future timestamps do not increase"):
        both.forecast_tokens(_timed_sample(0.0))  # no spacing to choose by: one error naming the sample
    # stride_cfg_weight / stride_soft_mix (inference only): the sampling of a stride's own network's samples
    tuned = resolve_method(f"{base},stride_models=2,stride_steps=2,stride_cfg_weight=0.5,stride_soft_mix=0.7").create()
    tuned.load(ck)
    for spacing, spec, w in ((0.1, base, 2.0), (0.2, own, 0.5)):
        assert tuned.sampling_for(tuned.network_for(_timed_sample(spacing))) == ((2.0, 0.0) if spec == base
                                                                                 else (0.5, 0.7))
        want = resolve_method(f"{spec},cfg_weight={w}").create()
        want.load(parts[spec])
        assert all(torch.equal(a, b) for a, b in zip(tuned.forecast_tokens(_timed_sample(spacing))[0],
                                                     want.forecast_tokens(_timed_sample(spacing))[0])), spacing
    mixed = resolve_method(f"{own},soft_mix=0.7").create()
    mixed.load(parts[own])
    depths = {name: m.forecast(_timed_sample(0.2, rays=360)).depths for name, m in (("tuned", tuned), ("mixed", mixed),
                                                                          ("plain", alone[own]))}
    assert all(np.array_equal(a, b) for a, b in zip(depths["tuned"], depths["mixed"]))
    assert not all(np.array_equal(a, b) for a, b in zip(depths["tuned"], depths["plain"]))  # the mix tells
    # stride_ensemble (inference only): a stride of its own forecast by its network and the shared one together
    ens = resolve_method(f"{base},stride_models=2,stride_steps=2,stride_ensemble=true").create()
    ens.load(ck)
    assert all(torch.equal(a, b) for a, b in zip(ens.forecast_tokens(_timed_sample(0.1))[0],
                                                 alone[base].forecast_tokens(_timed_sample(0.1))[0]))
    together = ens.network_for(_timed_sample(0.2))
    assert isinstance(together, WorldEnsemble) and together is ens.network_for_stride(2)
    for member, spec in zip(together.members, (own, base)):
        want = alone[spec].world.state_dict()
        assert all(torch.equal(member.state_dict()[k], want[k]) for k in want), spec
    # one_pass (inference only): the forecast tokens are forecast_one_pass's, by the network the spacing picks
    from pcfbench.methods.copilot4d.diffusion import forecast_one_pass

    one = resolve_method(base.replace("sampling_steps=2", "sampling_steps=1")
                         + ",stride_models=2,stride_steps=2,one_pass=true,top_k=1").create()
    one.load(ck)
    for spacing, spec in ((0.1, base), (0.2, own)):
        sample = _timed_sample(spacing)
        seq, rel, _ = one.world_inputs(sample)
        want = forecast_one_pass(alone[spec].world, seq[None], rel[None], 1, n_frames=MICRO_WORLD.n_frames,
                                 n_past=MICRO_WORLD.n_past, guidance=2.0)
        assert all(torch.equal(a, b[0]) for a, b in zip(one.forecast_tokens(sample)[0], want)), spacing
    # by stride (the world report's windows): each stride's own network; a stride it has none for is refused
    for stride, spec in ((1, base), (2, own)):
        got, want = both.network_for_stride(stride).state_dict(), alone[spec].world.state_dict()
        assert all(torch.equal(got[k], want[k]) for k in want), stride
    with pytest.raises(PcfbenchError, match="networks for strides 1/2, not 3"):
        both.network_for_stride(3)
    # the training objective scores one network: refused for the two, naming the parts
    from pcfbench.cli import build_cli

    r = CliRunner().invoke(build_cli(), ["world-report", "--method", f"{base},stride_models=2,stride_steps=2",
                                         "--train-on", f"kitti={kitti}", "--dataset", f"kitti={kitti}",
                                         "--objective-draws", "1"])
    assert r.exit_code != 0 and "--objective-draws scores one network" in r.output, r.output
    # a part trained here on another tokenizer: one error with the command that retrains it
    manifest = dict(parts[own].manifest, config=dict(parts[own].manifest["config"], tokenizer_sha256="0" * 64))
    parts[own].manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(PcfbenchError, match=r"tokenizer weights 000000000000.*`pcfbench train copilot4d:anchor_every=4,"
                                            r"config=micro,steps=2,strides=2,tokenizer_steps=2 --dataset kitti=.* --fresh`"):
        _train(f"{base},stride_models=2,stride_steps=2", kitti, fresh=True)
    for bad, why in (("stride_models=3", "among strides=1/2"), ("stride_models=2/2", "distinct"),
                     ("stride_steps=2", "name stride_models too"), ("stride_ensemble=true", "name stride_models too"),
                     ("stride_models=1/2,stride_ensemble=true", "leaves none of strides=1/2"),
                     ("stride_soft_mix=0.5", "stride_soft_mix=0.5 applies to the stride_models"),
                     ("stride_models=2,stride_soft_mix=0.5,frame=own", "stride_soft_mix=0.5 mixes in"),
                     ("stride_models=2,init_steps=1", "init_steps")):
        with pytest.raises(PcfbenchError, match=why):
            resolve_method(f"{base},{bad}")


def test_world_report_scores_the_objective_on_trained_and_held_out_windows(micro, kitti, tmp_path):
    """`pcfbench world-report --objective-draws` on a trained micro model: the report holds the
    training curve's tail and both sets of windows; windows made with other window options than
    the training's (another count than the manifest's) are refused by name."""
    from pcfbench.cli import build_cli

    _tokenizer(kitti)
    spec = f"copilot4d:{MICRO_TRAIN},steps=2"
    ck = _train(spec, kitti)
    args = ["world-report", "--method", spec, "--train-on", f"kitti={kitti}", "--dataset", f"kitti={kitti}",
            "--split", "test", "--windows", "2", "--objective-draws", "1", "--no-forecast",
            "--reports", str(tmp_path / "rep")]
    r = CliRunner().invoke(build_cli(), args)
    assert r.exit_code == 0, r.output
    md = tmp_path / "rep" / "copilot4d" / f"world-objective-copilot4d-{ck.sha256[:12]}-on-kitti-test.md"
    text = md.read_text()
    assert "| training curve, steps 1-2 | mixture |" in text
    assert "| trained on: kitti:train | future | 2 (1) |" in text and "| held out: kitti:test | future |" in text
    assert not list((tmp_path / "rep" / "copilot4d").glob("world-tokens-*"))  # --no-forecast
    # the forecast's report says how the tokens were decoded: as the method's options decode a sample
    for n, (opts, decoded) in enumerate((("", "Algorithm 2, a frame at a time: 10 step(s), top-3"),
                                         (",sampling_steps=1,top_k=1,one_pass=true", "every future frame in one pass"))):
        fc = ["world-report", "--method", spec + opts, "--train-on", f"kitti={kitti}", "--dataset", f"kitti={kitti}",
              "--split", "test", "--windows", "1", "--reports", str(tmp_path / f"fc{n}")]
        r = CliRunner().invoke(build_cli(), fc)
        assert r.exit_code == 0, r.output
        (md,) = (tmp_path / f"fc{n}" / "copilot4d").glob("world-tokens-*.md")
        assert ("one_pass=True" in md.name) == bool(opts) and f"- decoded: {decoded}" in md.read_text(), opts
    # the windows it trained on are not held out
    same = [a if a != "test" else "train" for a in args]
    r = CliRunner().invoke(build_cli(), same)
    assert r.exit_code != 0 and "is the data" in r.output and "held-out windows" in r.output
    # the checkpoint's manifest says how many windows it trained on; a spec that makes others is refused
    manifest = json.loads(ck.manifest_path.read_text())
    manifest["config"]["windows"] += 1
    ck.manifest_path.write_text(json.dumps(manifest))
    r = CliRunner().invoke(build_cli(), args)
    assert r.exit_code != 0 and "window options differ from its training's" in r.output


def test_inference_options_reuse_the_trained_weights(micro, kitti):
    """copilot4d:cfg_weight=0 trains nothing new: its checkpoint is the one of the same
    training options (which embeds its tokenizer: the tokenizer's own checkpoint is not needed
    any more); a training option changed is another checkpoint."""
    import shutil

    from pcfbench.training import find_checkpoint, open_training_data

    tok = _tokenizer(kitti)
    base = _train(f"copilot4d:{MICRO_TRAIN},steps=2", kitti)
    shutil.rmtree(tok.dir)
    other = _train(f"copilot4d:{MICRO},steps=2,cfg_weight=0,top_k=1,seed=3,readout=expected,threshold=0.5", kitti)
    assert other.dir == base.dir and other.sha256 == base.sha256
    assert other.manifest["options"]["cfg_weight"] == 2.0  # the training options, inference ones at defaults
    spec = resolve_method(f"copilot4d:{MICRO},steps=3,cfg_weight=0")
    assert find_checkpoint(spec, open_training_data(f"kitti={kitti}", progress=False).train_on) is None


# --------------------------------------------------------------------------- through the harness
@pytest.mark.slow
def test_both_methods_forecast_through_the_harness(micro, kitti, tmp_path):
    """Trained through `pcfbench train` (tiny configuration, a few steps), evaluated by
    `pcfbench run` at kitti-1s in worker processes: finite depths for every future sweep, and
    the same numbers when the cells are recomputed (forecasts seeded by the sample id)."""
    import pandas as pd

    from pcfbench.cli import build_cli

    runner, cli = CliRunner(), build_cli()
    tiny = "config=tiny,strides=2,anchor_every=4,sampling_steps=2,tokenizer_steps=2,steps=2"
    r = runner.invoke(cli, ["train", f"copilot4d:{tiny}", "--dataset", f"kitti={kitti}"])
    assert r.exit_code != 0 and "pcfbench train copilot4d-token-copy:steps=2" in r.output
    r = runner.invoke(cli, ["train", "copilot4d-token-copy:steps=2", "--dataset", f"kitti={kitti}"])
    assert r.exit_code == 0, r.output
    for method in ("copilot4d", "copilot4d-maskgit"):
        r = runner.invoke(cli, ["train", f"{method}:{tiny}", "--dataset", f"kitti={kitti}"])
        assert r.exit_code == 0, r.output
    args = ["run", "-m", f"copilot4d:{tiny}", "-m", f"copilot4d-maskgit:{tiny}", "--train-on", f"kitti={kitti}",
            "-d", f"kitti={kitti}", "-s", "kitti-1s", "--limit", "1", "-q", "--store", str(tmp_path / "store"),
            "--reports", str(tmp_path / "rep")]
    r = runner.invoke(cli, args)
    assert r.exit_code == 0, r.output

    def rows():
        out = {}
        for cell in sorted((tmp_path / "store").rglob("cell.json")):
            method = json.loads(cell.read_text())["spec"]["method"]
            out[method] = pd.concat([pd.read_parquet(p) for p in sorted((cell.parent / "rows").glob("*.parquet"))])
        return out

    first = rows()
    assert set(first) == {"copilot4d", "copilot4d-maskgit"}
    for df in first.values():
        assert len(df) == 5 and np.isfinite(df["l1_mean"].to_numpy(dtype=float)).all()
    r = runner.invoke(cli, args[:3] + args[5:] + ["--force"])  # copilot4d again
    assert r.exit_code == 0, r.output
    for method, df in rows().items():
        pd.testing.assert_frame_equal(df[["l1_mean", "chamfer_nf"]].reset_index(drop=True),
                                      first[method][["l1_mean", "chamfer_nf"]].reset_index(drop=True))


def test_steps_option_sets_the_learning_rate_decay():
    """`steps=N` trains N steps and decays the learning rate over those N (to 10 % at N), not
    over the configuration's own max_steps: a longer run is a whole schedule, not a tail at
    the floor."""
    from pcfbench.methods.copilot4d.diffusion import lr_at

    default = Copilot4D(resolve_method("copilot4d").options)
    longer = Copilot4D(resolve_method("copilot4d:steps=1500").options)
    assert default.world_cfg.name == "tiny-window"
    assert default.training_steps() == world_config.TINY_WINDOW.max_steps == world_config.TINY_WINDOW.decay_steps == 600
    assert longer.training_steps() == 1500
    cfg = longer.world_cfg
    assert lr_at(cfg, 600) > 0.5 * cfg.lr  # the default schedule is at its floor by then
    assert lr_at(default.world_cfg, 600) == pytest.approx(0.1 * cfg.lr)
    assert lr_at(cfg, 1500) == pytest.approx(0.1 * cfg.lr)
    assert lr_at(cfg, 1499) > lr_at(cfg, 1500)


def test_top_k_reaches_the_sampler(monkeypatch):
    """`top_k` is handed to Algorithm 2 as given (1: arg max), with the other sampling options."""
    from pcfbench.data import RayQuery, Sample
    from pcfbench.methods.copilot4d import diffusion, evaluate

    seen = {}

    def fake(model, past, T_ref_sensor, n_future, **kw):
        seen.update(kw)
        return [torch.zeros(1, 4, 4, dtype=torch.long)] * n_future

    monkeypatch.setattr(diffusion, "forecast_sequence", fake)
    monkeypatch.setattr(evaluate, "tokenize_sweep", lambda m, p: torch.zeros(4, 4, dtype=torch.long))
    cfg = world_config.WorldModelConfig(name="r", codebook_size=8, token_grid=4, n_past=2, n_future=1,
                                        dims=(8, 8, 8), heads=(1, 1, 1), windows=(4, 2, 1))
    m = Copilot4D()
    m.world_cfg, m.world = cfg, torch.nn.Linear(1, 1)
    q = RayQuery(np.zeros(3), np.array([[1.0, 0, 0]], np.float32))
    poses = np.repeat(np.eye(4)[None], 3, 0)
    s = Sample("s/1", "toy", "s", 1, tuple(np.zeros((1, 3), np.float32) for _ in range(2)), poses[:2],
               np.arange(2), poses[2:], np.arange(1), (q,))
    for k in (1, 5):
        m.options = resolve_method(f"copilot4d:top_k={k},sampling_steps=4,cfg_weight=1").options
        m.forecast_tokens(s)
        assert (seen["top_k"], seen["steps"], seen["guidance"], seen["metric"]) == (k, 4, 1.0, None)
    # mbr: the codebook's Euclidean distances reach it; an inference option, quiet at its default
    m.tokenizer = torch.nn.Module()
    m.tokenizer.vq = torch.nn.Module()
    m.tokenizer.vq.codebook = torch.nn.Parameter(torch.tensor([[0.0, 0.0], [3.0, 4.0], [0.0, 1.0]]))
    m.options = resolve_method("copilot4d:mbr=true").options
    m.forecast_tokens(s)
    assert torch.allclose(seen["metric"], torch.tensor([[0.0, 5.0, 1.0], [5.0, 0.0, 4.2426405], [1.0, 4.2426405, 0.0]]))
    assert "mbr" in Copilot4D.inference_options
    assert resolve_method("copilot4d:mbr=false").options_hash == resolve_method("copilot4d").options_hash
    # change_confidence: handed on as given; an inference option, quiet at its default; frame t0 only
    assert seen["change_confidence"] == 0.0
    m.options = resolve_method("copilot4d:change_confidence=0.4").options
    m.forecast_tokens(s)
    assert seen["change_confidence"] == 0.4
    assert "change_confidence" in Copilot4D.inference_options
    assert resolve_method("copilot4d:change_confidence=0").options_hash == resolve_method("copilot4d").options_hash
    with pytest.raises(PcfbenchError, match="frame=t0"):
        resolve_method("copilot4d:frame=own,change_confidence=0.4")
    with pytest.raises(PcfbenchError, match="change_confidence"):
        resolve_method("copilot4d:change_confidence=1.5")


def test_soft_mix_renders_the_expected_embedding_mixed_with_the_t0_codes(monkeypatch):
    """Hand-built: codes e0 = (0, 0), e1 = (4, 0), e2 = (0, 8); a frame of two tokens whose last
    step gives p = (1/2, 1/2, 0) and (0, 0, 1), over a t=0 map of codes 2 and 0. soft_mix=1
    renders E_p[e] = (2, 0) and (0, 8); 0.5 adds half of e2 and e0: (1, 4) and (0, 4). The
    forecast renders those maps, its sampled codes going nowhere but the context."""
    from pcfbench.data import RayQuery, Sample
    from pcfbench.methods.copilot4d import diffusion, evaluate

    m = Copilot4D()
    m.tokenizer = torch.nn.Module()
    m.tokenizer.vq = torch.nn.Module()
    m.tokenizer.vq.codebook = torch.nn.Parameter(torch.tensor([[0.0, 0.0], [4.0, 0.0], [0.0, 8.0]]))
    logits = torch.tensor([[0.0, 0.0, -float("inf")], [-float("inf"), -float("inf"), 0.0]]).view(1, 1, 2, 3)
    copy = torch.tensor([[2, 0]])
    for mix, want in ((1.0, [[[2.0, 0.0], [0.0, 8.0]]]), (0.5, [[[1.0, 4.0], [0.0, 4.0]]])):
        m.options = resolve_method(f"copilot4d:soft_mix={mix}").options
        (got,) = m.soft_maps([logits], copy)
        assert torch.allclose(got, torch.tensor(want))
    # through forecast: the last step's logits of each frame and the t=0 map make the rendered maps
    def fake(model, past, T_ref_sensor, n_future, final_logits=None, **kw):
        if final_logits is not None:
            final_logits.extend([logits] * n_future)
        return [torch.ones(1, 1, 2, dtype=torch.long)] * n_future

    monkeypatch.setattr(diffusion, "forecast_sequence", fake)
    monkeypatch.setattr(evaluate, "tokenize_sweep", lambda m, p: copy)
    rendered = []
    monkeypatch.setattr(evaluate, "render_queries",
                        lambda tok, codes, sample, *a, **k: rendered.append(codes) or [np.ones(1)] * len(codes))
    m.world_cfg = world_config.WorldModelConfig(name="r", codebook_size=3, token_grid=4, n_past=2, n_future=1,
                                                dims=(8, 8, 8), heads=(1, 1, 1), windows=(4, 2, 1))
    m.world = torch.nn.Linear(1, 1)
    q = RayQuery(np.zeros(3), np.array([[1.0, 0, 0]], np.float32))
    poses = np.repeat(np.eye(4)[None], 3, 0)
    s = Sample("s/1", "toy", "s", 1, tuple(np.zeros((1, 3), np.float32) for _ in range(2)), poses[:2],
               np.arange(2), poses[2:], np.arange(1), (q,))
    m.forecast(s)
    assert torch.allclose(rendered[-1][0], torch.tensor([[[1.0, 4.0], [0.0, 4.0]]]))
    m.options = resolve_method("copilot4d").options
    m.forecast(s)
    assert rendered[-1][0].dtype == torch.long and (rendered[-1][0] == 1).all()
    # an inference option, quiet at its default; mixing in the t=0 map needs frame t0; not with the gate
    assert "soft_mix" in Copilot4D.inference_options
    assert resolve_method("copilot4d:soft_mix=0").options_hash == resolve_method("copilot4d").options_hash
    with pytest.raises(PcfbenchError, match="frame=t0"):
        resolve_method("copilot4d:frame=own,soft_mix=0.5")
    assert resolve_method("copilot4d:frame=own,soft_mix=1").options.soft_mix == 1.0
    with pytest.raises(PcfbenchError, match="one at a time"):
        resolve_method("copilot4d:soft_mix=0.5,change_confidence=0.5")


def test_a_map_of_code_embeddings_decodes_as_its_codes(micro, kitti):
    """``evaluate.decode`` of the codebook rows of a token map is the decode of the map itself."""
    from pcfbench.methods.copilot4d import evaluate
    from pcfbench.methods.copilot4d.train import load_tokenizer

    tok = load_tokenizer(_tokenizer(kitti), torch.device("cpu")).eval()
    codes = torch.randint(0, MICRO_TOK.codebook_size, (MICRO_TOK.bev_tokens, MICRO_TOK.bev_tokens),
                          generator=torch.Generator().manual_seed(0))
    hard, soft = evaluate.decode(tok, codes), evaluate.decode(tok, tok.vq.codebook.detach()[codes])
    for a, b in zip(hard, soft):
        assert torch.equal(a, b)
    # a float map that is not one of embeddings (codes as floats, a wrong width) is refused, not decoded
    for bad in (codes.float(), tok.vq.codebook.detach()[codes][..., :-1]):
        with pytest.raises(ValueError, match="code_dim"):
            evaluate.decode(tok, bad)


def test_the_world_model_ships_without_its_tokenizer_when_the_tokenizer_ships(micro, kitti, tmp_path, monkeypatch):
    """As occworld's and bevworld's (tests/training/test_world_on_tokenizer.py): shipped after the
    shipped token-copy checkpoint of the same data, copilot4d leaves out its copy of the tokenizer."""
    from pcfbench.methods.copilot4d.token_copy import TokenCopy
    from tests_helpers import check_ships_without_its_tokenizer

    for cls in (TokenCopy, Copilot4D):
        monkeypatch.setattr(cls, "shipped_checkpoints", str(tmp_path / "shipped"))
    check_ships_without_its_tokenizer("copilot4d-token-copy:config=micro,steps=2", f"copilot4d:{MICRO},steps=2", kitti)


# --------------------------------------------------------------------------- the default run
def test_the_default_run_holds_both_world_models_beside_their_own_token_copy(monkeypatch, capsys):
    """With their checkpoints ready (pretended here; the shipped ones in the package), a run of
    the default method set scores copilot4d and copilot4d-maskgit as they ship (their default
    training: tiny-window) decoded in one causal pass with one arg max per token and rendered with
    soft_mix=0.3 (copilot4d with a network of its own for kitti-3s's stride), and token-copy twice: its default (the
    shipped tiny tokenizer) and the world models' own tokenizer, tiny-window, each a row of its
    own. A copy not ready is left out by its whole spec, with the command that trains it."""
    import pcfbench.training.checkpoints as cks
    from pcfbench.cli import _selected_methods
    from pcfbench.plugins import get_plugins

    monkeypatch.setattr(cks, "ready_shipped", lambda *a, **k: object())
    picked = [(m.name, m.raw) for m in _selected_methods(get_plugins(), ())]
    one_step = {"sampling_steps": "1", "top_k": "1", "soft_mix": "0.3", "one_pass": "true"}
    per_horizon = {**one_step, "stride_models": "6", "stride_steps": "500"}  # copilot4d: kitti-3s's own network
    for spec in [("copilot4d", per_horizon), ("copilot4d-maskgit", one_step), ("copilot4d-token-copy", {}),
                 ("copilot4d-token-copy", {"config": "tiny-window"})]:
        assert picked.count(spec) == 1, spec
    for m in _selected_methods(get_plugins(), ()):  # both world models decode in one pass (stop 84)
        assert m.name not in ("copilot4d", "copilot4d-maskgit") or m.options.one_pass, m.text()
    world = resolve_method("copilot4d")
    assert world.create().tokenizer_spec().options == resolve_method("copilot4d-token-copy:config=tiny-window").options

    def not_shipped(spec, *a, **k):
        return None if (spec.name == "copilot4d-token-copy" and spec.raw) or spec.name == "copilot4d-maskgit" else object()

    monkeypatch.setattr(cks, "ready_shipped", not_shipped)
    monkeypatch.setattr(cks, "may_have_checkpoint", lambda *a, **k: False)  # nothing trained here either
    picked = [(m.name, m.raw) for m in _selected_methods(get_plugins(), ())]
    assert ("copilot4d-token-copy", {}) in picked and ("copilot4d-token-copy", {"config": "tiny-window"}) not in picked
    assert ("copilot4d", per_horizon) in picked and not any(name == "copilot4d-maskgit" for name, _ in picked)
    err = capsys.readouterr().err
    assert ("copilot4d-token-copy:config=tiny-window is not trained on synthetic-town-realistic:train yet "
            "(`pcfbench train copilot4d-token-copy:config=tiny-window --dataset synthetic-town-realistic`)" in err)
    # the command that trains it names no inference option: one checkpoint whatever the sampling
    assert ("copilot4d-maskgit:one_pass=true,sampling_steps=1,soft_mix=0.3,top_k=1 is not trained on synthetic-town-realistic:train yet "
            "(`pcfbench train copilot4d-maskgit --dataset synthetic-town-realistic`)" in err)


def test_default_run_options_of_one_meaning_are_scored_once(monkeypatch, capsys):
    """Two option sets that resolve to the same options (here token-copy's default, tiny, written
    out) would be one cell twice: the default run keeps the first and says so."""
    import pcfbench.training.checkpoints as cks
    from pcfbench.cli import _selected_methods
    from pcfbench.methods.copilot4d.token_copy import TokenCopy
    from pcfbench.plugins import get_plugins

    monkeypatch.setattr(cks, "ready_shipped", lambda *a, **k: object())
    monkeypatch.setattr(TokenCopy, "default_run_options", ({}, {"config": "tiny"}, {"config": "tiny-window"}))
    picked = [(m.name, m.raw) for m in _selected_methods(get_plugins(), ()) if m.name == "copilot4d-token-copy"]
    assert picked == [("copilot4d-token-copy", {}), ("copilot4d-token-copy", {"config": "tiny-window"})]
    assert ("copilot4d-token-copy's default_run_options give copilot4d-token-copy:config=tiny the options of "
            "copilot4d-token-copy; scored once" in capsys.readouterr().err)
