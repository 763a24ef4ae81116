"""What a sample costs each built-in baseline per dataset size: the measurements docs/performance.md
is generated from (pcfbench.costtable).

    PCFBENCH_BENCH_FULL=1 PCFBENCH_COSTS_OUT=docs/performance-costs.json \
        .venv/bin/python -m pytest tests/benchmarks/test_bench_cost.py --benchmark-enable -s
    .venv/bin/python -m pcfbench.docs performance --out docs/performance.md

Per size, the five baselines run as the runner runs them (one pass over each sample for every
method, ``run_group``), on one thread, into a fresh store: first on one sample (warm-up: numba's
kernels, the page cache), then on ``SAMPLES``; the medians of the rows' ``t_load``,
``t_method`` and ``t_metrics`` per method are its share of the pass. Then each method alone
(``run_cell``, a one-method run) on the same samples: the median of its rows' sum is its cost
alone. Sizes: the toy street of the tests
(16 x 360 rays), and at full size the KITTI-sized toy street (64 x 1900) and, with
``PCFBENCH_BENCH_KITTI``, real KITTI sweeps. At full size it also measures the two ratios of
issue 48 side by side (alternating rounds, medians): the metric suite against two pykdtree
passes on the largest pair (test_bench_metrics) and the group pass against one run per method
(test_bench_group). ``PCFBENCH_COSTS_OUT``: where the JSON goes (else it is printed).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

from pcfbench.execution import available_cpus
from pcfbench.method import options_hash
from pcfbench.plugins import get_plugins
from pcfbench.running.group import run_group
from pcfbench.running.runner import RunOptions, default_metrics, run_cell
from pcfbench.store.cells import Cell, CellSpec

FULL = os.environ.get("PCFBENCH_BENCH_FULL") == "1"
KITTI = os.environ.get("PCFBENCH_BENCH_KITTI")
SPLIT = os.environ.get("PCFBENCH_BENCH_SPLIT", "train")
SAMPLES = int(os.environ.get("PCFBENCH_BENCH_SAMPLES", 4 if FULL else 2))
METHODS = ("copy-last", "raycast-4docc", "raycast-zbuffer", "raycast-voxel", "raycast-freespace")
#: KITTI's test split (sequences 08-10): what the projection scores
TEST_SPLIT = {"name": "KITTI Odometry test split (sequences 08-10)", "samples": {"kitti-1s": 6809, "kitti-3s": 6701}}


def _sizes(tmp: Path) -> list[tuple[dict, Path, str]]:
    from conftest import write_tiny_kitti

    out = []
    grids = [(16, 360)] + ([(64, 1900)] if FULL else [])
    for beams, azimuths in grids:
        root = write_tiny_kitti(tmp / f"toy{beams}x{azimuths}", num_sweeps=19 + SAMPLES, beams=beams, azimuths=azimuths)
        out.append(({"name": f"toy street, {beams} x {azimuths} rays",
                     "description": f"the tests' toy street seen by a {beams}-beam LiDAR, {azimuths} azimuths"}, root, "test"))
    if KITTI and FULL:
        out.append(({"name": "real KITTI sweeps", "description": f"KITTI Odometry sweeps of {Path(KITTI).name} ({SPLIT} split)"},
                    Path(KITTI), SPLIT))
    return out


def _costs(size: dict, root: Path, split: str, tmp: Path) -> list[dict]:
    metrics = default_metrics(get_plugins())
    options = RunOptions(progress=False, threads=1)

    def specs(limit):
        return [CellSpec(m, {}, options_hash(None), "kitti", str(root), split, "kitti-1s", "full-context", limit, metrics)
                for m in METHODS]

    run_group(specs(1), tmp / "warm", options)
    run_group(specs(SAMPLES), tmp / "store", options)
    for spec in specs(SAMPLES):  # each method alone, as a one-method run computes it
        run_cell(spec, tmp / "alone", options)
    out = []
    for spec in specs(SAMPLES):
        df = Cell(tmp / "store", spec).read_rows()
        per = df[df.status == "ok"].drop_duplicates("sample_id")
        alone = Cell(tmp / "alone", spec).read_rows()
        alone = alone[alone.status == "ok"].drop_duplicates("sample_id")
        points = int(df[df.status == "ok"]["n_gt"].median())
        out.append({"method": spec.method, "size": size["name"], "samples": int(len(per)), "gt_points": points,
                    "load_s": float(per.t_load.median()), "forecast_s": float(per.t_method.median()),
                    "metrics_s": float(per.t_metrics.median()),
                    "alone_s": float((alone.t_load + alone.t_method + alone.t_metrics).median())})
    return out


def _ratios(largest: tuple[dict, Path, str], tmp: Path) -> list[dict]:
    import test_bench_group
    import test_bench_metrics

    size, root, split = largest
    where = f"{size['name']}, kitti-1s"
    pair = test_bench_metrics.real_pair(str(root), split) if root == Path(KITTI or "") else \
        test_bench_metrics.toy_pair(64, 1900)
    rounds = 21
    _, _, suite = test_bench_metrics.alternating(*pair, rounds)
    out = [{"what": "metric suite, every metric, one sweep (copy-last's forecast)", "baseline":
            "two exact pykdtree passes (build and query, each way)", "ratio": suite, "bar": "<= 1.5",
            "rounds": rounds, "where": f"{where}, future sweep 5, {len(pair[0]):,} x {len(pair[1]):,} points"}]
    g, a, times = test_bench_group.measure(root, split, 6, 5, tmp / "group")
    out.append({"what": "the five baselines in one pass, 6 samples", "baseline":
                "one run per method, one after the other (same process)", "ratio": g / a, "bar": "<= 0.85",
                "rounds": len(times["group"]), "where": where})
    return out


def test_costs(tmp_path, benchmark):
    sizes = _sizes(tmp_path)
    costs = []
    for i, (size, root, split) in enumerate(sizes):
        costs += _costs(size, root, split, tmp_path / f"size{i}")
    ratios = _ratios(sizes[-1], tmp_path) if FULL else []
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    data = {
        "measured": {"date": time.strftime("%Y-%m-%d", time.gmtime()), "commit": commit,
                     "machine": f"{available_cpus()} CPU cores ({platform.processor() or platform.machine()}), one thread "
                                f"for the costs",
                     "load": " / ".join(f"{x:.1f}" for x in os.getloadavg())},
        "split": TEST_SPLIT,
        "sizes": [s for s, _, _ in sizes],
        "costs": costs,
        "ratios": ratios,
        "notes": ["GPU (`--metrics-backend torch` on CUDA): not measured here; no GPU was lent to this machine."],
    }
    text = json.dumps(data, indent=2) + "\n"
    out = os.environ.get("PCFBENCH_COSTS_OUT")
    if out:
        Path(out).write_text(text, encoding="utf-8")
    print("\n" + text)
    benchmark.pedantic(lambda: None, rounds=1, iterations=1)
    assert {c["method"] for c in costs} == set(METHODS)
    assert all(np.isfinite([c["load_s"], c["forecast_s"], c["metrics_s"]]).all() for c in costs)
    if FULL:
        assert [r["ratio"] for r in ratios] and all(np.isfinite(r["ratio"]) for r in ratios)
