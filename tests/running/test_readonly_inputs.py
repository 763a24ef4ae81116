"""Issue 15: a method cannot change what it is scored against."""

import numpy as np
import pytest

from pcfbench.data import Forecast, read_only_copy
from pcfbench.method import options_hash
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import load_plugins
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec
from pcfbench.testing import toy_sample


class MovesOrigins(CopyLast):
    """copy-last, but first moves every query origin onto its nearest predicted point's
    line of sight (here simply: 1 m forward), in place."""

    name = "moves-origins"

    def forecast(self, sample):
        for q in sample.queries:
            q.origin_ref[:] += 1.0
        return super().forecast(sample)


class ForcesWriteable(CopyLast):
    """copy-last that turns its input writeable again through the array's owner and then
    moves the query origins, pose and past points: it may change its copy, never the score."""

    name = "forces-writeable"

    def forecast(self, sample):
        forecast = Forecast(points_ref=tuple(np.array(p) for p in super().forecast(sample).points_ref))
        for arr in [q.origin_ref for q in sample.queries] + [q.directions_ref for q in sample.queries] + [
            sample.future_T_ref_sensor, *sample.past_points_ref
        ]:
            owner = arr.base if arr.base is not None else arr
            owner.flags.writeable = True
            owner[...] = 0
        return forecast


def _spec(root, method, metrics=("chamfer", "l1_mean")):
    return CellSpec(method, {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", 3,
                    tuple(metrics))


def _plugins():
    plugins = load_plugins()
    plugins.methods.add("moves-origins", MovesOrigins, "test")
    plugins.methods.add("forces-writeable", ForcesWriteable, "test")
    return plugins


def test_every_array_a_method_receives_is_read_only():
    sample, _ = toy_sample()
    seen = sample.for_method()
    arrays = [*seen.past_points_ref, seen.past_T_ref_sensor, seen.past_timestamps_ns, seen.future_T_ref_sensor,
              seen.future_timestamps_ns, seen.T_world_ref]
    for q in seen.queries:
        arrays += [q.origin_ref, q.directions_ref]
    for arr in arrays:
        assert not arr.flags.writeable
        with pytest.raises(ValueError, match="cannot set WRITEABLE flag"):
            arr.flags.writeable = True  # a view of a read-only copy cannot be made writeable
    # same values, other memory
    assert seen.sample_id == sample.sample_id
    for a, b in zip(seen.queries, sample.queries):
        np.testing.assert_array_equal(a.origin_ref, b.origin_ref)
        assert not np.shares_memory(a.directions_ref, b.directions_ref)
    for a, b in zip(seen.past_points_ref, sample.past_points_ref):
        assert a.dtype == b.dtype and not np.shares_memory(a, b)
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(read_only_copy(np.arange(3)), [0, 1, 2])


def test_a_method_moving_the_query_origins_in_place_fails_every_sample(tiny_kitti, store):
    result = run_cell(_spec(tiny_kitti, "moves-origins"), store, RunOptions(progress=False), plugins=_plugins())
    df = Cell(store, _spec(tiny_kitti, "moves-origins")).read_rows()
    assert result.failed == 3 and set(df.status) == {"failed"}
    assert all("ValueError" in e and "read-only" in e for e in df.error)


def test_a_method_forcing_its_copy_writeable_cannot_change_its_score(tiny_kitti, store):
    plugins = _plugins()
    run_cell(_spec(tiny_kitti, "copy-last"), store, RunOptions(progress=False), plugins=plugins)
    run_cell(_spec(tiny_kitti, "forces-writeable"), store, RunOptions(progress=False), plugins=plugins)
    ref = Cell(store, _spec(tiny_kitti, "copy-last")).read_rows().sort_values(["sample_id", "step"])
    got = Cell(store, _spec(tiny_kitti, "forces-writeable")).read_rows().sort_values(["sample_id", "step"])
    assert set(got.status) == {"ok"} and len(got) == len(ref) == 15
    for col in ("chamfer", "l1_mean", "n_gt", "n_pred"):
        np.testing.assert_array_equal(got[col].to_numpy(), ref[col].to_numpy())


def _mean_past(sample, scale):
    _mean_past.calls += 1
    return {"mean": np.mean(np.concatenate(sample.past_points_ref), axis=0) * scale, "scale": scale}


def test_what_methods_derive_from_a_sample_is_computed_once_and_read_only():
    """``Sample.derive``: the copies the runner gives each method on one sample share it; its
    arrays cannot be written; another argument is another value; a sample made any other way
    (``replace``, ``Sample(**...)``), whose inputs may differ, starts without it."""
    from dataclasses import replace

    from pcfbench.data import Sample

    sample, _ = toy_sample()
    _mean_past.calls = 0
    first = sample.for_method().derive(_mean_past, 2.0)
    again = sample.for_method().derive(_mean_past, 2.0)
    assert again is first and _mean_past.calls == 1
    np.testing.assert_allclose(first["mean"], np.mean(np.concatenate(sample.past_points_ref), axis=0) * 2.0)
    with pytest.raises(ValueError, match="read-only"):
        first["mean"][0] = 0.0
    assert sample.derive(_mean_past, 3.0)["scale"] == 3.0 and _mean_past.calls == 2
    moved = tuple(read_only_copy(p + 1.0) for p in sample.past_points_ref)
    for other in (replace(sample, past_points_ref=moved), Sample(**{**sample.__dict__, "past_points_ref": moved})):
        got = other.derive(_mean_past, 2.0)
        np.testing.assert_allclose(got["mean"], first["mean"] + 2.0, atol=1e-3)  # (float32 means)
    assert _mean_past.calls == 4
    with pytest.raises(ValueError, match="not a module-level function"):
        sample.derive(lambda s: 0)
