"""Running cells (README.md, "How data flows"): a cell is one method x dataset x split x setting.
The thread budget a cell hands its method and metrics (pcfbench.execution) and what a result
records of its code (pcfbench.provenance) sit below, beside the contract they serve.

    runner.py        resolves and runs a cell: samples in, forecasts scored, rows to the store
    workers.py       supervised worker processes: a crash or a timeout is a failed sample
    ray_executor.py  the same cells as Ray tasks on a cluster (docs/cluster.md)
    warmup.py        numba compilation overlapped with preparing data
    backfill.py      the explicit command that re-runs methods to add range bins to old cells
"""
