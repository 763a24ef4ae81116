"""Running cells (README.md, "How data flows"): a cell is one method x dataset x split x setting.

    runner.py        resolves and runs a cell: samples in, forecasts scored, rows to the store
    execution.py     the thread budget a method or metric may use (ExecutionContext)
    workers.py       supervised worker processes: a crash or a timeout is a failed sample
    ray_executor.py  the same cells as Ray tasks on a cluster (docs/cluster.md)
    warmup.py        numba compilation overlapped with preparing data
    provenance.py    what a result records of its code and environment (git commit, versions)
    backfill.py      the explicit command that re-runs methods to add range bins to old cells
"""
