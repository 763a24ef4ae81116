"""The world model's token report: changed and unchanged tokens apart, counted by hand."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
import torch

from pcfbench.methods.copilot4d.token_report import score_tokens, shares, world_token_report, write_token_report


def test_score_tokens_hand_case():
    last = np.array([[1, 1], [2, 2]])
    truth = np.array([[1, 5], [2, 6]])  # two tokens changed: (0, 1) and (1, 1)
    pred = np.array([[1, 5], [3, 2]])  # right on (0, 0), (0, 1); moved at (0, 1), (1, 0)
    c = score_tokens(pred, truth, last)
    assert c == {"tokens": 4, "changed": 2, "changed_hit": 1, "unchanged_hit": 1, "moved": 2, "moved_hit": 1}
    s = shares(c)
    assert s == {"changed_share": 0.5, "accuracy": 0.5, "changed_accuracy": 0.5, "unchanged_accuracy": 0.5,
                 "moved_share": 0.5, "moved_precision": 0.5}
    assert math.isnan(shares(score_tokens(last, last, last))["changed_accuracy"])
    with pytest.raises(ValueError, match="one shape"):
        score_tokens(pred, truth, last[:1])


@pytest.mark.parametrize("answer,one_pass", [("truth", False), ("last", False), ("truth", True)])
def test_report_scores_each_window_against_its_own_future(monkeypatch, tmp_path, answer, one_pass):
    """An oracle forecaster (the window's real future) is right on every changed token; a copier
    (the last past frame) on none of them and on every unchanged one; the past it is handed is
    the window's first n_past frames, and its poses all of the window's; the windows are decoded
    as the method decodes a sample: Algorithm 2, or with ``one_pass`` every frame in one pass."""
    from pcfbench.methods.copilot4d import diffusion
    from pcfbench.methods.copilot4d.forecaster import Copilot4D

    P, F, A = 2, 3, 4
    rng = np.random.default_rng(0)
    tokens = rng.integers(0, 5, (A, P + F, 3, 3)).astype(np.int16)
    windows = {"tokens": tokens, "poses": np.repeat(np.eye(4, dtype=np.float32)[None, None], A, 0).repeat(P + F, 1),
               "stride": np.array([2, 2, 6, 6])}
    seen = []

    networks = {2: torch.nn.Linear(1, 1), 6: torch.nn.Linear(1, 1)}  # a network per stride (stride_models)
    guidance = {2: 0.0, 6: 0.5}

    def fake_forecast(model, past, poses, n_future, *, sampler, **kw):
        a = next(i for i in range(A) if np.array_equal(tokens[i, :P], past[0].numpy()))
        assert model is networks[int(windows["stride"][a])]  # the network of the window's stride forecasts it
        seen.append((a, poses.shape[1], n_future, sampler))
        # the method's sampling options, the guidance weight that of the stride's network (stride_cfg_weight)
        stride = int(windows["stride"][a])
        assert (kw["n_frames"], kw["n_past"], kw["guidance"]) == (P + F, P, guidance[stride])
        if sampler == "algorithm 2":
            assert (kw["steps"], kw["top_k"], kw["change_confidence"]) == (2, 1, 0.3)
        out = tokens[a, P:] if answer == "truth" else np.repeat(tokens[a, P - 1][None], F, 0)
        return list(torch.from_numpy(out.astype(np.int64))[:, None])

    monkeypatch.setattr(diffusion, "forecast_sequence", lambda *a, **k: fake_forecast(*a, sampler="algorithm 2", **k))
    monkeypatch.setattr(diffusion, "forecast_one_pass", lambda *a, **k: fake_forecast(*a, sampler="one pass", **k))
    # a 3 x 3 grid over [-45, 45]^2 (centres at -30, 0, 30 m): the centre token within 20 m of the
    # sensor, the edge ones at 30 m (20-40 m), the corners at 42.4 m (40-60 m), none beyond 60 m
    method = types.SimpleNamespace(
        world_cfg=types.SimpleNamespace(n_past=P, n_future=F, n_frames=P + F), world=torch.nn.Linear(1, 1),
        network_for_stride=networks.__getitem__,
        tok_cfg=types.SimpleNamespace(x_range=(-45.0, 45.0), y_range=(-45.0, 45.0)),
        options=types.SimpleNamespace(seed=0, sampling_steps=2, cfg_weight=0.0, top_k=1, change_confidence=0.3,
                                      one_pass=one_pass),
        variant=types.SimpleNamespace(revise=True),
        code_metric=lambda: None,
        sampling_for=lambda net: (guidance[next(s for s, n in networks.items() if n is net)], 0.0))
    method.decode_future = types.MethodType(Copilot4D.decode_future, method)
    res = world_token_report(method, windows, log=lambda *_: None)
    assert sorted(seen) == [(a, P + F, F, "one pass" if one_pass else "algorithm 2") for a in range(A)]
    assert [(r["stride"], r["step"], r["windows"]) for r in res["rows"]] == [(s, f, 2) for s in (2, 6) for f in (1, 2, 3)]
    for r in res["rows"]:
        sel = np.flatnonzero(windows["stride"] == r["stride"])
        changed = int((tokens[sel, P + r["step"] - 1] != tokens[sel, P - 1]).sum())
        assert r["changed"] == changed and r["tokens"] == 2 * 9
        sh = shares(r)
        assert sh["changed_accuracy"] == (1.0 if answer == "truth" else 0.0)
        assert sh["unchanged_accuracy"] == 1.0
    ring_of = np.array([[2, 1, 2], [1, 0, 1], [2, 1, 2]])
    assert [(r["stride"], r["ring"]) for r in res["rings"]] == [(s, i) for s in (2, 6) for i in range(4)]
    for r in res["rings"]:
        sel = np.flatnonzero(windows["stride"] == r["stride"])
        where = ring_of == r["ring"]
        assert r["tokens"] == 2 * F * int(where.sum())
        assert r["changed"] == int((tokens[sel, P:][..., where] != tokens[sel, P - 1, None][..., where]).sum())
        assert r["changed_hit"] == (r["changed"] if answer == "truth" else 0)
    assert sum(r["changed"] for r in res["rings"]) == sum(r["changed"] for r in res["rows"])
    md, csv_path = write_token_report(res, {"method": "copilot4d|x"}, tmp_path, "r")
    text = md.read_text()
    assert "copilot4d\\|x" in text and "| 6 | 20-40 m | 2 |" in text and "| 2 | 60 m and beyond | 2 | nan %" in text
    assert len(csv_path.read_text().splitlines()) == 1 + 6 + 8


# --------------------------------------------------------------------------- the objective held out
class _LastFrameCopier(torch.nn.Module):
    """Predicts, everywhere, the input's token of the last past frame (code 0 where it is masked),
    and records whether it ran in training mode."""

    def __init__(self, V, n_past):
        super().__init__()
        self.V, self.n_past, self.mask_token = V, n_past, V
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.modes = []

    def forward(self, tokens, poses, mask):
        self.modes.append(self.training)
        last = tokens[:, self.n_past - 1: self.n_past].clamp(max=self.V - 1).expand_as(tokens)
        return torch.nn.functional.one_hot(last, self.V).float() * 10 + self.w


def _windows(seed, A=5, P=2, F=2, V=6):
    rng = np.random.default_rng(seed)
    tokens = rng.integers(0, V, (A, P + F, 3, 3)).astype(np.int16)
    keep = rng.random((A, F, 3, 3)) < 0.5  # about half the future keeps the last past frame's token
    tokens[:, P:] = np.where(keep, tokens[:, P - 1: P], tokens[:, P:])
    return {"tokens": tokens, "poses": np.broadcast_to(np.eye(4, dtype=np.float32), (A, P + F, 4, 4)).copy(),
            "stride": np.full(A, 2)}


def test_objective_report_counts_by_hand_and_draws_alike_for_every_set():
    """Under the "future" objective the past is clean, so a copier of the last past frame is right
    on every unchanged masked future token and on no changed one; the future tokens and the changed
    ones among them are counted by hand (draws x windows). Each set draws the same corruptions
    (a set reported alone gives the same row as beside another), the model runs in evaluation
    mode and is handed back in training mode."""
    from pcfbench.methods.copilot4d.diffusion import COPILOT4D
    from pcfbench.methods.copilot4d.token_report import objective_report, objective_shares

    P, V, draws = 2, 6, 3
    a, b = _windows(0), _windows(1)
    model = _LastFrameCopier(V, P)
    kw = dict(n_past=P, variant=COPILOT4D, label_smoothing=0.1, draws=draws, batch=2, log=lambda *_: None)
    res = objective_report(model, {"a": a, "b": b}, **kw)
    assert [(r["set"], r["objective"]) for r in res["rows"]] == [("a", "mixture"), ("a", "future"),
                                                                ("b", "mixture"), ("b", "future")]
    assert model.training and model.modes and not any(model.modes)
    for r in res["rows"]:
        w = a if r["set"] == "a" else b
        assert r["windows"] == 5 and r["draws"] == draws
        assert r["future"] == draws * 5 * 2 * 9
        assert r["future_changed"] == draws * int((w["tokens"][:, P:] != w["tokens"][:, P - 1: P]).sum())
        assert r["changed"] + r["unchanged"] <= r["masked"] <= r["scored"]
        if r["objective"] == "future":
            assert r["changed"] > 0 and r["unchanged"] > 0
            assert r["changed_hits"] == 0 and r["unchanged_hits"] == r["unchanged"]
            sh = objective_shares(r)
            assert sh["changed_accuracy"] == 0.0 and sh["unchanged_accuracy"] == 1.0
            assert all(r[f"changed_hits_r{i}"] == 0 == r[f"first_changed_hits_r{i}"] for i in range(5))
            assert sh["changed_loss"] > sh["unchanged_loss"]
        assert sum(r[f"changed_r{i}"] for i in range(5)) == r["changed"]
    alone = objective_report(model, {"b": b}, **kw)["rows"]
    assert alone == res["rows"][2:]
    twice = objective_report(model, {"a": a, "again": a}, **kw)["rows"]
    assert [dict(r, set=None) for r in twice[:2]] == [dict(r, set=None) for r in twice[2:]]
    few = objective_report(model, {"a": a}, **{**kw, "draws": 1}, max_windows=2)["rows"]
    assert few[0]["windows"] == 2 and few[0]["future"] == 2 * 2 * 9
    with pytest.raises(ValueError, match="draws=0"):
        objective_report(model, {"a": a}, **{**kw, "draws": 0})


def test_objective_sums_are_the_training_losss_measurements():
    """The same corruption (one seed) measured by training_loss (ratios) and objective_sums
    (sums and counts) gives the same figures."""
    from pcfbench.methods.copilot4d import diffusion as D
    from pcfbench.methods.copilot4d.token_report import objective_shares

    w = _windows(2)
    x0 = torch.from_numpy(w["tokens"].astype(np.int64))
    poses = torch.from_numpy(w["poses"])
    model = _LastFrameCopier(6, 2)
    for seed in range(4):
        _, stats = D.training_loss(model, x0, poses, 2, generator=torch.Generator().manual_seed(seed))
        sums = D.objective_sums(model, x0, poses, 2, generator=torch.Generator().manual_seed(seed))
        assert set(sums) == set(D.OBJECTIVE_SUMS)
        sh = objective_shares(sums)
        for k in ("changed_share", "changed_loss", "changed_accuracy", "unchanged_loss", "unchanged_accuracy",
                  "masked_accuracy"):
            assert sh[k] == pytest.approx(stats[k], rel=1e-6, nan_ok=True), k
        assert sums["hits"] / sums["scored"] == pytest.approx(stats["accuracy"])
        # the changed tokens by their frame's masked share, counted token by token
        c = D.corrupt(x0, 2, 6, D.COPILOT4D, torch.Generator().manual_seed(seed))
        edges = (0.5, 0.8, 0.95, 0.99)
        counts, first = [0] * 5, [0] * 5
        for b in range(x0.shape[0]):
            for t in range(2, x0.shape[1]):
                rate = float(c.masked[b, t].float().mean())
                i = sum(rate >= e for e in edges)
                for y in range(3):
                    for x in range(3):
                        if c.masked[b, t, y, x] and x0[b, t, y, x] != x0[b, 1, y, x]:
                            counts[i] += 1
                            first[i] += t == 2
        assert [sums[f"changed_r{i}"] for i in range(5)] == counts
        assert [sums[f"first_changed_r{i}"] for i in range(5)] == first and 0 < sum(first) < sum(counts)


def test_curve_tail_and_the_written_objective_report(tmp_path):
    from pcfbench.methods.copilot4d.diffusion import OBJECTIVE_SUMS
    from pcfbench.methods.copilot4d.token_report import curve_tail, write_objective_report

    cols = ("changed_share", "changed_loss", "changed_accuracy", "unchanged_loss", "unchanged_accuracy",
            "masked_accuracy")
    lines = ["step," + ",".join(cols)]
    for step in range(10, 301, 10):  # the last 100 steps: 210 .. 300, values 21 .. 30
        lines.append(f"{step}," + ",".join(str(step / 10) for _ in cols))
    (tmp_path / "curve.csv").write_text("\n".join(lines) + "\n")
    tail = curve_tail(tmp_path / "curve.csv")
    assert tail["steps"] == "201-300" and tail["changed_loss"] == pytest.approx(25.5)
    assert curve_tail(tmp_path / "missing.csv") is None
    # a training that went on from an 800-step one: its curve's steps 201-300 are steps 1001-1100
    assert curve_tail(tmp_path / "curve.csv", first_step=800)["steps"] == "1001-1100"
    row = dict.fromkeys(OBJECTIVE_SUMS, 0) | {"set": "held out: x|y", "objective": "future", "windows": 3, "draws": 2,
                                              "future": 10, "future_changed": 4, "changed": 4, "changed_hits": 1,
                                              "changed_ce": 8.0, "unchanged": 5, "unchanged_hits": 5,
                                              "unchanged_ce": 1.0, "masked": 9, "masked_hits": 6,
                                              "changed_r0": 4, "changed_hits_r0": 1}
    md, csv_path = write_objective_report({"rows": [row]}, {"method": "copilot4d"}, tmp_path, "o", curve=tail)
    text = md.read_text()
    assert "| training curve, steps 201-300 | mixture | | 2550.0 % | 25.50 |" in text
    assert "| held out: x\\|y | future | 3 (2) | 40.0 % | 2.00 | 25.0 % | 0.20 | 100.0 % | 66.7 % |" in text
    assert "| held out: x\\|y | future | all | 25.0 % (4) | nan % (0) | nan % (0) | nan % (0) | nan % (0) |" in text
    assert "| held out: x\\|y | future | first | nan % (0) | nan % (0) | nan % (0) | nan % (0) | nan % (0) |" in text
    assert len(csv_path.read_text().splitlines()) == 2


def test_world_report_refuses_to_report_nothing():
    from click.testing import CliRunner

    from pcfbench.cli import build_cli

    r = CliRunner().invoke(build_cli(), ["world-report", "--dataset", "synthetic-town", "--no-forecast"])
    assert r.exit_code != 0 and "nothing to report" in r.output


def test_reports_of_one_checkpoint_sampled_differently_have_their_own_names():
    """world-report and world-changes name their files by the checkpoint and by the inference
    options away from their defaults, so two samplings of one checkpoint do not overwrite each other."""
    from pcfbench.method import resolve_method
    from pcfbench.methods.copilot4d.plugin import _inference_suffix

    def suffix(spec):
        return _inference_suffix(resolve_method(spec).create())

    assert suffix("copilot4d:config=tiny-window,steps=800,sampling_steps=10") == ""  # training options, a default
    assert suffix("copilot4d:top_k=1,cfg_weight=0,sampling_steps=1") == "-cfg_weight=0.0-sampling_steps=1-top_k=1"
