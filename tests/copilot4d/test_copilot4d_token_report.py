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


@pytest.mark.parametrize("answer", ["truth", "last"])
def test_report_scores_each_window_against_its_own_future(monkeypatch, tmp_path, answer):
    """An oracle forecaster (the window's real future) is right on every changed token; a copier
    (the last past frame) on none of them and on every unchanged one; the past it is handed is
    the window's first n_past frames, and its poses all of the window's."""
    from pcfbench.methods.copilot4d import diffusion

    P, F, A = 2, 3, 4
    rng = np.random.default_rng(0)
    tokens = rng.integers(0, 5, (A, P + F, 3, 3)).astype(np.int16)
    windows = {"tokens": tokens, "poses": np.repeat(np.eye(4, dtype=np.float32)[None, None], A, 0).repeat(P + F, 1),
               "stride": np.array([2, 2, 6, 6])}
    seen = []

    def fake_forecast(model, past, poses, n_future, **kw):
        a = next(i for i in range(A) if np.array_equal(tokens[i, :P], past[0].numpy()))
        seen.append((a, poses.shape[1], n_future))
        assert (kw["steps"], kw["guidance"], kw["top_k"]) == (2, 0.0, 1)  # the method's sampling options
        out = tokens[a, P:] if answer == "truth" else np.repeat(tokens[a, P - 1][None], F, 0)
        return torch.from_numpy(out.astype(np.int64))[None]

    monkeypatch.setattr(diffusion, "forecast_tokens", fake_forecast)
    method = types.SimpleNamespace(
        world_cfg=types.SimpleNamespace(n_past=P, n_future=F), world=torch.nn.Linear(1, 1),
        options=types.SimpleNamespace(seed=0, sampling_steps=2, cfg_weight=0.0, top_k=1), variant=types.SimpleNamespace(revise=True))
    res = world_token_report(method, windows, log=lambda *_: None)
    assert sorted(seen) == [(a, P + F, F) for a in range(A)]
    assert [(r["stride"], r["step"], r["windows"]) for r in res["rows"]] == [(s, f, 2) for s in (2, 6) for f in (1, 2, 3)]
    for r in res["rows"]:
        sel = np.flatnonzero(windows["stride"] == r["stride"])
        changed = int((tokens[sel, P + r["step"] - 1] != tokens[sel, P - 1]).sum())
        assert r["changed"] == changed and r["tokens"] == 2 * 9
        sh = shares(r)
        assert sh["changed_accuracy"] == (1.0 if answer == "truth" else 0.0)
        assert sh["unchanged_accuracy"] == 1.0
    md, csv_path = write_token_report(res, {"method": "copilot4d|x"}, tmp_path, "r")
    assert "copilot4d\\|x" in md.read_text() and len(csv_path.read_text().splitlines()) == 7
