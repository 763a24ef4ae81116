"""pcfbench: a plugin-based benchmark harness for LiDAR point-cloud forecasting.

The public API for plugin authors is what ``import pcfbench`` gives (``__all__``)::

    import pcfbench

    class MyMethod(pcfbench.Method):
        name = "my-method"

        def forecast(self, sample: pcfbench.Sample) -> pcfbench.Forecast:
            ...

    @pcfbench.hookimpl
    def register_methods(register):
        register("my-method", MyMethod)

Names are imported on first use, so ``import pcfbench`` stays cheap and a plugin module can
import it at the top without pulling in the metrics or the runner.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: public name -> the module that defines it (a module itself when the value is None)
_EXPORTS: dict[str, str | None] = {
    # hooks
    "hookimpl": "pcfbench.hookspecs",
    "hookspec": "pcfbench.hookspecs",
    # the data a method receives and returns
    "Sample": "pcfbench.data",
    "Forecast": "pcfbench.data",
    "GroundTruth": "pcfbench.data",
    "RayQuery": "pcfbench.data",
    "Sweep": "pcfbench.data",
    # methods
    "Method": "pcfbench.method",
    "NoOptions": "pcfbench.method",
    # methods that learn: the contract and their checkpoints
    "TrainedMethod": "pcfbench.training",
    "TrainSource": "pcfbench.training",
    "TrainingRun": "pcfbench.training",
    "Checkpoint": "pcfbench.training",
    # typed options of methods and adapters (a help text per field)
    "option": "pcfbench.options",
    # the thread budget a method or metric may use (Method.execution)
    "ExecutionContext": "pcfbench.execution",
    # datasets
    "DatasetAdapter": "pcfbench.dataset",
    "Sequence": "pcfbench.dataset",
    "CheckReport": "pcfbench.dataset",
    "EgoBox": "pcfbench.boxes",
    # metrics
    "Metric": "pcfbench.metrics.base",
    "SweepContext": "pcfbench.metrics.base",
    # the closed sets of words (StrEnums: each member is its string)
    "Needs": "pcfbench.kinds",
    "Better": "pcfbench.kinds",
    "PolicyKind": "pcfbench.kinds",
    # protocol
    "Setting": "pcfbench.protocol",
    "SamplePolicy": "pcfbench.protocol",
    "Protocol": "pcfbench.protocol",
    "active_protocol": "pcfbench.protocol",
    # errors
    "PcfbenchError": "pcfbench.errors",
    "DataError": "pcfbench.errors",
    "UnknownNameError": "pcfbench.errors",
    "PluginError": "pcfbench.errors",
    # the testing kit (check_method, check_adapter, toy worlds)
    "testing": None,
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'pcfbench' has no attribute {name!r}")
    module = _EXPORTS[name]
    value = importlib.import_module(f"pcfbench.{name}") if module is None else getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
    from pcfbench import testing
    from pcfbench.data import Forecast, GroundTruth, RayQuery, Sample, Sweep
    from pcfbench.boxes import EgoBox
    from pcfbench.dataset import CheckReport, DatasetAdapter, Sequence
    from pcfbench.errors import DataError, PcfbenchError, PluginError, UnknownNameError
    from pcfbench.hookspecs import hookimpl, hookspec
    from pcfbench.method import Method, NoOptions
    from pcfbench.execution import ExecutionContext
    from pcfbench.options import option
    from pcfbench.training import Checkpoint, TrainedMethod, TrainingRun, TrainSource
    from pcfbench.metrics.base import Metric, SweepContext
    from pcfbench.kinds import Better, Needs, PolicyKind
    from pcfbench.protocol import Protocol, SamplePolicy, Setting, active_protocol
