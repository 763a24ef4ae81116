"""How a cell is named to a reader: its variant label and its one-line label.

Low in the import graph (it needs only the store's ``CellSpec``): the report, the sweeps and
the command line all name cells the same way without importing each other.
"""

from __future__ import annotations

from typing import Any

from pcfbench.store.cells import CellSpec


def method_label(method: str, options: dict) -> str:
    """A readable variant label: ``raycast-voxel (voxel=0.2, k=3)``; the bare name without options.
    A submission (``pcfbench score``) is named by its name and its file's sha256:
    ``my-model (submission 1a2b3c4d)``."""
    if not options:
        return method
    if method == "submission" and set(options) == {"name", "path", "sha256"}:
        return f"{options['name']} (submission {str(options['sha256'])[:8]})"
    return f"{method} (" + ", ".join(f"{k}={v}" for k, v in sorted(options.items())) + ")"


def trained_label(spec: CellSpec, meta: dict[str, Any]) -> str:
    """A trained method's row names its training data and checkpoint (two checkpoints side by
    side stay two rows), and says so when it was scored on that very data; an unfinished
    training or a training-data claim not verified is marked beside the data
    (``pcfbench.training.claims.claim_marks``), so it goes where the data goes (a footnote)."""
    from pcfbench.training.claims import claim_marks

    if not spec.train_on:
        return ""
    mark = ", ON ITS TRAINING DATA" if meta.get("evaluated_on_training_data") else ""
    claims = claim_marks(meta)
    data = f"{spec.train_on} ({'; '.join(claims)})" if claims else spec.train_on
    return f" [trained on {data}, ck {str(spec.checkpoint_sha256)[:8]}{mark}]"


def cell_label(spec: CellSpec) -> str:
    """``raycast-voxel (voxel=0.4) | synthetic-town:test | kitti-1s``: the row and the cell."""
    return spec.label.replace(spec.method, method_label(spec.method, spec.options), 1)
