"""Issue 48: a run scored with the torch searches (``RunOptions.metrics_backend``) writes the rows
of the numpy searches."""

import pandas as pd
import pytest

from pcfbench.errors import PcfbenchError


def test_a_run_scored_in_torch_writes_the_numpy_rows(tmp_path):
    from conftest import write_tiny_kitti

    from pcfbench.method import options_hash
    from pcfbench.running.runner import RunOptions, run_cell
    from pcfbench.store.cells import Cell, CellSpec

    root = write_tiny_kitti(tmp_path / "kitti", num_sweeps=20, beams=8, azimuths=120)  # ~900 points a sweep
    spec = CellSpec("copy-last", {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context",
                    2, ("chamfer", "chamfer_nf", "l1_mean", "l1@4docc", "absrel_median"))
    rows = {}
    for name in ("numpy", "torch"):
        run_cell(spec, tmp_path / name, RunOptions(progress=False, metrics_backend=name))
        df = Cell(tmp_path / name, spec).read_rows().sort_values(["sample_id", "step"]).reset_index(drop=True)
        rows[name] = df.drop(columns=["t_load", "t_method", "t_metrics"])
    assert len(rows["numpy"]) == 10
    pd.testing.assert_frame_equal(rows["torch"], rows["numpy"], check_exact=True)
    # each cell says how its rows were scored
    from pcfbench.metrics.torch_nn import default_device

    assert Cell(tmp_path / "numpy", spec).read_meta()["metrics_backend"] == [
        {"requested": "numpy", "backend": "numpy", "device": "cpu"}]
    assert Cell(tmp_path / "torch", spec).read_meta()["metrics_backend"] == [
        {"requested": "torch", "backend": "torch", "device": default_device()}]
    with pytest.raises(PcfbenchError, match="metrics backend must be one of auto, numpy, torch"):
        RunOptions(metrics_backend="gpu")


def test_the_cli_hands_the_backend_to_the_run_and_ray_refuses_another():
    import click

    from pcfbench.cli import _limits
    from pcfbench.protocol.validate import FORECAST_RATIO

    assert _limits("local", 120.0, 0.0, FORECAST_RATIO, "torch")["metrics_backend"] == "torch"
    assert _limits("ray", 120.0, 0.0, FORECAST_RATIO)["metrics_backend"] == "auto"
    with pytest.raises(click.UsageError, match="--metrics-backend apply to the local executor only"):
        _limits("ray", 120.0, 0.0, FORECAST_RATIO, "numpy")


def test_the_backends_of_a_resumed_cell_accumulate_once_each():
    from pcfbench.running.runner import RunOptions, _with_backend, scoring_backend

    numpy = scoring_backend(RunOptions(progress=False, metrics_backend="numpy"))
    torch = {"requested": "torch", "backend": "torch", "device": "cuda"}
    assert numpy == {"requested": "numpy", "backend": "numpy", "device": "cpu"}
    assert _with_backend(None, numpy) == [numpy]  # a new cell, or one written before the field
    assert _with_backend([numpy], numpy) == [numpy]
    assert _with_backend([numpy], torch) == [numpy, torch]  # resumed on a GPU: both, in order
    assert _with_backend([numpy, torch], numpy) == [numpy, torch]
    assert scoring_backend(RunOptions(progress=False, executor=object()))["resolved"] == "on each worker"
