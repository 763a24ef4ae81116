"""Issue 15: the leaderboard does not depend on the order chunks (or workers) wrote rows in."""

import json
import shutil

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pcfbench.reporting import stats
from pcfbench.method import options_hash
from pcfbench.reporting.report import write_reports
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec

METRICS = ("chamfer", "chamfer_nf", "l1_mean", "absrel_mean")


def _spec(root, method="copy-last"):
    return CellSpec(method, {}, options_hash(None), "kitti", str(root), "test", "kitti-1s", "full-context", None, METRICS)


def _rewrite_chunks(cell: Cell, rows: pd.DataFrame, pieces: list[np.ndarray]) -> None:
    rows_dir = cell.dir / "rows"
    shutil.rmtree(rows_dir)
    rows_dir.mkdir()
    for k, idx in enumerate(pieces):
        pq.write_table(pa.Table.from_pandas(rows.iloc[idx], preserve_index=False), rows_dir / f"chunk-{k:06d}.parquet")


def test_same_rows_in_other_chunk_orders_give_byte_identical_leaderboards(tiny_kitti, tmp_path):
    a = tmp_path / "a"
    run_cell(_spec(tiny_kitti), a, RunOptions(progress=False))
    cell_a = Cell(a, _spec(tiny_kitti))
    rows = cell_a.read_rows()
    # values whose sums depend on the order they are added in (as real metric values do,
    # in the last bit): the same rows, in every store below
    rng = np.random.default_rng(7)
    for m in METRICS:
        rows[m] = rng.uniform(0.1, 10.0, len(rows)) * 10.0 ** rng.integers(-3, 4, len(rows))
    by_sample = [np.flatnonzero(rows.sample_id.to_numpy() == s) for s in sorted(set(rows.sample_id))]
    orders = {
        "a": [np.concatenate(by_sample)],  # one chunk, in sample order
        "b": [np.concatenate(by_sample[::-1])[::-1]],  # one chunk, samples and steps reversed
        "c": [np.concatenate(p) for p in (by_sample[5:], by_sample[1:5][::-1], by_sample[:1])],  # three chunks
        "d": [np.concatenate([np.roll(i, 2) for i in by_sample[::2]]), np.concatenate(by_sample[1::2][::-1])],
    }
    outputs = {}
    for name, pieces in orders.items():
        store = tmp_path / name
        if name != "a":
            shutil.copytree(a, store)
        cell = Cell(store, _spec(tiny_kitti))
        _rewrite_chunks(cell, rows, pieces)
        pd.testing.assert_frame_equal(stats.in_sample_order(cell.read_rows()), stats.in_sample_order(rows),
                                      check_dtype=False)
        paths = write_reports(store, tmp_path / f"report-{name}")
        outputs[name] = {key: paths[key].read_bytes() for key in ("csv", "by_step", "comparisons", "md")}
    for name in "bcd":
        for key, blob in outputs[name].items():
            assert blob == outputs["a"][key], (name, key)
    # and the numbers are the flat means of the rows, taken in sample order
    lb = pd.read_csv(tmp_path / "report-a" / "leaderboard.csv")
    ordered = stats.in_sample_order(rows)
    for m in METRICS:
        assert lb[m].iloc[0] == float(np.nanmean(ordered[m].to_numpy()))


def test_in_sample_order_sorts_by_sample_then_step_stably():
    rows = pd.DataFrame({"sample_id": ["08/000010", "08/000002", "08/000010", "08/000002"], "step": [1, 1, 0, 0],
                         "v": [1, 2, 3, 4]})
    out = stats.in_sample_order(rows)
    assert out.v.tolist() == [4, 2, 3, 1] and out.index.tolist() == [0, 1, 2, 3]
    assert json.dumps(stats.in_sample_order(rows.iloc[::-1]).v.tolist()) == "[4, 2, 3, 1]"
