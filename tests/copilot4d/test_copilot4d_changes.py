"""`pcfbench world-changes`: what a world model's changes are worth (issue 42)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from pcfbench.errors import PcfbenchError
from pcfbench.methods.copilot4d.changes import (COPY, FORECAST, HITS, check_shares, evaluate_changes, random_changes,
                                                ring_labels, share_entry, token_rings, with_changes,
                                                write_changes)


def test_with_changes_takes_the_target_only_where_asked_and_it_differs():
    last = torch.tensor([[1, 2, 3], [4, 5, 6]])
    target = torch.tensor([[1, 9, 3], [8, 5, 7]])
    take = torch.tensor([[True, True, False], [False, True, True]])
    assert with_changes(last, target, take).tolist() == [[1, 9, 3], [4, 5, 7]]
    assert with_changes(last, target, torch.ones_like(take)).tolist() == target.tolist()
    assert with_changes(last, target, torch.zeros_like(take)).tolist() == last.tolist()
    with pytest.raises(ValueError, match="shapes"):
        with_changes(last, target[:1], take)


def test_a_random_share_changes_that_share_of_the_changed_tokens_and_nothing_else():
    g = torch.Generator().manual_seed(0)
    last = torch.randint(0, 4, (200, 200), generator=g)
    target = torch.where(torch.rand(last.shape, generator=g) < 0.5, (last + 1) % 4, last)
    changed = target != last
    for p in (0.1, 0.25, 0.5):
        out = random_changes(last, target, p, torch.Generator().manual_seed(1))
        assert torch.equal(out[~changed], last[~changed])  # never where the target keeps the t=0 token
        assert torch.all((out == last) | (out == target))
        assert float((out[changed] == target[changed]).double().mean()) == pytest.approx(p, abs=0.01)
    assert torch.equal(random_changes(last, target, 1.0, torch.Generator().manual_seed(1)), target)


def test_tokens_fall_in_the_rings_of_their_centres_distance():
    """4 x 4 tokens of 20 m over [-40, 40]^2: centres at +-10 and +-30 m, so 4 tokens at 14.1 m, 8
    at 31.6 m and 4 at 42.4 m."""
    cfg = SimpleNamespace(x_range=(-40.0, 40.0), y_range=(-40.0, 40.0))
    rings = token_rings(cfg, (4, 4))
    assert rings.tolist() == [[2, 1, 1, 2], [1, 0, 0, 1], [1, 0, 0, 1], [2, 1, 1, 2]]
    # a centre exactly on an edge belongs to the ring above it
    small = SimpleNamespace(x_range=(-20.0, 20.0), y_range=(-20.0, 20.0))
    assert token_rings(small, (2, 2), edges=(float(np.hypot(10.0, 10.0)),)).tolist() == [[1, 1], [1, 1]]
    assert ring_labels((20.0, 40.0)) == ["0-20 m", "20-40 m", "40 m and beyond"]


def test_changed_tokens_are_counted_per_ring():
    """The ceiling's changed share by ring on the 4 x 4 map above: the four centre tokens (ring 0),
    eight edge tokens (ring 1) and four corners (ring 2, 42.4 m; ring 3 empty); one centre token,
    two edge tokens and every corner changed."""
    from pcfbench.methods.copilot4d.evaluate import changed_by_ring

    cfg = SimpleNamespace(x_range=(-40.0, 40.0), y_range=(-40.0, 40.0))
    last = torch.zeros(4, 4, dtype=torch.long)
    codes = last.clone()
    codes[1, 1] = 3
    codes[0, 1] = codes[2, 0] = 5
    codes[0, 0] = codes[0, 3] = codes[3, 0] = codes[3, 3] = 1
    changed, tokens = changed_by_ring(cfg, codes, last)
    assert changed.tolist() == [1, 2, 4, 0] and tokens.tolist() == [4, 8, 4, 0]
    with pytest.raises(ValueError, match="shapes"):
        changed_by_ring(cfg, codes, last[:2])


def test_shares_lie_in_the_open_closed_unit_interval():
    assert check_shares(["0.1", 1]) == (0.1, 1.0)
    for bad in (0.0, -0.2, 1.5):
        with pytest.raises(PcfbenchError, match="must lie in"):
            check_shares([0.5, bad])


def _grid_codes(model, points):
    """A stand-in tokenizer: 4 x 4 cells of 20 m over [-40, 40]^2, each coded by its point count."""
    xy = np.asarray(points, np.float64)[:, :2]
    inside = np.all(np.abs(xy) < 40, axis=1)
    cell = ((xy[inside] + 40) // 20).astype(int)
    counts = np.zeros((4, 4), np.int64)
    np.add.at(counts, (cell[:, 0], cell[:, 1]), 1)
    return torch.from_numpy(np.minimum(counts // 15, 40))


def _render(model, codes, sample, T_frame_ref, *, generator=None, **render):
    """A stand-in renderer: every ray of future sweep k at 5 m plus the mean code of map k."""
    maps = codes if isinstance(codes, (list, tuple)) else [codes] * len(sample.queries)
    return [np.full(len(q.directions_ref), 5.0 + float(torch.as_tensor(c).double().mean()))
            for q, c in zip(sample.queries, maps)]


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    from conftest import write_tiny_kitti

    import pcfbench.methods.copilot4d.evaluate as ev
    from pcfbench.methods.copilot4d.data import open_dataset

    monkeypatch.setattr(ev, "tokenize_sweep", _grid_codes)
    monkeypatch.setattr(ev, "render_queries", _render)
    root = write_tiny_kitti(tmp_path / "kitti", sequences=("08",), num_sweeps=24)
    return open_dataset("kitti", root)


def _method(forecast, frame="t0"):
    return SimpleNamespace(name="copilot4d", options=SimpleNamespace(frame=frame, seed=0),
                           tokenizer=SimpleNamespace(cfg=SimpleNamespace(x_range=(-40.0, 40.0), y_range=(-40.0, 40.0))),
                           render={"threshold": 0.02, "noise": False, "readout": "median"},
                           forecast_tokens=lambda sample: (forecast(sample), None, None))


def _t0_map(sample):
    from pcfbench.methods.copilot4d.forecaster import transform

    return _grid_codes(None, transform(sample.past_points_ref[-1], np.linalg.inv(sample.past_T_ref_sensor[-1])))


def test_a_forecast_that_copies_scores_as_token_copy_and_the_full_share_as_the_ceiling(tiny, tmp_path):
    """A forecast that repeats the t=0 map changes nothing: it and its right changes score
    token-copy's numbers, it is right on every unchanged token and on no changed one; the bound
    right on every change (share 1) is the ceiling."""
    res = evaluate_changes(_method(lambda s: [_t0_map(s)] * s.num_future), tiny, "test", "kitti-1s",
                           change_shares=(0.5, 1.0), log=lambda *a: None)
    m = res["means"]
    assert res["samples"] > 0
    for name in ("chamfer_nf", "l1_mean", "l1_median"):
        assert m[FORECAST][name] == pytest.approx(m[COPY][name], rel=1e-12)
        assert m[HITS][name] == pytest.approx(m[COPY][name], rel=1e-12)
        assert m[share_entry(1.0)][name] == pytest.approx(m["ceiling"][name], rel=1e-12)
    counts = res["counts"]
    assert len(counts) == 5 and all(c["tokens"] == 16 * res["samples"] for c in counts)
    assert sum(c["changed"] for c in counts) > 0  # the stand-in tokenizer sees the drive move
    for c in counts:
        assert c["moved"] == c["moved_hit"] == c["changed_hit"] == 0
        assert c["unchanged_hit"] == c["tokens"] - c["changed"]
    assert m["ceiling"]["l1_mean"] != pytest.approx(m[COPY]["l1_mean"])  # the entries differ at all
    # the rings split the same counts: 4, 8 and 4 of each map's 16 tokens, nothing beyond 60 m
    for key in ("tokens", "changed", "unchanged_hit"):
        assert sum(r[key] for r in res["by_ring"]) == sum(c[key] for c in counts)
    assert [r["tokens"] for r in res["by_ring"]] == [5 * res["samples"] * n for n in (4, 8, 4, 0)]
    md, csv_path = write_changes(res, {"method": "copilot4d"}, tmp_path / "r", "w")
    assert md.name == "w.md" and "| its right changes only |" in md.read_text() and "| 0-20 m |" in md.read_text()
    assert csv_path.read_text().startswith("entry,chamfer_nf,l1_mean,l1_median,")


def test_only_the_right_changes_enter_the_bound(tiny):
    """A forecast that sets every token to code 0: where the truth is 0 and the t=0 map is not, it
    is a right change (the bound takes it), anywhere else a wrong one or none; the counts are the
    hand count over the same maps."""
    from pcfbench.methods.copilot4d.ceiling import future_targets
    from pcfbench.protocol import SampleBuilder
    from pcfbench.plugins import get_setting

    res = evaluate_changes(_method(lambda s: [torch.zeros(4, 4, dtype=torch.long)] * s.num_future), tiny, "test",
                           "kitti-1s", change_shares=(0.25,), max_samples=3, log=lambda *a: None)
    builder = SampleBuilder(tiny, get_setting("kitti-1s"))
    keys = builder.sample_keys("test")
    keys = [keys[i] for i in np.unique(np.linspace(0, len(keys) - 1, 3).round().astype(int))]
    expect = [dict(changed=0, changed_hit=0, moved=0, moved_hit=0) for _ in range(5)]
    for seq_name, ref in keys:
        sample, _ = builder.build(seq_name, ref)
        last = _t0_map(sample.for_method())
        target, _ = future_targets(None, sample, builder, seq_name, ref, "t0")
        for k, t in enumerate(target):
            expect[k]["changed"] += int((t != last).sum())
            expect[k]["changed_hit"] += int(((t != last) & (t == 0)).sum())
            expect[k]["moved"] += int((last != 0).sum())
            expect[k]["moved_hit"] += int(((last != 0) & (t == 0)).sum())
    assert [{k: c[k] for k in expect[0]} for c in res["counts"]] == expect
    assert res["samples"] == 3 and len(res["rows"][HITS]) == 15


def test_the_t0_map_and_the_targets_come_from_the_same_points(tiny):
    """The report tokenizes the t=0 map from what the world model is given and the targets from
    the builder's sensor-frame sweeps: for the t=0 sweep both give the same points, so a forecast
    that copies is not charged with changes that are only two pipelines disagreeing."""
    from pcfbench.methods.copilot4d.forecaster import transform
    from pcfbench.plugins import get_setting
    from pcfbench.protocol import SampleBuilder

    builder = SampleBuilder(tiny, get_setting("kitti-1s"))
    for seq_name, ref in builder.sample_keys("test")[:3]:
        sample, _ = builder.build(seq_name, ref)
        given = transform(sample.for_method().past_points_ref[-1], np.linalg.inv(sample.past_T_ref_sensor[-1]))
        built = builder.points_sensor(builder.sequence(seq_name), ref)
        assert given.shape == built.shape
        np.testing.assert_allclose(given, built, atol=1e-5)


def test_the_command_defaults_to_the_modules_shares():
    from pcfbench.cli import build_cli
    from pcfbench.methods.copilot4d.changes import CHANGE_SHARES

    option = next(p for p in build_cli().commands["world-changes"].params if p.name == "shares")
    assert check_shares(option.default.split(",")) == CHANGE_SHARES


def test_frame_own_is_refused(tiny):
    with pytest.raises(PcfbenchError, match="frame=t0 only"):
        evaluate_changes(_method(lambda s: [], frame="own"), tiny, "test", "kitti-1s")
