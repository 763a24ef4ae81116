"""The Argoverse 2 4D occupancy challenge's JSON files, both ways: query rays out (read back
bit for bit), a submission of depths in (scored as the same depths answered by a plugin)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from pcfbench.cli import build_cli
from pcfbench.data import Forecast
from pcfbench.datasets.av2 import write_av2
from pcfbench.datasets.layout import SequenceData
from pcfbench.errors import PcfbenchError
from pcfbench.exchange.challenge import (open_challenge_submission, ray_depths, read_challenge_queries,
                                         write_challenge_queries)
from pcfbench.exchange.commands import score_submission
from pcfbench.exchange.questions import open_questions
from pcfbench.method import Method, resolve_method
from pcfbench.methods.copy_last import CopyLast
from pcfbench.plugins import load_plugins
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import Cell, CellSpec, iter_cells
from pcfbench.testing import toy_world_sweeps

LOGS = ("0c6e62d7-bdfa-3061-8d3d-03b13aa21f68", "1f2e3d4c-0000-4000-8000-000000000001")
METRICS = ("chamfer", "chamfer_nf", "chamfer_nf@4docc", "l1_mean", "absrel_mean", "l1_median", "l1_ray", "absrel_ray")


@pytest.fixture(scope="module")
def av2(tmp_path_factory):
    """Two Argoverse 2 LiDAR-dataset logs of 20 sweeps (real columns: float16 x, y, z in
    feather files, poses by timestamp): av2-1s has 2 samples in each."""
    root = tmp_path_factory.mktemp("av2") / "av2"
    logs = []
    for seed, log in enumerate(LOGS):
        pts, poses, times = toy_world_sweeps(20, beams=8, azimuths=90, seed=seed)
        ts = 315_967_376_859_506_000 + np.round(times * 1e9).astype(np.int64)
        logs.append(SequenceData.from_arrays(log, "val", pts, poses, ts))
    write_av2(root, logs)
    return root, open_questions("av2", str(root), "val", "av2-1s", "full-context")


def test_the_query_json_reads_back_into_the_same_rays(av2, tmp_path):
    root, q = av2
    out = tmp_path / "query_rays.json"
    counts = write_challenge_queries(q, out)
    data = json.loads(out.read_text())
    assert set(data) == {"queries", "pcfbench"} and data["pcfbench"] == q.answers()
    assert len(data["queries"]) == 1 and data["queries"][0]["horizon"] == "1s"
    assert sorted(data["queries"][0]["rays"]) == sorted(LOGS)
    hz, rays = read_challenge_queries(out)
    assert hz == "1s" and len(rays) == len(q.keys) == counts["samples"] == 4
    total = 0
    for key in q.keys:
        sample, truth = q.builder.build(*key)
        seq = q.builder.sequence(key[0])
        frame = f"{int(seq.timestamps_ns[key[1]])}.feather"
        assert frame == Path(seq.points_source(key[1])).name  # the t=0 sweep's file, as the kit names frames
        sweeps = rays[(key[0].split("/")[1], frame)]
        assert len(sweeps) == 5
        for (origins, dirs), query, gt in zip(sweeps, sample.queries, truth.future_points_ref):
            want_o = np.broadcast_to(query.origin_ref, (len(query), 3))
            assert origins.dtype == np.float64 and origins.tobytes() == np.ascontiguousarray(want_o).tobytes()
            assert dirs.dtype == np.float32 and dirs.tobytes() == query.directions_ref.tobytes()
            assert len(dirs) == len(gt) > 0
            total += len(dirs)
    assert total == counts["rays"]
    by_cli = tmp_path / "cli.json"
    res = CliRunner().invoke(build_cli(), ["challenge", "queries", "-d", f"av2={root}", "-s", "av2-1s", "--split", "val",
                                           "-o", str(by_cli), "-q"])
    assert res.exit_code == 0, res.output
    assert res.output == f"4 samples, {total} rays of av2:val av2-1s -> {by_cli}\n"
    assert by_cli.read_bytes() == out.read_bytes()


def test_hand_written_challenge_files_read_as_the_kit_documents_them(tmp_path):
    queries = tmp_path / "q.json"
    queries.write_text('{"queries": [{"horizon": "3s", "rays": {"log-a": {"315.feather": '
                       '[[[0, 0, 0, 1, 0, 0], [0.5, 0, 1, 0, 1, 0]], []]}}}]}')
    hz, rays = read_challenge_queries(queries)
    assert hz == "3s" and list(rays) == [("log-a", "315.feather")]
    (o0, d0), (o1, d1) = rays[("log-a", "315.feather")]
    assert o0.tolist() == [[0, 0, 0], [0.5, 0, 1]] and d0.tolist() == [[1, 0, 0], [0, 1, 0]] and d0.dtype == np.float32
    assert o1.shape == d1.shape == (0, 3)

    sub = tmp_path / "s.json"
    sub.write_text('{"queries": [{"horizon": "3s", "rays": {"log-a": {"315.feather": [[[12.5], [3.25]], []]}}}]}')
    f = open_challenge_submission(sub)
    assert f.keys == {("log-a", "315.feather")} and f.answers is None and f.horizon == "3s"
    depths = f.arrays(("log-a", "315.feather"))["depths"]
    assert depths[0].tolist() == [12.5, 3.25] and depths[1].shape == (0,)

    for text, match in [
        ('{"queries": [{"horizon": "3s", "rays": {"log-a": {"315.feather": [[[12.5, 1.0]]]}}}]}',
         r"log log-a, frame 315.feather, future sweep 0: expected a list of \[d\] per ray \(1 number\(s\) each\), "
         r"got shape \(1, 2\)"),
        ('{"queries": [{"horizon": "3s", "rays": {"log-a": {"315.feather": [[[1.0], [2.0, 3.0]]]}}}]}',
         r"future sweep 0: expected a list of \[d\] per ray .* got ragged or not numbers"),
        ('{"rays": {}}', r"is not a challenge file"),
        ('{"queries": [', r"cannot read .* as JSON"),
    ]:
        sub.write_text(text)
        with pytest.raises(PcfbenchError, match=match):
            open_challenge_submission(sub)


class CopyLastDepths(Method):
    """copy-last answered as depths, one per query ray, as the challenge export computes them."""

    name = "copy-last-depths"

    def forecast(self, sample):
        return Forecast(depths=tuple(ray_depths(sample, CopyLast().forecast(sample))))


def _rows(store: Path, method: str) -> pd.DataFrame:
    (d,) = [d for d, meta in iter_cells(store) if meta["spec"]["method"] == method]
    return Cell.at(store, d.relative_to(store)).read_rows().sort_values(["sample_id", "step"]).reset_index(drop=True)


def _run(root: Path, store: Path, method: str, plugins) -> None:
    spec = CellSpec(method, {}, resolve_method(method, plugins).options_hash, "av2", str(root), "val", "av2-1s",
                    "full-context", None, METRICS)
    run_cell(spec, store, RunOptions(progress=False), plugins=plugins)


@pytest.fixture(scope="module")
def exported(av2, tmp_path_factory):
    """copy-last's forecasts exported as a challenge submission by the command line."""
    root, _q = av2
    out = tmp_path_factory.mktemp("export") / "copy-last.json"
    res = CliRunner().invoke(build_cli(), ["challenge", "export", "-m", "copy-last", "-d", f"av2={root}", "-s", "av2-1s",
                                           "--split", "val", "-o", str(out), "-q"])
    assert res.exit_code == 0, res.output
    assert res.output.startswith("copy-last: 4 samples, ") and res.output.endswith(f" depths -> {out}\n")
    return out


def test_a_submission_json_of_copy_lasts_depths_scores_as_copy_last(av2, exported, tmp_path):
    root, q = av2
    store = tmp_path / "store"
    result, checked = score_submission(exported, "copy-last-json", q, store, METRICS)
    assert checked.answered == 4 and result.failed == 0
    assert json.loads((result.path / "cell.json").read_text())["submission"]["layout"] == "challenge-json"
    plugins = load_plugins()
    plugins.methods.add("copy-last-depths", CopyLastDepths, "test")
    _run(root, store, "copy-last-depths", plugins)
    _run(root, store, "copy-last", plugins)
    json_rows, depth_rows, points_rows = _rows(store, "submission"), _rows(store, "copy-last-depths"), _rows(store, "copy-last")
    columns = ["sample_id", "step", "status", "n_gt", "n_pred", *METRICS]
    # every metric equal to copy-last answering the same depths in-process
    pd.testing.assert_frame_equal(json_rows[columns], depth_rows[columns], check_exact=True)
    # and against copy-last's points: the ray-depth metrics read the same point per ray (the
    # depths in float32); the Chamfer distances differ (the depths' points lie on the rays)
    for m in ("l1_mean", "absrel_mean", "l1_median"):
        np.testing.assert_allclose(json_rows[m], points_rows[m], rtol=1e-6, err_msg=m)
    assert points_rows["l1_ray"].isna().all() and json_rows["l1_ray"].notna().all()


def test_a_challenge_submission_answering_other_questions_or_rays_is_refused(av2, exported, tmp_path):
    _root, q = av2
    data = json.loads(exported.read_text())
    log, frames = next(iter(data["queries"][0]["rays"].items()))
    frame = sorted(frames)[0]
    sid = f"val/{log}/{[i for s, i in q.keys if s == f'val/{log}'][0]:06d}"

    def refused(obj, match):
        path = tmp_path / "hostile.json"
        path.write_text(json.dumps(obj))
        with pytest.raises(PcfbenchError, match=match) as err:
            score_submission(path, "hostile", q, tmp_path / "store", ("chamfer",))
        assert str(path) in str(err.value) and not (tmp_path / "store").exists()
        return str(err.value)

    other = json.loads(json.dumps(data))
    other["queries"][0]["horizon"] = "3s"
    refused(other, r"answers horizon '3s', setting av2-1s is '1s'")
    other = json.loads(json.dumps(data))
    other["pcfbench"]["data_fingerprint"] = "0" * 16
    assert "data_fingerprint: the file's '0000000000000000'" in refused(other, "answers other questions")
    bare = {"queries": data["queries"]}  # without pcfbench's answers: checked by horizon and rays
    other = json.loads(json.dumps(bare))
    n = len(other["queries"][0]["rays"][log][frame][1])
    other["queries"][0]["rays"][log][frame][1].pop()
    refused(other, rf"sample {sid}, future sweep 1: depths have shape \({n - 1},\), expected \({n},\)")
    other = json.loads(json.dumps(bare))
    other["queries"][0]["rays"][log]["999.feather"] = other["queries"][0]["rays"][log][frame]
    refused(other, r"has 1 sample\(s\) that av2:val av2-1s \(full-context\) does not have: .*999.feather")
    other = json.loads(json.dumps(bare))
    del other["queries"][0]["rays"][log][frame]
    refused(other, rf"misses 1 of the 4 samples: {sid}; pass --partial")
    for bad in (float("nan"), float("inf")):
        other = json.loads(json.dumps(bare))
        other["queries"][0]["rays"][log][frame][3][5] = [bad]  # json writes NaN, Infinity; Python's reader takes them
        refused(other, rf"sample {sid}, future sweep 3: 1 depth\(s\) are NaN or inf")
