"""Where the metrics' nearest-neighbour searches run: ``numpy`` (k-d trees and bucket grids on the
CPU, pcfbench.metrics.nn) or ``torch`` (brute force on a GPU, pcfbench.metrics.torch_nn; on the
CPU where there is none); ``auto`` takes torch when a CUDA GPU is there, else numpy.

Both give the reference's values (the golden tolerance; the same float64 formulas, so in
practice the same bits); everything but the searches is the same code either way.
"""

from __future__ import annotations

import os
from functools import cached_property, lru_cache

import numpy as np

from pcfbench.errors import PcfbenchError
from pcfbench.metrics.base import SweepContext

BACKENDS = ("auto", "numpy", "torch")


@lru_cache(maxsize=1)
def cuda_present() -> bool:
    """Whether torch sees a CUDA GPU; torch is imported only where an NVIDIA driver is loaded."""
    if not os.path.exists("/proc/driver/nvidia/version"):
        return False
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def resolve(backend: str) -> str:
    """``numpy`` or ``torch`` for a ``BACKENDS`` name (``auto``: torch when ``cuda_present``)."""
    if backend not in BACKENDS:
        raise PcfbenchError(f"metrics backend {backend!r} is not one of {', '.join(BACKENDS)}")
    if backend == "auto":
        return "torch" if cuda_present() else "numpy"
    return backend


def context_class(backend: str) -> type[SweepContext]:
    """The SweepContext class whose searches run on ``backend`` (a ``BACKENDS`` name)."""
    return TorchSweepContext if resolve(backend) == "torch" else SweepContext


class TorchSweepContext(SweepContext):
    """A SweepContext whose nearest-neighbour searches run in torch (``TorchSearch``: the GPU
    when there is one); every other quantity is the CPU context's."""

    @cached_property
    def search(self):
        from pcfbench.metrics.torch_nn import TorchSearch

        return TorchSearch()

    def share_out(self, searches) -> None:
        """Nothing to share out over the CPU threads: the device runs the searches."""

    @cached_property
    def nn_pred_to_gt(self) -> tuple[np.ndarray, np.ndarray]:
        return self.search.nearest_3d(self.pred64, self.gt64)

    @cached_property
    def nn_gt_to_pred(self) -> tuple[np.ndarray, np.ndarray]:
        return self.search.nearest_3d(self.gt64, self.pred64)

    def _cropped_torch(self, full: tuple[np.ndarray, np.ndarray], q_in: np.ndarray, t_in: np.ndarray,
                       queries: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """As SweepContext._cropped_nn: only the cropped queries whose nearest point lies outside
        the crop are searched again, within the cropped targets."""
        d2, idx = full[0][q_in], full[1][q_in]
        redo = np.flatnonzero(~t_in[idx])
        if redo.size:
            d2[redo] = self.search.nearest_3d(queries[np.flatnonzero(q_in)[redo]], targets[t_in])[0]
        return d2

    @cached_property
    def nn_pred_to_gt_roi(self) -> np.ndarray:
        return self._cropped_torch(self.nn_pred_to_gt, self.pred_in_roi, self.gt_in_roi, self.pred64, self.gt64)

    @cached_property
    def nn_gt_to_pred_roi(self) -> np.ndarray:
        return self._cropped_torch(self.nn_gt_to_pred, self.gt_in_roi, self.pred_in_roi, self.gt64, self.pred64)

    @cached_property
    def _angular_nearest(self) -> tuple[np.ndarray, np.ndarray]:
        return self.search.nearest_angles(self.pred_rel, self.gt_rel, self.truth.gt_angles)
