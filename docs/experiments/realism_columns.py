"""The realistic town at fewer azimuth columns: its rankings and what it costs (docs/realism.md,
"Fewer columns").

Generate ``synthetic-town-realistic`` (the current physics) with COLUMNS azimuth steps per beam
instead of 2048, then compare it with the real drive as any generated root::

    .venv/bin/python docs/experiments/realism_columns.py generate OUT COLUMNS [SPLITS]
    .venv/bin/pcfbench synthetic compare --real kitti=ROOT --real-split train \\
        --domain synthetic-town-realistic=OUT --split test --out REPORT --store STORE

SPLITS: comma-separated (default ``test``; ``test,train,val`` for the seven towns).

What the five baselines and the metrics cost per kitti-1s sample on each root, one thread, the
roots alternated ROUNDS times in one process (N test samples spread evenly over the split; medians
of the load, forecast and scoring times the runner records)::

    .venv/bin/python docs/experiments/realism_columns.py cost N ROUNDS LABEL=DATASET=ROOT ...

Run ``cost`` on an otherwise idle machine: a neighbour's job moves these times.
"""

from __future__ import annotations

import dataclasses
import statistics
import sys

METHODS = ("copy-last", "raycast-4docc", "raycast-freespace", "raycast-voxel", "raycast-zbuffer")


def generate(out: str, columns: int, splits: str = "test") -> None:
    from pcfbench.datasets.synthetic.domains import get_domain
    from pcfbench.datasets.synthetic.generate import generate_domain

    d = get_domain("synthetic-town-realistic")
    d = dataclasses.replace(d, sensor=dataclasses.replace(d.sensor, azimuth_steps=columns))
    generate_domain(d, out, splits=tuple(splits.split(",")), progress=True)


def cost(n: int, rounds: int, roots: list[str]) -> None:
    from pcfbench.execution import ExecutionContext, applied
    from pcfbench.method import resolve_method
    from pcfbench.plugins import get_plugins
    from pcfbench.runner import default_metrics, process_sample, resolve
    from pcfbench.store import CellSpec

    plugins = get_plugins()
    one = ExecutionContext(1)
    labels = [r.split("=", 2) for r in roots]
    cells = {}
    for label, dataset, root in labels:
        for m in METHODS:
            spec_m = resolve_method(m, plugins)
            spec = CellSpec(spec_m.name, dict(spec_m.raw), spec_m.options_hash, dataset, root, "test", "kitti-1s",
                            "full-context", None, default_metrics(plugins))
            res = resolve(spec, plugins)
            res.bind(one)
            keys = res.builder.sample_keys("test")
            cells[label, m] = (res, keys[:: max(1, len(keys) // n)][:n])
    times: dict = {}
    with applied(one):
        for _ in range(rounds):
            for label, _, _ in labels:
                for m in METHODS:
                    res, keys = cells[label, m]
                    for key in keys:
                        row = process_sample(res, key)[0]
                        times.setdefault((label, m), []).append((row["t_load"], row["t_method"], row["t_metrics"]))
    for label, _, _ in labels:
        total = 0.0
        for m in METHODS:
            load, method, metrics = (statistics.median(t[i] for t in times[label, m]) for i in range(3))
            total += load + method + metrics
            print(f"{label:12s} {m:18s} load {load:6.3f} s  forecast {method:6.3f} s  metrics {metrics:6.3f} s")
        print(f"{label:12s} the five baselines: {total:.2f} s a sample (sum of the medians)")


if __name__ == "__main__":
    if len(sys.argv) >= 4 and sys.argv[1] == "generate":
        generate(sys.argv[2], int(sys.argv[3]), *sys.argv[4:5])
    elif len(sys.argv) >= 5 and sys.argv[1] == "cost":
        cost(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4:])
    else:
        sys.exit(__doc__)
